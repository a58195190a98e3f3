"""The sensors' fast paths give the numbers of their plain forms (issue 12).

- the RGBD floor: runs of one colour (the run-radius texture) read what blending every pixel reads;
- the RGBD walls found per polygon edge agree with the raster march;
- the frame's noise has the documented spread and follows the seed;
- the LIDAR's two-beams-at-a-time march gives the ranges and cell counts of one beam at a time;
- the LIDAR scanned per edge reads every beam's nearest crossing of every edge.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from qcarlab.constants import DEFAULT_PARAMS
from qcarlab.sim import _kernels
from qcarlab.sim.camera import COLOR_NOISE_SD, DEPTH_NOISE, RGBDCamera
from qcarlab.sim.lidar import Lidar
from qcarlab.sim.raster import floor_runs, run_radii, run_squares
from qcarlab.sim.world import load_world, world_from_dict

P = DEFAULT_PARAMS
EAST = (0.0, 0.0, 0.0)


def _blend_all(tex: np.ndarray, tw: int, th: int, X: np.ndarray, Y: np.ndarray, bg: int) -> np.ndarray:
    """Bilinear samples at 16.16 fixed-point texel positions, every pixel blended (numpy)."""
    ix, iy = X >> 16, Y >> 16
    wx, wy = (X >> 8) & 255, (Y >> 8) & 255
    words = tex.astype(np.int64)

    def at(i, j):
        ok = (i >= 0) & (j >= 0) & (i < tw) & (j < th)
        return np.where(ok, words[np.clip(j, 0, th - 1) * tw + np.clip(i, 0, tw - 1)], bg)

    out = np.array([_kernels._bilinear.py_func(int(a), int(b), int(c), int(d), int(x), int(y))
                    for a, b, c, d, x, y in zip(at(ix, iy), at(ix + 1, iy), at(ix, iy + 1), at(ix + 1, iy + 1), wx, wy)])
    return out.astype(np.uint32)


def test_run_radii_bound_uniform_blocks():
    tex = np.zeros((40, 50), np.uint32)
    tex[10:30, 20:24] = 7  # a stripe: blocks touching it are not uniform
    r = run_radii(tex)
    assert r[0].max() == 0 and r[:, 0].max() == 0 and r[-1].max() == 0 and r[:, -1].max() == 0
    assert r[15, 19] == 0 and r[15, 23] == 0  # straddling the stripe's edges
    assert r[15, 21] >= 1  # inside the stripe
    # every block within R - 1 of a block with radius R is uniform
    ys, xs = np.nonzero(r)
    for y, x in zip(ys[::37], xs[::37]):
        k = int(r[y, x]) - 1
        assert (r[max(y - k, 0) : y + k + 1, max(x - k, 0) : x + k + 1] > 0).all()


def test_run_squares_are_the_largest_uniform_squares_at_each_corner():
    rng = np.random.default_rng(5)
    r = (rng.random((30, 41)) < 0.93).astype(np.uint8)
    r[:, 0] = r[0] = 0
    sq = run_squares(r)
    for q in range(4):
        sx, sy = (-1 if q & 1 else 1), (-1 if q & 2 else 1)
        for y in range(30):
            for x in range(41):
                def uniform(s):  # the s x s blocks from (x, y) toward q's corner, all inside and uniform
                    xs, ys = x + sx * np.arange(s), y + sy * np.arange(s)
                    if xs.min() < 0 or ys.min() < 0 or xs.max() >= 41 or ys.max() >= 30:
                        return False
                    return bool((r[np.ix_(ys, xs)] > 0).all())
                s = int(sq[q, y, x])
                assert (s == 0 or uniform(s)) and not uniform(s + 1), (q, x, y, s)


@pytest.mark.parametrize("world", ["track", "stop-sign"])
def test_floor_runs_read_what_blending_reads(world):
    w = load_world(world)
    fl = floor_runs(w, 200.0)
    rng = np.random.default_rng(3)
    W = 640
    scratch = [np.empty(W, np.int64) for _ in range(7)]
    for lev in range(len(fl.levels)):
        off, tw, th = (int(v) for v in fl.levels[lev])
        tex = fl.texels[off : off + tw * th]
        for _ in range(12):
            # a row's samples: a line through the texture at a random angle and scale (magnified
            # and minified), starting anywhere, also off the texture's edges
            X0 = int(rng.uniform(-20, tw + 20) * 65536)
            Y0 = int(rng.uniform(-20, th + 20) * 65536)
            step = rng.uniform(0.05, 1.5) * 65536
            ang = rng.uniform(-math.pi, math.pi)
            dX, dY = int(step * math.cos(ang)), int(step * math.sin(ang))
            crow = np.zeros(W, np.uint32)
            flo = np.zeros(W, np.int32)
            sq = fl.squares[(1 if dX < 0 else 0) | (2 if dY < 0 else 0)]  # the quadrant the row moves into
            _kernels._floor_row(crow, 0, flo, fl.texels, sq, off, tw, th, X0, dX, Y0, dY, 0x00404040, *scratch,
                                np.zeros(0, np.int64), 1.0)
            u = np.arange(W, dtype=np.int64)
            want = _blend_all(tex, tw, th, X0 + u * dX, Y0 + u * dY, 0x00404040)
            # the top byte is alpha (set), the colour bytes must agree exactly
            assert np.array_equal(crow & 0x00FFFFFF, want & 0x00FFFFFF)


def _room():
    return world_from_dict({
        "floor": {"size": [9, 9], "color": "gray"},
        "walls": [{"points": [[-4, -4], [4, -4], [4, 4], [-4, 4]], "closed": True, "height": 1.0}],
        "obstacles": [
            {"shape": "box", "center": [1.5, 0.3], "size": [0.3, 0.5], "height": 0.12, "color": "red"},
            {"shape": "box", "center": [2.6, -0.6], "size": [0.4, 0.4], "height": 0.6, "color": "blue"},
            {"shape": "circle", "center": [2.0, 0.9], "radius": 0.15, "height": 0.4, "color": "green"},
            # not convex: a ray may enter and leave it twice
            {"shape": "polygon", "points": [[1.2, -1.3], [1.8, -1.3], [1.8, -0.7], [1.5, -1.0], [1.2, -0.7]],
             "height": 0.5, "color": "brown"},
        ],
        "balls": [{"start": [2.4, 0.2], "direction": "90deg", "speed": 0.0, "color": "orange"}],
    })


@pytest.mark.parametrize("pose", [EAST, (0.3, -0.2, 0.4), (-1.0, 1.0, -0.3)])
def test_walls_found_per_edge_agree_with_the_raster_march(pose):
    w = _room()
    by_edge = RGBDCamera(w)
    marched = RGBDCamera(w)
    marched.vector_walls = False
    a, b = by_edge.render(pose), marched.render(pose)
    # they differ at outlines (a pixel apart where the raster's cells round) and on faces seen at
    # grazing angles, where the march's hit misses exact()'s tolerance and shades as a grid wall
    differ = np.abs(a.color.astype(int) - b.color.astype(int)).max(axis=2) > 8
    assert differ.mean() < 0.02
    both = (a.depth > 0) & (b.depth > 0)
    assert ((a.depth > 0) != (b.depth > 0)).mean() < 0.005
    assert np.median(np.abs(a.depth[both] - b.depth[both])) < 1e-5


def test_a_box_behind_a_taller_wall_makes_no_layer():
    w = world_from_dict({
        "floor": {"size": [9, 9]},
        "walls": [{"points": [[2.0, -4], [2.0, 4]], "height": 1.0}],
        "obstacles": [{"shape": "box", "center": [3.0, 0.0], "size": [0.4, 6.0], "height": 0.3}],
    })
    cam = RGBDCamera(w)
    x, y, yaw = cam.camera_pose(EAST)
    assert cam._columns(x, y, yaw, cam._view.balls_at(0.0)) == 1  # the wall alone


def test_frame_noise_spread_and_seed():
    w = world_from_dict({"floor": {"size": [9, 9], "color": "gray"},
                         "walls": [{"points": [[2.05, -4], [2.05, 4]], "height": 1.0, "color": "gray"}]})
    clean = RGBDCamera(w).render(EAST)
    f1 = RGBDCamera(w, rng=np.random.default_rng(9)).render(EAST)
    f2 = RGBDCamera(w, rng=np.random.default_rng(9)).render(EAST)
    f3 = RGBDCamera(w, rng=np.random.default_rng(10)).render(EAST)
    assert np.array_equal(f1.color, f2.color) and np.array_equal(f1.depth, f2.depth)
    assert not np.array_equal(f1.color, f3.color)
    wall = (slice(100, 200), slice(100, 540))  # the wall's face, 2 - rgbd_x metres away
    z = 2.0 - P.rgbd_x
    dz = f1.depth[wall] - clean.depth[wall]
    assert np.std(dz) == pytest.approx(DEPTH_NOISE * z * z, rel=0.15)
    dc = f1.color[wall].astype(float) - clean.color[wall].astype(float)
    assert np.std(dc) == pytest.approx(COLOR_NOISE_SD, rel=0.15)
    assert abs(np.mean(dc)) < 0.1 and abs(np.mean(dz)) < 0.002


@pytest.mark.parametrize("world,beams", [("track", 800), ("obstacles", 801), ("hallway", 360)])
def test_lidar_pairs_give_the_single_beam_ranges(world, beams):
    w = load_world(world)
    lidar = Lidar(w, beams=beams)
    lidar.vector_walls = False  # the marched path (a vector world is scanned per edge by default)
    r = lidar._raster
    rng = np.random.default_rng(5)
    for _ in range(5):
        pose = (rng.uniform(-1.5, 1.5), rng.uniform(-1.0, 1.0), rng.uniform(-3, 3))
        got = lidar.true_ranges(pose)
        cells = lidar.last_cell_steps
        sx, sy, syaw = lidar.sensor_pose(pose)
        one = np.empty(1)
        want, total = np.empty(beams), 0
        for i in range(beams):
            total += _kernels.lidar_scan(
                sx, sy, syaw, lidar._cos[i : i + 1], lidar._sin[i : i + 1], P.lidar_max_range, r.x0, r.y0, r.res,
                r.cells, r.tiles, r.tiles_x, r.kinds, r.poly_start, r.poly_count, r.verts, r.circles,
                lidar._no_balls, lidar._no_noise, P.lidar_min_range, -1, one)
            want[i] = one[0]
        assert np.array_equal(got, want)
        # the same cells looked at, less the shared first look from the LIDAR's own cell
        assert cells <= total


def _every_edge(lidar: Lidar, pose) -> np.ndarray:
    """Each beam against every polygon edge and circle of the LIDAR's raster (numpy): the nearest."""
    ox, oy, yaw = lidar.sensor_pose(pose)
    e, r = lidar._edges, lidar._raster
    ang = yaw + lidar.angles
    dx, dy = np.cos(ang)[:, None], np.sin(ang)[:, None]
    ax, ay, ex, ey = e[:, 0] - ox, e[:, 1] - oy, e[:, 2] - e[:, 0], e[:, 3] - e[:, 1]
    den = dx * ey - dy * ex
    with np.errstate(all="ignore"):
        s, t = (ax * dy - ay * dx) / den, (ax * ey - ay * ex) / den
    t = np.where((s >= 0) & (s < 1) & (t >= 0) & (den != 0), t, np.inf).min(axis=1)
    for lab in np.nonzero(r.kinds == 2)[0]:
        qx, qy, rad = r.circles[lab, 0] - ox, r.circles[lab, 1] - oy, r.circles[lab, 2]
        b = -(qx * dx[:, 0] + qy * dy[:, 0])
        disc = b * b - (qx * qx + qy * qy - rad * rad)
        with np.errstate(invalid="ignore"):
            tc = -b - np.sqrt(disc)
        t = np.minimum(t, np.where((disc >= 0) & (tc >= 0), tc, np.inf))
    t[t > P.lidar_max_range] = np.inf
    return t


