"""Getting out of a moving obstacle's way (sheet 6.1 Task 4; the race-car report's rolling ball):
a few manoeuvres are tried ahead of time on a model of the car, and the one that keeps the car
farthest from the obstacle, without touching a wall, is driven. Pure: numpy in, numbers out.

The obstacle (a :class:`~qcarlab.control.moving_obstacles.Track`: centre ``b``, velocity over the
ground ``u``, radius ``rho``) is taken to go on in a straight line, ``b(t) = b + u t``. Each
manoeuvre is a target line and a speed: drive (or back up, at a negative speed) along the line
parallel to the obstacle's track at a lateral offset ``y_t`` from it (for an obstacle that comes
at the car head-on; for one that crosses, the line of the car's own heading). One steering law
drives every manoeuvre, on the model and on the car (:func:`offset_steering`)::

    y      = (p - o) . n,   psi = heading - heading of the line          (the car on the line's frame)
    psi_d  = sign(v) clip(atan((y_t - y) / l), -psi_max, psi_max)       (head for the offset line
                                                                         l = max(0.35 m, 0.9 s |v|) ahead)
    delta  = clip(atan(L k_psi (psi_d - psi) / v), -0.5, 0.5)          (turn the heading there)

The model (:func:`rollout`) is the kinematic bicycle about the car's centre the simulator uses
(``beta = atan(tan(delta) / 2)``, ``psi' = v cos(beta) tan(delta) / L``), the steering servo's
first-order lag (``steering_tau`` + 40 ms of command delay), and the speed reaching its reference
at up to ``accel`` m/s^2 (the PI controller at the 0.3 throttle limit: about 2 m/s^2). Each
manoeuvre's clearances over the horizon: to the obstacle, the distance from its predicted centre to
the car's footprint less ``rho``; to the walls, the nearest static LIDAR return to the footprint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from qcarlab.constants import DEFAULT_PARAMS, QCarParams

# (the compiled kernels, qcarlab.control._kernels, are imported where first called: importing numba
# costs some 0.2 s, which a process that only lists the labs' blocks, as the grader does, need not pay)

__all__ = ["Manoeuvre", "Obstacle", "LineFrame", "choose", "line_frame", "offset_steering", "rollout"]

LOOK_MIN = 0.35  # m: the offset line is aimed at at least this far ahead ...
LOOK_TIME = 0.9  # s: ... or this many seconds of driving (a fast car slants in more gently)
PSI_MAX = 0.5  # rad: the steepest heading towards the offset line
K_PSI = 2.5  # 1/s: how fast the heading error is turned away
HEAD_ON = math.radians(60.0)  # a track within this of the car's reverse heading comes at it head-on


@dataclass(frozen=True)
class Obstacle:
    """A moving obstacle now: centre (m, body frame), velocity over the ground (m/s), radius (m)."""

    x: float
    y: float
    vx: float
    vy: float
    radius: float


@dataclass(frozen=True)
class LineFrame:
    """A line through ``origin`` along the unit vector ``e`` (body frame); ``n`` is ``e`` turned left."""

    ox: float
    oy: float
    ex: float
    ey: float

    @property
    def heading(self) -> float:
        return math.atan2(self.ey, self.ex)

    def lateral(self, x, y):
        """Signed distance (m, + = left of the line) of the point(s) (x, y)."""
        return (np.asarray(x) - self.ox) * -self.ey + (np.asarray(y) - self.oy) * self.ex


@dataclass(frozen=True)
class Manoeuvre:
    """Drive at ``speed`` (m/s; < 0 backs up) to the line ``offset`` m to the left of ``frame``'s
    line (``None``: keep the wheels straight)."""

    name: str
    speed: float
    offset: float | None


def line_frame(ob: Obstacle) -> LineFrame:
    """The frame the manoeuvres are set in: the obstacle's track, pointing the way the car drives,
    when it comes at the car head-on; else the car's own heading through its centre."""
    sp = math.hypot(ob.vx, ob.vy)
    if sp > 1e-6:
        ex, ey = -ob.vx / sp, -ob.vy / sp  # against the obstacle's motion
        if math.acos(max(-1.0, min(1.0, ex))) <= HEAD_ON:
            return LineFrame(ob.x, ob.y, ex, ey)
    return LineFrame(0.0, 0.0, 1.0, 0.0)


