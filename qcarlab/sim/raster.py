"""Rasters the sensors precompute once per world: the floor texture, brightness, occupancy + labels.

- :func:`draw_floor`: the floor seen from above (markings, regions' brightness) as a BGR image;
  the cameras sample it, the top-down render starts from it.
- :func:`build_raster`: the static shapes as a label grid (cell -> index of the shape covering it,
  -1 = free) with a distance transform (distance in cells from each free cell to the nearest
  occupied one) so a ray can skip empty space, both in one uint16 a cell for the kernels
  (:func:`cell_map`; a ROS map's walls alone also as one-byte 8 x 8 tiles, :func:`tile_map`),
  plus per-shape tables (kind, height, colour, polygon vertices or circle) so a hit can be
  refined to the exact surface.

Raster cells: cell (row, col) covers x in [x0 + col res, x0 + (col + 1) res) and
y in [y0 + row res, y0 + (row + 1) res): row 0 is the *bottom* (y grows with the row), unlike
images. ROS maps keep their own cells; vector worlds are drawn at :data:`RASTER_RES`.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import pickle
import shutil
import sys
import tempfile
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from qcarlab.errors import InputError
from qcarlab.sim import _kernels
from qcarlab.sim.world import Solid, World

RASTER_RES = 0.005  # m, cell size of vector worlds' rasters (coarsened to stay under MAX_RASTER_CELLS)
MAX_RASTER_CELLS = 6_000_000
MAX_TEXTURE_PIXELS = 9_000_000  # the floor texture is coarsened past this (large ROS maps)
BRIGHTNESS_RES = 0.05  # m, cell size of the brightness grid
_SHIFT = 4  # fractional bits for cv2 drawing
_ONE = 1 << _SHIFT

KIND_GRID, KIND_POLYGON, KIND_CIRCLE = 0, 1, 2


def _fixed(pts: np.ndarray) -> np.ndarray:
    return np.round(pts * _ONE).astype(np.int32)


# --------------------------------------------------------------------------------------------
# floor texture
# --------------------------------------------------------------------------------------------
def _dash(points: np.ndarray, closed: bool, paint: float, gap: float) -> list[np.ndarray]:
    """Cut a polyline into dashes of length ``paint`` separated by ``gap`` (along its length)."""
    pts = np.vstack([points, points[:1]]) if closed else points
    seg = np.diff(pts, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    total = cum[-1]
    out = []
    s = 0.0
    while s < total:
        e = min(s + paint, total)
        ss = np.concatenate([[s], cum[(cum > s) & (cum < e)], [e]])
        xs = np.interp(ss, cum, pts[:, 0])
        ys = np.interp(ss, cum, pts[:, 1])
        out.append(np.column_stack((xs, ys)))
        s += paint + gap
    return out


def draw_floor(world: World, px_per_m: float) -> tuple[np.ndarray, tuple[float, float, float]]:
    """The floor texture: (BGR uint8 image, (x0, y1, px_per_m)); see :func:`floor_texture`."""
    fw, fh = world.floor_size
    ppm = float(px_per_m)
    if fw * fh * ppm * ppm > MAX_TEXTURE_PIXELS:
        ppm = math.sqrt(MAX_TEXTURE_PIXELS / (fw * fh))
    w, h = max(1, int(math.ceil(fw * ppm))), max(1, int(math.ceil(fh * ppm)))
    x0, y0 = world.floor_origin
    y1 = y0 + fh
    img = np.empty((h, w, 3), np.uint8)
    img[:] = world.floor_color

    def px(p: np.ndarray) -> np.ndarray:
        return _fixed(np.column_stack(((p[:, 0] - x0) * ppm - 0.5, (y1 - p[:, 1]) * ppm - 0.5)))

    if world.grid is not None:
        g = world.grid
        # unknown cells a little darker, occupied cells (seen from above) in the wall colour
        shade = np.zeros(g.occupied.shape, np.uint8)
        shade[g.unknown] = 1
        shade[g.occupied] = 2
        shade = cv2.resize(shade[::-1], (w, h), interpolation=cv2.INTER_NEAREST)
        img[shade == 1] = (np.array(world.floor_color) * 0.8).astype(np.uint8)
        img[shade == 2] = g.wall_color

    for m in world.markings:
        color = tuple(int(c) for c in m.color)
        if m.filled:
            cv2.fillPoly(img, [px(m.points)], color, cv2.LINE_AA, _SHIFT)
            continue
        thick = max(1, int(round(m.width * ppm)))
        pieces = _dash(m.points, m.closed, *m.dash) if m.dash else [m.points]
        closed = m.closed and not m.dash
        for piece in pieces:
            cv2.polylines(img, [px(piece)], closed, color, thick, cv2.LINE_AA, _SHIFT)

    if world.regions:
        gain = np.ones((h, w), np.float32)
        for r in world.regions:
            cv2.fillPoly(gain, [px(r.polygon)], float(r.brightness), cv2.LINE_8, _SHIFT)
        img = cv2.convertScaleAbs(img.astype(np.float32) * gain[:, :, None])
    return img, (x0, y1, ppm)


def floor_pyramid(world: World, px_per_m: float, levels: int = 6) -> tuple[list[np.ndarray], tuple[float, float, float]]:
    """The floor texture as BGRA (alpha 255) and its ``cv2.pyrDown`` levels (cached on the world).

    Returns (levels, (x0, y1, px_per_m)); level L pixel i is centred on level-0 pixel i * 2^L.
    Four channels because OpenCV's warps and remaps have fast paths for them (about 2.5 x those
    of three).
    """
    key = ("floor_pyramid", float(px_per_m), int(levels))
    if key in world._cache:
        return world._cache[key]
    tex, frame = floor_texture(world, px_per_m)
    out = [cv2.cvtColor(tex, cv2.COLOR_BGR2BGRA)]
    for _ in range(levels - 1):
        if min(out[-1].shape[:2]) < 8:
            break
        out.append(cv2.pyrDown(out[-1]))
    world._cache[key] = (out, frame)
    return out, frame


@dataclass(frozen=True)
class FloorRuns:
    """The floor pyramid as the RGBD kernel samples it (see :func:`floor_runs`)."""

    texels: np.ndarray  # uint32, every level's packed BGR texels one after the other, row-major
    levels: np.ndarray  # int64 (L, 3): offset into texels, width, height of each level
    x0: float  # level 0's frame, as floor_texture's: texel (col, row) centred on
    y1: float  # x = x0 + (col + 0.5) / ppm, y = y1 - (row + 0.5) / ppm
    ppm: float
    #: uint8 (4, len(texels)): for each block the side of the largest square of uniform blocks
    #: with that block at a corner, toward -col when bit 0 of the first index is set (else
    #: +col) and toward -row when bit 1 is (:func:`run_squares`); the kernel reads the one its
    #: row's direction moves into
    squares: np.ndarray


def run_radii(tex: np.ndarray) -> np.ndarray:
    """How far a bilinear sample may move and still read one colour: R[j, i] (uint8, <= 255).

    Block (i, j) is the 2 x 2 texels (i..i+1, j..j+1) a bilinear sample with floor(x) = i,
    floor(y) = j reads; it is *uniform* when its four texels are equal (the sample is then that
    colour exactly, whatever its weights). R is the Chebyshev distance (in blocks) from block
    (i, j) to the nearest block that is not uniform; blocks on the texture's edge rows and
    columns count as not uniform (their samples read the border), so R = 0 there. Every block
    within R - 1 of a block with R >= 1 is uniform, and overlapping uniform blocks share texels:
    all samples whose block is within R - 1 of (i, j) read the colour of texel (i, j).
    """
    h, w = tex.shape[:2]
    p = tex.view(np.uint32).reshape(h, w) if tex.ndim == 3 else tex
    uni = np.zeros((h, w), np.uint8)
    if h >= 2 and w >= 2:
        a = p[:-1, :-1]
        same = (a == p[:-1, 1:]) & (a == p[1:, :-1]) & (a == p[1:, 1:])
        uni[:-1, :-1] = same
    uni[0, :] = 0
    uni[:, 0] = 0
    uni[-1, :] = 0
    uni[:, -1] = 0
    if not uni.any():
        return uni
    dist = cv2.distanceTransform(uni, cv2.DIST_C, 3)
    return np.minimum(dist, 255).astype(np.uint8)


def run_squares(radii: np.ndarray) -> np.ndarray:
    """For each block, the side (in blocks, <= 255) of the largest square of uniform blocks
    (``radii`` > 0, :func:`run_radii`) with that block at its corner, extending toward +col and
    +row: (4, h, w) uint8, index q for the square toward -col (bit 0 of q) and -row (bit 1).

    A sample moving along a row of a level camera stays in such a square, so reads one colour,
    until it has moved that many blocks along either axis; in a run of uniform blocks the square
    ahead of the sample reaches the next non-uniform block at once, where :func:`run_radii`'s
    square centred on it grows one doubling at a time from the block's last edge (about 2.3
    times as many runs over the track's floor). S = 1 + min(right, below, below-right) for a
    uniform block, 0 else: row by row from the far side, each row's recurrence along the row
    solved as a running minimum (numpy, no per-block Python)."""
    uni = radii > 0
    h, w = uni.shape
    out = np.zeros((4, h, w), np.uint8)
    idx = np.arange(w, dtype=np.int32)
    for q in range(4):
        u = uni[:: -1 if q & 2 else 1, :: -1 if q & 1 else 1]
        s = np.zeros((h + 1, w + 1), np.int32)  # a row and a column of zeros beyond the far side
        for j in range(h - 1, -1, -1):
            below = s[j + 1]
            t = np.minimum(below[:-1], below[1:])
            # S[i] = min over i' >= i of c[i'] - i, c = t + 1 + i' (uniform) or i' (not): the
            # recurrence S[i] = min(t[i] + 1, S[i + 1] + 1) unrolled up to the next non-uniform
            c = np.where(u[j], t + 1 + idx, idx)
            m = np.minimum.accumulate(c[::-1])[::-1]
            s[j, :w] = np.where(u[j], m - idx, 0)
        sq = np.minimum(s[:h, :w], 255).astype(np.uint8)
        out[q] = sq[:: -1 if q & 2 else 1, :: -1 if q & 1 else 1]
    return out


def floor_runs(world: World, px_per_m: float, levels: int = 6) -> FloorRuns:
    """The floor pyramid (:func:`floor_pyramid`) packed for the RGBD kernel (cached on the world):
    each texel one uint32 whose low three bytes are B, G, R and whose top byte is the run radius
    of its block (:func:`run_radii`), all levels in one array. A row of a level camera's floor is
    a straight line through the texture, so where the radius allows the kernel fills a run of
    pixels with one colour instead of blending each (the same result as blending them)."""
    key = ("floor_runs", float(px_per_m), int(levels))
    if key not in world._cache:
        inputs = (world.floor_size, world.floor_origin, world.floor_color, world.markings, world.regions, world.grid)
        world._cache[key] = on_disk(FloorRuns, key, inputs, lambda: _floor_runs(world, px_per_m, levels))
    return world._cache[key]


def _floor_runs(world: World, px_per_m: float, levels: int) -> FloorRuns:
    pyr, (x0, y1, ppm) = floor_pyramid(world, px_per_m, levels)
    parts, squares, table, off = [], [], [], 0
    for lev in pyr:
        h, w = lev.shape[:2]
        b = lev.astype(np.uint32)  # as integers (B | G << 8 | R << 16), whatever the byte order
        words = b[:, :, 0] | (b[:, :, 1] << 8) | (b[:, :, 2] << 16)
        r = run_radii(words)
        parts.append((words | (r.astype(np.uint32) << 24)).reshape(-1))
        squares.append(run_squares(r).reshape(4, -1))
        table.append((off, w, h))
        off += w * h
    out = FloorRuns(np.ascontiguousarray(np.concatenate(parts)), np.array(table, np.int64).reshape(-1, 3),
                    float(x0), float(y1), float(ppm), np.ascontiguousarray(np.concatenate(squares, axis=1)))
    return out


# --------------------------------------------------------------------------------------------
# the rasters on disk: a world's are drawn once per machine, not once per run
# --------------------------------------------------------------------------------------------
CACHE_ENV = "QCARLAB_CACHE"  #: a folder for the cache ("off": none); default ~/.cache/qcarlab
KEEP = 48  #: entries kept on disk (a floor is about 17 MB, a raster 2-9 MB), the most recently made
#: kinds of entries kept in a pool of their own, and how many: a camera's noise tiles (1.5 MB, one
#: per seed used) never push a world's floor or raster out
OWN_POOL = {"noise": 16}


def _pool(kind: str) -> str | None:
    """The pool an entry of ``kind`` is counted in: its own (:data:`OWN_POOL`), else None (the worlds')."""
    return kind if kind in OWN_POOL else None


def cache_folder() -> Path | None:
    where = os.environ.get(CACHE_ENV, "")
    if where.lower() == "off":
        return None
    if where:
        return Path(where)
    base = os.environ.get("XDG_CACHE_HOME") or (Path.home() / ".cache")
    return Path(base) / "qcarlab"


def on_disk(cls: type, key: tuple, inputs: tuple, build: Any) -> Any:
    """``build()`` (a dataclass of arrays and numbers, ``cls``), kept in :func:`cache_folder` under
    a hash of ``key``, ``inputs`` (what it is made from: the world's parts it reads) and the
    source of the code that makes it (this module and the world's) and qcarlab's version, so a
    change of any of them makes it anew.

    An entry is a folder of one ``.npy`` file a field (no pickle), made in a scratch folder and
    renamed into place whole. It is read back memory-mapped copy-on-write: a run reads only the
    pages it touches (a floor is some 35 MB, of which a camera sees a part), and its arrays are
    ordinary writable ndarrays to numba and numpy (an ``.npz`` was read whole through zipfile's
    checksum: 0.1-0.25 s a run). An entry that cannot be read is made again; without a writable
    folder, made each time as before."""
    folder = cache_folder()
    if folder is None:
        return build()
    try:
        path = folder / f"{key[0]}-{_fingerprint(key, inputs)}"
    except (TypeError, pickle.PicklingError):
        return build()
    names = [f.name for f in fields(cls)]
    try:
        got = {}
        for name in names:
            a = np.asarray(np.load(path / f"{name}.npy", mmap_mode="c", allow_pickle=False))
            got[name] = a if a.ndim else a.item()
        return cls(**got)
    except (OSError, ValueError, TypeError, EOFError):  # not made yet, or damaged: made (and written) again
        shutil.rmtree(path, ignore_errors=True)
    out = build()
    tmp = None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key[0]}-", dir=folder))
        for name in names:
            np.save(tmp / f"{name}.npy", np.asarray(getattr(out, name)), allow_pickle=False)
        try:
            os.rename(tmp, path)  # whole or not at all; another run may have put it there first
            tmp = None
        except OSError:
            pass
        pool = _pool(key[0])  # entries counted with those of their pool only
        kept = sorted((p for p in folder.iterdir() if not p.name.startswith(".")
                       and _pool(p.name.partition("-")[0]) == pool),
                      key=lambda p: p.stat().st_mtime, reverse=True)
        for old in kept[OWN_POOL.get(pool, KEEP):]:  # those of worlds (or of code) not used for a while
            shutil.rmtree(old, ignore_errors=True) if old.is_dir() else old.unlink(missing_ok=True)
    except OSError:
        pass  # a read-only or full home: made each run, as before
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return out