@pytest.mark.parametrize("world", ["track", "obstacles", "hallway", "stop-sign"])
@pytest.mark.parametrize("beams,fov", [(800, None), (1080, 4.7), (7, None)])
def test_lidar_per_edge_is_every_beam_against_every_edge(world, beams, fov):
    w = load_world(world)
    lidar = Lidar(w, beams=beams, fov=fov)
    assert lidar.vector_walls
    rng = np.random.default_rng(8)
    checked = 0
    for _ in range(25):
        pose = (rng.uniform(-2.5, 2.5), rng.uniform(-2.0, 2.0), rng.uniform(-3.2, 3.2))
        got = lidar.true_ranges(pose)
        if not got.any():  # inside a shape: every beam hits at 0; marched, nearer than the minimum range
            marched = Lidar(w, beams=beams, fov=fov)
            marched.vector_walls = False
            assert (marched.true_ranges(pose) < P.lidar_min_range).all()
            assert not lidar.scan(pose).ranges.any() and not marched.scan(pose).ranges.any()  # the device reads 0
            continue
        want = _every_edge(lidar, pose)
        assert np.array_equal(np.isfinite(got), np.isfinite(want))
        fin = np.isfinite(got)
        assert np.allclose(got[fin], want[fin], rtol=0, atol=1e-9)
        checked += 1
    assert checked >= 10