def offset_steering(y, psi, v, offset: float, params: QCarParams = DEFAULT_PARAMS):
    """The steering (rad) that takes a car at lateral position ``y`` (m) with heading ``psi`` (rad,
    both in the line's frame) at speed ``v`` (m/s, signed) to the line at ``offset``; see the module
    docstring. Works on arrays (broadcast), compiled (:func:`qcarlab.control._kernels.offset_steer`)."""
    from qcarlab.control._kernels import offset_steer

    law = (float(params.wheelbase), float(params.max_steering), LOOK_MIN, LOOK_TIME, PSI_MAX, K_PSI)
    if all(np.ndim(a) == 0 for a in (y, psi, v, offset)):
        return offset_steer(float(y), float(psi), float(v), float(offset), *law)
    y, psi, v, offset = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (y, psi, v, offset)))
    out = np.empty(y.shape)
    for i in np.ndindex(y.shape):
        out[i] = offset_steer(float(y[i]), float(psi[i]), float(v[i]), float(offset[i]), *law)
    return out


def _footprint_distance(px, py, cx, cy, cyaw, half_len, half_wid):
    """Distance (m) from points (px, py) to car rectangles at (cx, cy, cyaw); broadcasting."""
    c, s = np.cos(cyaw), np.sin(cyaw)
    dx, dy = px - cx, py - cy
    u = np.abs(c * dx + s * dy) - half_len
    w = np.abs(-s * dx + c * dy) - half_wid
    return np.hypot(np.maximum(u, 0.0), np.maximum(w, 0.0))


