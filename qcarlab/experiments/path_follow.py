"""Path following (lab sheet section 4): the PathFollowing model on any car.

Each tick (``--rate``, 100 Hz by default)::

    v      = basic_speed_estimation(tach)                     # encoder -> m/s
    pose   = estimator(v, last steering, dt [, gyro z])        # bicycle model (or truth)
    target = LookaheadTarget(path)(pose)                       # forward-only look-ahead point
    delta  = pure_pursuit | follow_the_carrot | stanley        # steering
    v_ref  = min(v_desired, sqrt(2 a_stop s_remaining))        # slows down to stop at the goal
    u      = speed_controller(v_ref, v)                        # feed-forward PI -> throttle

The sheet's model never stops (its stated limitation); here the car brakes along a profile and
stops within ``goal_tolerance`` of the last point. On a simulator the run is scored against the
true pose: RMS and max cross-track error to the reference polyline, completion, speed tracking,
final distance to the goal and the dead-reckoning drift.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from qcarlab.car.base import Car, Command, Readout
from qcarlab.car.lamps import ALL_OFF, parse_lamps
from qcarlab.control.pose import BicyclePoseEstimator
from qcarlab.control.speed import SpeedController, basic_speed_estimation, turn_speed_handling
from qcarlab.control.steering import LookaheadTarget, follow_the_carrot, pure_pursuit, stanley
from qcarlab.control.tracking import Polyline, cross_track_errors, progress_along
from qcarlab.errors import InputError
from qcarlab.experiments.loop import STOP, check_rate, run_loop
from qcarlab.experiments.result import Result

CONTROLLERS = ("pure-pursuit", "carrot", "stanley")
POSE_SOURCES = ("bicycle", "gyro", "truth")
A_STOP = 0.8  # m/s^2, the deceleration the stop profile plans with
_BRAKE = parse_lamps(["brake"])


@dataclass
class FollowConfig:
    """Everything that shapes a run; the defaults are the tuned lab values."""

    controller: str = "pure-pursuit"
    lookahead: float = 0.3  # m, pure pursuit / carrot look-ahead distance
    k_carrot: float = 1.0
    k_stanley: float = 2.0
    speed: float = 0.5  # m/s desired
    kp: float = 0.3
    ki: float = 1.0
    kff: float = 0.1
    pose: str = "bicycle"
    goal_tolerance: float = 0.1  # m
    laps: int = 1
    rate: float = 100.0  # Hz
    turn_speed: bool = False  # turn_speed_handling on the desired speed
    max_time: float | None = None  # s; default from the path length and speed

    def check(self) -> None:
        if self.controller not in CONTROLLERS:
            raise InputError(f"--controller must be one of {', '.join(CONTROLLERS)}, got {self.controller!r}")
        if self.pose not in POSE_SOURCES:
            raise InputError(f"--pose must be one of {', '.join(POSE_SOURCES)}, got {self.pose!r}")
        for name in ("lookahead", "speed", "goal_tolerance"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"--{name.replace('_', '-')} must be a positive number, got {value}")
        for name in ("k_carrot", "k_stanley", "kp", "ki", "kff"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"--{name.replace('_', '-')} must be a non-negative number, got {value}")
        if self.speed > 3.0:
            raise InputError(f"--speed {self.speed} m/s is beyond what the car can do at the throttle limit (3 m/s)")
        if not (isinstance(self.laps, int) and self.laps >= 1):
            raise InputError(f"--laps must be a positive integer, got {self.laps}")
        check_rate(self.rate)


def repeat_laps(path: np.ndarray, laps: int) -> np.ndarray:
    """The path driven ``laps`` times. Only closed paths repeat: the gap from the last point back
    to the first is at most two typical segments (the sheet's circle stops one 0.1 rad step short)."""
    if laps == 1:
        return path
    seg = np.hypot(*np.diff(path, axis=0).T)
    if math.dist(path[0], path[-1]) > max(0.05, 2.0 * float(np.median(seg[seg > 0]))):
        raise InputError("--laps needs a closed path (its last point back at its first)")
    return np.vstack([path] + [path[1:]] * (laps - 1))


def follow_path(car: Car, path: np.ndarray, cfg: FollowConfig, on_tick=None) -> Result:
    """Drive ``path`` with ``car``; return metrics, the log and the figures."""
    cfg.check()
    route = repeat_laps(np.asarray(path, dtype=float), cfg.laps)
    poly = Polyline(route)
    p = car.params
    truth0 = car.truth()
    if cfg.pose == "truth" and truth0 is None:
        raise InputError("--pose truth needs the simulator (a real car has no ground truth)")
    start = (truth0.x, truth0.y, truth0.yaw) if truth0 is not None else (route[0, 0], route[0, 1], _heading(route))
    estimator = BicyclePoseEstimator(start, p)
    search = LookaheadTarget(poly, cfg.lookahead)
    pi = SpeedController(cfg.kp, cfg.ki, cfg.kff, throttle_limit=car.throttle_limit)
    dt = 1.0 / cfg.rate
    goal = route[-1]
    end_zone = poly.length - max(cfg.goal_tolerance, cfg.lookahead) - 0.05
    max_time = cfg.max_time or (1.5 * poly.length / cfg.speed + 10.0)
    rec: dict[str, list[float]] = {k: [] for k in ("est_x", "est_y", "est_yaw", "v_ref", "v_meas", "target_x", "target_y")}
    state = {"steer": 0.0, "arrived": False, "first": True}

    def step(t: float, r: Readout) -> Command | object:
        v = basic_speed_estimation(r.tach, p)
        if state["first"]:
            state["first"] = False
        elif cfg.pose == "gyro":
            estimator(v, state["steer"], dt, yaw_rate=float(r.gyro[2]))
        else:
            estimator(v, state["steer"], dt)
        if cfg.pose == "truth":
            tr = car.truth()
            pose = (tr.x, tr.y, tr.yaw)
        else:
            pose = estimator.pose
        target, index, progress = search(pose)
        remaining = poly.length - progress
        if not state["arrived"] and (
            remaining <= 0.0 or (progress >= end_zone and math.dist(pose[:2], goal) <= cfg.goal_tolerance)
        ):
            state["arrived"] = True
        if state["arrived"]:
            delta, v_ref = 0.0, 0.0
            if abs(v) < 0.01:
                return STOP
        else:
            if cfg.controller == "pure-pursuit":
                delta = pure_pursuit(pose, target, p.wheelbase, max_steering=p.max_steering)
            elif cfg.controller == "carrot":
                delta = follow_the_carrot(pose, target, cfg.k_carrot, max_steering=p.max_steering)
            else:
                delta = stanley(pose, poly, index, v, cfg.k_stanley, p.wheelbase, max_steering=p.max_steering)
            v_ref = turn_speed_handling(cfg.speed, delta, cfg.turn_speed)
            v_ref = min(v_ref, math.sqrt(2.0 * A_STOP * max(remaining - 0.5 * cfg.goal_tolerance, 0.0)))
        throttle = pi(v_ref, v, dt)
        state["steer"] = delta
        for key, value in (("est_x", pose[0]), ("est_y", pose[1]), ("est_yaw", pose[2]), ("v_ref", v_ref),
                           ("v_meas", v), ("target_x", target[0]), ("target_y", target[1])):
            rec[key].append(value)
        return Command(throttle, delta, _BRAKE if state["arrived"] else ALL_OFF)

    log = run_loop(car, step, max_time, cfg.rate, on_tick=on_tick)
    cols = {k: np.asarray(v) for k, v in log.arrays().items()}
    n = log.ticks
    for key in rec:
        cols[key] = np.asarray(rec[key][:n])
    metrics = score_run(cols, route, cfg, truth=truth0 is not None, stopped=log.stopped_early)
    metrics["config"] = asdict(cfg)
    return Result("path-follow", metrics, logs={"log.csv": _log_columns(cols)}, figures={})


def _heading(path: np.ndarray) -> float:
    d = path[1] - path[0]
    return math.atan2(d[1], d[0])


def score_run(cols: dict[str, np.ndarray], route: np.ndarray, cfg: FollowConfig, truth: bool, stopped: bool) -> dict:
    """The run's metrics: tracking against the reference, speed tracking, stop, drift.

    ``completion`` is the fraction of the path's length reached; a car that stopped within the
    goal tolerance of the last point has reached all of it.
    """
    if truth:
        driven = np.c_[cols["true_x"], cols["true_y"]]
    else:
        driven = np.c_[cols["est_x"], cols["est_y"]]
    errors = cross_track_errors(driven, route)
    progress = progress_along(driven, route)
    length = float(Polyline(route).length)
    worst = int(np.argmax(errors))
    duration = float(cols["t"][-1] + 1.0 / cfg.rate) if len(cols["t"]) else 0.0
    moving = cols["v_ref"] > 0.0
    speed_err = (cols["v_meas"] - cols["v_ref"])[moving]
    step_len = np.hypot(np.diff(driven[:, 0]), np.diff(driven[:, 1]))
    final_distance = float(np.hypot(*(driven[-1] - route[-1])))
    at_goal = stopped and final_distance <= cfg.goal_tolerance
    completion = 1.0 if at_goal else (float(min(1.0, progress[-1] / length)) if length > 0 else 0.0)
    metrics = {
        "experiment": "path-follow",
        "pose_source_for_scoring": "truth" if truth else "estimate",
        "path_points": int(len(route)),
        "path_length_m": length,
        "rms_cross_track_m": float(np.sqrt(np.mean(errors**2))),
        "max_cross_track_m": float(errors[worst]),
        "worst_point": [float(driven[worst, 0]), float(driven[worst, 1])],
        "completion": completion,
        "duration_s": duration,
        "mean_speed_mps": float(step_len.sum() / duration) if duration > 0 else 0.0,
        "speed_rms_error_mps": float(np.sqrt(np.mean(speed_err**2))) if speed_err.size else 0.0,
        "final_distance_to_goal_m": final_distance,
        "stopped_at_goal": at_goal,
    }
    if truth:
        drift = np.hypot(cols["est_x"] - cols["true_x"], cols["est_y"] - cols["true_y"])
        metrics["pose_drift_m"] = float(drift[-1])
        metrics["pose_drift_max_m"] = float(drift.max())
    return metrics


def _log_columns(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    keep = ["t", "target_x", "target_y", "est_x", "est_y", "est_yaw", "true_x", "true_y", "true_yaw",
            "throttle", "steering", "v_ref", "v_meas", "true_speed"]
    return {k: cols[k] for k in keep if k in cols}
