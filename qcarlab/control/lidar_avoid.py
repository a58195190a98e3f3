"""LIDAR obstacle detection and avoidance (lab sheet section 6.1): the sheet's two MATLAB Function
blocks and the Task 4 combination. Pure: numpy in, numbers out; no car, no I/O.

Every function takes the scan as the car gives it (:class:`qcarlab.sensors.LidarScan`): ``angles``
in the body frame, counter-clockwise from forward (REP-103: + = left), ``ranges`` in metres from
the LIDAR, ``0`` = no return. A return is the body-frame point ``x = r cos(theta)`` (forward),
``y = r sin(theta)`` (left). On the QCar the LIDAR sits on the roof just behind the car's centre
(``QCarParams.lidar_x = -0.0108``), so its front bumper is ``length / 2 - lidar_x = 0.223 m`` ahead of the LIDAR:
a stop distance is measured from the LIDAR, as the sheet's function sees it.

- :func:`lidar_stop` ("LIDAR Stop.slx", Figure 60): speed only, 0 when an obstacle is near.
- :func:`lidar_steer` ("LIDAR Basic/Base.slx", Figure 61): steering only, up to +-0.5 rad away
  from the obstacle; the speed is untouched.
- :class:`LidarAvoid` (Task 4, open problem): both at once, as the window state machine of the
  race-car team's report (Stop, Straight, Straight Left/Right, Turn Left/Right, Back) with LIDAR
  windows along the arcs the car can drive (:func:`free_distance`) and a back-up recovery; and,
  for the report's rolling ball, the small objects tracked from scan to scan
  (:mod:`qcarlab.control.moving_obstacles`) and a moving one dodged (:mod:`qcarlab.control.dodge`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from qcarlab.beams import cos_sin
from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.control.dodge import Manoeuvre, Obstacle, choose, line_frame, offset_steering, rollout
from qcarlab.control.moving_obstacles import Motion, PreparedScan, Track, Tracker, prepare_scan, scan_clusters, scan_motion

__all__ = ["LidarAvoid", "STATES", "forward_range", "free_distance", "lidar_steer", "lidar_stop",
           "rear_free_distance", "scan_points"]

MAX_STEER = 0.5  # rad, the sheet's steering strategy's limit


def scan_points(ranges, angles, lidar_x: float = 0.0) -> np.ndarray:
    """The returns as (m, 2) points in the car's body frame (x forward, y left) about its centre;
    beams without a return (range 0, or not finite) are dropped. ``lidar_x``: the LIDAR's offset
    ahead of the centre (0 on the QCar)."""
    r = np.asarray(ranges, dtype=float)
    cos_a, sin_a = cos_sin(np.asarray(angles, dtype=float))
    ok = np.isfinite(r) & (r > 0.0)
    r = r[ok]
    return np.column_stack((lidar_x + r * cos_a[ok], r * sin_a[ok]))


def forward_range(ranges, angles, half_width: float = 0.15) -> float:
    """Nearest range (m) among the returns in the forward window, ``inf`` if the window is empty.

    The window is the corridor the car drives through when it goes straight: returns with
    ``x = r cos(theta) > 0`` and ``|y| = |r sin(theta)| <= half_width``. A corridor, not a cone:
    a cone of +-10 deg is only +-7 cm wide at 0.4 m, narrower than the car (0.192 m).
    """
    r = np.asarray(ranges, dtype=float)
    cos_a, sin_a = cos_sin(np.asarray(angles, dtype=float))
    ok = np.isfinite(r) & (r > 0.0)
    x, y = r * cos_a, r * sin_a
    sel = ok & (x > 0.0) & (np.abs(y) <= half_width)
    return float(r[sel].min()) if sel.any() else math.inf


def lidar_stop(ranges, angles, desired_speed: float, stop_distance: float = 0.4, half_width: float = 0.15) -> float:
    """The sheet's stop strategy ("LIDAR Stop", Figure 60): the speed to command.

        v = 0              if some return in the forward window has r < stop_distance
        v = desired_speed  otherwise

    The forward window is :func:`forward_range`'s corridor of +-``half_width`` (m) ahead of the
    car (0.15 m: the car's half width 0.096 m plus 5 cm). ``stop_distance`` is measured from the
    LIDAR (by the car's centre, 0.223 m behind the front bumper). Acts on the speed only.
    """
    return 0.0 if forward_range(ranges, angles, half_width) < stop_distance else float(desired_speed)


def lidar_steer(
    ranges,
    angles,
    desired_speed: float = 0.0,
    detect_distance: float = 1.0,
    full_distance: float = 0.4,
    fov: float = math.radians(90.0),
    max_steering: float = MAX_STEER,
) -> float:
    """The sheet's steering strategy ("LIDAR Basic/Base", Figure 61): the steering angle (rad).

    Take the nearest return (r*, theta*) with ``|theta| <= fov`` and ``r < detect_distance``; steer
    away from its side, harder the closer it is::

        delta = -sign(theta*) * max_steering * clip((detect_distance - r*) / (detect_distance - full_distance), 0, 1)

    so an obstacle on the left (theta* > 0) gives a right turn (delta < 0), full lock (0.5 rad)
    from ``full_distance`` in. An obstacle dead ahead (theta* = 0) is passed on the side with
    more room (the side whose nearest return in the window is farther; left on a tie). Nothing in
    the window: 0. ``desired_speed`` is the sheet's input (the block's fixed signature is
    ``lidar_steer(distances, headings, desired_speed)``); the speed is not this block's business
    (the sheet: "the speed remains untouched"), so the reference does not use it.
    """
    r = np.asarray(ranges, dtype=float)
    a = np.remainder(np.asarray(angles, dtype=float) + math.pi, 2.0 * math.pi) - math.pi
    sel = np.isfinite(r) & (r > 0.0) & (np.abs(a) <= fov) & (r < detect_distance)
    if not sel.any():
        return 0.0
    rs, as_ = r[sel], a[sel]
    i = int(np.argmin(rs))
    r_star, th = float(rs[i]), float(as_[i])
    if th > 0.0:
        side = 1.0
    elif th < 0.0:
        side = -1.0
    else:  # dead ahead: the obstacle counts as being on the side with less room
        left, right = rs[as_ > 0.0], rs[as_ < 0.0]
        room_left = float(left.min()) if left.size else math.inf
        room_right = float(right.min()) if right.size else math.inf
        side = -1.0 if room_left >= room_right else 1.0
    span = max(detect_distance - full_distance, 1e-9)
    gain = min(1.0, max(0.0, (detect_distance - r_star) / span))
    return -side * max_steering * gain


def free_distance(
    points: np.ndarray,
    steering: float,
    params: QCarParams = DEFAULT_PARAMS,
    margin: float = 0.05,
    horizon: float = 3.0,
) -> float:
    """How far (m, along the path of the car's centre) the car can drive forward with the wheels at
    ``steering`` before its footprint, grown by ``margin``, meets one of ``points`` (body frame
    about the centre, from :func:`scan_points`). Capped at ``horizon``.

    Straight (steering 0): the corridor ``|y| <= w = width/2 + margin`` ahead of the front bumper::

        d = min over points with |y| <= w and x >= length/2 of (x - length/2)

    Turning: the kinematic bicycle turns about ``C = (-L/2, R)`` with ``R = L / tan(delta)`` (the
    rear axle's radius; L the wheelbase). With ``a = L/2 + length/2`` (rear axle to front bumper)
    and ``R_in = |R| - w``, the footprint sweeps the annulus ``R_in <= rho <= hypot(|R| + w, a)``.
    A point at ``rho = |P - C|`` and at angle ``phi`` around C (0 at the rear axle, + in the
    direction of travel) is first touched by the car's leading edge at that radius, at angle::

        phi_lead = acos(R_in / rho)   if rho <= hypot(a, R_in)   (the inner side)
                 = asin(a / rho)      otherwise                 (the front bumper)

    and the centre then has driven ``(phi - phi_lead) * hypot(R, L/2)``. Points beside or behind
    the leading edge (``phi < phi_lead``) are not in the way of forward motion. Compiled
    (:func:`qcarlab.control._kernels.free_distance`: one pass over the points).
    """
    from qcarlab.control._kernels import free_distance as kernel

    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    # (fresh writable float64 columns and Python floats: the one signature compiled, whatever came in; a
    # student's sandboxed process cannot write numba's cache, so it must never need another)
    return float(kernel(pts[:, 0].copy(), pts[:, 1].copy(), float(steering), float(params.length) / 2.0,
                        float(params.width) / 2.0 + float(margin), float(params.wheelbase), float(horizon)))


def rear_free_distance(points: np.ndarray, params: QCarParams = DEFAULT_PARAMS, margin: float = 0.05,
                       horizon: float = 3.0) -> float:
    """Free distance (m) behind the rear bumper in the corridor ``|y| <= width/2 + margin``."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    half_len, w = params.length / 2.0, params.width / 2.0 + margin
    if not len(pts):
        return float(horizon)
    x, y = pts[:, 0], pts[:, 1]
    sel = (np.abs(y) <= w) & (x <= -half_len)
    return float(min(horizon, (-half_len - x[sel]).min())) if sel.any() else float(horizon)


class _Scan:
    """A scan as :meth:`LidarAvoid.step` reads it (ranges, angles, time)."""

    __slots__ = ("ranges", "angles", "t")

    def __init__(self, ranges: np.ndarray, angles: np.ndarray, t: float):
        self.ranges, self.angles, self.t = ranges, angles, t


STATES = ("stop", "straight", "straight-left", "straight-right", "turn-left", "turn-right", "back",
          "dodge-left", "dodge-right", "give-way")


@dataclass
class AvoidWindows:
    """The windows of one scan: free distance (m) along each arc and behind the car."""

    turn_left: float
    gentle_left: float
    straight: float
    gentle_right: float
    turn_right: float
    rear: float


class LidarAvoid:
    """Task 4: avoid obstacles and stop (then back up) before contact. A state machine after the
    race-car team's report (shared seeds 003), with LIDAR windows instead of depth windows.

    Windows: the free distance :func:`free_distance` (grown by ``margin``) along five arcs, full
    lock left ``+turn_steering``, gentle left ``+gentle_steering``, straight, gentle right, full
    lock right; and :func:`rear_free_distance` behind. ``gap = stop_distance - length/2`` is the
    sheet's stop distance (from the LIDAR) expressed ahead of the bumper. Each scan:

    - no scan -> **stop** (the report: no data, Stop);
    - about to make contact: the free distance along the arc being driven is below ``gap``
      -> **stop** (speed 0, brake) for ``stop_hold`` s, then **back**;
    - **straight** (delta 0): when ``straight < turn_distance + latency * v_close`` -> **turn-left** if
      ``turn_left >= turn_right`` else **turn-right**; when ``gentle_left - gentle_right >
      balance`` -> **straight-left** (delta = +gentle_steering), ``< -balance`` -> **straight-right**;
    - **straight-left/right**: back to **straight** when the difference falls below ``balance/2``
      (hysteresis) or the arc ahead gets shorter than the turn distance (then as straight);
    - **turn-left/right** (full lock, speed x ``turn_speed_factor``): until ``straight >=
      clear_distance`` -> **straight**;
    - **back** (the report's collision recovery; speed ``-back_speed``, wheels turned to the side
      opposite the planned turn so the nose swings towards the room): until a forward arc is clear
      (``max(turn_left, straight, turn_right) >= clear_distance``), ``back_distance`` m are
      reversed, or the rear gets within ``gap`` -> **turn** to the side with more room.

    Speed in the forward states: ``min(speed x factor, max(sqrt(2 decel (ahead - gap)), min_speed))``
    with ``ahead`` the free distance along the arc being driven (it slows down as it closes in;
    ``factor`` = ``turn_speed_factor`` in turns, else 1). ``v_close`` is the larger of the speed
    last commanded and the rate at which the straight window shrank over the last two scans (an
    obstacle rolling towards the car closes faster than the car drives); ``latency`` (0.26 s: a
    scan period plus the steering servo's lag) turns it into extra distance. The contact check
    uses ``max(gap, margin + stopping_distance(v))``, so a fast car stops in time.

    Moving obstacles (``dodge``, on by default; the report's rolling ball). A window cannot tell a
    ball rolling at the car from a wall: it turns when the ball is about 1 m off, too late, and
    often to the ball's side. So each scan is also matched against the last one
    (:func:`~qcarlab.control.moving_obstacles.scan_motion`: the car's own motion, from the
    walls), its small free-standing objects (:func:`~qcarlab.control.moving_obstacles.scan_clusters`)
    are followed (:class:`~qcarlab.control.moving_obstacles.Tracker`), and one that moves over the
    ground at 0.35 m/s or more and will pass within 1 m of the car (closest approach still ahead)
    is a threat; its returns leave the windows. For a threat the manoeuvres of
    :mod:`qcarlab.control.dodge` are tried on a model of the car until the obstacle has passed
    (wheels straight on, stop, and ahead at ``speed`` or backing up at ``dodge_back_speed`` to a
    line 0.3, 0.45 or 0.6 m left or right of the obstacle's track); when going on straight
    clears it by 15 cm the windows keep driving, else the best manoeuvre is driven (**dodge-left**,
    **dodge-right**, or **give-way** for standing or going straight on) until the obstacle's
    closest approach is behind it, then **straight**. A last stop holds for the walls (the
    commanded arc or the rear 5 cm from a return).

    ``step(scan, speed)`` takes the scan (or None) and the desired speed, returns
    ``(speed_ref, steering)``; ``state`` and ``windows`` show why (``movers``: the moving tracks,
    ``dodges``: how many times it got out of one's way).
    """

    def __init__(
        self,
        stop_distance: float = 0.4,
        turn_distance: float = 0.62,
        clear_distance: float = 1.0,
        balance: float = 0.4,
        gentle_steering: float = 0.15,
        turn_steering: float = MAX_STEER,
        turn_speed_factor: float = 0.7,
        back_speed: float = 0.2,
        back_distance: float = 0.4,
        stop_hold: float = 0.3,
        margin: float = 0.05,
        decel: float = 0.8,
        latency: float = 0.26,
        min_speed: float = 0.1,
        params: QCarParams = DEFAULT_PARAMS,
        scan_period: float | None = None,
        dodge: bool = True,
        dodge_back_speed: float = 0.3,
    ):
        self.params = params
        self.scan_period = 1.0 / params.lidar_rate if scan_period is None else float(scan_period)
        self.decel, self.latency, self.min_speed = decel, latency, min_speed
        self.gap = max(stop_distance - params.length / 2.0, 0.0)
        self.turn_distance, self.clear_distance = turn_distance, clear_distance
        self.balance = balance
        self.gentle_steering, self.turn_steering = gentle_steering, turn_steering
        self.turn_speed_factor = turn_speed_factor
        self.back_speed, self.back_distance, self.stop_hold = back_speed, back_distance, stop_hold
        self.margin = margin
        self.dodge, self.dodge_speed_back = dodge, dodge_back_speed
        self.tracker = Tracker()
        self.reset()

    def reset(self) -> None:
        self.state = "straight"
        self.windows: AvoidWindows | None = None
        self.side = 1.0  # the turn planned after backing up: +1 left, -1 right
        self._since = 0.0  # s in the current stop/back state
        self._backed = 0.0  # m reversed in the current back state
        self._t: float | None = None
        self._v = 0.0  # the last speed commanded
        self._closing: list[float] = [0.0, 0.0]  # how fast the straight window shrank, last two scans
        self._prev_straight: float | None = None
        self.backups = 0
        self._clock = 0.0
        self.tracker.reset()
        self._prev_scan: PreparedScan | None = None  # the last scan, ready to be matched
        self._delta = 0.0  # the wheels' angle as the servo model has it (rad)
        self._cmd_delta = 0.0  # the steering last commanded
        self.v_est = 0.0  # the car's speed (m/s) from the last two scans' match
        self.motion: Motion | None = None
        self.movers: list[Track] = []
        self._static: np.ndarray | None = None  # this scan's returns less the moving objects'
        self.manoeuvre: str | None = None
        self._side = 0.0  # the side a dodge moves to: +1 left, -1 right, 0 none yet
        self.dodges = 0

    def _perceive(self, scan, dt: float) -> np.ndarray:
        """The car's motion since the last scan, the small objects tracked, the moving ones; returns
        the static returns (body frame about the centre: the moving objects' returns left out)."""
        r = np.asarray(scan.ranges, dtype=float)
        a = np.asarray(scan.angles, dtype=float)
        pts = scan_points(r, a, self.params.lidar_x)
        if not self.dodge:
            return pts
        L = self.params.wheelbase
        # the servo model: the wheels follow the command with the servo's lag
        self._delta += (self._cmd_delta - self._delta) * (1.0 - math.exp(-dt / self.params.steering_tau)) \
            if dt > 0.0 else 0.0
        motion = None
        prepared = prepare_scan(r, a)
        if self._prev_scan is not None and dt > 0.0:
            v = self.v_est
            guess = (v * dt, 0.0, v * math.tan(self._delta) / L * dt)
            motion = scan_motion(self._prev_scan, prepared, guess)
            if motion.matched:
                self.v_est = motion.dx / dt
            else:
                self.v_est = self._v
        self._prev_scan = prepared
        self.motion = motion
        self.tracker.update(float(scan.t), motion, scan_clusters(r, a, self.params.lidar_x))
        self.movers = self.tracker.moving()
        if not self.movers:
            return pts
        keep = np.ones(len(pts), dtype=bool)
        for tr in self.movers:
            if tr.cluster is not None:
                keep[tr.cluster.index] = False
        return pts[keep]

    def _threats(self) -> list[Obstacle]:
        """The moving objects coming towards the car: still ahead of their closest approach (the
        relative motion ``w = u - (v, 0)``; ``t* = -b . w / |w|^2 > 0``) and passing within 1 m."""
        out = []
        for tr in self.movers:
            (vx, vy), _ = tr.velocity()
            bx, by = (float(c) for c in tr.position())
            wx, wy = vx - self.v_est, vy
            w2 = wx * wx + wy * wy
            if w2 < 1e-6:
                continue
            t_star = -(bx * wx + by * wy) / w2
            miss = math.hypot(bx + wx * t_star, by + wy * t_star)
            if 0.0 < t_star < 6.0 and miss < 1.0:
                out.append(Obstacle(bx, by, float(vx), float(vy), tr.extent / 2.0 + 0.04))
        return out

    def _dodge(self, threats: list[Obstacle], static: np.ndarray, speed: float) -> tuple[float, float] | None:
        """Out of a moving obstacle's way (:mod:`qcarlab.control.dodge`): the manoeuvres tried on
        the model, the best one's command for this scan; None when not dodging yet and going on
        with the wheels straight clears it by 15 cm (the windows keep driving)."""
        first = min(threats, key=lambda ob: math.hypot(ob.x, ob.y))
        frame = line_frame(first)
        y_car = float(frame.lateral(0.0, 0.0))
        if frame.ox == 0.0 and frame.oy == 0.0:  # crossing: offsets from the car's own line
            offsets = [0.0, 0.3, -0.3]
        else:
            offsets = [0.3, -0.3, 0.45, -0.45, 0.6, -0.6]
        v_fwd = float(speed)
        ms = [Manoeuvre("hold", v_fwd, None), Manoeuvre("stop", 0.0, None)]
        ms += [Manoeuvre(f"ahead{o:+.2f}", v_fwd, o) for o in offsets]
        ms += [Manoeuvre(f"back{o:+.2f}", -self.dodge_speed_back, o) for o in offsets]
        near = static[np.hypot(static[:, 0], static[:, 1]) < 3.5] if len(static) else static
        if len(near) > 240:
            near = near[np.linspace(0, len(near) - 1, 240).astype(int)]
        # long enough for the obstacle to pass the car standing still (when it comes at it)
        t_pass = max(0.0, -(first.x * first.vx + first.y * first.vy) / max(first.vx ** 2 + first.vy ** 2, 1e-6))
        horizon = min(7.0, max(2.0, t_pass + 1.0))
        # (choose() reads a wall clearance up to its want_wall, 0.15 m: farther ones need not be measured)
        ball, wall = rollout(ms, threats, frame, near, self.v_est, self._delta, self.params, horizon=horizon,
                             wall_cap=0.15)
        if self.manoeuvre is None and ball[0] >= 0.15:
            return None  # going on as the windows say clears it
        i = choose(ms, ball, wall, self.manoeuvre, y_car, self._side)
        m = ms[i]
        if self.manoeuvre is None:
            self.dodges += 1
        self.manoeuvre = m.name
        if m.offset is not None and abs(m.offset - y_car) > 0.05:
            self._side = 1.0 if m.offset > y_car else -1.0
        if m.offset is None:
            delta = 0.0
        else:
            delta = float(offset_steering(y_car, -frame.heading, m.speed if abs(self.v_est) < 0.05 else self.v_est,
                                          m.offset, self.params))
        self.state = "give-way" if m.offset is None or not self._side else (
            "dodge-left" if self._side > 0 else "dodge-right")
        return m.speed, delta

    def _windows(self, scan, pts: np.ndarray | None = None) -> AvoidWindows:
        if pts is None:
            pts = scan_points(scan.ranges, scan.angles, self.params.lidar_x)
        f = lambda d: free_distance(pts, d, self.params, self.margin)  # noqa: E731
        g, s = self.gentle_steering, self.turn_steering
        return AvoidWindows(f(s), f(g), f(0.0), f(-g), f(-s), rear_free_distance(pts, self.params, self.margin))

    def _steering(self) -> float:
        return {"straight-left": self.gentle_steering, "straight-right": -self.gentle_steering,
                "turn-left": self.turn_steering, "turn-right": -self.turn_steering,
                "back": -self.side * self.turn_steering}.get(self.state, 0.0)

    def _ahead(self, w: AvoidWindows) -> float:
        """Free distance along the arc the current state drives."""
        return {"straight-left": w.gentle_left, "straight-right": w.gentle_right, "turn-left": w.turn_left,
                "turn-right": w.turn_right}.get(self.state, w.straight)

    def _enter(self, state: str) -> None:
        if state != self.state:
            self.state = state
            self._since = 0.0
            self._backed = 0.0

    def _turn_side(self, w: AvoidWindows) -> float:
        """+1 (left) or -1 (right): the side whose arcs are longer; on a tie (within 5 cm: boxed in,
        every arc about 0) the side whose nearest return beside the car is farther."""
        left, right = w.turn_left + w.gentle_left, w.turn_right + w.gentle_right
        if abs(left - right) < 0.05 and self._static is not None and len(self._static):
            y = self._static[:, 1]
            near_x = np.abs(self._static[:, 0]) <= self.params.length
            room_l = float(y[near_x & (y > 0)].min()) if (near_x & (y > 0)).any() else math.inf
            room_r = float(-y[near_x & (y < 0)].max()) if (near_x & (y < 0)).any() else math.inf
            return 1.0 if room_l >= room_r else -1.0
        return 1.0 if left >= right else -1.0

    def __call__(self, ranges, angles, desired_speed: float) -> tuple[float, float]:
        """The ``lidar_avoid`` block: ``(speed_cmd m/s, steering_cmd rad)`` from one scan (the
        block's fixed signature). Scans are taken to come ``scan_period`` s apart (10 Hz)."""
        self._clock += self.scan_period
        return self.step(_Scan(np.asarray(ranges, dtype=float), np.asarray(angles, dtype=float), self._clock),
                         desired_speed)

    def step(self, scan, speed: float) -> tuple[float, float]:
        """One decision per LIDAR scan: ``(speed_ref m/s, steering rad)`` for desired ``speed``."""
        v, delta = self._decide(scan, speed)
        self._cmd_delta = float(delta)
        return v, delta

    def _decide(self, scan, speed: float) -> tuple[float, float]:
        if scan is None:
            self._enter("stop")
            self._t = None
            self._v = 0.0
            self._prev_scan = None
            return 0.0, 0.0
        dt = 0.0 if self._t is None else max(0.0, float(scan.t) - self._t)
        self._t = float(scan.t)
        static = self._static = self._perceive(scan, dt)
        w = self.windows = self._windows(scan, static)
        self._since += dt
        threats = self._threats() if self.dodge else []
        if threats:
            cmd = self._dodge(threats, static, speed)
            if cmd is not None:
                v, delta = cmd
                # the manoeuvres were tried against the walls; a last stop for what does not move
                if v > 0.0 and free_distance(static, delta, self.params, 0.0) < 0.05:
                    v = 0.0
                elif v < 0.0 and rear_free_distance(static, self.params, 0.0) < 0.05:
                    v = 0.0
                self._v = v
                self._prev_straight = w.straight
                return v, delta
        if self.manoeuvre is not None:  # out of the way: the windows drive again
            self.manoeuvre = None
            self._side = 0.0
            self.state = "straight"
            self._since = 0.0
            self._closing = [0.0, 0.0]
        if self._prev_straight is not None and dt > 0.0:
            rate = (self._prev_straight - w.straight) / dt
            self._closing = [self._closing[1], min(max(rate, 0.0), 3.0)]
        self._prev_straight = w.straight
        st = self.state
        if st == "stop":
            if self._since >= self.stop_hold:
                self.side = self._turn_side(w)
                self.backups += 1
                self._enter("back")
            else:
                self._v = 0.0
                return 0.0, 0.0
        elif st == "back":
            self._backed += self.back_speed * dt
            if max(w.turn_left, w.straight, w.turn_right) >= self.clear_distance and self._backed > 0.05 \
                    or self._backed >= self.back_distance or w.rear < self.gap:
                best = max(w.turn_left, w.straight, w.turn_right)
                if w.straight >= self.clear_distance and w.straight >= best - 1e-9:
                    self._enter("straight")
                else:
                    self._enter("turn-left" if self._turn_side(w) > 0 else "turn-right")
        elif st in ("turn-left", "turn-right"):
            if w.straight >= self.clear_distance:
                self._enter("straight")
        elif st in ("straight-left", "straight-right"):
            diff = w.gentle_left - w.gentle_right
            if w.straight < self.turn_distance + self.latency * max(abs(self._v), min(self._closing)) or (diff if st == "straight-left" else -diff) < self.balance / 2.0:
                self._enter("straight")
        v_now = abs(self._v)
        # an obstacle coming towards the car (the report's rolling ball) closes faster than the car
        # drives: the window's shrink rate, when two scans in a row agree, counts instead
        closing = max(v_now, min(self._closing))
        turn_distance = self.turn_distance + self.latency * closing
        if self.state == "straight":
            diff = w.gentle_left - w.gentle_right
            if w.straight < turn_distance:
                self._enter("turn-left" if w.turn_left >= w.turn_right else "turn-right")
            elif diff > self.balance:
                self._enter("straight-left")
            elif diff < -self.balance:
                self._enter("straight-right")
        if self.state == "back":
            self._v = -abs(self.back_speed)
            return self._v, self._steering()
        # the sheet's stop, along the arc actually driven: about to make contact -> stop, then back up
        ahead = self._ahead(w)
        if ahead < max(self.gap, self.margin + self.stopping_distance(v_now)):
            self._enter("stop")
            self._v = 0.0
            return 0.0, 0.0
        factor = self.turn_speed_factor if self.state in ("turn-left", "turn-right") else 1.0
        v = float(speed) * factor
        cap = max(math.sqrt(2.0 * self.decel * max(ahead - self.gap, 0.0)), self.min_speed)
        self._v = min(v, cap)
        return self._v, self._steering()

    def stopping_distance(self, v: float) -> float:
        """Distance (m) the car covers from a scan that says stop to rest at speed ``v``: a scan
        period of latency (0.1 s) then braking at about 1 m/s^2 (the PI controller at the 0.3
        throttle limit, measured): ``0.1 v + v^2 / 2``."""
        return 0.1 * v + v * v / 2.0
