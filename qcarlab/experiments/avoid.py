"""LIDAR obstacle detection and avoidance (lab sheet section 6.1) on any car.

The model, :class:`AvoidLab`, is the sheet's Figure 59; each tick (``rate``, 100 Hz)::

    v      = basic_speed_estimation(tach)                      # encoder -> m/s
    scan   = car.read_lidar()                                  # a new turn every 0.1 s (10 Hz)
    on a new scan (distances, headings: body frame, ahead 0, + = left, in (-pi, pi]; 0 m = no return):
        stop:     v_ref = lidar_stop(d, h, speed), delta = 0               (Task 1-2)
        steer:    v_ref = speed, delta = lidar_steer(d, h, speed)          (Task 3)
        combined: v_ref, delta = lidar_avoid(d, h, speed)                  (Task 4, open problem;
                  the reference also tracks moving objects between scans and dodges them)
        student:  the same with the student's own lidar_avoid
    depth (the race-car report's strategy, on the RGBD camera instead of the LIDAR):
        on a new depth frame (30 Hz): l, m, r = depth_windows(depth)       # mean depth, 3 windows
                                      v_ref, delta = depth_avoid(l, m, r, speed)   # the state machine
    u      = speed_controller(v_ref, v, dt)                    # feed-forward PI -> throttle
    lamps  = indicator_and_lamps(delta, v_ref)

Every block is looked up by its sheet name: ``--use mine.py`` with ``lidar_stop``, ``lidar_steer``,
``lidar_avoid``, ``depth_windows`` or ``depth_avoid`` runs the same model with the student's
functions.

The PI controller is disarmed (integrator reset, throttle 0) while ``v_ref = 0`` and the car is at
rest, so a stopped car does not creep on the integrator's charge.

Collisions. The simulator does not model contact, so the run checks it itself, every tick, from
the true pose: the exact distance between the car's footprint (a ``length`` x ``width`` =
0.425 x 0.192 m rectangle about its centre) and every solid of the world that reaches below the
car's roof (walls, boxes, posts, sign plates: :meth:`World.static_solids`) and every ball at that
instant (:meth:`World.obstacles_at`, as a circle of the ball's radius: the body is as high as the
ball's equator). Polygons are compared edge by edge (a separating-axis test for crossing, else the
nearest vertex-edge distance, which is exact for disjoint convex pieces), circles by the distance
from their centre to the rectangle. ``min_clearance_m`` is the smallest distance over the run; a
distance of 0 is a collision, which ends the run (the car is stopped). Only a simulated car in a
local world is checked (``collisions`` is null otherwise).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from collections.abc import Mapping
from functools import partial

from qcarlab.blocks import BlockSpec
from qcarlab.car.base import Car, Command, Readout
from qcarlab.car.lamps import lamps_named
from qcarlab.constants import QCarParams
from qcarlab.control.depth_avoid import DepthAvoid
from qcarlab.control.lidar_avoid import LidarAvoid, forward_range, lidar_steer, lidar_stop
from qcarlab.control.speed import KFF, KI, KP, SpeedController, basic_speed_estimation
from qcarlab.errors import InputError
from qcarlab.experiments.lidar_scan import lidar_world_pose
from qcarlab.control.lamps import indicator_and_lamps
from qcarlab.experiments.loop import STOP, Step, check_rate, run_loop
from qcarlab.experiments.model import BASIC_SPEED_ESTIMATION, INDICATOR_AND_LAMPS, SPEED_CONTROLLER, LabModel, finish
from qcarlab.experiments.result import Result
from qcarlab.sim.contact import Clearance, PathClearance  # noqa: F401  (Clearance: as before, importable here)
from qcarlab.perception.depth_windows import depth_windows

STRATEGIES = ("stop", "steer", "combined", "student", "depth")
REST_SPEED = 0.01  # m/s: below this the car counts as at rest


@dataclass
class AvoidConfig:
    """Everything that shapes a run; the defaults are the lab's."""

    strategy: str = "combined"
    speed: float = 0.3  # m/s desired
    stop_distance: float = 0.4  # m from the LIDAR (by the car's centre)
    half_width: float = 0.15  # m, the stop window's half width (car half width 0.096 + 5 cm)
    duration: float = 20.0  # s
    rate: float = 100.0  # Hz
    kp: float = KP
    ki: float = KI
    kff: float = KFF

    def check(self, params: QCarParams) -> None:
        if self.strategy not in STRATEGIES:
            raise InputError(f"--strategy must be one of {', '.join(STRATEGIES)}, got {self.strategy!r}")
        if not (math.isfinite(self.speed) and 0.0 < self.speed <= 3.0):
            raise InputError(f"--speed must be in (0, 3] m/s, got {self.speed}")
        front = params.length / 2.0 - params.lidar_x  # the bumper's distance ahead of the LIDAR
        if not (math.isfinite(self.stop_distance) and front < self.stop_distance <= params.lidar_max_range):
            raise InputError(f"--stop-distance must be in ({front:g}, {params.lidar_max_range:g}] m (measured from "
                             f"the LIDAR, {front:g} m behind the front bumper), got {self.stop_distance}")
        if not (math.isfinite(self.half_width) and 0.0 < self.half_width <= 2.0):
            raise InputError(f"--half-width must be in (0, 2] m, got {self.half_width}")
        if not (math.isfinite(self.duration) and 0.0 < self.duration <= 3600.0):
            raise InputError(f"--duration must be in (0, 3600] s, got {self.duration}")
        check_rate(self.rate)