@functools.lru_cache(maxsize=1)
def _code_hash() -> str:
    """The hash of qcarlab's version and the source of the code that makes the cached rasters (read once)."""
    from qcarlab import __version__

    code = b"".join(Path(m.__file__).read_bytes() for m in (sys.modules[__name__], sys.modules[World.__module__]))
    return hashlib.sha256(__version__.encode() + code).hexdigest()


def _fingerprint(key: tuple, inputs: tuple) -> str:
    return hashlib.sha256(pickle.dumps((_code_hash(), key, inputs), protocol=4)).hexdigest()[:32]


@dataclass(frozen=True)
class Brightness:
    """Per-cell brightness gain (rows from the bottom, y up); 1.0 outside every region."""

    gain: np.ndarray  # float32 (ny, nx)
    x0: float
    y0: float
    res: float


def brightness_grid(world: World) -> Brightness:
    key = ("brightness",)
    if key in world._cache:
        return world._cache[key]
    xmin, ymin, xmax, ymax = world.bounds
    res = BRIGHTNESS_RES
    nx, ny = int(math.ceil((xmax - xmin) / res)) + 2, int(math.ceil((ymax - ymin) / res)) + 2
    x0, y0 = xmin - res, ymin - res
    gain = np.ones((ny, nx), np.float32)
    for r in world.regions:
        p = _fixed(np.column_stack(((r.polygon[:, 0] - x0) / res - 0.5, (r.polygon[:, 1] - y0) / res - 0.5)))
        cv2.fillPoly(gain, [p], float(r.brightness), cv2.LINE_8, _SHIFT)
    out = Brightness(gain, x0, y0, res)
    world._cache[key] = out
    return out


