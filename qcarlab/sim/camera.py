"""The simulated cameras: the Intel D435 RGBD camera and the four CSI wide-angle cameras.

    >>> import numpy as np
    >>> from qcarlab.sim.world import load_world
    >>> from qcarlab.sim.camera import RGBDCamera, CSICameras, stitch_panorama
    >>> world = load_world("track")
    >>> cam = RGBDCamera(world, rng=np.random.default_rng(0))
    >>> frame = cam.render(world.start)          # RGBDFrame: color (480, 640, 3) BGR, depth (480, 640) m
    >>> cam.intrinsics                            # fx, fy, cx, cy, width, height
    >>> csi = CSICameras(world, rng=np.random.default_rng(0)).render(world.start)
    >>> pano = stitch_panorama(csi)               # right | rear | left | front, 3280 x 410

**RGBD (D435).** A pinhole at the mount (``rgbd_x`` ahead of the car's centre, ``rgbd_z`` above
the floor, looking forward, pitched down by ``rgbd_pitch``), 640 x 480, square pixels, vertical
field of view ``rgbd_vfov`` (42.5 deg; the D435's 69.4 deg horizontal FOV is that of its 16:9
mode: at 4:3 the sensor is cropped to about 55 deg, as the real camera's 640 x 480 intrinsics,
fx = fy = 616 px, show). Pixel (u, v): u to the right, v down; the principal point is the image
centre (cx, cy) = (319.5, 239.5), so the two middle columns straddle the optical axis. The depth
image is aligned to the colour image and holds the **z-depth from the camera** (the distance
along the optical axis from the D435's optical centre, as the RealSense reports it): a wall 2 m
ahead of the car's centre reads ``2 - rgbd_x`` = 1.92 m in the middle of the image. Depth is 0
(no data) nearer than :data:`RGBD_MIN_DEPTH` and beyond ``rgbd_max_depth``. Noise: colour
+-:data:`COLOR_NOISE_SD` levels per channel, depth sigma = :data:`DEPTH_NOISE` * z^2.

**CSI.** Four 160 deg equidistant fisheye cameras (r = f theta), 820 x 410, on the roof
``csi_front_x``/``csi_rear_x`` on the axis and ``csi_side_y`` to the sides, facing front, rear, left
and right, ``csi_z`` above the floor.

How it is drawn. The RGBD camera (a level pinhole, rendered upright, row-major):

1. each image column is a vertical plane; what it meets is found per *edge* in a world of
   polygons and circles (each edge in front of the camera projected to the columns it spans and
   intersected exactly with just those rays; ``vector_walls``), or by marching the world's raster
   for a ROS map's grid; the walls, obstacles and balls it sees, up to the first that covers the
   column, become *layers* of the column (rows, colour, depth = a + b / (v - cy)), far to near
   (:func:`~qcarlab.sim._kernels.column_layers`);
2. one pass per image row (:func:`~qcarlab.sim._kernels.compose_rows`), each row in cache: the
   floor, a top-down texture (markings, brightness regions) at the level of its mipmap whose
   texels match the row's footprint: a row of a level camera is a straight line through the
   texture, so where the square of uniform texels ahead of a sample (``raster.run_squares``,
   the quadrant the row moves into) says the next pixels all read one colour they are filled
   at once (the same numbers as blending each), the rest are blended bilinearly in one
   vectorised batch; the floor's depth is one number per row; then the layers, the stop-sign
   sprites (depth-tested), the depth's noise and range limits, the row's BGR bytes. Rows the
   layers cover in every column skip the floor; a row one wall covers end to end is that wall's
   BGR bytes (made once a frame) with the row's noise, its depths (a front face's: one per
   column, made once a frame) finished in a single pass, as are a row's that shows the floor
   alone;
3. with each row's BGR bytes, its colour noise (one int8 tile), in the same pass. The realism
   profile's exposure gain (``render(..., gain=)``) scales the colours as they are drawn.

A camera pitched down renders the level view so, then rotates it (a homography). The CSI views
are drawn per column in a transposed buffer (:func:`~qcarlab.sim._kernels.render_columns`,
the floor by a precomputed per-pixel ray map) and remapped to the fisheye.

Speed (one core, ``benchmarks/bench_sensors.py``): no transposes, no per-frame warps of the
floor, each output byte written once; every frame in the calling thread (a helper thread that
drew half the rows cost more than it saved once a frame took 0.4 ms: handing it over and waking
it up). Noise comes from precomputed tiles at random offsets.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from qcarlab.constants import csi_mounts, DEFAULT_PARAMS, QCarParams
from qcarlab.sensors import CameraIntrinsics, CSIFrames, RGBDFrame
from qcarlab.sim import _kernels
from qcarlab.sim import raster as raster_kinds
from qcarlab.sim.raster import brightness_grid, build_raster, floor_pyramid, floor_runs
from qcarlab.sim.world import Sign, World, load_world

__all__ = [
    "COLOR_NOISE_SD",
    "CSICameras",
    "DEPTH_NOISE",
    "RGBDCamera",
    "RGBD_MIN_DEPTH",
    "stitch_panorama",
]

RGBD_MIN_DEPTH = 0.1  # m: the D435 reads 0 nearer than this
DEPTH_NOISE = 0.004  # depth noise sigma = DEPTH_NOISE * z^2 (m): 4 mm at 1 m, 16 mm at 2 m
COLOR_NOISE_SD = 2.5  # colour noise, levels of 255 per channel
DEPTH_TILE_STEP = 1.0 / 32.0  # the depth noise tile's unit (standard deviations): +-3.97 sigma in int8
FLOOR_PX_PER_M = 200.0  # floor texture resolution (5 mm texels)
MAX_VIEW_DIST = 30.0  # m, how far the cameras look for walls
LIGHT_DIR = (0.6, 0.8)  # horizontal direction of the light that shades vertical faces
CSI_OVERSAMPLE = 0.8  # cylinder pixels per fisheye pixel at the centre of a CSI view
_NOISE_PAD = 48
_SPRITE = 128
_NO_NOISE = np.zeros((0, 0), np.int8)
_NO_CNOISE = np.zeros((1, 0), np.int8)
_NO_BGR = np.zeros((0, 0), np.uint8)
_NO_SIGNS = (np.zeros((0, 5), np.int64), np.zeros(0, np.float64), np.zeros(0, np.uint32))


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------
def _stop_sprites() -> tuple[np.ndarray, np.ndarray]:
    """Front (red octagon, white border, STOP) and back (grey octagon) of a stop sign, BGRA."""
    s = _SPRITE
    c = (s - 1) / 2.0
    ang = math.pi / 8.0 + np.arange(8) * math.pi / 4.0

    def octagon(half_flats: float) -> np.ndarray:
        r = half_flats / math.cos(math.pi / 8.0)
        return np.round(np.column_stack((c + r * np.cos(ang), c - r * np.sin(ang))) * 16).astype(np.int32)

    front = np.zeros((s, s, 4), np.uint8)
    back = np.zeros((s, s, 4), np.uint8)
    cv2.fillPoly(front, [octagon(s / 2.0)], (235, 235, 235, 255), cv2.LINE_AA, 4)
    cv2.fillPoly(front, [octagon(s / 2.0 * 0.88)], (16, 16, 200, 255), cv2.LINE_AA, 4)
    font = cv2.FONT_HERSHEY_DUPLEX
    scale = cv2.getFontScaleFromHeight(font, int(s * 0.24), 3)
    (tw, th), _ = cv2.getTextSize("STOP", font, scale, 3)
    alpha = front[:, :, 3].copy()  # anti-aliased text blends the alpha too: the letters' edges went see-through
    cv2.putText(front, "STOP", (int(c - tw / 2), int(c + th / 2)), font, scale, (235, 235, 235, 255), 3, cv2.LINE_AA)
    front[:, :, 3] = alpha
    cv2.fillPoly(back, [octagon(s / 2.0)], (150, 150, 150, 255), cv2.LINE_AA, 4)
    return front, back


_SPRITES: tuple[np.ndarray, np.ndarray] | None = None


def _sprites() -> tuple[np.ndarray, np.ndarray]:
    global _SPRITES
    if _SPRITES is None:
        _SPRITES = _stop_sprites()
    return _SPRITES


@dataclass(frozen=True)
class NoiseTiles:
    """A camera's noise tiles and the state its generator is left in after drawing them."""

    tile: np.ndarray  # int8 (rows, 3 columns): rint(N(0, color_sd)), clipped to +-127
    depth: np.ndarray  # int8 (rows, columns): rint(N(0, 1) / DEPTH_TILE_STEP), clipped; (0, 0) when none
    after: str  # the generator's state after the draws, as JSON


