"""Geometric steering controllers of the lab sheet (section 4.1) and the look-ahead target search.

All angles in rad, positions in m, world frame X right / Y up, yaw counter-clockwise from +X,
positive steering = turn left. ``pose`` is ``(x, y, yaw)`` of the car's CENTRE (the point the
sheet's bicycle model and the simulator report), except for :func:`pure_pursuit`, which takes the
rear axle's (:func:`rear_axle` converts). Each controller returns the steering angle at
the wheels ``delta``; pass ``max_steering`` (e.g. ``DEFAULT_PARAMS.max_steering`` = 0.5) to clip
it to ``[-max_steering, max_steering]``, otherwise it is returned unclipped (the car clips too).

A tick of the sheet's PathFollowing model::

    search = LookaheadTarget(path, lookahead=0.5)
    axle = rear_axle(pose)
    target, index, progress = search(axle[:2])      # l_d measured from the rear axle
    delta = pure_pursuit(axle, target, 0.5, wheelbase=0.256, max_steering=0.5)
"""

from __future__ import annotations

import math
import numbers
from bisect import bisect_right
from typing import NamedTuple

import numpy as np

from qcarlab.constants import DEFAULT_PARAMS
from qcarlab.control.tracking import Polyline
from qcarlab.errors import InputError

__all__ = [
    "LookaheadTarget",
    "Target",
    "follow_the_carrot",
    "pure_pursuit",
    "rear_axle",
    "stanley",
    "wrap_angle",
]


_PI = math.pi
_TWO_PI = 2.0 * math.pi