# --------------------------------------------------------------------------------------------
# occupancy raster with labels and a distance transform
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Raster:
    """Static shapes as cells (see the module docstring) and the tables to refine a hit exactly."""

    x0: float
    y0: float
    res: float
    label: np.ndarray  # int32 (ny, nx), -1 = free, else index into the tables
    cells: np.ndarray  # uint16 (ny, nx), what the kernels read: see cell_map()
    tiles: np.ndarray  # uint8 (8 x 8-cell tiles, flat) of a ROS map's walls alone for the LIDAR, else empty: see tile_map()
    tiles_x: int  # tiles a row
    kinds: np.ndarray  # int32 (L,): KIND_GRID, KIND_POLYGON, KIND_CIRCLE
    heights: np.ndarray  # float64 (L,) top of each shape above the floor
    colors: np.ndarray  # float32 (L, 3) BGR
    poly_start: np.ndarray  # int32 (L,) first vertex of each polygon in verts
    poly_count: np.ndarray  # int32 (L,)
    verts: np.ndarray  # float64 (V, 2)
    circles: np.ndarray  # float64 (L, 3): cx, cy, r

    @property
    def shape(self) -> tuple[int, int]:
        return self.label.shape  # type: ignore[return-value]


def cell_map(label: np.ndarray) -> np.ndarray:
    """The kernels' uint16 cell map of a label grid (-1 = free): an occupied cell holds
    ``OCC + label``; a free cell the distance from its centre to the nearest occupied cell's
    centre (the exact Euclidean distance transform) in units of ``DT_UNIT`` cells, rounded down
    and capped at ``OCC - 1`` (about 4,096 cells), so that a ray's jump is never longer than
    the true distance allows. One array of 2 bytes a cell (was two of 4): the map stays in the
    cache while a simulation also renders camera frames."""
    free = (label < 0).astype(np.uint8)
    if free.all():
        return np.full(label.shape, _kernels.OCC - 1, np.uint16)
    dt = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    q = np.floor(np.minimum(dt, (_kernels.OCC - 1) * _kernels.DT_UNIT) / _kernels.DT_UNIT).astype(np.uint16)
    return np.where(label >= 0, (label + _kernels.OCC).astype(np.uint16), q)