# --------------------------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------------------------
#: The blocks of the LIDAR obstacle diagram (sheet 6.1, Figures 59-61), in the sheet's order.
BLOCKS = (
    BASIC_SPEED_ESTIMATION,
    BlockSpec("lidar_stop", "lidar_stop(distances, headings, desired_speed) -> speed_cmd",
              "m (0 = no return), rad (body frame: ahead 0, left +, right -, in (-pi, pi]), m/s -> m/s",
              "6.1 Tasks 1-2, Figure 60", "Stop strategy: 0 when an obstacle is near ahead, else the desired "
              "speed. Acts on the speed only.", "speed",
              fill="The stop strategy (LIDAR Stop.slx): set the speed to 0 when the QCar is near an obstacle "
              "ahead, else the desired speed. distances[i] is the range (m) of the return at headings[i] "
              "(rad, body frame: 0 straight ahead, positive to the left, negative to the right, in (-pi, pi]; "
              "behind is +-pi); 0 m means no return. The LIDAR is by the "
              "car's centre: the front bumper is 0.223 m ahead of it.",
              example="lidar_stop(np.array([0.3]), np.array([0.0]), 0.3) == 0.0 (an obstacle 0.3 m dead ahead)"),
    BlockSpec("lidar_steer", "lidar_steer(distances, headings, desired_speed) -> steering_cmd",
              "m, rad, m/s -> rad (+ = left, within +-0.5)", "6.1 Task 3, Figure 61",
              "Steering strategy: up to +-0.5 rad away from the obstacle. The speed is untouched.", "steering",
              fill="The steering strategy (LIDAR Basic.slx): set the steering angle up to 0.5 or -0.5 rad "
              "depending on where the detected obstacle is (steer away from it). The speed remains "
              "untouched: return the steering angle only (rad, + = left).",
              example="lidar_steer(np.array([0.5]), np.array([0.3]), 0.3) < 0 (obstacle ahead-left: turn right)"),
    BlockSpec("lidar_avoid", "lidar_avoid(distances, headings, desired_speed) -> (speed_cmd, steering_cmd)",
              "m, rad, m/s -> (m/s, rad)", "6.1 Task 4 (open problem)",
              "Both strategies combined: avoid the obstacles, stop before contact (a class may keep state).",
              "speed_steering", stateful=True,
              fill="Open problem: combine the speed and steering strategies. The QCar should avoid the "
              "obstacles, and stop if it is about to make contact with one. Return (speed_cmd m/s, "
              "steering_cmd rad). A class (with __call__ and an optional reset) may keep a state between "
              "scans, as the race-car report's state machine does.",
              example="lidar_avoid(np.array([0.25]), np.array([0.0]), 0.3)[0] == 0.0 (about to touch: stop)"),
    BlockSpec("depth_windows", "depth_windows(depth) -> (left, middle, right)",
              "m image (0 = no data) -> m, m, m (0 = no data in that window)", "race-car report (seeds 003)",
              "--strategy depth: the mean depth of three windows at the left, middle and right of the RGBD "
              "depth image."),
    BlockSpec("depth_avoid", "depth_avoid(left, middle, right, desired_speed) -> (speed_cmd, steering_cmd)",
              "m, m, m, m/s -> (m/s, rad)", "race-car report (seeds 003)",
              "--strategy depth: the report's state machine (stop, straight, straight left/right, turn "
              "left/right, back) on the three windows (a class: it keeps its state).", "speed_steering",
              stateful=True),
    SPEED_CONTROLLER,
    INDICATOR_AND_LAMPS,
)