def test_many_edges_in_a_column_fall_back_to_the_march():
    # 20 low slabs in a row ahead (40 crossings a column, more than CMAX): the frame is marched
    # (which keeps the KMAX nearest shapes of a column, as the per-edge path does)
    slabs = [{"shape": "box", "center": [0.6 + 0.25 * i, 0.0], "size": [0.05, 3.0], "height": 0.02 + 0.004 * i}
             for i in range(20)]
    w = world_from_dict({"floor": {"size": [12, 12]},
                         "walls": [{"points": [[6.5, -6], [6.5, 6]], "height": 1.0}], "obstacles": slabs})
    cam = RGBDCamera(w)
    x, y, yaw = cam.camera_pose(EAST)
    v, r = cam._view, cam._view.raster
    ok = _kernels.vector_crossings(cam._cr_t, cam._cr_e, cam._ncr, x, y, yaw, v.cos_c, v.sin_c, cam._level.fx,
                                   cam._level.cx, cam._edges, r.kinds, r.circles)
    assert not ok  # overflowed
    f = cam.render(EAST)
    marched = RGBDCamera(w)
    marched.vector_walls = False
    g = marched.render(EAST)
    assert np.array_equal(f.color, g.color) and np.array_equal(f.depth, g.depth)
    # the first slab's front face, 0.575 m ahead of the car's centre (rows 412-437)
    assert f.depth[425, 300:340] == pytest.approx(0.575 - P.rgbd_x, abs=1e-3)


