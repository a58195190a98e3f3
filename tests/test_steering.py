"""Steering controllers' equations, the forward-only look-ahead search, and tracking errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qcarlab import paths
from qcarlab.control import steering, tracking
from qcarlab.control.steering import LookaheadTarget, follow_the_carrot, pure_pursuit, rear_axle, stanley, wrap_angle
from qcarlab.control.tracking import cross_track_errors, progress_along
from qcarlab.errors import InputError

L = 0.256
START = (0.0, 0.0, -math.pi / 2)  # the sheet's start pose, heading -Y


def test_wrap_angle():
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    assert wrap_angle(-7.0) == pytest.approx(-7.0 + 2 * math.pi)
    assert wrap_angle(math.pi) == pytest.approx(-math.pi)
    assert np.allclose(wrap_angle(np.array([0.0, 2 * math.pi + 0.1, -0.1])), [0.0, 0.1, -0.1])


def test_pure_pursuit_equation():
    # pose is the rear axle; target straight ahead -> no steering
    assert pure_pursuit(START, (0.0, -1.0), 0.5, L) == 0.0
    # target 90 deg to the left of the rear axle at distance l_d -> atan(2 L / l_d) > 0
    ld = 0.5
    d = pure_pursuit((0.0, 0.0, 0.0), (0.0, ld), ld, L)
    assert d == pytest.approx(math.atan(2 * L / ld)) and d > 0
    # from the centre's pose through rear_axle: the axle is L/2 behind the centre
    assert pure_pursuit(rear_axle((0.0, 0.0, 0.0), L), (-L / 2, ld), ld, L) == pytest.approx(math.atan(2 * L / ld))
    # heading -Y: the car's left is +X
    assert pure_pursuit(START, (ld, 0.0), ld, L) == pytest.approx(math.atan(2 * L / ld))
    assert pure_pursuit(START, (-ld, 0.0), ld, L) == pytest.approx(-math.atan(2 * L / ld))
    # l_d is the chord to the target (exact near the path's end, where the target is nearer)
    d45 = pure_pursuit((0, 0, 0), (1.0, 1.0), 2.0, L)
    assert d45 == pytest.approx(math.atan(2 * L * math.sin(math.pi / 4) / math.sqrt(2.0)))
    # clipping only when asked
    assert pure_pursuit((0, 0, 0), (0.0, 0.1), 0.1, L) > 0.5236
    assert pure_pursuit((0, 0, 0), (0.0, 0.1), 0.1, L, max_steering=0.5236) == 0.5236
    assert pure_pursuit((0, 0, 0), (0.0, -0.1), 0.1, L, max_steering=0.5236) == -0.5236


def test_pure_pursuit_arc_passes_through_the_target():
    rear = np.array([0.3, -0.2])
    yaw = 0.7
    target = np.array([0.9, 0.6])
    delta = pure_pursuit((*rear, yaw), target, 1.0, L)
    radius = L / math.tan(delta)  # rear-axle turning radius of the bicycle
    centre = rear + radius * np.array([-math.sin(yaw), math.cos(yaw)])
    assert np.hypot(*(target - centre)) == pytest.approx(abs(radius))


def test_follow_the_carrot_sign_and_gain():
    # carrot ahead-left of a car heading -Y: bearing -45 deg, heading -90 deg -> Psi_e = +45 deg
    assert follow_the_carrot(START, (1.0, -1.0), 1.0) == pytest.approx(math.pi / 4)
    assert follow_the_carrot(START, (1.0, -1.0), 2.0) == pytest.approx(math.pi / 2)
    assert follow_the_carrot(START, (-1.0, -1.0), 1.0) == pytest.approx(-math.pi / 4)
    assert follow_the_carrot(START, (0.0, -2.0), 3.0) == 0.0
    # wrapped across +-pi: heading 3.0 rad, carrot at bearing -3.0 rad -> small left turn
    pose = (0.0, 0.0, 3.0)
    assert follow_the_carrot(pose, (math.cos(-3.0), math.sin(-3.0)), 1.0) == pytest.approx(2 * math.pi - 6.0)
    assert follow_the_carrot(START, (1.0, -1.0), 2.0, max_steering=0.5236) == 0.5236


def test_stanley_cross_track_and_heading_terms():
    path = np.array([[-1.0, 0.0], [0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    # on the path, aligned -> 0
    assert stanley((0.0, 0.0, 0.0), path, 1, 0.5, k=1.0, wheelbase=L) == pytest.approx(0.0)
    # path 0.1 m to the car's left -> steer left by atan2(k e, soft + v)
    d = stanley((0.0, -0.1, 0.0), path, 1, 0.5, k=2.0, wheelbase=L, softening=0.1)
    assert d == pytest.approx(math.atan2(2.0 * 0.1, 0.6))
    assert stanley((0.0, 0.1, 0.0), path, 1, 0.5, k=2.0, wheelbase=L) < 0
    # heading error only: front axle on the path (centre behind it), yaw 0.1 -> delta = -0.1
    pose = (-(L / 2) * math.cos(0.1), -(L / 2) * math.sin(0.1), 0.1)
    assert stanley(pose, path, 1, 0.5, wheelbase=L) == pytest.approx(-0.1)


def test_lookahead_interpolates_and_stops_at_the_end():
    p1 = paths.line(3, 4)
    search = LookaheadTarget(p1, lookahead=0.5)
    point, index, progress = search((0.0, -1.2))
    assert np.allclose(point, [0.0, -1.7]) and index == 1 and progress == pytest.approx(1.2)
    # off the path by 0.3: the circle of radius 0.5 meets the path 0.4 further on
    point, _, progress = search((0.3, -2.0))
    assert np.allclose(point, [0.0, -2.4]) and progress == pytest.approx(2.0)
    # the end within l_d: the last point
    point, index, progress = search((0.0, -2.7))
    assert np.array_equal(point, [0.0, -3.0]) and index == 2
    point, _, progress = search((0.0, -3.5))  # past the end
    assert np.array_equal(point, [0.0, -3.0]) and progress == pytest.approx(3.0)
    # farther than l_d from the path: the point l_d ahead of the projection
    search.reset()
    point, index, progress = search((2.0, -1.0))
    assert np.allclose(point, [0.0, -1.5]) and progress == pytest.approx(1.0)
    # the start: a car at (0,0) heading -Y aims l_d down the line
    search.reset()
    assert np.allclose(search((0.0, 0.0)).point, [0.0, -0.5])


def test_lookahead_never_moves_back():
    search = LookaheadTarget(paths.line(3, 4), lookahead=0.5)
    search((0.0, -2.0))
    point, _, progress = search((0.0, -0.5))  # the car moved back: progress is kept
    assert progress == pytest.approx(2.0) and np.allclose(point, [0.0, -2.5])


def test_lookahead_stays_on_the_butterfly_branch_through_the_crossing():
    p4 = paths.butterfly(2, 2)
    poly = tracking.Polyline(p4)
    ld = 0.5
    search = LookaheadTarget(p4, lookahead=ld)
    # drive the first wing, 2 cm to the side of the path, up to and through the mid crossing
    n = np.gradient(p4[1:], axis=0)[:, ::-1] * [1, -1]
    n /= np.hypot(*n.T)[:, None]
    driven = p4[1:] + 0.02 * n
    last = -1.0
    for i in range(1, 600):
        point, index, progress = search(driven[i])
        assert progress >= last
        last = progress
        # the target is on the path about l_d ahead, never on the other branch
        _, s_target = poly.nearest(point[None])
        assert progress <= s_target[0] <= progress + 1.5 * ld, i
    # at the crossing itself: a fresh search that has followed the first wing, fed the origin
    search.reset()
    for i in range(1, 450):
        search(p4[i])
    point, _, progress = search((0.0, 0.0))
    assert progress == pytest.approx(poly.length / 2, abs=0.05)
    assert point[0] < 0 and point[1] < 0  # continues into the second wing (x<0, y<0)
    # a global nearest-point search would have picked the start of the path instead
    assert tracking.progress_along([(0.0, 0.0)], p4, ordered=False)[0] == 0.0


class _CountingList(list):
    """A list that counts the items read from it (the walks index the path's vertex lists)."""

    reads = 0

    def __getitem__(self, i):
        _CountingList.reads += 1
        return super().__getitem__(i)


def test_lookahead_cost_is_bounded_by_its_window():
    dense = np.column_stack([np.zeros(200_001), -np.arange(200_001) * 1e-3])  # 200 m, 1 mm steps
    search = LookaheadTarget(dense, lookahead=0.5, max_segments=50)
    search.poly._x = _CountingList(search.poly._x)  # every segment walked reads its vertex's x
    _CountingList.reads = 0
    point, index, progress = search((0.0, -150.0))  # far ahead: at most max_segments are walked
    assert index == 50 and np.allclose(point, [0.0, -0.551])
    assert 51 <= _CountingList.reads <= 60
    _CountingList.reads = 0
    for y in np.arange(0.05, 0.06, 0.001):
        search((0.0, -y))
    # a few segments per tick when the car moves a few mm, plus the target's scan, which the
    # window also bounds (50 vertices, not the 500 within l_d): nothing like the path's 200,000
    assert 11 * 50 <= _CountingList.reads <= 11 * 60


def test_lookahead_rejects_bad_lookahead():
    for bad in (0, -0.5, float("nan"), "far", True):
        with pytest.raises(InputError, match="look-ahead"):
            LookaheadTarget(paths.line(), lookahead=bad)


def test_cross_track_errors_hand_cases():
    path = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0]])
    pts = np.array([[1.0, 1.0], [-1.0, 0.0], [3.0, 4.0], [1.0, -0.5], [2.5, 1.0], [2.0, 1.0]])
    assert np.allclose(cross_track_errors(pts, path), [1.0, 1.0, math.hypot(1, 2), 0.5, 0.5, 0.0])
    assert cross_track_errors(np.zeros((0, 2)), path).shape == (0,)
    # many points against the butterfly, chunked: matches a brute-force loop
    p4 = paths.butterfly(2, 2)
    rng = np.random.default_rng(1)
    pts = rng.uniform(-2.5, 2.5, size=(3000, 2))
    e = cross_track_errors(pts, p4)
    a, d = p4[:-1], np.diff(p4, axis=0)
    l2 = (d**2).sum(1)
    for q, ei in zip(pts[:50], e[:50], strict=True):
        t = np.clip(((q - a) * d).sum(1) / np.where(l2 > 0, l2, 1), 0, 1)
        assert ei == pytest.approx(np.hypot(*(a + t[:, None] * d - q).T).min(), abs=1e-12)


def test_progress_along():
    path = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0]])
    pts = np.array([[0.5, 0.1], [1.9, -0.2], [2.2, 1.0], [2.0, 2.5]])
    assert np.allclose(progress_along(pts, path), [0.5, 1.9, 3.0, 4.0])
    assert np.allclose(progress_along(pts, path, ordered=False), [0.5, 1.9, 3.0, 4.0])
    # the butterfly driven in order: progress follows the arc length to the end (no jump to 0)
    p4 = paths.butterfly(2, 2)
    s = progress_along(p4, p4)
    assert np.all(np.diff(s) >= 0) and s[-1] == pytest.approx(paths.path_length(p4))
    assert np.allclose(s, tracking.Polyline(p4).cum)


def test_control_imports_no_car_sim_net_or_cli():
    import ast
    import inspect

    for mod in (steering, tracking):
        tree = ast.parse(inspect.getsource(mod))
        names = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
        names += [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
        assert not [m for m in names if m and m.split(".")[:2][-1] in {"car", "sim", "net", "cli"}]