def lamp_text(names) -> str:
    """The lamps a block lit, for the log: names joined by '+' ('' = all off)."""
    return "+".join(names)


class AvoidLab(LabModel):
    """The sheet's LIDAR obstacle model (6.1) as a block diagram; see the module docstring."""

    lab = "avoid"
    BLOCKS = BLOCKS

    def __init__(self, cfg: AvoidConfig, params: QCarParams, throttle_limit: float,
                 blocks: Mapping[str, Any] | None = None):
        self.cfg, self.p, self.throttle_limit = cfg, params, throttle_limit
        super().__init__(blocks)
        if cfg.strategy == "student" and "lidar_avoid" not in self.student:
            raise InputError("--strategy student runs your own lidar_avoid: give it with --use FILE.py "
                             "(a function or class named lidar_avoid) or --block lidar_avoid=FILE.py:FUNC")
        self.scan_t = None
        self.v_ref, self.delta, self.front, self.state = 0.0, 0.0, math.inf, ""
        self.n_scans = 0
        self.rest = None
        self.scans: list[tuple[np.ndarray, tuple[float, float, float] | None]] = []
        self.scan_pose = None  # (t) -> the LIDAR's world pose, on a simulator
        self.frame_dt, self.next_frame, self.n_frames = 1.0 / params.rgbd_rate, 0.0, 0
        self.windows = (math.nan, math.nan, math.nan)
        self._headings: tuple[np.ndarray, np.ndarray] | None = None

    def headings(self, angles: np.ndarray) -> np.ndarray:
        """The scan's beam angles as the LIDAR blocks receive them: body frame, ahead 0, left
        positive, right negative, in (-pi, pi] (a scan's angles come as 0..2 pi); the same array for
        the same beams, made once."""
        if self._headings is None or self._headings[0] is not angles:
            h = np.where(angles > math.pi, angles - 2.0 * math.pi, angles)
            h.setflags(write=False)
            self._headings = (angles, h)
        return self._headings[1]

    def reference_blocks(self) -> dict[str, Any]:
        c, p = self.cfg, self.p
        return {
            "basic_speed_estimation": partial(basic_speed_estimation, params=p),
            "lidar_stop": partial(lidar_stop, stop_distance=c.stop_distance, half_width=c.half_width),
            "lidar_steer": lidar_steer,
            "lidar_avoid": LidarAvoid(stop_distance=c.stop_distance, params=p),
            "depth_windows": depth_windows,
            "depth_avoid": DepthAvoid(),
            "speed_controller": SpeedController(c.kp, c.ki, c.kff, throttle_limit=self.throttle_limit),
            "indicator_and_lamps": partial(indicator_and_lamps, threshold=0.2),
        }

    def _depth(self, t: float) -> None:
        """--strategy depth: on a new RGBD frame, the three windows and the state machine."""
        if t + 1e-9 < self.next_frame:
            return
        self.next_frame = (math.floor((t + 1e-9) / self.frame_dt) + 1) * self.frame_dt
        frame = self.read_rgbd()
        if frame is None or getattr(frame, "depth", None) is None:
            self.v_ref, self.delta, self.state = 0.0, 0.0, "stop"  # the report: no data, Stop
            return
        self.n_frames += 1
        left, middle, right = self.depth_windows(frame.depth)
        self.windows = (float(left), float(middle), float(right))
        self.front = float(middle) if middle > 0 else 0.0
        self.v_ref, self.delta = self.depth_avoid(left, middle, right, self.cfg.speed)
        self.state = str(getattr(self.depth_avoid, "state", "depth"))

    def step(self, t: float, r: Readout, dt: float) -> Step:
        c = self.cfg
        v = self.basic_speed_estimation(r.tach)
        if c.strategy == "depth":
            self._depth(t)
            v_ref, delta = self.v_ref, self.delta
            if v_ref == 0.0 and abs(v) < REST_SPEED and self.rest is None and self.front > 0:
                self.rest = {"t": t, "range_m": self.front}
            throttle = self.speed_controller(v_ref, v, dt)
            left, middle, right = self.windows
            names = tuple(self.indicator_and_lamps(delta, v_ref))
            return Step(Command(throttle, delta, lamps_named(names)),
                        {"v_ref": v_ref, "v_meas": v, "front_range": self.front, "state": self.state,
                         "depth_left": left, "depth_middle": middle, "depth_right": right,
                         "lamps": lamp_text(names)})
        scan = self.read_lidar()
        if scan is not None and scan.t != self.scan_t:
            self.scan_t = scan.t
            self.n_scans += 1
            d, h = scan.ranges, self.headings(scan.angles)
            self.front = forward_range(d, h, c.half_width)
            if c.strategy == "stop":
                self.v_ref, self.delta, self.state = self.lidar_stop(d, h, c.speed), 0.0, ""
                self.state = "go" if self.v_ref > 0 else "stop"
            elif c.strategy == "steer":
                self.v_ref, self.delta, self.state = c.speed, self.lidar_steer(d, h, c.speed), "steer"
            else:
                self.v_ref, self.delta = self.lidar_avoid(d, h, c.speed)
                self.state = str(getattr(self.lidar_avoid, "state", "avoid"))
            self.scans.append((scan.points(), self.scan_pose(scan.t) if self.scan_pose else None))
        v_ref, delta = self.v_ref, self.delta
        if v_ref == 0.0 and abs(v) < REST_SPEED and self.rest is None and math.isfinite(self.front):
            self.rest = {"t": t, "range_m": self.front}
        throttle = self.speed_controller(v_ref, v, dt)  # speed_controller holds a car at rest with throttle 0
        names = tuple(self.indicator_and_lamps(delta, v_ref))
        return Step(Command(throttle, delta, lamps_named(names)),
                    {"v_ref": v_ref, "v_meas": v, "front_range": self.front, "state": self.state,
                     "lamps": lamp_text(names)})


