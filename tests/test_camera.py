"""The simulated cameras against the pinhole model and hand-computed geometry."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from qcarlab.constants import DEFAULT_PARAMS
from qcarlab.sensors import CSIFrames
from qcarlab.sim.camera import RGBD_MIN_DEPTH, CSICameras, RGBDCamera, stitch_panorama
from qcarlab.sim.world import load_world, world_from_dict

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BERLIN = DATA / "maps" / "berlin.yaml"
P = DEFAULT_PARAMS
EAST = (0.0, 0.0, 0.0)  # car at the origin heading +X: the camera looks along +X


def room(**extra):
    d = {"floor": {"size": [9, 9], "color": "gray"}}
    d.update(extra)
    return world_from_dict(d)


def wall_at_x(x: float, height: float = 1.0, color: str = "white") -> dict:
    return {"points": [[x + 0.05, -4], [x + 0.05, 4]], "thickness": 0.1, "height": height, "color": color}


def red_mask(img: np.ndarray) -> np.ndarray:
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    m1 = cv2.inRange(hsv, (0, 100, 100), (10, 255, 255))
    m2 = cv2.inRange(hsv, (170, 100, 100), (180, 255, 255))
    return (m1 | m2) > 0


def yellow_mask(img: np.ndarray) -> np.ndarray:
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    return cv2.inRange(hsv, (15, 100, 100), (35, 255, 255)) > 0


def test_intrinsics_are_the_d435_at_640x480():
    cam = RGBDCamera(room())
    k = cam.intrinsics
    f = 240 / math.tan(P.rgbd_vfov / 2)
    assert (k.width, k.height) == (640, 480)
    assert k.fx == pytest.approx(f) and k.fy == pytest.approx(f)
    assert 610 < f < 620  # as the real D435 colour stream at 640 x 480
    assert (k.cx, k.cy) == (319.5, 239.5)


def test_frame_types_and_sizes():
    f = RGBDCamera(load_world("track"), rng=np.random.default_rng(0)).render(load_world("track").start, t=0.5)
    assert f.t == 0.5
    assert f.color.shape == (480, 640, 3) and f.color.dtype == np.uint8
    assert f.depth.shape == (480, 640) and f.depth.dtype == np.float32
    ok = f.depth > 0
    assert ok.mean() > 0.5 and f.depth[ok].min() >= RGBD_MIN_DEPTH and f.depth.max() <= P.rgbd_max_depth


def test_wall_two_metres_ahead_in_the_depth_image():
    # the wall's face 2 m ahead of the car's centre: the camera, rgbd_x = 0.19 m ahead of the
    # centre, reads the z-depth 2 - 0.19 m
    w = room(walls=[wall_at_x(2.0)])
    f = RGBDCamera(w).render(EAST)
    centre = f.depth[238:242, 318:322]
    assert centre == pytest.approx(2.0 - P.rgbd_x, abs=1e-4)
    # z-depth, not range: the whole wall reads the same (above the floor line)
    assert f.depth[150, 20] == pytest.approx(2.0 - P.rgbd_x, abs=1e-4)
    noisy = RGBDCamera(w, rng=np.random.default_rng(1)).render(EAST)
    assert noisy.depth[230:250, 310:330].mean() == pytest.approx(2.0 - P.rgbd_x, abs=0.01)


def test_wall_rows_follow_the_pinhole():
    d, h = 3.0 - P.rgbd_x, 0.8
    w = room(walls=[wall_at_x(3.0, height=h, color="white")])
    f = RGBDCamera(w).render(EAST)
    fy, cy = RGBDCamera(w).intrinsics.fy, 239.5
    top = cy - (h - P.rgbd_z) * fy / d
    bottom = cy + P.rgbd_z * fy / d
    col = f.depth[:, 320]
    rows = np.nonzero(np.abs(col - d) < 1e-3)[0]
    assert rows.min() == pytest.approx(top, abs=1.0)
    assert rows.max() == pytest.approx(bottom, abs=1.0)


def test_occlusion_box_in_front_of_a_wall_and_its_top():
    # a 0.10 m box (lower than the camera, 0.14 m) 1 m ahead, 0.2 m deep, in front of a wall
    w = room(walls=[wall_at_x(3.0)], obstacles=[{"shape": "box", "center": [1.1, 0.0], "size": [0.2, 0.6], "height": 0.10, "color": "blue"}])
    f = RGBDCamera(w).render(EAST)
    fy, cy, zc = RGBDCamera(w).intrinsics.fy, 239.5, P.rgbd_z
    d_front, d_back = 1.0 - P.rgbd_x, 1.2 - P.rgbd_x
    v_front_top = cy + (zc - 0.10) * fy / d_front
    v_back_top = cy + (zc - 0.10) * fy / d_back
    v_foot = cy + zc * fy / d_front
    # the front face
    mid = int(round((v_front_top + v_foot) / 2))
    assert f.depth[mid, 320] == pytest.approx(d_front, abs=1e-4)
    # the top face, seen from above, between the front and the back edges
    vt = int(round((v_front_top + v_back_top) / 2))
    expect = (zc - 0.10) * fy / (vt - cy)
    assert f.depth[vt, 320] == pytest.approx(expect, rel=1e-3)
    assert d_front < f.depth[vt, 320] < d_back
    # above the box: the floor behind it, then the wall
    assert f.depth[int(v_back_top) - 3, 320] > d_back
    assert f.depth[200, 320] == pytest.approx(3.0 - P.rgbd_x, abs=1e-4)
    # blue where the box is
    b, g, r = f.color[mid, 320].astype(int)
    assert b > r + 40


def test_stop_sign_red_pixels_sit_where_the_pinhole_puts_them():
    # a stop sign 1.5 m ahead and 0.25 m to the right, facing the car
    sx, sy, h = 1.5, -0.25, 0.22
    w = room(walls=[wall_at_x(4.0)], signs=[{"type": "stop", "position": [sx, sy], "facing": "180deg", "size": 0.15, "height": h}])
    cam = RGBDCamera(w)
    f = cam.render(EAST)
    k = cam.intrinsics
    face_x = sx - (0.012 + 0.005)  # the face is just in front of the post
    Z = face_x - P.rgbd_x
    u = k.cx + k.fx * (-sy) / Z  # to the right: +u
    v = k.cy + k.fy * (P.rgbd_z - h) / Z  # above the camera: -v
    m = red_mask(f.color)
    assert m.sum() > 300
    vs, us = np.nonzero(m)
    # STOP letters are white: the red pixels are nearly symmetric about the centre
    assert us.mean() == pytest.approx(u, abs=2.0)
    assert vs.mean() == pytest.approx(v, abs=3.0)
    # the sign's size: 0.15 m across the flats
    assert us.max() - us.min() == pytest.approx(0.15 * 0.88 * k.fx / Z, abs=3.0)
    # the depth at the centre of the red pixels is the sign's distance
    assert f.depth[int(round(vs.mean())), int(round(us.mean()))] == pytest.approx(Z, abs=0.01)


def test_stop_sign_from_behind_is_not_red():
    w = room(signs=[{"type": "stop", "position": [1.5, 0.0], "facing": "0deg"}])
    f = RGBDCamera(w).render(EAST)
    assert red_mask(f.color).sum() == 0


def test_stop_sign_world_shows_the_sign_until_close():
    w = load_world("stop-sign")
    cam = RGBDCamera(w, rng=np.random.default_rng(2))
    for dist in (2.0, 1.0, 0.35):  # distance from the camera to the sign's face along -Y
        y_cam = -2.5 + 0.017 + dist
        pose = (0.0, y_cam + P.rgbd_x, -math.pi / 2)
        f = cam.render(pose)
        m = red_mask(f.color)
        assert m.sum() > 50, dist
        vs, us = np.nonzero(m)
        assert us.mean() > 320  # on the right
        d = np.median(f.depth[m])
        assert d == pytest.approx(dist, abs=0.05)


def test_yellow_line_projects_where_it_should():
    # a yellow line on the floor along +X, 0.30 m to the left of the car
    off = 0.30
    w = room(markings=[{"points": [[-1, off], [8, off]], "width": 0.04, "color": "yellow"}])
    cam = RGBDCamera(w)
    k = cam.intrinsics
    m = yellow_mask(cam.render(EAST).color)
    for v in (270, 300, 330, 360):
        Z = P.rgbd_z * k.fy / (v - k.cy)  # the floor's distance at this row
        u_expect = k.cx - k.fx * off / Z
        us = np.nonzero(m[v])[0]
        assert len(us) > 0
        assert us.mean() == pytest.approx(u_expect, abs=1.0), v
        # the line's width (4 cm), within the blur of the floor texture's 5 mm texels (nearer
        # than 1.5 m; farther the texture's coarser levels widen it, as a real lens blurs it)
        if Z < 1.5:
            assert len(us) * Z / k.fx == pytest.approx(0.04, abs=0.015)


def test_track_shows_yellow_left_and_white_right():
    w = load_world("track")
    f = RGBDCamera(w, rng=np.random.default_rng(0)).render(w.start)
    y = yellow_mask(f.color[380:])
    hsv = cv2.cvtColor(f.color[380:], cv2.COLOR_BGR2HSV)
    white = cv2.inRange(hsv, (0, 0, 200), (180, 40, 255)) > 0
    assert y.sum() > 500 and white.sum() > 500
    assert np.nonzero(y)[1].mean() < 320 < np.nonzero(white)[1].mean()


def test_brightness_regions_darken_what_is_seen_there():
    walls = [wall_at_x(2.0)]
    plain = RGBDCamera(room(walls=walls)).render(EAST).color
    dim = RGBDCamera(room(walls=walls, regions=[{"rect": [-5, -5, 5, 5], "brightness": 0.5}])).render(EAST).color
    for v in (100, 400):  # the wall and the floor
        assert dim[v, 320].astype(float) == pytest.approx(plain[v, 320].astype(float) * 0.5, abs=2)


def test_ball_appears_and_moves():
    w = room(walls=[wall_at_x(4.0)], balls=[{"start": [1.5, -3.0], "direction": "90deg", "speed": 1.0, "radius": 0.12, "color": "orange"}])
    cam = RGBDCamera(w)
    before = cam.render(EAST, t=0.0)
    at = cam.render(EAST, t=3.0)  # the ball at (1.5, 0): straight ahead
    Z = 1.5 - 0.12 - P.rgbd_x
    v = int(round(239.5 + (P.rgbd_z - 0.12) * cam.intrinsics.fy / (1.5 - P.rgbd_x)))
    assert at.depth[v, 320] == pytest.approx(Z, abs=0.01)
    assert before.depth[v, 320] == pytest.approx(4.0 - P.rgbd_x, abs=1e-3)


def test_pitched_camera():
    pitch = 0.15
    params = dataclasses.replace(P, rgbd_pitch=pitch)
    w = room(walls=[wall_at_x(2.0, height=2.0)])
    cam = RGBDCamera(w, params)
    f = cam.render(EAST)
    d = 2.0 - P.rgbd_x
    # looking down 0.15 rad from 0.14 m, the optical axis meets the floor (before the wall) at
    # the distance h / sin(pitch) along the axis: that is the centre's z-depth
    assert f.depth[239:241, 319:321].mean() == pytest.approx(P.rgbd_z / math.sin(pitch), rel=3e-3)
    # looking up, the axis meets the wall at z-depth d / cos(pitch)
    up = RGBDCamera(w, dataclasses.replace(P, rgbd_pitch=-pitch)).render(EAST)
    assert up.depth[239:241, 319:321].mean() == pytest.approx(d / math.cos(pitch), rel=2e-3)
    # the wall's foot is seen at the pitched pinhole's row
    k = cam.intrinsics
    v_foot = k.cy + k.fy * math.tan(math.atan(P.rgbd_z / d) - pitch)
    col = f.depth[:, 320]
    rows = np.nonzero(col > 0)[0]
    wall_rows = rows[np.abs(col[rows] - d / np.cos(np.arctan((rows - k.cy) / k.fy) + pitch) * np.cos(np.arctan((rows - k.cy) / k.fy))) < 0.01]
    assert wall_rows.max() == pytest.approx(v_foot, abs=1.5)


def test_same_seed_same_frame():
    w = load_world("track")
    a = RGBDCamera(w, rng=np.random.default_rng(5)).render(w.start)
    b = RGBDCamera(w, rng=np.random.default_rng(5)).render(w.start)
    c = RGBDCamera(w, rng=np.random.default_rng(6)).render(w.start)
    assert np.array_equal(a.color, b.color) and np.array_equal(a.depth, b.depth)
    assert not np.array_equal(a.color, c.color)
    clean = RGBDCamera(w).render(w.start)
    assert np.abs(a.color.astype(int) - clean.color.astype(int)).mean() == pytest.approx(2.0, abs=1.0)


def test_csi_views_order_and_panorama():
    # a red wall to the right (-Y), green behind (-X), blue to the left (+Y), yellow in front (+X)
    walls = [
        {"points": [[-3, -2], [3, -2]], "height": 2.0, "color": "red"},
        {"points": [[-2, -3], [-2, 3]], "height": 2.0, "color": "green"},
        {"points": [[-3, 2], [3, 2]], "height": 2.0, "color": "blue"},
        {"points": [[2, -3], [2, 3]], "height": 2.0, "color": "yellow"},
    ]
    w = room(walls=walls)
    csi = CSICameras(w, rng=np.random.default_rng(0))
    frames = csi.render(EAST, t=1.0)
    assert isinstance(frames, CSIFrames) and frames.t == 1.0
    expect = {"right": "red", "rear": "green", "left": "blue", "front": "yellow"}
    hue = {"red": (0, 8), "green": (50, 75), "blue": (105, 125), "yellow": (20, 30)}
    for name, img in zip(("right", "rear", "left", "front"), frames.as_list()):
        assert img.shape == (410, 820, 3) and img.dtype == np.uint8
        h = cv2.cvtColor(img[150:160, 405:415], cv2.COLOR_BGR2HSV)[..., 0].astype(int)
        lo, hi = hue[expect[name]]
        assert lo <= np.median(h) <= hi, name
    pano = stitch_panorama(frames)
    assert pano.shape == (410, 4 * 820, 3)
    assert np.array_equal(pano[:, 820:1640], frames.rear)


def test_csi_wide_angle_sees_160_degrees():
    # a narrow pillar 75 deg to the left of the front camera is inside its 160 deg view
    ang = math.radians(75)
    cx = P.csi_front_x + 2 * math.cos(ang)
    w = room(obstacles=[{"shape": "circle", "center": [cx, 2 * math.sin(ang)], "radius": 0.1, "height": 2.0, "color": "red"}])
    img = CSICameras(w).render_one("front", EAST)
    m = red_mask(img)
    assert m.sum() > 50
    # equidistant fisheye: r = f * theta on the horizon row, left of the centre
    f = 410 / (P.csi_fov / 2)
    us = np.nonzero(m[205])[0]
    assert us.mean() == pytest.approx(409.5 - f * ang, abs=4)


def test_cameras_in_a_ros_map():
    if not BERLIN.is_file():
        pytest.skip("shared/data/maps/berlin.yaml not available")
    w = load_world(BERLIN)
    f = RGBDCamera(w, rng=np.random.default_rng(0)).render(w.start)
    assert (f.depth > 0).mean() > 0.3
    csi = CSICameras(w).render(w.start)
    assert csi.front.shape == (410, 820, 3)


# --- threads, processes, the floor composited under the rest ------------------------------------
def _frames(cam_factory, poses):
    cam = cam_factory()
    return [cam.render(p, t=0.1 * i) for i, p in enumerate(poses)]


def test_cameras_in_two_threads_at_once():
    # two cameras rendering concurrently (the kernels let go of the GIL) get their own frames
    import threading

    w = load_world("track")
    poses = [(x, -1.7, 0.05 * x) for x in np.linspace(-1.0, 1.0, 12)]
    expect = _frames(lambda: RGBDCamera(w, rng=np.random.default_rng(3)), poses)
    got: dict[int, list] = {}

    def run(k: int) -> None:
        got[k] = _frames(lambda: RGBDCamera(w, rng=np.random.default_rng(3)), poses)

    threads = [threading.Thread(target=run, args=(k,)) for k in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout=60)
    for k in range(2):
        assert len(got[k]) == len(poses)
        for a, b in zip(got[k], expect, strict=True):
            assert np.array_equal(a.color, b.color) and np.array_equal(a.depth, b.depth)


def _render_in_child(q):
    w = load_world("track")
    f = RGBDCamera(w, rng=np.random.default_rng(0)).render(w.start)
    q.put(float(f.depth.mean()))


def test_camera_works_in_a_forked_child():
    # a child forked from a parent that rendered (numba's and OpenCV's state) renders the same
    import multiprocessing as mp

    if "fork" not in mp.get_all_start_methods():
        pytest.skip("no fork on this platform")
    w = load_world("track")
    parent = RGBDCamera(w, rng=np.random.default_rng(0)).render(w.start)
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    proc = ctx.Process(target=_render_in_child, args=(q,))
    proc.start()
    proc.join(timeout=60)
    assert proc.exitcode == 0
    assert q.get(timeout=5) == pytest.approx(float(parent.depth.mean()))


def test_sign_below_the_horizon_stays_over_the_floor():
    # a low stop sign (its plate below the camera) is drawn over floor pixels: the floor,
    # composited under everything else, must not cover it
    w = room(signs=[{"type": "stop", "position": [1.2, 0.0], "facing": "180deg", "size": 0.1, "height": 0.07}])
    cam = RGBDCamera(w)
    f = cam.render(EAST)
    m = red_mask(f.color)
    assert m.sum() > 200
    vs, _ = np.nonzero(m)
    assert vs.mean() > cam.intrinsics.cy + 5  # below the horizon