@pytest.mark.skipif(not _kernels.HAVE_NUMBA, reason="numba not installed: there is only the Python path")
@pytest.mark.parametrize("fov", [None, 4.7])
def test_lidar_per_edge_compiled_and_python_agree(fov):
    w = load_world("hallway")
    lidar = Lidar(w, beams=200, fov=fov)
    r = lidar._raster
    sx, sy, syaw = lidar.sensor_pose((0.3, -1.2, 0.7))
    args = (sx, sy, syaw, lidar._cos, lidar._sin, lidar._a0, lidar._da, lidar._full, P.lidar_max_range, lidar._edges,
            r.kinds, r.circles, lidar._balls(0.0), lidar._no_noise, P.lidar_min_range, -1)
    a, b = np.empty(200), np.empty(200)
    _kernels.lidar_scan_edges(*args, a)
    _kernels.lidar_scan_edges.py_func(*args, b)
    assert np.array_equal(a, b)


@pytest.mark.parametrize("gain", [1.0, 1.3])
def test_a_frame_drawn_in_pieces_is_the_frame_drawn_whole(gain):
    """The track's wall spans the view (its rows are copies of its bytes made once a frame, its
    depths of its columns' once a frame): rows drawn a few at a time, starting and ending inside
    the wall's rows, the floor's and between, give the whole frame's pixels, noise and exposure
    on."""
    world = load_world("track")
    pose = (0.2, -1.7, 0.1)
    whole = RGBDCamera(world, P, np.random.default_rng(7)).render(pose, 0.5, gain)
    rows = RGBDCamera(world, P, np.random.default_rng(7)).render_rows(pose, 0.5, gain)
    for a, b in ((100, 101), (5, 90), (250, 300), (0, 3), (400, 480), (90, 250), (300, 400)):
        assert np.array_equal(rows.color_rows(a, b), whole.color[a:b]), (a, b)
        assert np.array_equal(rows.depth_rows(a, b), whole.depth[a:b]), (a, b)
    assert np.array_equal(rows.color, whole.color) and np.array_equal(rows.depth, whole.depth)
    assert (whole.depth[:100] > 0).any()  # the wall, near enough to be measured (in part)
