"""The simulated LIDAR against hand-computed geometry."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from qcarlab.constants import DEFAULT_PARAMS
from qcarlab.errors import InputError
from qcarlab.sim import _kernels
from qcarlab.sim.lidar import Lidar
from qcarlab.sim.world import load_world, world_from_dict

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BERLIN = DATA / "maps" / "berlin.yaml"
P = DEFAULT_PARAMS
HEAD_S = (0.0, 0.0, -math.pi / 2)  # the sheet's start: origin heading -Y


def room(**extra):
    """A 10 x 10 m floor with nothing on it unless given."""
    d = {"floor": {"size": [10, 10]}}
    d.update(extra)
    return world_from_dict(d)


def wall_ahead(dist: float = 2.0):
    # the car at the origin heading -Y: a wall whose face is `dist` ahead of the LIDAR (which
    # sits lidar_x = -1.08 cm ahead of the car's centre, i.e. just behind it)
    y = -dist - 0.05 - P.lidar_x
    return room(walls=[{"points": [[-3, y], [3, y]], "thickness": 0.1, "height": 1.0}])


def beam(lidar: Lidar, angle: float) -> int:
    return int(round((angle % (2 * math.pi)) / (2 * math.pi) * lidar.beams)) % lidar.beams


def test_angles_are_ccw_from_forward():
    lidar = Lidar(room(), beams=8)
    assert lidar.angles == pytest.approx(np.arange(8) * math.pi / 4)
    assert Lidar(room()).beams == P.lidar_beams == 800
    with pytest.raises(InputError):
        Lidar(room(), beams=0)


def test_wall_two_metres_ahead_reads_two_metres_at_beam_0():
    w = wall_ahead(2.0)
    exact = Lidar(w).scan(HEAD_S)
    assert exact.ranges[0] == pytest.approx(2.0, abs=1e-6)
    # neighbouring beams see the same plane at 2 / cos(angle)
    a = exact.angles[5]
    assert exact.ranges[5] == pytest.approx(2.0 / math.cos(a), abs=1e-6)
    noisy = Lidar(w, rng=np.random.default_rng(3)).scan(HEAD_S)
    assert noisy.ranges[0] == pytest.approx(2.0, abs=4 * P.lidar_noise)
    err = noisy.ranges[:20] - exact.ranges[:20]
    assert 0.002 < err.std() < 0.01


def test_lidar_offset_from_the_car_centre():
    params = dataclasses.replace(P, lidar_x=0.1)
    lidar = Lidar(wall_ahead(2.0), params)
    assert lidar.sensor_pose(HEAD_S) == pytest.approx((0.0, -0.1, -math.pi / 2))
    # the wall is 2 m ahead of the default mount; this LIDAR sits 0.1 - lidar_x further forward
    assert lidar.scan(HEAD_S).ranges[0] == pytest.approx(2.0 - (0.1 - P.lidar_x), abs=1e-6)


def test_box_to_the_left_shows_at_plus_90_degrees():
    # heading -Y, the car's left is +X: a box 1 m to the left, 0.3 m deep, 0.4 m long
    w = room(obstacles=[{"shape": "box", "center": [1.15, 0.0], "size": [0.3, 0.4], "height": 0.4}])
    s = Lidar(w, beams=720).scan(HEAD_S)
    hit = s.ranges > 0
    assert hit.any()
    i = int(np.argmin(np.where(hit, s.ranges, np.inf)))
    assert s.angles[i] == pytest.approx(math.pi / 2, abs=math.radians(0.6))
    assert s.ranges[i] == pytest.approx(1.0, abs=1e-6)
    # the box spans atan(0.2 / 1.0) either side of +90 deg and nothing else is there
    span = s.angles[hit]
    assert span.min() == pytest.approx(math.pi / 2 - math.atan(0.2), abs=math.radians(1))
    assert span.max() == pytest.approx(math.pi / 2 + math.atan(0.2), abs=math.radians(1))


def test_scan_turns_with_the_car():
    w = room(obstacles=[{"shape": "circle", "center": [2.0, 0.0], "radius": 0.25, "height": 0.5}])
    for yaw in (0.0, 1.0, -2.5):
        # put the car 2 m from the pillar, facing it, at various headings
        pose = (2.0 - 2.0 * math.cos(yaw), -2.0 * math.sin(yaw), yaw)
        r = Lidar(w, beams=360).scan(pose).ranges
        assert r[0] == pytest.approx(1.75 - P.lidar_x, abs=1e-6)  # the LIDAR is lidar_x ahead of the centre


def test_no_return_and_too_close_read_zero():
    assert not Lidar(room(), beams=90).scan(HEAD_S).ranges.any()  # nothing within 18 m
    w = room(obstacles=[{"shape": "circle", "center": [0.0, -0.2], "radius": 0.1, "height": 0.5}])
    r = Lidar(w, beams=360).scan(HEAD_S).ranges
    assert r[0] == 0.0  # 0.1 m away: nearer than the 0.15 m minimum
    far = room(floor={"size": [40, 40]}, walls=[{"points": [[-5, -19], [5, -19]]}])
    assert Lidar(far, beams=36).scan(HEAD_S).ranges[0] == 0.0  # 18.96 m: beyond 18 m
    near = room(floor={"size": [40, 40]}, walls=[{"points": [[-5, -17], [5, -17]]}])
    assert Lidar(near, beams=36).scan(HEAD_S).ranges[0] == pytest.approx(16.95 - P.lidar_x)  # within 18 m


def test_low_shapes_are_below_the_scan_plane():
    w = room(obstacles=[{"shape": "box", "center": [0, -1.0], "size": [0.5, 0.2], "height": 0.15}])
    assert Lidar(w, beams=36).scan(HEAD_S).ranges[0] == 0.0
    w = room(obstacles=[{"shape": "box", "center": [0, -1.0], "size": [0.5, 0.2], "height": 0.25}])
    assert Lidar(w, beams=36).scan(HEAD_S).ranges[0] == pytest.approx(0.9 - P.lidar_x)


def test_stop_sign_post_reflects():
    w = room(signs=[{"type": "stop", "position": [0.0, -1.5], "facing": "90deg", "size": 0.15, "height": 0.5}])
    r = Lidar(w, beams=3600).scan(HEAD_S).ranges
    # the plate is above the scan plane (0.425-0.575 m), the 12 mm post is not
    assert r[0] == pytest.approx(1.5 - 0.012 - P.lidar_x, abs=1e-6)


def test_rolling_ball_is_seen_where_it_is():
    w = room(balls=[{"start": [-3.0, -1.0], "direction": 0.0, "speed": 1.0, "radius": 0.12}])
    lidar = Lidar(w, beams=360)
    assert lidar.scan(HEAD_S, t=0.0).ranges[0] == 0.0
    # at t = 3 s the ball is at (0, -1): the scan plane (lidar_z = 0.186 m) cuts it in a circle of
    # radius sqrt(0.12^2 - (0.186 - 0.12)^2), seen from the LIDAR lidar_x ahead of the centre
    cut = math.sqrt(0.12**2 - (P.lidar_z - 0.12) ** 2)
    assert lidar.scan(HEAD_S, t=3.0).ranges[0] == pytest.approx(1.0 - P.lidar_x - cut, abs=1e-9)


def test_same_seed_same_scan():
    w = load_world("obstacles")
    a = Lidar(w, rng=np.random.default_rng(7)).scan(w.start)
    b = Lidar(w, rng=np.random.default_rng(7)).scan(w.start)
    c = Lidar(w, rng=np.random.default_rng(8)).scan(w.start)
    assert np.array_equal(a.ranges, b.ranges)
    assert not np.array_equal(a.ranges, c.ranges)
    assert a.t == 0.0


def test_obstacles_world_matches_figure_62():
    w = load_world("obstacles")
    s = Lidar(w, beams=360).scan(w.start)
    ahead = s.ranges[(np.abs(np.angle(np.exp(1j * s.angles))) < math.radians(10)) & (s.ranges > 0)]
    assert 0.5 < ahead.min() < 1.5
    for centre in (math.pi / 2, -math.pi / 2):  # boxes to both sides
        side = np.abs(np.angle(np.exp(1j * (s.angles - centre)))) < math.radians(40)
        assert 0.5 < s.ranges[side & (s.ranges > 0)].min() < 1.5


def ros_world(tmp_path: Path, img: np.ndarray, res: float = 0.05) -> Path:
    cv2.imwrite(str(tmp_path / "g.png"), img)
    p = tmp_path / "g.yaml"
    p.write_text(yaml.safe_dump({"image": "g.png", "resolution": res, "origin": [0.0, 0.0, 0.0],
                                 "negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.196}))
    return p


def test_ros_map_walls_are_exact_to_the_cell(tmp_path):
    img = np.full((100, 100), 254, np.uint8)
    img[:, 80] = 0  # a wall column: cells x in [4.00, 4.05)
    w = load_world(ros_world(tmp_path, img))
    s = Lidar(w, beams=360).scan((1.0, 2.5, 0.0))
    d = 3.0 - P.lidar_x  # the wall face at x = 4.00, the LIDAR at x = 1 + lidar_x
    assert s.ranges[0] == pytest.approx(d, abs=1e-9)
    a = s.angles[20]
    assert s.ranges[20] == pytest.approx(d / math.cos(a), abs=1e-9)


def test_scan_in_berlin_has_returns_all_around():
    if not BERLIN.is_file():
        pytest.skip("shared/data/maps/berlin.yaml not available")
    w = load_world(BERLIN)
    s = Lidar(w, beams=1080, rng=np.random.default_rng(0)).scan(w.start)
    ok = s.ranges > 0
    assert ok.mean() > 0.8
    assert s.ranges[ok].min() >= P.lidar_min_range and s.ranges.max() <= P.lidar_max_range
    for q in range(4):  # returns in every quadrant
        sector = (s.angles >= q * math.pi / 2) & (s.angles < (q + 1) * math.pi / 2)
        assert ok[sector].mean() > 0.5
    # every return lies on (next to) an occupied cell of the map
    g = w.grid
    x, y, yaw = Lidar(w).sensor_pose(w.start)
    r, a = s.ranges[ok] + 0.01, s.angles[ok] + yaw  # 1 cm past the surface (noise is 5 mm)
    rows = np.floor((y + r * np.sin(a) - g.origin[1]) / g.resolution).astype(int)
    cols = np.floor((x + r * np.cos(a) - g.origin[0]) / g.resolution).astype(int)
    near = np.zeros(len(rows), bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            near |= g.occupied[np.clip(rows + dr, 0, 599), np.clip(cols + dc, 0, 599)]
    assert near.mean() > 0.99


@pytest.mark.skipif(not _kernels.HAVE_NUMBA, reason="numba not installed: there is only the Python path")
def test_compiled_and_python_kernels_agree():
    w = load_world("hallway")
    lidar = Lidar(w, beams=90)
    r = lidar._raster
    out_c = np.empty(90)
    out_p = np.empty(90)
    args = (0.0, -1.0, -1.2, lidar._cos, lidar._sin, w.params.lidar_max_range, r.x0, r.y0, r.res, r.cells, r.tiles, r.tiles_x, r.kinds,
            r.poly_start, r.poly_count, r.verts, r.circles, np.zeros((0, 3)), np.zeros(0), 0.15, 0)
    _kernels.lidar_scan(*args, out_c)
    _kernels.lidar_scan.py_func(*args, out_p)
    assert np.allclose(out_c, out_p)


def boundary_room():
    """A 10 x 10 m room whose raster puts the pose (0.5, 1.0) on a cell corner, with a box whose
    top-left corner is 2 cells to the side of the beam running down the boundary x = 0.5."""
    return room(walls=[{"points": [[-5, -5], [5, -5], [5, 5], [-5, 5]], "closed": True}],
                obstacles=[{"shape": "box", "center": [0.755, -0.5], "size": [0.49, 1.0]}])


def test_a_beam_along_a_cell_boundary_costs_steps_in_proportion_to_its_length():
    """The stall case: from a pose on a cell corner, beam 600 (straight -Y) runs exactly along the
    boundary x = 0.5 past the corner of a box. The old cell walk restarted from floor(x), landed
    back in the cell it had just left and advanced 1e-6 cells a time (some 10^6 re-entries, 20 ms
    for the scan instead of 0.5); now every cell looked at moves the ray on by a cell or more."""
    w = boundary_room()
    lidar = Lidar(w, beams=800)
    lidar.vector_walls = False  # march the raster (a vector world is scanned per edge by default)
    r = lidar._raster
    assert (0.5 - r.x0) / r.res == 1112.0 and (1.0 - r.y0) / r.res == 1212.0  # on the corner
    ranges = lidar.true_ranges((0.5, 1.0, 0.0))
    on_boundary = lidar.last_cell_steps
    assert ranges[600] == pytest.approx(5.95, abs=1e-9)  # 1.0 down to the wall's face at -4.95
    lidar.true_ranges((0.5013, 1.0013, 0.0))  # 1.3 mm off the boundary
    off_boundary = lidar.last_cell_steps
    assert on_boundary <= 1.5 * off_boundary
    # and in absolute terms: at most 3 cells looked at per cell of each beam's length
    assert on_boundary <= 3 * np.sum(np.minimum(ranges, 12.0)) / r.res + 10 * lidar.beams
    one = Lidar(w, beams=4)  # beams 0, 90, 180, 270 deg: all four along cell boundaries
    one.vector_walls = False
    rr = one.true_ranges((0.5, 1.0, 0.0))
    assert one.last_cell_steps <= 3 * np.sum(rr) / r.res + 40


def test_sector_scanner_angles():
    lidar = Lidar(room(), beams=1080, fov=4.7)
    assert lidar.angles[0] == pytest.approx(-2.35) and lidar.angles[-1] == pytest.approx(2.35)
    assert len(lidar.scan(HEAD_S).ranges) == 1080
    with pytest.raises(InputError):
        Lidar(room(), beams=1, fov=1.0)
    with pytest.raises(InputError):
        Lidar(room(), beams=10, fov=float("nan"))


def test_tiled_map_gives_the_same_ranges_as_the_cell_map():
    """A ROS map's LIDAR raster is marched in its one-byte tiled form: the same ranges (to 1e-9 m)
    as the two-byte cell map, from poses all over berlin."""
    if not BERLIN.is_file():
        pytest.skip("shared/data/maps/berlin.yaml not available")
    w = load_world(BERLIN)
    lidar = Lidar(w, beams=360)
    r = lidar._raster
    assert r.tiles.size > 0 and r.tiles.size >= r.cells.size
    rng = np.random.default_rng(3)
    for _ in range(10):
        g = w.grid
        while True:
            row, col = rng.integers(0, 600, 2)
            if not g.occupied[row, col]:
                break
        pose = (g.origin[0] + (col + 0.5) * g.resolution, g.origin[1] + (row + 0.5) * g.resolution, rng.uniform(-3, 3))
        tiled = lidar.true_ranges(pose)
        out = np.empty(360)
        sx, sy, syaw = lidar.sensor_pose(pose)
        _kernels.lidar_scan(sx, sy, syaw, lidar._cos, lidar._sin, w.params.lidar_max_range, r.x0, r.y0, r.res, r.cells, np.zeros(0, np.uint8), 0,
                            r.kinds, r.poly_start, r.poly_count, r.verts, r.circles, np.zeros((0, 3)), np.zeros(0), 0.15, -1, out)
        fin = np.isfinite(out)
        assert np.array_equal(np.isfinite(tiled), fin) and np.allclose(tiled[fin], out[fin], rtol=0, atol=1e-9)


def test_a_beam_along_a_cell_boundary_of_a_ros_map_costs_steps_in_proportion(tmp_path):
    """The same bound on a ROS map, marched in its tiled form: a 10 x 10 m map of 5 cm cells, the
    pose on a cell corner, beam 600 running down the boundary x = 5.0 past a box corner two cells
    to its side."""
    img = np.full((200, 200), 254, np.uint8)
    img[[0, -1], :] = 0
    img[:, [0, -1]] = 0
    img[200 - 80 : 200 - 20, 102:150] = 0  # grid rows 20..79 (image row 0 is the top), cols 102..149
    cv2.imwrite(str(tmp_path / "box.pgm"), img)
    (tmp_path / "box.yaml").write_text(yaml.safe_dump({"image": "box.pgm", "resolution": 0.05, "origin": [0.0, 0.0, 0.0],
                                                       "negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.196}))
    w = load_world(tmp_path / "box.yaml")
    lidar = Lidar(w, beams=800)
    r = lidar._raster
    assert r.tiles.size > 0
    assert (5.0 - r.x0) / r.res == pytest.approx(round((5.0 - r.x0) / r.res), abs=1e-9)  # on a boundary
    ranges = lidar.true_ranges((5.0, 7.5, 0.0))
    on_boundary = lidar.last_cell_steps
    assert ranges[600] == pytest.approx(7.5 - 0.05, abs=1e-9)  # down to the bottom wall's top face
    lidar.true_ranges((5.013, 7.513, 0.0))
    assert on_boundary <= 1.5 * lidar.last_cell_steps
    assert on_boundary <= 3 * np.sum(np.minimum(ranges, 12.0)) / r.res + 10 * lidar.beams
