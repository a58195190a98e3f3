"""The fast scoring geometry gives the same numbers, bit for bit, as the plain definitions.

``Polyline.nearest`` only evaluates the segments that can hold a point's nearest, and
``progress_along`` walks a trajectory in vectorised blocks; both must agree exactly with the
straightforward computations they replaced (every segment; one ``walk_forward`` per point).
"""

from __future__ import annotations

import numpy as np
import pytest

from qcarlab import paths
from qcarlab.control.tracking import Polyline, cross_track_errors, progress_along


def nearest_all_segments(points, path):
    """The definition as nearest() computed it before: every point against every segment (the
    same float operations), ties to the earliest segment."""
    poly = Polyline(path)
    q = np.asarray(points, dtype=float).reshape(-1, 2)
    ax, ay = poly.points[:-1, 0], poly.points[:-1, 1]
    dx, dy = np.diff(poly.points[:, 0]), np.diff(poly.points[:, 1])
    l2 = poly.seglen**2
    inv = np.divide(1.0, l2, out=np.zeros_like(l2), where=l2 > 0.0)
    ux, uy, c0 = dx * inv, dy * inv, (ax * dx + ay * dy) * inv
    qx, qy = q[:, 0:1], q[:, 1:2]
    t = np.clip(qx * ux + qy * uy - c0, 0.0, 1.0)
    ex = (ax + t * dx - qx) ** 2 + (ay + t * dy - qy) ** 2
    k = np.argmin(ex, axis=1)
    r = np.arange(len(k))
    return np.sqrt(ex[r, k]), poly.cum[k] + t[r, k] * poly.seglen[k]


def progress_point_by_point(points, path):
    """The definition: walk_forward from the previous point's segment, the running maximum."""
    poly = Polyline(path)
    out, j, best = [], 0, 0.0
    for px, py in np.asarray(points, dtype=float).reshape(-1, 2).tolist():
        j, t, _ = poly.walk_forward(j, px, py, poly.n)
        best = max(best, poly._cum[j] + t * poly._len[j])
        out.append(best)
    return np.array(out)


def driven(path, step, offset, rng, laps=1):
    """A car's trajectory along ``path``: ``step`` m apart, ``offset`` m of noise to the side."""
    p = np.vstack([path] + [path[1:]] * (laps - 1))
    seg = np.hypot(*np.diff(p, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    at = np.arange(0.0, s[-1], step)
    pts = np.c_[np.interp(at, s, p[:, 0]), np.interp(at, s, p[:, 1])]
    return pts + rng.normal(0.0, offset, pts.shape), p


CASES = [
    ("circle, 3 laps", paths.circle(), 0.005, 0.003, 3),
    ("butterfly p3", paths.butterfly(4, 4), 0.005, 0.01, 1),
    ("butterfly p4", paths.butterfly(2, 2), 0.005, 0.02, 1),
    ("line", paths.line(3, 4), 0.005, 0.05, 1),
    ("circle, coarse steps", paths.circle(), 0.05, 0.1, 2),
]


@pytest.mark.parametrize(("name", "path", "step", "offset", "laps"), CASES, ids=[c[0] for c in CASES])
def test_nearest_and_progress_equal_the_definitions(name, path, step, offset, laps):
    rng = np.random.default_rng(3)
    pts, route = driven(path, step, offset, rng, laps)
    dist, s = Polyline(route).nearest(pts)
    ref_dist, ref_s = nearest_all_segments(pts, route)
    assert np.array_equal(dist, ref_dist) and np.array_equal(s, ref_s)
    assert np.array_equal(progress_along(pts, route), progress_point_by_point(pts, route))


def test_progress_walk_decides_near_ties_like_the_scalar_walk():
    # a right angle: points on the bisector are equally far from both legs (a tie at every
    # point), points 1e-13 m either side of it, a point far away and a NaN (the walk runs on)
    corner = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.0, 2.0], [3.0, 2.0]])
    u = np.linspace(0.2, 0.8, 200)
    tie = np.c_[1.0 - u * 0.3, u * 0.3]
    # and points whose distances to the two legs differ by the walk's own 1e-12, give or take
    # a few ulps (the numpy distances leave those to the scalar code)
    y = np.repeat(np.linspace(0.2, 0.4, 20), 11)
    edge = np.c_[1.0 - y - 1e-12 + np.tile(np.arange(-5, 6), 20) * 2e-16, y]
    pts = np.vstack([tie, tie + 1e-13, tie - 1e-13, [[5.0, 5.0]], [[np.nan, 0.5]], tie[::-1] + [0.0, 1.0]])
    k = np.tile(np.arange(-5, 6), 20)
    pts = np.vstack([edge[k < 0], edge[k == 0], edge[k > 0], pts])  # the walk stays at the first leg while it can
    for route in (corner, np.repeat(corner, 2, axis=0)):  # and with zero-length segments
        assert np.array_equal(progress_along(pts, route), progress_point_by_point(pts, route))
        poly = Polyline(route)
        j, walked = 0, []
        for px, py in pts.tolist():
            j = poly.walk_forward(j, px, py, poly.n)[0]
            walked.append(j)
        assert poly.walk_trajectory(pts).tolist() == walked  # the vectorised walk itself
    # a walk that must cross many segments in one point (a jump ahead of the window)
    dense = np.c_[np.linspace(0.0, 10.0, 2001), np.zeros(2001)]
    jump = np.array([[0.0, 0.1], [0.001, 0.1], [7.5, 0.1], [7.5, 0.2], [9.9, -0.1]])
    assert np.array_equal(progress_along(jump, dense), progress_point_by_point(jump, dense))
    poly = Polyline(dense)
    j, walked = 0, []
    for px, py in jump.tolist():
        j = poly.walk_forward(j, px, py, poly.n)[0]
        walked.append(j)
    assert poly.walk_trajectory(jump).tolist() == walked == [0, 0, 1500, 1500, 1980]


def test_cross_track_of_scattered_points_equals_the_definition():
    rng = np.random.default_rng(5)
    route = paths.butterfly(2, 2)
    pts = rng.uniform(-3.0, 3.0, (300, 2))  # no order at all: blocks are wide, the result the same
    assert np.array_equal(cross_track_errors(pts, route), nearest_all_segments(pts, route)[0])