class _Collisions:
    """The avoid run's collision check, every tick, balls included (ends the run at contact).

    A tick whose pose the referee's bound shows clear of every wall (:meth:`PathClearance.edges_if_clear
    <qcarlab.sim.contact.PathClearance.edges_if_clear>`: most ticks) has only its circles measured then;
    its walls' exact clearance is measured with the other such ticks' at once after the run
    (:meth:`finish`), which fills the log's column and ``min_clear``: the same numbers. A recorded
    or live run (the recorder sends each tick's values as it goes) measures every tick then."""

    def __init__(self, model: AvoidLab, world: Any, car: Car):
        self.model, self.car = model, car
        self.checker = PathClearance(world, car.params)  # (Clearance's numbers, the poses a tick apart)
        self.truth0 = car.truth()
        self.min_clear, self.collision, self.max_from_start = math.inf, None, 0.0
        self.defer = getattr(car, "recorder", None) is None
        self._rows = 0  # the log's rows so far (one a step that does not stop the run)
        self._later: list[tuple] = []  # (row, x, y, cos, sin, the circles' clearance, the edges that may be nearest)

    def start(self, car: Car, dt: float) -> None:
        self.model.start(car, dt)

    def step(self, t: float, r: Readout, dt: float):
        tr = self.car.truth()
        later = edges = None
        if self.defer:
            edges = self.checker.edges_if_clear(tr.x, tr.y, tr.yaw)
            if edges is not None:
                circles, _ = self.checker.circle_clearance(tr.x, tr.y, tr.yaw, tr.t)
                if circles > 0.0:
                    later = circles
        if later is None:
            clear, where = self.checker(tr.x, tr.y, tr.yaw, tr.t)
            self.min_clear = min(self.min_clear, clear)
        self.max_from_start = max(self.max_from_start, math.hypot(tr.x - self.truth0.x, tr.y - self.truth0.y))
        if later is None and clear <= 0.0:
            self.collision = {"t": t, "x": tr.x, "y": tr.y, "yaw": tr.yaw, "obstacle": list(where) if where else None,
                              "speed_mps": float(self.model.basic_speed_estimation(r.tach))}
            return STOP
        out = self.model.step(t, r, dt)
        if later is not None and self.model.rest is not None and "gap_m" not in self.model.rest:
            clear, _ = self.checker(tr.x, tr.y, tr.yaw, tr.t)  # the gap at rest: now (the same number)
            self.min_clear = min(self.min_clear, clear)
            later = None
        if later is None:
            out.log["clearance"] = clear
        else:
            out.log["clearance"] = math.nan  # (measured in finish)
            self._later.append((self._rows, tr.x, tr.y, math.cos(tr.yaw), math.sin(tr.yaw), later, edges))
        self._rows += 1
        if self.model.rest is not None and "gap_m" not in self.model.rest:
            self.model.rest["gap_m"] = clear
        return out

    def finish(self, log: Any) -> None:
        """The deferred ticks' clearances: their walls' at once, the nearer of those and their
        circles' (a circle only when strictly nearer, as PathClearance), into the log and ``min_clear``."""
        if not self._later:
            return
        rows, x, y, c, s, circles, edges = zip(*self._later)
        x, y, c, s, circles = (np.array(v) for v in (x, y, c, s, circles))
        walls = self.checker.walls_at(x, y, c, s, list(edges))
        clear = np.where(circles < walls, circles, walls).tolist()
        column = log.columns["clearance"]
        for i, v in zip(rows, clear):
            if i < len(column):  # (a run stopped by Ctrl-C between the referee's step and the log's row)
                column[i] = v
        self.min_clear = min(self.min_clear, min(clear))
        self._later = []