def _draw_tiles(rng: np.random.Generator, shape: tuple[int, int], color_sd: float, depth: bool) -> NoiseTiles:
    """The tiles drawn from ``rng``: ``color_sd * z`` for the colour (what ``rng.normal(0,
    color_sd)`` draws), then the depth's standard normals as float32."""
    n = np.empty(shape + (3,))
    rng.standard_normal(out=n)
    n *= color_sd
    # rint(n) as int8, (rows, 3 columns) bytes: a pixel gets clip(c + rint(n)), what adding
    # the tile's + part and subtracting its - part (two saturating passes) gave, in one pass
    # of half the bytes (:func:`~qcarlab.sim._kernels.color_noise`)
    np.rint(n, out=n)
    np.clip(n, -127.0, 127.0, out=n)
    tile = n.astype(np.int8).reshape(shape[0], -1)
    # depth: standard normal in int8 steps of DEPTH_TILE_STEP (a quarter of the float32
    # tile's bytes: the tile stays in the cache beside the frame)
    d = np.zeros((0, 0), np.int8)
    if depth:
        z = rng.standard_normal(shape, dtype=np.float32)
        z /= np.float32(DEPTH_TILE_STEP)
        np.rint(z, out=z)
        np.clip(z, np.float32(-127.0), np.float32(127.0), out=z)
        d = z.astype(np.int8)
    return NoiseTiles(tile, d, json.dumps(rng.bit_generator.state))


def noise_tiles(rng: np.random.Generator, shape: tuple[int, int], color_sd: float, depth: bool) -> NoiseTiles:
    """:func:`_draw_tiles`, kept on disk (:func:`qcarlab.sim.raster.on_disk`) under the generator's
    state and the code that draws them, and ``rng`` left as the draws leave it: the same tiles and
    the same generator afterwards, without drawing a million normals (some 15 ms, 30-50 ms with the
    fresh pages of a new process) each time a camera is made with the same seed."""
    state = rng.bit_generator.state
    try:
        before = json.dumps(state, sort_keys=True)
    except TypeError:  # a generator whose state is not plain numbers: drawn each time
        return _draw_tiles(rng, shape, color_sd, depth)
    code = _draw_tiles.__code__
    key = ("noise", shape, float(color_sd), bool(depth), DEPTH_TILE_STEP)
    tiles = raster_kinds.on_disk(NoiseTiles, key, (before, code.co_code, repr(code.co_consts)),
                                 lambda: _draw_tiles(rng, shape, color_sd, depth))
    try:
        rng.bit_generator.state = json.loads(tiles.after)  # (already so when they were drawn just now)
    except (ValueError, TypeError, KeyError):  # a damaged entry: the generator is still as it was
        return _draw_tiles(rng, shape, color_sd, depth)
    return tiles


class _Noise:
    """Precomputed noise tiles (:func:`noise_tiles`); each frame takes a window at an offset drawn
    from the rng."""

    def __init__(self, rng: np.random.Generator, w: int, h: int, color_sd: float, depth: bool):
        self.rng = rng
        self.w, self.h = w, h
        tiles = noise_tiles(rng, (w + _NOISE_PAD, h + _NOISE_PAD), color_sd, depth)
        self.tile = tiles.tile
        self.depth = tiles.depth if depth else None

    def windows(self) -> list[int]:
        """This frame's window offsets: (row, col) for the colour's tiles, (unused), then depth's.

        Six 10-bit fields of one raw 64-bit draw, each scaled to 0 .. _NOISE_PAD - 1
        (``Generator.integers`` costs some 20 us a call, a noticeable part of a frame)."""
        x = int(self.rng.bit_generator.random_raw())
        return [(((x >> (10 * i)) & 1023) * _NOISE_PAD) >> 10 for i in range(6)]

    def color(self, img: np.ndarray, o: list[int], v0: int = 0) -> None:
        """Noise on ``img`` (BGR uint8, in place), rows v0.. of a frame (all of it by default),
        window ``o[0:2]`` (from :meth:`windows`): the pixel gets clip(c + rint(n)), n ~ N(0,
        color_sd)."""
        _kernels.color_noise(img.reshape(img.shape[0], -1), self.tile, o[0] + v0, o[1])