def tile_map(cells: np.ndarray) -> tuple[np.ndarray, int]:
    """The one-byte tiled form of a one-shape raster's cell map (the kernels' ``march_tiles``):
    8 x 8-cell tiles, row-major tiles of row-major cells, 64 bytes each (one cache line); an
    occupied cell is ``TILE_OCC``, a free cell its distance value in units of ``TILE_UNIT`` cells
    (rounded down from the cell map's, capped at 254); the edge tiles are padded with occupied
    cells that no ray reaches (it leaves the grid first). Returns (tiles, tiles a row)."""
    k = _kernels
    ny, nx = cells.shape
    occ = cells >= k.OCC
    q = np.minimum((cells.astype(np.int64) * k.DT_UNIT / k.TILE_UNIT).astype(np.int64), k.TILE_OCC - 1)
    c8 = np.where(occ, k.TILE_OCC, q).astype(np.uint8)
    ty, tx = (ny + 7) // 8, (nx + 7) // 8
    pad = np.full((ty * 8, tx * 8), k.TILE_OCC, np.uint8)
    pad[:ny, :nx] = c8
    return np.ascontiguousarray(pad.reshape(ty, 8, tx, 8).transpose(0, 2, 1, 3)).reshape(-1), tx


def build_raster(world: World, z: float | None = None, res: float | None = None) -> Raster:
    """The raster of the shapes a sensor sees (cached on the world).

    ``z=None``: the cameras' raster of every shape standing on the floor (walls, obstacles, sign
    posts; sign plates are drawn by the camera itself). ``z`` = a height (the LIDAR's): only the
    shapes cut by the horizontal plane at that height, sign plates included; ROS map walls always.
    """
    key = ("raster", z, res)
    if key not in world._cache:
        inputs = (world.solids, world.signs, world.grid, world.floor_size, world.floor_origin)
        world._cache[key] = on_disk(Raster, key, inputs, lambda: _build_raster(world, z, res))
    return world._cache[key]