def avoid(car: Car, cfg: AvoidConfig, world: Any = None, on_tick=None, *,
          blocks: Mapping[str, Any] | None = None, wrap=None) -> Result:
    """Drive ``car`` with the LIDAR strategy ``cfg.strategy``; return metrics, the log, the scans.

    ``world`` (the simulator's, when local) enables the collision check and the drive figure.
    ``blocks`` replaces any block of :data:`BLOCKS` by name. ``wrap(model) -> model`` wraps the
    model the loop runs (the trials roll their balls that way).
    """
    world = world if world is not None else getattr(car, "world", None)  # a local simulator's
    p = car.params
    cfg.check(p)
    truth0 = car.truth()
    lab = AvoidLab(cfg, p, car.throttle_limit, blocks)
    lab.read_lidar = car.read_lidar
    lab.read_rgbd = car.read_rgbd
    if truth0 is not None:
        lab.scan_pose = lambda t: lidar_world_pose(car, t)
    guard = _Collisions(lab, world, car) if (world is not None and truth0 is not None) else None
    dt = 1.0 / cfg.rate
    model = guard or lab
    log = run_loop(car, wrap(model) if wrap else model, cfg.duration, cfg.rate, on_tick=on_tick)
    if guard is not None:
        guard.finish(log)
    cols: dict[str, np.ndarray] = log.arrays()
    n = log.ticks
    if "clearance" not in cols:
        cols["clearance"] = np.full(n, math.nan)
    truth1 = car.truth()
    duration = n * dt
    if truth1 is not None:
        distance = truth1.distance - truth0.distance
    else:
        distance = float(np.sum(np.abs(cols["v_meas"]))) * dt if n else 0.0
    rest = lab.rest
    states = {}
    if n and cfg.strategy in ("combined", "student", "depth"):
        names, counts = np.unique(cols["state"].astype(str), return_counts=True)
        states = {str(k): float(c) * dt for k, c in zip(names, counts)}
    collision = guard.collision if guard else None
    metrics = {
        "experiment": "avoid",
        "strategy": cfg.strategy,
        "collisions": None if guard is None else (1 if collision else 0),
        "collision": collision,
        "min_clearance_m": None if guard is None else float(guard.min_clear),
        "distance_m": float(distance),
        "max_distance_from_start_m": float(guard.max_from_start) if guard is not None else None,
        "duration_s": float(duration),
        "mean_speed_mps": float(distance / duration) if duration > 0 else 0.0,
        "stopped_before_obstacle": rest["range_m"] if rest else None,
        "stop_gap_m": rest.get("gap_m") if rest else None,
        "stopped_at_s": rest["t"] if rest else None,
        "scans": lab.n_scans,
    }
    if cfg.strategy == "depth":
        metrics["depth_frames"] = lab.n_frames
    if cfg.strategy in ("combined", "student", "depth"):
        machine = lab.depth_avoid if cfg.strategy == "depth" else lab.lidar_avoid
        metrics["backups"] = getattr(machine, "backups", None)
        if getattr(machine, "dodges", None) is not None:
            metrics["dodges"] = machine.dodges  # times it got out of a moving obstacle's way
        metrics["time_in_state_s"] = states
    metrics["config"] = asdict(cfg)
    finish(metrics, log, lab, None, goal=not collision, goal_text="")
    if collision:
        metrics["goal_reached"], metrics["failure"] = False, (
            f"collision at ({collision['x']:.2f}, {collision['y']:.2f}) m, t = {collision['t']:.2f} s")
    keep = ["t", "true_x", "true_y", "true_yaw", "true_speed", "throttle", "steering", "v_ref", "v_meas",
            "front_range", "clearance", "state", "depth_left", "depth_middle", "depth_right", "lamps"]
    log_cols = {k: cols[k] for k in keep if k in cols}
    return Result("avoid", metrics, logs={"log.csv": log_cols}, data={"scans": lab.scans, "log": cols})