def wrap_angle(a: float | np.ndarray) -> float | np.ndarray:
    """Wrap an angle (or array of angles) to [-pi, pi): ``(a + pi) mod 2 pi - pi``."""
    if type(a) is float:  # the controllers' case: plain float arithmetic, no numpy on a scalar
        return (a + _PI) % _TWO_PI - _PI
    if np.ndim(a) == 0:
        return (float(a) + _PI) % _TWO_PI - _PI
    return (np.asarray(a, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi


def _clip(delta: float, max_steering: float | None) -> float:
    if max_steering is None:
        return delta
    return min(max(delta, -max_steering), max_steering)


def pure_pursuit(
    pose: np.ndarray | tuple[float, float, float],
    target: np.ndarray | tuple[float, float],
    lookahead: float | None = None,
    wheelbase: float = DEFAULT_PARAMS.wheelbase,
    *,
    max_steering: float | None = None,
) -> float:
    """Pure pursuit (sheet 4.1.4, the ``pure_pursuit`` block): ``delta = atan(2 L sin(alpha) / l_d)``.

    ``pose`` is ``(x, y, yaw)`` of the REAR AXLE, the point of the kinematic bicycle that moves
    tangent to the heading, so the arc through the target is exact there; ``target`` the
    look-ahead point ``(x, y)`` on the path::

        alpha = wrap(atan2(y_t - y_r, x_t - x_r) - yaw)       # target bearing from the heading
        l_d   = |target - (x_r, y_r)|                         # the chord to the target

    The sheet's block divides by its LookAheadDistance parameter; this one divides by the chord
    itself, which is that distance when the target lies ``lookahead`` from the axle and stays
    exact near the path's end, where the target is nearer (``lookahead`` is then not needed; it
    is used only when the target is on the axle). ``alpha > 0`` (target on the left) gives
    ``delta > 0``. Clipped to ``+-max_steering`` if given. A target on the axle itself gives 0.
    """
    xr, yr, yaw = float(pose[0]), float(pose[1]), float(pose[2])
    dx, dy = float(target[0]) - xr, float(target[1]) - yr
    dist = math.hypot(dx, dy)
    if dist == 0.0:
        return 0.0
    ld = dist if dist > 0.0 else float(lookahead or 0.0)
    alpha = (math.atan2(dy, dx) - yaw + _PI) % _TWO_PI - _PI  # wrap_angle
    delta = math.atan(2.0 * wheelbase * math.sin(alpha) / ld)
    if max_steering is None:
        return delta
    return min(max(delta, -max_steering), max_steering)


def rear_axle(pose: np.ndarray | tuple[float, float, float], wheelbase: float = DEFAULT_PARAMS.wheelbase
              ) -> tuple[float, float, float]:
    """The rear axle's pose from the centre's: ``(x - L/2 cos yaw, y - L/2 sin yaw, yaw)``."""
    x, y, yaw = float(pose[0]), float(pose[1]), float(pose[2])
    half = wheelbase / 2.0
    return (x - half * math.cos(yaw), y - half * math.sin(yaw), yaw)


def follow_the_carrot(
    pose: np.ndarray | tuple[float, float, float],
    target: np.ndarray | tuple[float, float],
    k_carrot: float = 1.0,
    *,
    max_steering: float | None = None,
) -> float:
    """Follow the carrot (sheet 4.1.3): ``delta = K_carrot * Psi_e``.

    ``Psi_e = wrap(atan2(y_t - y, x_t - x) - yaw)``: the carrot's bearing from the car's centre
    minus the heading. Clipped to ``+-max_steering`` if given.
    """
    x, y, yaw = float(pose[0]), float(pose[1]), float(pose[2])
    dx, dy = float(target[0]) - x, float(target[1]) - y
    if dx == 0.0 and dy == 0.0:
        return 0.0
    psi_e = wrap_angle(math.atan2(dy, dx) - yaw)
    return _clip(k_carrot * psi_e, max_steering)


def stanley(
    pose: np.ndarray | tuple[float, float, float],
    path: np.ndarray | Polyline,
    index: int,
    speed: float,
    k: float = 1.0,
    wheelbase: float = DEFAULT_PARAMS.wheelbase,
    *,
    softening: float = 0.1,
    window: int = 50,
    max_steering: float | None = None,
) -> float:
    """Stanley controller (beyond the sheet; Thrun et al. 2006): front-axle path tracking.

    ``delta = psi_e + atan2(k * e, softening + |v|)`` where, at the front axle
    ``p_f = (x + L/2 cos yaw, y + L/2 sin yaw)``, ``q`` is the nearest point of the path segments
    ``index - 1 .. index + window`` (``index`` from :class:`LookaheadTarget`), ``psi_e =
    wrap(theta_path - yaw)`` the heading error to that segment, and ``e = cross(t, q - p_f)`` the
    signed cross-track distance (positive when the path lies to the car's left). Clipped to
    ``+-max_steering`` if given.
    """
    poly = path if isinstance(path, Polyline) else Polyline(path)
    x, y, yaw = float(pose[0]), float(pose[1]), float(pose[2])
    fx, fy = x + 0.5 * wheelbase * math.cos(yaw), y + 0.5 * wheelbase * math.sin(yaw)
    lo = min(max(int(index) - 1, 0), poly.n - 2)
    hi = min(poly.n - 2, lo + 1 + max(int(window), 1))
    best_j, best_t, best_d = -1, 0.0, math.inf
    for j in range(lo, hi + 1):
        if poly._len[j] == 0.0:
            continue
        t, d = poly.segment_projection(j, fx, fy)
        if d < best_d:
            best_j, best_t, best_d = j, t, d
    if best_j < 0:
        return 0.0
    ax, ay = poly._x[best_j], poly._y[best_j]
    dx, dy = poly._x[best_j + 1] - ax, poly._y[best_j + 1] - ay
    seg = poly._len[best_j]
    tx, ty = dx / seg, dy / seg
    qx, qy = ax + best_t * dx, ay + best_t * dy
    e = tx * (qy - fy) - ty * (qx - fx)
    psi_e = wrap_angle(math.atan2(dy, dx) - yaw)
    return _clip(psi_e + math.atan2(k * e, softening + abs(float(speed))), max_steering)


class Target(NamedTuple):
    """What :class:`LookaheadTarget` returns: unpacks as ``point, index, progress``."""

    point: np.ndarray  # (2,) the look-ahead point, m
    index: int  # the path segment (its first vertex) the car is on
    progress: float  # arc length of the car's projection on the path, m (never decreases)


class LookaheadTarget:
    """Forward-only look-ahead point search on a path (the sheet's Pure Pursuit "LookAheadDistance").

    Each call projects ``position`` on the path searching forward from the last projection only
    (the first local minimum of the distance ahead, at most ``max_segments`` segments), so a path
    that crosses itself (the butterfly at the origin) never makes it jump to the other branch.
    The target is then the first point AFTER the projection whose distance from ``position`` is
    ``l_d``, interpolated on its segment (the circle of radius ``l_d`` about the car leaving the
    path). Special cases: the path end within ``l_d`` -> the last point; the car farther than
    ``l_d`` from the path -> the point ``l_d`` ahead of the projection along the path. Cost per
    call is O(segments walked), bounded by ``max_segments``, never O(N).

    Stateful: ``reset()`` starts again from the path's beginning.
    """

    def __init__(self, path: np.ndarray, lookahead: float, max_segments: int = 1000) -> None:
        if isinstance(lookahead, bool) or not isinstance(lookahead, numbers.Real) or not (
            math.isfinite(lookahead) and lookahead > 0.0
        ):
            raise InputError(f"look-ahead distance must be a positive number of metres, got {lookahead!r}")
        self.poly = path if isinstance(path, Polyline) else Polyline(path)
        self.lookahead = float(lookahead)
        self.max_segments = int(max_segments)
        self.reset()

    @property
    def length(self) -> float:
        """Path length, m."""
        return self.poly.length

    def reset(self) -> None:
        """Forget the progress: the next call searches from the start of the path."""
        self.index = 0
        self.progress = 0.0

    def __call__(self, position: np.ndarray | tuple[float, float]) -> Target:
        tx, ty, j, s = self.locate(float(position[0]), float(position[1]))
        return Target(np.array([tx, ty]), j, s)

    def locate(self, px: float, py: float) -> tuple[float, float, int, float]:
        """:meth:`__call__` for a position ``(px, py)`` given as floats, returning plain floats:
        ``(target_x, target_y, index, progress)`` (the lab's tick: no array is made)."""
        poly = self.poly
        ld = self.lookahead
        xs, ys = poly._x, poly._y
        j, t, d0 = poly.walk_forward(self.index, px, py, self.max_segments)
        hypot = math.hypot
        cum, seglen = poly._cum, poly._len
        s = cum[j] + t * seglen[j]
        if s < self.progress:  # never move back along the path
            s = self.progress
            t = 0.0 if seglen[j] == 0.0 else (s - cum[j]) / seglen[j]
            d0 = hypot(px - xs[j] - t * (xs[j + 1] - xs[j]), py - ys[j] - t * (ys[j + 1] - ys[j]))
        self.index, self.progress = j, s
        if d0 >= ld:  # the point l_d ahead of the projection along the path (Polyline.point_at)
            q = min(max(s + ld, 0.0), poly.length)
            i = min(max(bisect_right(cum, q) - 1, 0), poly.n - 2)
            u = 0.0 if seglen[i] == 0.0 else min(1.0, (q - cum[i]) / seglen[i])
            return xs[i] + u * (xs[i + 1] - xs[i]), ys[i] + u * (ys[i + 1] - ys[i]), j, s
        # first vertex ahead at distance >= l_d from the car
        last = j + 1 + self.max_segments
        if last > poly.n - 1:
            last = poly.n - 1
        k = j + 1
        while k <= last and hypot(xs[k] - px, ys[k] - py) < ld:
            k += 1
        if k > last:
            # nothing ahead leaves the circle: the end is within l_d (or the window is exhausted)
            return xs[last], ys[last], j, s
        if k == j + 1:
            ax, ay = xs[j] + t * (xs[j + 1] - xs[j]), ys[j] + t * (ys[j + 1] - ys[j])
        else:
            ax, ay = xs[k - 1], ys[k - 1]
        # |a + u (b - a) - p| = l_d, the exit root u in (0, 1]
        dx, dy = xs[k] - ax, ys[k] - ay
        wx, wy = ax - px, ay - py
        qa = dx * dx + dy * dy
        qb = 2.0 * (wx * dx + wy * dy)
        qc = wx * wx + wy * wy - ld * ld
        if qa == 0.0:
            u = 1.0
        else:
            disc = qb * qb - 4.0 * qa * qc
            u = (-qb + math.sqrt(0.0 if 0.0 > disc else disc)) / (2.0 * qa)  # max(disc, 0)
            if 0.0 > u:  # u = min(max(u, 0), 1), as the builtins order it
                u = 0.0
            if 1.0 < u:
                u = 1.0
        return ax + u * dx, ay + u * dy, j, s
