"""Worlds: the YAML format, shipped worlds, ROS maps, validation errors, the top-down render."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from qcarlab.errors import InputError
from qcarlab.sim.raster import build_raster, floor_texture
from qcarlab.sim.render import render_topdown, world_to_pixel
from qcarlab.sim.world import COLORS, list_worlds, load_world, world_from_dict

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BERLIN = DATA / "maps" / "berlin.yaml"

SHIPPED = ["hallway", "obstacles", "stop-sign", "studio", "track"]


def write(tmp_path: Path, data, name: str = "w.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return p


def base(**extra):
    d = {"floor": {"size": [4, 4]}}
    d.update(extra)
    return d


def bgr(name: str) -> tuple[int, int, int]:
    r, g, b = COLORS[name]
    return (b, g, r)


# --- shipped worlds --------------------------------------------------------------------------
def test_list_worlds_names_and_descriptions():
    got = dict(list_worlds())
    assert sorted(got) == SHIPPED
    assert all(len(d) > 10 for d in got.values())


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_world_loads_with_a_free_start_on_the_floor(name):
    w = load_world(name)
    assert w.name == name
    x, y, yaw = w.start
    x0, y0, x1, y1 = w.floor_bounds
    assert x0 < x < x1 and y0 < y < y1
    r = build_raster(w)
    row, col = int((y - r.y0) / r.res), int((x - r.x0) / r.res)
    # the car's footprint is free of shapes (0.21 m around the centre)
    k = int(0.21 / r.res)
    assert (r.label[row - k : row + k, col - k : col + k] < 0).all()


def test_sheet_start_pose_in_the_path_following_worlds():
    for name in ("studio", "obstacles", "stop-sign", "hallway"):
        assert load_world(name).start == pytest.approx((0.0, 0.0, -math.pi / 2))


def test_studio_holds_both_butterflies():
    w = load_world("studio")
    x0, y0, x1, y1 = w.floor_bounds
    # the 4 m butterfly spans x, y in [-4, 4]; the car (0.425 m long) must stay inside the walls
    assert x0 < -4.3 and x1 > 4.3 and y0 < -4.3 and y1 > 4.3


def test_track_start_is_in_the_right_lane_heading_along_it():
    w = load_world("track")
    x, y, yaw = w.start
    # bottom straight: centre line at y = -1.5, outer edge at -1.9; driving +X, right = -Y
    assert yaw == pytest.approx(0.0)
    assert -1.9 < y < -1.5 and abs(y + 1.7) < 0.05


# --- the YAML format -------------------------------------------------------------------------
def test_full_world_parses(tmp_path):
    data = {
        "name": "demo",
        "description": "all sections",
        "floor": {"size": [6, 5], "origin": [-1, -2], "color": "#102030"},
        "background": [10, 20, 30],
        "start": {"x": 1, "y": 0.5, "yaw": "90deg"},
        "markings": [
            {"points": [[0, 0], [2, 0]], "width": 0.05, "color": "yellow", "dashed": True},
            {"rect": [0, 1, 1, 2], "color": "asphalt"},
            {"polygon": [[0, 0], [1, 0], [0, 1]], "color": [1, 2, 3]},
        ],
        "regions": [{"rect": [0, 0, 1, 1], "brightness": 0.5}],
        "walls": [{"points": [[-1, -2], [5, -2], [5, 3]], "height": 1.0, "thickness": 0.1}],
        "obstacles": [
            {"shape": "box", "center": [2, 2], "size": [0.4, 0.3], "yaw": 0.3},
            {"shape": "circle", "center": [3, 1], "radius": 0.1, "height": 0.5, "color": "blue"},
            {"shape": "polygon", "points": [[0, 0], [0.5, 0], [0.2, 0.4]]},
        ],
        "signs": [{"type": "stop", "position": [2, -1], "facing": "180deg"}],
        "balls": [{"start": [0, 0], "direction": 0, "speed": 1.0, "start_time": 1.0, "distance": 2.0}],
    }
    w = load_world(write(tmp_path, data))
    assert w.name == "demo" and w.floor_origin == (-1, -2)
    assert w.floor_color == (0x30, 0x20, 0x10)  # BGR of #102030
    assert w.background == (30, 20, 10)
    assert w.start == pytest.approx((1, 0.5, math.pi / 2))
    assert len(w.markings) == 3 and w.markings[0].dash == (0.3, 0.2) and w.markings[1].filled
    assert len(w.solids) == 2 + 3  # two wall segments, three obstacles
    assert w.signs[0].facing == pytest.approx(math.pi)
    assert w.markings[0].color == bgr("yellow")


def test_balls_roll_wait_and_stop():
    w = world_from_dict(base(balls=[{"start": [1, 2], "direction": "90deg", "speed": 0.5, "start_time": 1.0, "distance": 1.0}]))
    (c0,) = w.obstacles_at(0.5)
    assert (c0.x, c0.y) == pytest.approx((1, 2))
    (c1,) = w.obstacles_at(2.0)
    assert (c1.x, c1.y) == pytest.approx((1, 2.5))
    (c2,) = w.obstacles_at(100.0)
    assert (c2.x, c2.y) == pytest.approx((1, 3.0))


def test_floor_texture_has_the_marking_where_it_is_painted():
    w = world_from_dict(base(markings=[{"points": [[-2, 0.5], [2, 0.5]], "width": 0.05, "color": "yellow"}]))
    tex, (x0, y1, ppm) = floor_texture(w, 100)
    col = int((1.0 - x0) * ppm)
    row_on = int((y1 - 0.5) * ppm)
    row_off = int((y1 - 0.8) * ppm)
    assert tuple(tex[row_on, col]) == bgr("yellow")
    assert tuple(tex[row_off, col]) != bgr("yellow")


def test_regions_scale_the_floor():
    w = world_from_dict(base(regions=[{"rect": [0, 0, 2, 2], "brightness": 0.5}]))
    tex, (x0, y1, ppm) = floor_texture(w, 50)
    lit = tex[int((y1 - 1) * ppm), int((1 - x0) * ppm)].astype(int)
    plain = tex[int((y1 + 1) * ppm), int((-1 - x0) * ppm)].astype(int)
    assert np.allclose(lit, plain * 0.5, atol=1)


def test_add_box_invalidates_rasters():
    w = load_world("obstacles")
    r1 = build_raster(w)
    w.add_box(0.0, -2.5, 0.3, 0.3, height=0.4)
    r2 = build_raster(w)
    assert r2 is not r1 and len(r2.kinds) == len(r1.kinds) + 1


# --- validation: one line naming the file and the field ----------------------------------------
@pytest.mark.parametrize(
    "data, field, words",
    [
        ({"walls": []}, "floor", "missing"),
        (base(floor={"size": "big"}), "floor.size", "expected [x, y]"),
        (base(obstacles=[{"shape": "box", "center": [0, 0], "size": [1, 1]}, {"shape": "circle", "center": [0, 0], "radius": 1},
                         {"shape": "circle", "center": [1, 1], "radius": -0.2}]), "obstacles[2].radius", "expected a positive number"),
        (base(obstacles=[{"shape": "triangle", "center": [0, 0]}]), "obstacles[0].shape", "unknown shape"),
        (base(obstacles=[{"shape": "box", "center": [0, 0]}]), "obstacles[0].size", "missing"),
        (base(obstacles=[{"shape": "circle", "center": [0, 0], "radius": 1, "size": [1, 1]}]), "obstacles[0].size", "not a field"),
        (base(walls=[{"points": [[0, 0], [1, "a"]]}]), "walls[0].points[1][1]", "expected a number"),
        (base(walls=[{"points": [[0, 0]]}]), "walls[0].points", "at least 2"),
        (base(markings=[{"points": [[0, 0], [1, 0]], "color": "chartreuse-ish"}]), "markings[0].color", "unknown colour"),
        (base(markings=[{"rect": [0, 0, 1, 1], "width": 0.1}]), "markings[0].width", "only for line"),
        (base(signs=[{"type": "yield", "position": [0, 0], "facing": 0}]), "signs[0].type", "unknown sign"),
        (base(signs=[{"type": "stop", "position": [0, 0]}]), "signs[0].facing", "missing"),
        (base(balls=[{"start": [0, 0], "direction": "north", "speed": 1}]), "balls[0].direction", "angle"),
        (base(start=[0, 0, 0, 0]), "start", "expected [x, y, yaw]"),
        (base(regions=[{"rect": [0, 0, 1, 1]}]), "regions[0].brightness", "missing"),
        (base(wals=[]), "wals", "unknown field"),
        (base(floor={"size": [4, 4], "colour": "red"}), "floor.colour", "unknown field"),
    ],
)
def test_bad_world_files_give_one_line_with_file_and_field(tmp_path, data, field, words):
    p = write(tmp_path, data, "bad.yaml")
    with pytest.raises(InputError) as e:
        load_world(p)
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith(f"{p}: {field}: "), msg
    assert words in msg


def test_error_message_format_of_the_brief(tmp_path):
    p = write(tmp_path, base(obstacles=[{}, {}, {"shape": "circle", "center": [0, 0], "radius": -1}]), "x.yaml")
    # obstacles[0] is already wrong (no shape): the first fault is the one reported
    with pytest.raises(InputError, match=r"x\.yaml: obstacles\[0\]\.shape: missing"):
        load_world(p)
    p = write(tmp_path, base(obstacles=[{"shape": "circle", "center": [0, 0], "radius": -1}]), "x.yaml")
    with pytest.raises(InputError) as e:
        load_world(p)
    assert str(e.value) == f"{p}: obstacles[0].radius: expected a positive number, got -1"


def test_yaml_syntax_error_names_the_line(tmp_path):
    p = write(tmp_path, "floor:\n  size: [4, 4\nwalls: []\n", "broken.yaml")
    with pytest.raises(InputError, match=r"broken\.yaml line \d+"):
        load_world(p)


def test_unknown_name_lists_the_shipped_worlds():
    with pytest.raises(InputError, match="shipped: hallway, obstacles, stop-sign, studio, track"):
        load_world("moon")
    with pytest.raises(InputError, match="no such world file"):
        load_world("nowhere/x.yaml")


def test_shipped_error_names_the_worlds_file(tmp_path):
    with pytest.raises(InputError, match="^not_a_mapping.yaml: expected a world"):
        world_from_dict([1, 2], source="not_a_mapping.yaml")


# --- ROS map_server maps ---------------------------------------------------------------------
def ros_map(tmp_path: Path, img: np.ndarray, **over) -> Path:
    cv2.imwrite(str(tmp_path / "m.pgm"), img)
    data = {"image": "m.pgm", "resolution": 0.1, "origin": [-1.0, -2.0, 0.0], "negate": 0,
            "occupied_thresh": 0.65, "free_thresh": 0.196}
    data.update(over)
    return write(tmp_path, data, "m.yaml")


def test_ros_map_orientation_and_thresholds(tmp_path):
    img = np.full((20, 30), 254, np.uint8)  # free
    img[0, 0] = 0  # occupied, top-left of the image = highest y, lowest x
    img[19, 29] = 205  # unknown, bottom-right
    w = load_world(ros_map(tmp_path, img))
    g = w.grid
    assert g is not None and g.occupied.shape == (20, 30) and g.resolution == 0.1
    assert g.occupied[19, 0] and g.occupied.sum() == 1  # grid rows grow with y
    assert g.unknown[0, 29] and g.unknown.sum() == 1
    assert g.cell_of(-1.0 + 0.05, -2.0 + 19 * 0.1 + 0.05) == (19, 0)
    assert w.floor_size == pytest.approx((3.0, 2.0))
    x, y, _ = w.start
    assert g.occupied[g.cell_of(x, y)] == False  # noqa: E712


def test_ros_map_negate(tmp_path):
    img = np.zeros((10, 10), np.uint8)
    img[5, 5] = 255
    w = load_world(ros_map(tmp_path, img, negate=1))
    assert w.grid.occupied.sum() == 1 and w.grid.occupied[4, 5]


def test_ros_map_start_and_wall_height_keys(tmp_path):
    img = np.full((10, 10), 254, np.uint8)
    w = load_world(ros_map(tmp_path, img, start=[-0.5, -1.5, "45deg"], wall_height=1.5, name="tiny"))
    assert w.start == pytest.approx((-0.5, -1.5, math.pi / 4))
    assert w.grid.wall_height == 1.5 and w.name == "tiny"


@pytest.mark.parametrize(
    "over, field",
    [
        ({"image": "missing.png"}, "image"),
        ({"resolution": -0.1}, "resolution"),
        ({"origin": "here"}, "origin"),
        ({"negate": 3}, "negate"),
        ({"free_thresh": 0.9}, "free_thresh"),
        ({"occupied": 0.9}, "occupied"),
    ],
)
def test_bad_ros_maps(tmp_path, over, field):
    p = ros_map(tmp_path, np.full((4, 4), 254, np.uint8), **over)
    with pytest.raises(InputError) as e:
        load_world(p)
    assert str(e.value).startswith(f"{p}: {field}"), str(e.value)
    assert "\n" not in str(e.value)


def test_berlin_loads():
    if not BERLIN.is_file():
        pytest.skip("shared/data/maps/berlin.yaml not available")
    w = load_world(BERLIN)
    g = w.grid
    assert g.occupied.shape == (600, 600) and g.resolution == pytest.approx(0.05)
    assert w.floor_origin == pytest.approx((-11.60654, -26.520793))
    assert 0.02 < g.occupied.mean() < 0.98
    assert not g.occupied[g.cell_of(*w.start[:2])]


# --- top-down render -------------------------------------------------------------------------
def test_render_topdown_draws_path_and_start():
    w = load_world("studio")
    path = np.array([[0.0, 0.0], [0.0, -3.0]])
    img = render_topdown(w, px_per_m=50, path=path, poses=np.array([[1.0, 1.0, 0.0], [2.0, 1.0, 0.0]]))
    x0, y0, x1, y1 = w.bounds
    assert img.shape[1] == pytest.approx((x1 - x0 + 0.5) * 50, abs=2)
    assert img.shape[0] == pytest.approx((y1 - y0 + 0.5) * 50, abs=2)
    c, r = np.round(world_to_pixel(w, [[0.0, -2.0]], 50)[0]).astype(int)
    assert tuple(img[r, c]) == (200, 40, 200)  # the path, magenta
    c, r = np.round(world_to_pixel(w, [[1.5, 1.0]], 50)[0]).astype(int)
    assert tuple(img[r, c]) == (30, 30, 220)  # the trajectory, red
    c, r = np.round(world_to_pixel(w, [[-4.45, -3.5]], 50)[0]).astype(int)
    assert tuple(img[r, c]) == bgr("darkgray")  # the cabinet


def test_render_topdown_of_a_ros_map():
    if not BERLIN.is_file():
        pytest.skip("shared/data/maps/berlin.yaml not available")
    img = render_topdown(load_world(BERLIN), px_per_m=10)
    assert img.shape[0] > 290 and img.dtype == np.uint8


def test_the_documented_example_loads(tmp_path):
    import textwrap

    import qcarlab.sim.world as world_module

    doc = world_module.__doc__
    block = doc.split("Unknown keys are refused, so a typo is reported rather than ignored::", 1)[1]
    block = block.split("\nA ROS ", 1)[0]
    w = load_world(write(tmp_path, textwrap.dedent(block), "example.yaml"))
    assert w.name == "my-room" and len(w.solids) == 4 + 3  # a closed 4-segment wall, 3 obstacles
    assert w.signs and w.balls and w.regions and len(w.markings) == 2