def rollout(manoeuvres: list[Manoeuvre], obstacles: list[Obstacle], frame: LineFrame, static: np.ndarray,
            v0: float, delta0: float, params: QCarParams = DEFAULT_PARAMS, horizon: float = 4.0,
            dt: float = 0.05, accel: float = 2.0, delay: float = 0.04,
            period: float = 0.1, wall_cap: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
    """Drive every manoeuvre on the model from the car's state now (centre at the origin, heading 0,
    speed ``v0``, wheels at ``delta0``) for ``horizon`` s, the steering law evaluated once a
    ``period`` (a LIDAR scan) and held; return each one's smallest clearance (m) to the obstacles
    and to the ``static`` points ((m, 2), body frame) over that time, and, for the obstacles, as
    they roll on 4 m past the horizon with the car standing where it got to. ``wall_cap`` (m): a
    wall clearance of ``wall_cap`` or more may come back as ``inf`` (only the points that may be
    nearer are measured: those within ``wall_cap`` plus the footprint's half diagonal of the
    box round a manoeuvre's positions); below it, the same number."""
    from qcarlab.control._kernels import drive_paths

    k = len(manoeuvres)
    vref = np.array([m.speed for m in manoeuvres], dtype=float)
    off = np.array([0.0 if m.offset is None else m.offset for m in manoeuvres], dtype=float)
    free = np.array([m.offset is None for m in manoeuvres], dtype=bool)
    steps = int(round(horizon / dt))
    hold = max(1, int(round(period / dt)))  # a new command on each scan, held between them as the car does
    xs, ys, yaws = drive_paths(float(v0), float(delta0), vref, off, free, float(frame.ox), float(frame.oy),
                               float(frame.ex), float(frame.ey), float(frame.heading), float(params.wheelbase),
                               float(params.max_steering), float(params.steering_tau + delay), steps, float(dt),
                               float(accel), hold, LOOK_MIN, LOOK_TIME, PSI_MAX, K_PSI)
    x, y, yaw = (a[-1] if steps else np.zeros(k) for a in (xs, ys, yaws))  # where each manoeuvre got to
    hl, hw = params.length / 2.0, params.width / 2.0
    t = (np.arange(steps) + 1) * dt
    ball = np.full(k, np.inf)
    for ob in obstacles:
        bx = (ob.x + ob.vx * t)[:, None]
        by = (ob.y + ob.vy * t)[:, None]
        ball = np.minimum(ball, (_footprint_distance(bx, by, xs, ys, yaws, hl, hw) - ob.radius).min(axis=0))
        # after the horizon the car is taken to stand where it got to, the obstacle to roll 4 m on
        sp = max(math.hypot(ob.vx, ob.vy), 0.2)
        t_on = horizon + np.arange(1, 81) * (0.05 / sp)
        bx = (ob.x + ob.vx * t_on)[:, None]
        by = (ob.y + ob.vy * t_on)[:, None]
        ball = np.minimum(ball, (_footprint_distance(bx, by, x[None, :], y[None, :], yaw[None, :], hl, hw)
                                 - ob.radius).min(axis=0))
    wall = np.full(k, np.inf)
    pts = np.asarray(static, dtype=float).reshape(-1, 2)
    if len(pts):  # every 0.1 s of the way is enough for the walls (the car moves < 10 cm)
        every = max(1, int(round(0.1 / dt)))
        xw, yw, aw = xs[every - 1::every, :, None], ys[every - 1::every, :, None], yaws[every - 1::every, :, None]
        if math.isinf(wall_cap):
            dist = _footprint_distance(pts[None, None, :, 0], pts[None, None, :, 1], xw, yw, aw, hl, hw)
            wall = dist.min(axis=(0, 2))
        else:  # a point farther than reach from every position of the car is farther than wall_cap from it
            reach = math.hypot(hl, hw) + wall_cap + 1e-6
            lo_x, hi_x = xw.min(axis=0)[:, 0] - reach, xw.max(axis=0)[:, 0] + reach
            lo_y, hi_y = yw.min(axis=0)[:, 0] - reach, yw.max(axis=0)[:, 0] + reach
            px, py = pts[:, 0], pts[:, 1]
            for j in range(k):
                sel = (px >= lo_x[j]) & (px <= hi_x[j]) & (py >= lo_y[j]) & (py <= hi_y[j])
                if sel.any():
                    wall[j] = _footprint_distance(px[sel][None, :], py[sel][None, :], xw[:, j], yw[:, j], aw[:, j],
                                                  hl, hw).min()
    return np.maximum(ball, 0.0), np.maximum(wall, 0.0)


def choose(manoeuvres: list[Manoeuvre], ball: np.ndarray, wall: np.ndarray, current: str | None = None,
           y_car: float = 0.0, side: float = 0.0, want_ball: float = 0.3, want_wall: float = 0.15) -> int:
    """The manoeuvre to drive: the largest ``min(ball, want_ball) + min(wall, want_wall)`` (as
    far from the obstacle as from the walls, up to enough of each), less 1 cm per 0.1 m the car
    has to move across (from ``y_car``, its lateral position in the manoeuvres' frame), 8 cm for
    backing up and 1 m for touching a wall; plus 3 cm for the one being driven, 5 cm for one of
    its kind (ahead or backing up, to a line or not) and 5 cm for moving across to ``side`` (+1
    left, -1 right: the side chosen before), so the choice does not flip between scans on a
    centimetre."""
    best, best_s = 0, -math.inf
    cur = next((m for m in manoeuvres if m.name == current), None)
    for i, m in enumerate(manoeuvres):
        s = min(float(ball[i]), want_ball) + min(float(wall[i]), want_wall)
        s -= 0.1 * abs((y_car if m.offset is None else m.offset) - y_car) + (0.08 if m.speed < 0.0 else 0.0)
        if float(wall[i]) <= 0.01:
            s -= 1.0  # touches a wall
        if m.name == current:
            s += 0.03
        if cur is not None and (m.speed < 0.0) == (cur.speed < 0.0) and (m.offset is None) == (cur.offset is None):
            s += 0.05  # going on the way it goes (not from ahead to backing up on a centimetre)
        if side and m.offset is not None and (m.offset - y_car) * side > 0.0:
            s += 0.05  # the side already chosen
        if s > best_s:
            best, best_s = i, s
    return best