def _build_raster(world: World, z: float | None, res: float | None) -> Raster:
    solids: list[Solid] = []
    for s in world.static_solids():
        if z is None:
            if s.z0 <= 0.0:
                solids.append(s)
        elif s.z0 <= z < s.height:
            solids.append(s)

    xmin, ymin, xmax, ymax = world.bounds
    g = world.grid
    if g is not None:
        r = g.resolution
        # align the raster to the grid's cells, grown to hold every other shape
        pad = 2
        c0 = int(math.floor((xmin - g.origin[0]) / r)) - pad
        r0 = int(math.floor((ymin - g.origin[1]) / r)) - pad
        c1 = int(math.ceil((xmax - g.origin[0]) / r)) + pad
        r1 = int(math.ceil((ymax - g.origin[1]) / r)) + pad
        nx, ny = c1 - c0, r1 - r0
        x0, y0 = g.origin[0] + c0 * r, g.origin[1] + r0 * r
    else:
        r = float(res) if res else RASTER_RES
        area = (xmax - xmin + 0.1) * (ymax - ymin + 0.1)
        if area / (r * r) > MAX_RASTER_CELLS:
            r = math.sqrt(area / MAX_RASTER_CELLS)
        nx = int(math.ceil((xmax - xmin) / r)) + 4
        ny = int(math.ceil((ymax - ymin) / r)) + 4
        x0, y0 = xmin - 2 * r, ymin - 2 * r

    label = np.full((ny, nx), -1, np.int32)
    kinds, heights, colors, pstart, pcount, circles = [], [], [], [], [], []
    verts: list[np.ndarray] = []
    nverts = 0
    if g is not None:
        gy, gx = g.occupied.shape
        rr0, cc0 = -r0, -c0  # where the grid's row/col 0 sits in the raster
        label[rr0 : rr0 + gy, cc0 : cc0 + gx][g.occupied] = 0
        kinds.append(KIND_GRID)
        heights.append(g.wall_height)
        colors.append(g.wall_color)
        pstart.append(0)
        pcount.append(0)
        circles.append((0.0, 0.0, 0.0))

    for s in solids:
        idx = len(kinds)
        kinds.append(KIND_POLYGON if s.kind == "polygon" else KIND_CIRCLE)
        heights.append(s.height)
        colors.append(s.color)
        if s.kind == "polygon":
            assert s.points is not None
            pts = s.points
            pstart.append(nverts)
            pcount.append(len(pts))
            verts.append(pts)
            nverts += len(pts)
            circles.append((0.0, 0.0, 0.0))
            cells = _fixed(np.column_stack(((pts[:, 0] - x0) / r - 0.5, (pts[:, 1] - y0) / r - 0.5)))
            cv2.fillPoly(label, [cells], idx, cv2.LINE_8, _SHIFT)
        else:
            assert s.center is not None
            pstart.append(0)
            pcount.append(0)
            circles.append((s.center[0], s.center[1], s.radius))
            c = _fixed(np.array([[(s.center[0] - x0) / r - 0.5, (s.center[1] - y0) / r - 0.5]]))[0]
            rad = max(1, int(round(s.radius / r * _ONE)))
            cv2.circle(label, (int(c[0]), int(c[1])), rad, idx, -1, cv2.LINE_8, _SHIFT)

    if len(kinds) > _kernels.MAX_LABELS:
        raise InputError(f"world {world.name!r}: {len(kinds)} shapes, more than the sensors' raster holds "
                         f"({_kernels.MAX_LABELS})")
    cells = cell_map(label)
    # a ROS map alone (coarse cells, where a 63.5-cell cap on the jumps costs nothing): tiles too
    one_grid = len(kinds) == 1 and kinds[0] == KIND_GRID
    tiles, tiles_x = tile_map(cells) if one_grid else (np.zeros(0, np.uint8), 0)
    out = Raster(
        x0=float(x0),
        y0=float(y0),
        res=float(r),
        label=label,
        cells=cells,
        tiles=tiles,
        tiles_x=tiles_x,
        kinds=np.array(kinds, np.int32),
        heights=np.array(heights, np.float64),
        colors=np.array(colors, np.float32).reshape(-1, 3),
        poly_start=np.array(pstart, np.int32),
        poly_count=np.array(pcount, np.int32),
        verts=np.vstack(verts).astype(np.float64) if verts else np.zeros((0, 2)),
        circles=np.array(circles, np.float64).reshape(-1, 3),
    )
    return out


def floor_texture(world: World, px_per_m: float = 200.0) -> tuple[np.ndarray, tuple[float, float, float]]:
    """The floor seen from above: (BGR image, (x0, y1, px_per_m)) with markings and brightness.

    Pixel (col, row) covers world x = x0 + (col + 0.5) / px_per_m, y = y1 - (row + 0.5) / px_per_m
    (row 0 is the top edge, y = y1). Cached per resolution in the world.
    """
    key = ("floor", float(px_per_m))
    if key not in world._cache:
        world._cache[key] = draw_floor(world, px_per_m)
    return world._cache[key]