def drive_figure(world: Any, result: Result, every: int = 2) -> Any:
    """``drive.png``: over the world seen from above (balls where they were at the end), axes in
    metres, the driven path, the LIDAR returns of every ``every``-th scan in the world frame (the
    last scan apart), the car at the start and at the end and, after a collision, where it hit; a
    legend says which is which (:func:`qcarlab.plots.drive_figure`). Returns the matplotlib Figure."""
    from qcarlab import plots
    from qcarlab.experiments.worlds import figure_map

    log = result.data["log"]
    poses = np.column_stack((log["true_x"], log["true_y"], log["true_yaw"])) if "true_x" in log else None
    t_end = float(log["t"][-1]) if len(log.get("t", [])) else 0.0
    background, extent = figure_map(world, t=t_end, show_start=poses is None)
    scans = [(pts, pose) for pts, pose in result.data["scans"] if pose is not None and len(pts)]
    shown = [to_world_pts(pts, pose) for i, (pts, pose) in enumerate(scans) if i % every == 0 or i == len(scans) - 1]
    return plots.drive_figure(background, extent, poses, shown, result.metrics)


def to_world_pts(pts: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
    """Body-frame LIDAR points (already dropped of no-returns) to the world, given the LIDAR's pose."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return np.column_stack((x + c * pts[:, 0] - s * pts[:, 1], y + s * pts[:, 0] + c * pts[:, 1]))