_NO_LUT = np.zeros(0, np.int64)


def _pixel_box(pts: np.ndarray, nx: int, ny: int) -> tuple[int, int, int, int] | None:
    """The whole pixels ``x0..x1, y0..y1`` (ends exclusive) covering the points ``pts`` (n, 2),
    clipped to an ``nx`` x ``ny`` image; None when nothing of it is inside."""
    x0 = max(int(math.floor(pts[:, 0].min())), 0)
    x1 = min(int(math.ceil(pts[:, 0].max())) + 1, nx)
    y0 = max(int(math.floor(pts[:, 1].min())), 0)
    y1 = min(int(math.ceil(pts[:, 1].max())) + 1, ny)
    return None if x0 >= x1 or y0 >= y1 else (x0, x1, y0, y1)


def exposure_lut(gain: float) -> np.ndarray:
    """The exposure ``gain`` as a table of the 256 levels: saturate(rint(gain c)) in float32,
    the numbers of ``cv2.convertScaleAbs(c, alpha=gain)`` (:class:`~qcarlab.sim.realism.CameraEffects`);
    empty for gain 1 (none)."""
    if gain == 1.0:
        return _NO_LUT
    out = np.empty(256, np.int64)
    _kernels.exposure_table(float(gain), out)
    return out


class _ColumnView:
    """A level camera whose columns are vertical planes: a pinhole or a cylindrical panorama.

    Column u looks along azimuth ``az[u]`` (rad, left positive) from the camera's forward
    direction; a point at horizontal distance d and height z is at row
    ``cy - (z - cam_z) * k[u] * fy / d``. A cylindrical view (the CSI cameras) is drawn
    *transposed* (one row per image column, so each column's pixels are contiguous): colour as
    BGRA (``color4`` (W, H, 4) uint8, the same memory as ``color_t`` (W, H) uint32 packed
    pixels, which the numba kernel writes one word at a time). A pinhole (the RGBD camera) is
    drawn upright by :class:`RGBDCamera`, from the per-row tables planned here.
    """

    def __init__(
        self,
        world: World,
        mount: tuple[float, float, float, float],
        az: np.ndarray,
        k: np.ndarray,
        fy: float,
        cy: float,
        height: int,
        pinhole: CameraIntrinsics | None,
        tex_level: int = 0,
    ):
        self.world = world
        self.mx, self.my, self.cam_z, self.myaw = mount
        self.W, self.H = len(az), int(height)
        self.fy, self.cy = float(fy), float(cy)
        self.cos_c = np.ascontiguousarray(np.cos(az))
        self.sin_c = np.ascontiguousarray(np.sin(az))
        self.k = np.ascontiguousarray(k, dtype=np.float64)
        self.pinhole = pinhole
        self.raster = build_raster(world)
        self.gain = brightness_grid(world)
        if pinhole is not None:  # the kernel's packed pyramid (on disk after a world's first run: not drawn again)
            self.floor = floor_runs(world, FLOOR_PX_PER_M)
            n_levels, (tx0, ty1, ppm) = len(self.floor.levels), (self.floor.x0, self.floor.y1, self.floor.ppm)
        else:  # the BGRA pyramid the remap samples
            self.levels, (tx0, ty1, ppm) = floor_pyramid(world, FLOOR_PX_PER_M)
            n_levels = len(self.levels)
        self.tex_x0, self.tex_y1, self.ppm = tx0, ty1, ppm
        self.bg = tuple(int(c) for c in world.background) + (255,)
        self.bg_packed = np.uint32(_kernels.pack_bgr(*self.bg[:3]))
        self.r0 = int(math.floor(self.cy)) + 1  # first row below the horizon
        h_rows = np.arange(self.H, dtype=np.float64)
        below = h_rows >= self.r0
        # horizontal distance along the column ray at which each row meets the floor (k = 1)
        dist = np.full(self.H, np.inf)
        dist[below] = self.cam_z * self.fy / (h_rows[below] - self.cy)
        self.row_dist = dist
        # the floor's depth: a pinhole's z-depth is the same along an image row (the horizontal
        # distance along column u's ray is dist * k[u]); a cylinder view (k = 1) records the
        # horizontal distance, the same numbers
        self.row_depth = dist.astype(np.float32)
        self._no_balls = np.zeros((0, 6), np.float64)
        if pinhole is not None:
            self._plan_levels(n_levels)
        else:
            self.floor_depth = np.ascontiguousarray(np.broadcast_to(self.row_depth, (self.W, self.H)))
            self.color4 = np.empty((self.W, self.H, 4), np.uint8)
            self.color_t = self.color4.view(np.uint32).reshape(self.W, self.H)
            self.depth_t = np.empty((self.W, self.H), np.float32)
            self._plan_rays(tex_level)

    # --- floor: pinhole, a texture level per row ----------------------------------------------
    def _plan_levels(self, n_levels: int) -> None:
        """``row_lev``: the floor texture's level (of ``n_levels``) for each image row (0 above the horizon)."""
        assert self.pinhole is not None
        texel = 1.0 / self.ppm
        z = self.row_dist[self.r0 :]
        # footprint of a pixel on the floor: geometric mean of its across (z/fx) and along
        # (z^2/(h fy)) extents; choose the texture level whose texels match it
        foot = np.sqrt((z / self.pinhole.fx) * (z * z / (self.cam_z * self.fy)))
        lev = np.clip(np.floor(np.log2(np.maximum(foot / texel, 1.0))), 0, n_levels - 1).astype(np.int64)
        self.row_lev = np.zeros(self.H, np.int64)
        self.row_lev[self.r0 :] = lev

    # --- floor: any projection by a per-pixel ray map ------------------------------------------
    def _plan_rays(self, tex_level: int) -> None:
        d = self.row_dist[self.r0 :]  # (Hb,)
        fx = d[None, :] * self.cos_c[:, None]  # camera frame: x forward, y left
        fy = d[None, :] * self.sin_c[:, None]
        self.ray_xy = np.ascontiguousarray(np.stack([fx, fy], axis=-1).astype(np.float32))  # (W, Hb, 2)
        self.ray_level = min(tex_level, len(self.levels) - 1)

    def _floor_rays(self, cx_w: float, cy_w: float, yaw: float) -> None:
        sc = (2**self.ray_level) / self.ppm
        h0 = 0.5 / self.ppm  # level-L pixel i is centred on level-0 pixel i * 2^L
        s, c = math.sin(yaw), math.cos(yaw)
        # camera (x fwd, y left) -> world -> texture pixel of the level
        A = np.array(
            [
                [c / sc, -s / sc, (cx_w - self.tex_x0 - h0) / sc],
                [-s / sc, -c / sc, (self.tex_y1 - h0 - cy_w) / sc],
            ]
        )
        m = cv2.transform(self.ray_xy, A)
        cv2.remap(
            self.levels[self.ray_level], m, None, cv2.INTER_LINEAR, dst=self.color4[:, self.r0 :],
            borderMode=cv2.BORDER_CONSTANT, borderValue=self.bg,
        )

    # --- a frame ----------------------------------------------------------------------------------
    def camera_pose(self, pose: tuple[float, float, float]) -> tuple[float, float, float]:
        x, y, yaw = (float(v) for v in pose)
        c, s = math.cos(yaw), math.sin(yaw)
        return (x + c * self.mx - s * self.my, y + s * self.mx + c * self.my, yaw + self.myaw)

    def draw(self, pose: tuple[float, float, float], t: float) -> None:
        """Draw a cylindrical view into ``color_t``/``depth_t`` (transposed; depth = inf where
        nothing): the floor, then the walls, obstacles, balls and signs. (A pinhole view is
        drawn upright by :class:`RGBDCamera`.)"""
        assert self.pinhole is None
        cx_w, cy_w, yaw = self.camera_pose(pose)
        self._floor_rays(cx_w, cy_w, yaw)
        self.draw_objects(cx_w, cy_w, yaw, t)

    def balls_at(self, t: float) -> np.ndarray:
        """The moving balls at time ``t`` as the kernels take them: (m, 6) x, y, radius, B, G, R."""
        balls = self.world.obstacles_at(t) if self.world.balls else ()
        return np.array([(c.x, c.y, c.radius, *c.color) for c in balls], np.float64).reshape(-1, 6) if balls else self._no_balls

    def draw_objects(self, cx_w: float, cy_w: float, yaw: float, t: float) -> None:
        """The numba kernel over the floor drawn in a cylindrical view: the background above the
        horizon and the floor's depth, then the walls, obstacles and balls far to near; then the
        signs."""
        b = self.balls_at(t)
        r, g = self.raster, self.gain
        _kernels.render_columns(
            self.color_t, self.depth_t, self.floor_depth, self.bg_packed, self.r0, False,
            cx_w, cy_w, self.cam_z, yaw, self.cos_c, self.sin_c, self.k, self.fy, self.cy, MAX_VIEW_DIST,
            r.x0, r.y0, r.res, r.cells, r.kinds, r.heights, r.colors, r.poly_start, r.poly_count,
            r.verts, r.circles, g.gain, g.x0, g.y0, g.res, b, LIGHT_DIR[0], LIGHT_DIR[1],
        )
        for sign in self.world.signs:
            self._draw_sign(sign, cx_w, cy_w, yaw)

    def project(self, pts: np.ndarray, cx_w: float, cy_w: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """World points (n, 3) -> transposed pixel coords (n, 2: row-in-image v, column u) and depth."""
        c, s = math.cos(yaw), math.sin(yaw)
        rx, ry = pts[:, 0] - cx_w, pts[:, 1] - cy_w
        fwd = rx * c + ry * s
        left = -rx * s + ry * c
        up = pts[:, 2] - self.cam_z
        if self.pinhole is not None:
            p = self.pinhole
            u = p.cx - p.fx * left / fwd
            v = p.cy - p.fy * up / fwd
            return np.column_stack((v, u)), fwd
        dh = np.hypot(fwd, left)
        az = np.arctan2(left, fwd)
        u = self.col_of_az(az)
        v = self.cy - self.fy * up / dh
        return np.column_stack((v, u)), dh

    def col_of_az(self, az: np.ndarray) -> np.ndarray:
        """Image column of an azimuth (rad, + = left) for a pinhole view: u = cx - fx tan(az).
        Wide-angle views (``_CylinderView``) override this with their own projection."""
        p = self.pinhole
        if p is None:
            raise TypeError(f"{type(self).__name__} has no pinhole intrinsics: it must define col_of_az")
        return p.cx - p.fx * np.tan(az)

    def _sign_quad(self, sign: Sign, cx_w: float, cy_w: float, yaw: float):
        """A sign's plate seen from the camera: (its corners in transposed pixel coordinates (4, 2:
        v, u; top-left, top-right, bottom-right, bottom-left as the viewer sees them), the depth
        of its centre, True when its front faces the camera, its light gain), or None when it is
        behind or too near the camera."""
        px, py, pz = sign.plate_center
        to_cam = (cx_w - px) * math.cos(sign.facing) + (cy_w - py) * math.sin(sign.facing)
        front = to_cam > 0.0
        half = sign.size / 2.0
        rx, ry = math.cos(sign.facing + math.pi / 2.0), math.sin(sign.facing + math.pi / 2.0)
        if not front:  # seen from behind, the viewer's right is the other way
            rx, ry = -rx, -ry
        sq = np.array(
            [
                [px - rx * half, py - ry * half, pz + half],
                [px + rx * half, py + ry * half, pz + half],
                [px + rx * half, py + ry * half, pz - half],
                [px - rx * half, py - ry * half, pz - half],
            ]
        )
        pix, dep = self.project(sq, cx_w, cy_w, yaw)
        if np.any(dep < 0.05):
            return None
        _, dcen = self.project(np.array([[px, py, pz]]), cx_w, cy_w, yaw)
        g = self.gain
        gi = int((py - g.y0) / g.res)
        gj = int((px - g.x0) / g.res)
        gain = float(g.gain[gi, gj]) if 0 <= gi < g.gain.shape[0] and 0 <= gj < g.gain.shape[1] else 1.0
        return pix, float(dcen[0]), front, gain

    @staticmethod
    def _sprite_patch(pix: np.ndarray, front: bool, gain: float, rows: int, cols: int):
        """The sprite warped onto the quad ``pix`` ((4, 2) x, y in the patch's own image): a
        BGRA patch of rows x cols, its colour scaled by ``gain``."""
        s = _SPRITE
        # sprite pixel centres: corners of the octagon's square are at -0.5 and s - 0.5
        src = np.array([[-0.5, -0.5], [s - 0.5, -0.5], [s - 0.5, s - 0.5], [-0.5, s - 0.5]], np.float32)
        Hs = cv2.getPerspectiveTransform(src, pix.astype(np.float32))
        sprite = _sprites()[0 if front else 1]
        patch = cv2.warpPerspective(sprite, Hs, (cols, rows), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        if gain != 1.0:
            patch[:, :, :3] = cv2.convertScaleAbs(patch[:, :, :3], alpha=gain)
        return patch

    def _draw_sign(self, sign: Sign, cx_w: float, cy_w: float, yaw: float) -> None:
        """A sign into the transposed buffers of a cylindrical view, depth-tested."""
        q = self._sign_quad(sign, cx_w, cy_w, yaw)
        if q is None:
            return
        pix, d, front, gain = q
        box = _pixel_box(pix, self.H, self.W)
        if box is None:
            return
        x0, x1, y0, y1 = box
        # transposed image coords: x = v (image row), y = u (image column); the patch has rows =
        # image columns, like the transposed buffers
        patch = self._sprite_patch(pix - [x0, y0], front, gain, y1 - y0, x1 - x0)
        zroi = self.depth_t[y0:y1, x0:x1]
        mask = (patch[:, :, 3] > 127) & (zroi > d)
        if not mask.any():
            return
        roi = self.color4[y0:y1, x0:x1]
        roi[:, :, :3][mask] = patch[:, :, :3][mask]
        roi[:, :, 3][mask] = 255
        zroi[mask] = d

    def sign_patches(self, cx_w: float, cy_w: float, yaw: float):
        """The signs of an upright pinhole view as :func:`~qcarlab.sim._kernels.compose_rows`
        draws them: (table (n, 5) int64 of rows v0..v1, columns u0..u1 and offset into the
        pixels, depths (n,), packed pixels uint32)."""
        tabs, deps, pixs, off = [], [], [], 0
        for sign in self.world.signs:
            q = self._sign_quad(sign, cx_w, cy_w, yaw)
            if q is None:
                continue
            pix, d, front, gain = q
            uv = pix[:, ::-1]  # (u, v)
            box = _pixel_box(uv, self.W, self.H)
            if box is None:
                continue
            u0, u1, v0, v1 = box
            patch = self._sprite_patch(uv - [u0, v0], front, gain, v1 - v0, u1 - u0).astype(np.uint32)
            words = patch[:, :, 0] | (patch[:, :, 1] << 8) | (patch[:, :, 2] << 16) | (patch[:, :, 3] << 24)
            tabs.append((v0, v1, u0, u1, off))
            deps.append(d)
            pixs.append(words.reshape(-1))
            off += words.size
        if not tabs:
            return _NO_SIGNS
        return np.array(tabs, np.int64), np.array(deps, np.float64), np.ascontiguousarray(np.concatenate(pixs))


def _level_view_size(W: int, H: int, fx: float, fy: float, cx: float, cy: float, pitch: float):
    """Level-camera image bounds (u0, v0, u1, v1) covering a camera pitched down by ``pitch``."""
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    c, s = math.cos(pitch), math.sin(pitch)
    # pitched optical frame (X right, Y down, Z fwd) -> level optical frame: rotation about X
    R = np.array([[1, 0, 0], [0, c, s], [0, -s, c]])
    Hm = K @ R @ np.linalg.inv(K)
    corners = np.array([[-0.5, -0.5, 1], [W - 0.5, -0.5, 1], [W - 0.5, H - 0.5, 1], [-0.5, H - 0.5, 1]]).T
    q = Hm @ corners
    q = q[:2] / q[2]
    return q[0].min(), q[1].min(), q[0].max(), q[1].max(), Hm, R


# --------------------------------------------------------------------------------------------
# the RGBD camera
# --------------------------------------------------------------------------------------------
class _Plan:
    """What an unpitched RGBD frame's rows are drawn from, fixed when it is taken: the camera's
    pose, the noise's windows, the balls, the signs' patches, the exposure (gain and table)."""

    __slots__ = ("cam", "o", "balls", "gain", "lut", "signs", "n_layers")

    def __init__(self, cam: tuple[float, float, float], o: list[int] | None, balls: np.ndarray, gain: float):
        self.cam, self.o, self.balls, self.gain = cam, o, balls, gain
        self.lut = exposure_lut(gain) if gain != 1.0 else _NO_LUT
        self.signs = _NO_SIGNS
        self.n_layers = 0


class RowFrame:
    """An RGBD frame (:meth:`RGBDCamera.render_rows`) whose rows are drawn when first read:
    ``color_rows(a, b)`` / ``depth_rows(a, b)`` draw rows a..b-1 (both images) and return them;
    ``color`` / ``depth`` draw the rest; :meth:`whole` is the :class:`RGBDFrame`. ``shape`` is (H, W)."""

    __slots__ = ("t", "shape", "_camera", "_plan", "_finish", "_color", "_depth", "_todo")

    def __init__(self, camera: RGBDCamera, plan: _Plan, t: float, finish: Any = None):
        H, W = camera.intrinsics.height, camera.intrinsics.width
        self.t, self.shape = t, (H, W)
        self._camera, self._plan, self._finish = camera, plan, finish
        self._color = np.empty((H, W, 3), np.uint8)
        self._depth = np.empty((H, W), np.float32)
        self._todo = np.ones(H, bool)  # rows not drawn yet

    def _draw(self, a: int, b: int) -> None:
        H = self.shape[0]
        a, b = max(0, min(a, H)), max(0, min(b, H))
        todo = self._todo[a:b]
        if not todo.any():
            return
        if todo.all():
            runs = [(a, b)]
        else:  # the runs of rows not drawn yet
            edges = np.flatnonzero(np.diff(np.concatenate(([False], todo, [False])).astype(np.int8))) + a
            runs = list(zip(edges[::2].tolist(), edges[1::2].tolist()))
        assert self._plan is not None and self._camera is not None
        for s, e in runs:
            self._camera._draw_rows(self._plan, self._color, self._depth, s, e)
            if self._finish is not None:
                self._finish(self._color[s:e])
        todo[:] = False
        if not self._todo.any():  # all drawn: the camera and the plan are not needed any more
            self._camera = self._plan = self._finish = None

    def color_rows(self, a: int, b: int) -> np.ndarray:
        """Rows ``a:b`` of the colour image (a slice's meaning: negative counts from the bottom)."""
        a, b, _ = slice(a, b).indices(self.shape[0])
        self._draw(a, b)
        return self._color[a:b]

    def depth_rows(self, a: int, b: int) -> np.ndarray:
        """Rows ``a:b`` of the depth image (as :meth:`color_rows`)."""
        a, b, _ = slice(a, b).indices(self.shape[0])
        self._draw(a, b)
        return self._depth[a:b]

    @property
    def color(self) -> np.ndarray:
        self._draw(0, self.shape[0])
        return self._color

    @property
    def depth(self) -> np.ndarray:
        self._draw(0, self.shape[0])
        return self._depth

    def whole(self) -> RGBDFrame:
        """The whole frame (every row drawn) as an :class:`RGBDFrame`."""
        self._draw(0, self.shape[0])
        return RGBDFrame(t=self.t, color=self._color, depth=self._depth)


class RGBDCamera:
    """The Intel D435 at its mount: ``render(pose, t)`` -> :class:`~qcarlab.sensors.RGBDFrame`."""

    def __init__(self, world: World | str, params: QCarParams = DEFAULT_PARAMS, rng: np.random.Generator | None = None):
        self.world = world if isinstance(world, World) else load_world(world, params)
        self.params = params
        p = params
        W, H = int(p.rgbd_width), int(p.rgbd_height)
        f = (H / 2.0) / math.tan(p.rgbd_vfov / 2.0)
        self.intrinsics = CameraIntrinsics(fx=f, fy=f, cx=(W - 1) / 2.0, cy=(H - 1) / 2.0, width=W, height=H)
        self.pitch = float(p.rgbd_pitch)
        intr = self.intrinsics
        if abs(self.pitch) < 1e-9:
            level = intr
            self._rot = None
        else:
            u0, v0, u1, v1, Hm, R = _level_view_size(W, H, intr.fx, intr.fy, intr.cx, intr.cy, self.pitch)
            a0, b0 = int(math.floor(u0)) - 1, int(math.floor(v0)) - 1
            lw, lh = int(math.ceil(u1)) + 2 - a0, int(math.ceil(v1)) + 2 - b0
            level = CameraIntrinsics(intr.fx, intr.fy, intr.cx - a0, intr.cy - b0, lw, lh)
            # pitched pixel -> level pixel (for remapping), and the depth factor z_p = z_l / (R r)_z
            T = np.array([[1, 0, -a0], [0, 1, -b0], [0, 0, 1.0]])
            self._rot = T @ Hm
            us, vs = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
            rz = R[2, 0] * (us - intr.cx) / intr.fx + R[2, 1] * (vs - intr.cy) / intr.fy + R[2, 2]
            self._depth_factor = (1.0 / rz).astype(np.float32)
        self._level = level
        u = np.arange(level.width, dtype=np.float64)
        xn = (u - level.cx) / level.fx
        self._view = _ColumnView(
            self.world, (p.rgbd_x, 0.0, p.rgbd_z, 0.0), np.arctan(-xn), np.sqrt(1.0 + xn * xn),
            level.fy, level.cy, level.height, level,
        )
        self.rng = rng
        self._noise = _Noise(rng, H, W, COLOR_NOISE_SD, True) if rng is not None else None
        self._color4 = np.empty((level.height, level.width, 4), np.uint8)  # the level view, upright
        self._color4_u32 = self._color4.view(np.uint32).reshape(level.height, level.width)
        # what compose_rows reads that the pose does not change
        lw, lh = level.width, level.height
        rows = np.arange(lh, dtype=np.float64)
        self._rowf = np.where(rows > level.cy, level.fy / np.maximum(rows - level.cy, 1e-9), 0.0)
        self._floor = self._view.floor
        # the layers column_layers writes (see there), and the first floor row of each column
        n = _kernels.LMAX
        self._ltop, self._lbot, self._lball = (np.empty((n, lw), np.int32) for _ in range(3))
        self._lcol = np.empty((n, lw), np.uint32)
        self._lza, self._lzb, self._lbd, self._lbe, self._lbg = (np.empty((n, lw), np.float32) for _ in range(5))
        self._lrange = np.empty((n, 4), np.int64)
        self._flo = np.empty(lw, np.int32)
        r = self._view.raster
        #: find walls and obstacles per polygon edge (True: no ROS grid among the shapes) or by
        #: marching the raster (see _kernels.column_layers)
        self.vector_walls = not bool(len(r.kinds) and r.kinds[0] == raster_kinds.KIND_GRID)
        self._edges = _kernels.edge_table(r.kinds, r.poly_start, r.poly_count, r.verts)
        self._cr_t = np.empty((lw, _kernels.CMAX), np.float64)  # scratch of vector_crossings
        self._cr_e = np.empty((lw, _kernels.CMAX), np.int64)
        self._ncr = np.empty(lw, np.int64)
        self._layers_of: _Plan | None = None  # the frame whose layers are in the buffers above

    @property
    def rate(self) -> float:
        return self.params.rgbd_rate

    def camera_pose(self, pose: tuple[float, float, float]) -> tuple[float, float, float]:
        """The camera's (x, y, yaw) in the world for a car pose."""
        return self._view.camera_pose(pose)

    def render(self, pose: tuple[float, float, float], t: float = 0.0, gain: float = 1.0) -> RGBDFrame:
        """The colour image (BGR uint8) and aligned depth (float32 m, 0 = none) seen from ``pose``.

        ``gain``: the auto-exposure's (:class:`~qcarlab.sim.realism.CameraEffects`), applied
        where the colours are drawn (saturate(rint(gain c)) per channel, the numbers of
        ``cv2.convertScaleAbs``), before the sensor's noise: a frame with a gain costs what one
        without does (a pass of its own over the frame took 0.1 ms). Without noise the frame is
        exactly the ungained frame through ``convertScaleAbs``."""
        if self._rot is None:  # (render_rows' frame drawn whole at once, without its row bookkeeping)
            H, W = self.intrinsics.height, self.intrinsics.width
            color, depth = np.empty((H, W, 3), np.uint8), np.empty((H, W), np.float32)
            self._draw_rows(self._plan(pose, t, gain), color, depth, 0, H)
            return RGBDFrame(t=float(t), color=color, depth=depth)
        gain = float(gain)
        v = self._view
        cx_w, cy_w, yaw = v.camera_pose(pose)
        W, H = self.intrinsics.width, self.intrinsics.height
        o = self._noise.windows() if self._noise is not None else None
        balls = v.balls_at(t)
        layers = (self._columns(cx_w, cy_w, yaw, balls), balls)
        signs = v.sign_patches(cx_w, cy_w, yaw)
        lv = self._level
        depth = np.empty((lv.height, lv.width), np.float32)
        # pitched: the level view upright, then rotated
        self._compose(depth, (cx_w, cy_w, yaw), layers, signs, None, 0, lv.height)
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        c4 = cv2.warpPerspective(self._color4, self._rot, (W, H), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        color = cv2.cvtColor(c4, cv2.COLOR_BGRA2BGR)
        if gain != 1.0:  # after the rotation's blending, as on an unpitched frame's colours
            cv2.convertScaleAbs(color, dst=color, alpha=gain)
        if o is not None:
            assert self._noise is not None
            self._noise.color(color, o)
        depth = cv2.warpPerspective(depth, self._rot, (W, H), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                    borderMode=cv2.BORDER_REPLICATE)
        depth = cv2.multiply(depth, self._depth_factor)
        self._finish_depth(depth, o)
        return RGBDFrame(t=float(t), color=color, depth=depth)

    def render_rows(self, pose: tuple[float, float, float], t: float = 0.0, gain: float = 1.0,
                    finish: Any = None) -> RowFrame | RGBDFrame:
        """:meth:`render`'s frame, its rows drawn when first read (:class:`RowFrame`): a reader of
        some rows (the lane lab's band, its obstacle window) pays for those alone; the pixels are
        :meth:`render`'s. ``finish(color_rows)``: a row-wise effect on the colour (the realism
        profile's horizontal motion blur), applied to the rows as they are drawn. Everything
        random (the noise's windows) is drawn now, as :meth:`render` draws it. A pitched camera
        rotates the whole view: its frame is drawn at once (an :class:`RGBDFrame`)."""
        if self._rot is not None:
            frame = self.render(pose, t, gain)
            if finish is not None:
                finish(frame.color)
            return frame
        return RowFrame(self, self._plan(pose, t, gain), float(t), finish)

    def _plan(self, pose: tuple[float, float, float], t: float, gain: float) -> _Plan:
        """What an unpitched frame from ``pose`` at ``t`` is drawn from (:class:`_Plan`), its
        layers found (:meth:`_layers`) and the noise's windows drawn."""
        gain = float(gain)
        v = self._view
        cam = v.camera_pose(pose)
        o = self._noise.windows() if self._noise is not None else None
        plan = _Plan(cam, o, v.balls_at(t), gain)
        self._layers(plan)
        plan.signs = v.sign_patches(*cam)
        if gain != 1.0:  # the signs' colours, once (the layers' with each drawing of them: _layers)
            _kernels.gain_words(plan.signs[2], plan.lut)
        return plan

    def _layers(self, plan: _Plan) -> int:
        """The layers of every column for ``plan``'s pose (:meth:`_columns`, their colours through
        its exposure table), unless they are in the buffers already; returns how many."""
        if self._layers_of is not plan:
            plan.n_layers = self._columns(*plan.cam, plan.balls)
            if plan.gain != 1.0:
                _kernels.gain_words(self._lcol[: plan.n_layers].reshape(-1), plan.lut)
            self._layers_of = plan
        return plan.n_layers

    def _draw_rows(self, plan: _Plan, color: np.ndarray, depth: np.ndarray, a: int, b: int) -> None:
        """Rows a..b of ``plan``'s (unpitched) frame, done, into ``color`` and ``depth``."""
        layers = (self._layers(plan), plan.balls)
        self._rows(color, depth, plan.cam, layers, plan.signs, plan.o, (plan.gain, plan.lut), a, b)

    def _columns(self, cx_w: float, cy_w: float, yaw: float, balls: np.ndarray) -> int:
        """The layers of every column (:func:`~qcarlab.sim._kernels.column_layers`); returns how many."""
        v = self._view
        r, g = v.raster, v.gain
        return _kernels.column_layers(
            self._ltop, self._lbot, self._lcol, self._lza, self._lzb, self._lball, self._lbd, self._lbe, self._lbg,
            self._lrange, self._flo, v.r0, v.H, cx_w, cy_w, v.cam_z, yaw, v.cos_c, v.sin_c, v.k,
            self._level.fx, self._level.cx, v.fy, v.cy, MAX_VIEW_DIST, r.x0, r.y0, r.res, r.cells, r.kinds, r.heights,
            r.colors, r.poly_start, r.poly_count, r.verts, r.circles, g.gain, g.x0, g.y0, g.res, balls,
            LIGHT_DIR[0], LIGHT_DIR[1], self.vector_walls, self._edges, self._cr_t, self._cr_e, self._ncr,
        )

    def _compose(self, depth, cam, layers: tuple[int, np.ndarray], signs, o: list[int] | None, a: int, b: int,
                 bgr: np.ndarray = _NO_BGR, gain: tuple[float, np.ndarray] = (1.0, _NO_LUT)) -> None:
        """Rows a..b of the level view into ``_color4`` and ``depth``
        (:func:`~qcarlab.sim._kernels.compose_rows`); unpitched, the depth finished too (range
        limits, and noise in the windows ``o`` unless None). A pitched view's depth is finished
        after the rotation. With ``bgr`` (the frame's colour as (H, 3 W) bytes) the colour goes
        there instead of ``_color4``, with its noise (windows ``o``). ``gain``: the exposure and its
        table (:func:`exposure_lut`; see
        :meth:`render`; the layers' and signs' colours carry it already)."""
        v, fl, lv = self._view, self._floor, self._level
        finish = self._rot is None
        dn, na, nb = self._depth_noise(o if finish else None)
        cn, ca, cb = (self._noise.tile, o[0], o[1]) if o is not None and self._noise is not None else (_NO_CNOISE, 0, 0)
        cx_w, cy_w, yaw = cam
        n_layers, balls = layers
        g, lut = gain
        _kernels.compose_rows(
            self._color4_u32, depth, a, b, v.r0, v.bg_packed, v.row_depth, self._rowf,
            fl.texels, fl.squares, fl.levels, v.row_lev, v.row_dist, cx_w, cy_w, yaw, lv.fx, lv.cx, fl.x0, fl.y1, fl.ppm, self._flo,
            n_layers, self._ltop, self._lbot, self._lcol, self._lza, self._lzb, self._lrange, self._lball, self._lbd,
            self._lbe, self._lbg, balls, v.k, v.cam_z, v.fy, v.cy, signs[0], signs[1], signs[2],
            finish, dn, na, nb, DEPTH_NOISE * DEPTH_TILE_STEP, RGBD_MIN_DEPTH, float(self.params.rgbd_max_depth), bgr,
            cn, ca, cb, lut, g,
        )

    def _rows(self, color: np.ndarray, depth: np.ndarray, cam, layers: tuple[int, np.ndarray], signs, o: list[int] | None,
              gain: tuple[float, np.ndarray], a: int, b: int) -> None:
        """Rows a..b of an unpitched frame, done: composed and finished into ``color`` (BGR, the
        colour noise and exposure on) and ``depth``."""
        self._compose(depth, cam, layers, signs, o, a, b, color.reshape(color.shape[0], -1), gain)

    def _depth_noise(self, o: list[int] | None) -> tuple[np.ndarray, int, int]:
        if o is None:
            return _NO_NOISE, 0, 0
        assert self._noise is not None and self._noise.depth is not None
        return self._noise.depth, o[4], o[5]

    def _finish_depth(self, depth: np.ndarray, o: list[int] | None) -> None:
        """The depth image as the D435 reports it: inf -> 0 (no data), noise sigma
        DEPTH_NOISE z^2 (windows ``o``, None = no noise), 0 beyond the range and too near."""
        tile, na, nb = self._depth_noise(o)
        _kernels.finish_depth(depth, tile, na, nb, DEPTH_NOISE * DEPTH_TILE_STEP, RGBD_MIN_DEPTH,
                              float(self.params.rgbd_max_depth))


# --------------------------------------------------------------------------------------------
# the CSI cameras
# --------------------------------------------------------------------------------------------
CSI_ORDER = ("right", "rear", "left", "front")


class _CylinderView(_ColumnView):
    def __init__(self, world: World, mount, half_az: float, half_tan: float, f: float):
        W = int(math.ceil(2.0 * half_az * f))
        H = int(math.ceil(2.0 * half_tan * f))
        self.az0 = half_az
        self.f_az = (W - 1) / (2.0 * half_az)  # columns per radian
        az = half_az - np.arange(W) / self.f_az
        super().__init__(world, mount, az, np.ones(W), f, (H - 1) / 2.0, H, None, tex_level=1)

    def col_of_az(self, az: np.ndarray) -> np.ndarray:
        return (self.az0 - az) * self.f_az


class CSICameras:
    """The four 160 deg CSI cameras: ``render(pose, t)`` -> :class:`~qcarlab.sensors.CSIFrames`."""

    def __init__(self, world: World | str, params: QCarParams = DEFAULT_PARAMS, rng: np.random.Generator | None = None):
        self.world = world if isinstance(world, World) else load_world(world, params)
        self.params = params
        p = params
        W, H = int(p.csi_width), int(p.csi_height)
        self.width, self.height = W, H
        self.f = (W / 2.0) / (p.csi_fov / 2.0)  # equidistant fisheye: r = f * theta (px/rad)
        cx, cy = (W - 1) / 2.0, (H - 1) / 2.0
        # rays of every fisheye pixel in the optical frame (X right, Y down, Z forward)
        us, vs = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
        du, dv = us - cx, vs - cy
        r = np.hypot(du, dv)
        th = r / self.f
        phi = np.arctan2(dv, du)
        X, Y, Z = np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)
        az = np.arctan2(-X, Z)  # left positive
        tan_el = -Y / np.hypot(X, Z)
        half_az = float(np.abs(az).max()) + 0.02
        half_tan = float(np.abs(tan_el).max()) + 0.02
        fc = self.f * CSI_OVERSAMPLE
        mounts = csi_mounts(p)
        self._views = {name: _CylinderView(self.world, mounts[name], half_az, half_tan, fc) for name in CSI_ORDER}
        v0 = self._views["front"]
        # fisheye pixel -> transposed cylinder pixel: x = cylinder row, y = cylinder column
        map_x = (v0.cy - v0.fy * tan_el).astype(np.float32)
        map_y = v0.col_of_az(az).astype(np.float32)
        self._m1, self._m2 = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
        self.rng = rng
        self._noise = _Noise(rng, H, W, COLOR_NOISE_SD, False) if rng is not None else None

    @property
    def rate(self) -> float:
        return self.params.csi_rate

    def render_one(self, name: str, pose: tuple[float, float, float], t: float = 0.0) -> np.ndarray:
        """One view (``right``, ``rear``, ``left`` or ``front``) as BGR uint8 (height, width, 3)."""
        v = self._views[name]
        v.draw(pose, t)
        img = cv2.cvtColor(cv2.remap(v.color4, self._m1, self._m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE),
                           cv2.COLOR_BGRA2BGR)
        if self._noise is not None:
            self._noise.color(img, self._noise.windows())
        return img

    def render(self, pose: tuple[float, float, float], t: float = 0.0) -> CSIFrames:
        """The four views at once, in the sheet's order right, rear, left, front."""
        imgs = [self.render_one(n, pose, t) for n in CSI_ORDER]
        return CSIFrames(float(t), *imgs)


def stitch_panorama(frames: CSIFrames | list[np.ndarray]) -> np.ndarray:
    """The four CSI views side by side in the sheet's order: right | rear | left | front."""
    imgs = frames.as_list() if isinstance(frames, CSIFrames) else list(frames)
    if len(imgs) != 4:
        raise ValueError(f"expected 4 views (right, rear, left, front), got {len(imgs)}")
    h = min(i.shape[0] for i in imgs)
    return np.hstack([i[:h] for i in imgs])
