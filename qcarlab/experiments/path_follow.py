"""Path following (lab sheet section 4): the PathFollowing model on any car.

The model, :class:`PathFollowingLab`, is the sheet's diagram; each tick (``--rate``, 100 Hz)::

    v      = basic_speed_estimation(tach)                          # encoder -> m/s
    pose   = pose_estimator(pose, v, last steering, dt, gyro z)    # bicycle model (or truth)
    axle   = rear_axle(pose)                                       # pure pursuit's arc starts there
    target = LookaheadTarget(path, lookahead)(axle)                # the point l_d ahead of the axle
    delta  = pure_pursuit(axle, target, lookahead, L)              # or follow_the_carrot, stanley
                                                                   # (their targets: from the centre)
    v_ref  = turn_speed_handling(v_desired, delta)                 # (when --turn-speed)
    v_ref  = min(v_ref, sqrt(2 a_stop s_remaining))                # slows down to stop at the goal
    u      = speed_controller(v_ref, v, dt)                        # feed-forward PI -> throttle

Every block is looked up by its sheet name, so ``blocks={"pure_pursuit": my_fn}`` (or ``--use``)
runs the same model with the student's function. The sheet's model never stops (its stated
limitation); here the car brakes along a profile and stops within ``goal_tolerance`` of the last
point. On a simulator the run is scored against the true pose: RMS and max cross-track error to
the reference polyline, completion, speed tracking, final distance to the goal, the dead-reckoning
drift, and whether the car hit a wall or left the world (then the run stops: a goal missed).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from qcarlab.blocks import BlockSpec, StudentBlock, together
from qcarlab.car.base import Car, Command, Readout
from qcarlab.car.lamps import ALL_OFF, parse_lamps
from qcarlab.constants import QCarParams
from qcarlab.control.pose import BicyclePoseEstimator
from qcarlab.control.speed import KFF, KI, KP, SpeedController, speed_estimation, turn_speed_handling
from qcarlab.control.steering import LookaheadTarget, follow_the_carrot, pure_pursuit, rear_axle, stanley
from qcarlab.control.tracking import Polyline, cross_track_errors, progress_along
from qcarlab.errors import InputError
from qcarlab.experiments.loop import STOP, Step, check_rate, run_loop
from qcarlab.experiments.model import BASIC_SPEED_ESTIMATION, TURN_SPEED_HANDLING, LabModel, finish
from qcarlab.experiments.result import Result
from qcarlab.experiments.safety import WorldWatch

CONTROLLERS = ("pure-pursuit", "carrot", "stanley")
POSE_SOURCES = ("bicycle", "gyro", "truth")
A_STOP = 0.8  # m/s^2, the deceleration the stop profile plans with
_BRAKE = parse_lamps(["brake"])
_new_tuple = tuple.__new__  # Command is a named tuple: made without its Python-level __new__ every tick


@dataclass
class FollowConfig:
    """Everything that shapes a run; the defaults are the tuned lab values."""

    controller: str = "pure-pursuit"
    lookahead: float = 0.3  # m, pure pursuit / carrot look-ahead distance
    k_carrot: float = 1.0
    k_stanley: float = 2.0
    speed: float = 0.5  # m/s desired
    kp: float = KP
    ki: float = KI
    kff: float = KFF
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


#: The blocks of the path-following diagram (sheet 4, Figures 34-43), in the sheet's order.
BLOCKS = (
    BASIC_SPEED_ESTIMATION,
    BlockSpec("pose_estimator", "pose_estimator(pose, speed, steering, dt, yaw_rate) -> pose",
              "(m, m, rad), m/s, rad, s, rad/s or None -> (m, m, rad)", "4.1.1, Figure 34",
              "Dead reckoning: the pose dt later by the kinematic bicycle (yaw_rate: the gyro's, "
              "with --pose gyro, else None).", "pose", stateful=True),
    BlockSpec("pure_pursuit", "pure_pursuit(pose, target, lookahead, wheelbase) -> steering",
              "(m, m, rad) of the rear axle, (m, m), m, m -> rad (+ = left)", "4.1.4, 4.2.2 Tasks 3-4",
              "Steering onto the look-ahead point: atan(2 L sin(alpha) / l_d).", "steering",
              fill="Pure pursuit: steer the car so that its rear axle drives the circular arc through the "
              "look-ahead point. alpha = the target's bearing from the heading, l_d = the look-ahead "
              "distance; delta = atan(2 L sin(alpha) / l_d). Then tune the look-ahead (Tasks 3-4).",
              example="pure_pursuit((0, 0, 0), (0.0, 0.5), 0.5, 0.256) == atan(2 * 0.256 / 0.5) ~ 0.797"),
    BlockSpec("follow_the_carrot", "follow_the_carrot(pose, target, k_carrot) -> steering",
              "(m, m, rad) of the centre, (m, m), 1 -> rad", "4.1.3", "Steering K * heading error to the "
              "carrot (--controller carrot).", "steering"),
    BlockSpec("stanley", "stanley(pose, path, index, speed, k, wheelbase) -> steering",
              "(m, m, rad), Polyline, segment, m/s, 1, m -> rad", "beyond the sheet (Thrun 2006)",
              "Front-axle path tracking (--controller stanley).", "steering"),
    TURN_SPEED_HANDLING,
    BlockSpec("speed_controller", "speed_controller(v_ref, v_measured, dt) -> throttle",
              "m/s, m/s, s -> duty fraction", "4.2.3, Figure 43",
              "Feed-forward PI from the desired speed to the throttle (a class: it integrates).", "throttle",
              stateful=True,
              fill="The speed controller: a feed-forward PI. e = v_ref - v; throttle = K_ff v_ref + K_p e + "
              "K_i integral(e dt), limited to +-0.3. A class keeps the integral between calls. Then tune "
              "K_p and K_i (4.2.3) and explain your choice.",
              example="SpeedController()(0.5, 0.0, 0.01) -> 0.1 * 0.5 + 0.3 * 0.5 + 1.0 * 0.5 * 0.01 = 0.205"),
)


class PathFollowingLab(LabModel):
    """The sheet's PathFollowing model (section 4) as a block diagram; see the module docstring."""

    lab = "path-follow"
    BLOCKS = BLOCKS

    def __init__(self, route: np.ndarray, cfg: FollowConfig, params: QCarParams, throttle_limit: float,
                 start: tuple[float, float, float], truth=None, blocks: Mapping[str, Any] | None = None):
        self.cfg, self.p, self.throttle_limit = cfg, params, throttle_limit
        super().__init__(blocks)
        self.poly = Polyline(route)
        self.search = LookaheadTarget(self.poly, cfg.lookahead)
        self.goal = route[-1]
        self.end_zone = self.poly.length - max(cfg.goal_tolerance, cfg.lookahead) - 0.05
        self.truth = truth  # the simulator's truth(), for --pose truth
        self.pose = tuple(start)
        self.steer = 0.0
        self.arrived = False
        self.first = True
        # a student's steering block gets the target as an array (as the sheet's template says
        # and as it always has); the reference functions take the two floats as they are
        array_target = isinstance(self.pure_pursuit, StudentBlock) or isinstance(self.follow_the_carrot, StudentBlock)
        # the tick's constants, looked up once (the step runs 100 times a simulated second); the
        # half wheelbase is rear_axle's wheelbase / 2 (the same number)
        self._tick = (self.poly.length, params.wheelbase / 2.0, params.wheelbase, params.max_steering,
                      0.5 * cfg.goal_tolerance, 2.0 * A_STOP, cfg.lookahead, cfg.speed, cfg.turn_speed, self.end_zone,
                      cfg.controller == "pure-pursuit", cfg.pose == "gyro", cfg.pose == "truth", array_target)

    def reference_blocks(self) -> dict[str, Any]:
        c, p = self.cfg, self.p
        # the steering blocks as they are: step() clips whatever a steering block returns (the
        # student's too) to +-max_steering, which is what binding max_steering would do first
        # (a keyword bound with functools.partial costs more than the controller's arithmetic)
        return {
            "basic_speed_estimation": speed_estimation(p),
            "pose_estimator": BicyclePoseEstimator(p),
            "pure_pursuit": pure_pursuit,
            "follow_the_carrot": follow_the_carrot,
            "stanley": stanley,
            "turn_speed_handling": turn_speed_handling,
            "speed_controller": SpeedController(c.kp, c.ki, c.kff, throttle_limit=self.throttle_limit),
        }

    def step(self, t: float, r: Readout, dt: float) -> Step | object:
        # the run's constants, unpacked at once (attribute by attribute costs more, every tick)
        (length, half_wheelbase, wheelbase, m, stop_margin, two_a_stop, lookahead, speed, turn_speed, end_zone,
         pursuit, gyro, true_pose, array_target) = self._tick
        v = self.basic_speed_estimation(r.tach)
        if self.first:
            self.first = False
        else:
            yaw_rate = float(r.gyro[2]) if gyro else None  # (a student's may use it)
            self.pose = self.pose_estimator(self.pose, v, self.steer, dt, yaw_rate)
        est = self.pose
        if true_pose:
            tr = self.truth()
            pose = (tr.x, tr.y, tr.yaw)
        else:
            pose = est
        if pursuit:  # pure pursuit's look-ahead is measured from the rear axle (its arc starts there)
            axle = rear_axle(pose, wheelbase)
            tx, ty, index, progress = self.search.locate(axle[0], axle[1])
            # the path left ahead of the car's centre (pure pursuit's search runs L/2 behind it)
            remaining = length - progress - half_wheelbase
        else:
            tx, ty, index, progress = self.search.locate(float(pose[0]), float(pose[1]))
            remaining = length - progress
        arrived = self.arrived
        if not arrived and (
            remaining <= 0.0 or (progress >= end_zone and math.dist(pose[:2], self.goal) <= self.cfg.goal_tolerance)
        ):
            arrived = self.arrived = True
        if arrived:
            delta, v_ref = 0.0, 0.0
            if abs(v) < 0.01:
                return STOP
        else:
            target = np.array((tx, ty)) if array_target else (tx, ty)
            if pursuit:
                steering, steering_args = self.pure_pursuit, (axle, target, lookahead, wheelbase)
            elif self.cfg.controller == "carrot":
                steering, steering_args = self.follow_the_carrot, (pose, target, self.cfg.k_carrot)
            else:
                steering, steering_args = self.stanley, (pose, self.poly, index, v, self.cfg.k_stanley, wheelbase)
            room = remaining - stop_margin
            v_stop = math.sqrt(two_a_stop * (0.0 if 0.0 > room else room))
            if turn_speed:  # the desired speed depends on the steering: one block after the other
                delta = steering(*steering_args)
                delta = -m if -m > delta else (m if m < delta else delta)
                v_ref = self.turn_speed_handling(speed, delta)
                throttle = self.speed_controller(v_stop if v_stop < v_ref else v_ref, v, dt)
            else:  # the two blocks of the tick together (a student's two: one round trip to their process)
                v_ref = v_stop if v_stop < speed else speed
                delta, throttle = together(steering, steering_args, self.speed_controller, (v_ref, v, dt))
                # delta = min(max(delta, -m), m), written out (the builtins cost more)
                delta = -m if -m > delta else (m if m < delta else delta)
            if v_stop < v_ref:  # v_ref = min(v_ref, v_stop)
                v_ref = v_stop
        if arrived:
            throttle = self.speed_controller(v_ref, v, dt)
        self.steer = delta
        return Step(_new_tuple(Command, (throttle, delta, _BRAKE if arrived else ALL_OFF)),  # Command(...)
                    {"est_x": est[0], "est_y": est[1], "est_yaw": est[2], "v_ref": v_ref, "v_meas": v,
                     "target_x": tx, "target_y": ty})


def follow_path(car: Car, path: np.ndarray, cfg: FollowConfig, on_tick=None, *,
                blocks: Mapping[str, Any] | None = None, world: Any = None) -> Result:
    """Drive ``path`` with ``car``; return metrics, the log and the figures.

    ``blocks`` replaces any block of :data:`BLOCKS` by name (a function or class);
    ``world`` (a simulated car's, when local) ends the run when the car hits a wall or leaves it.
    """
    world = world if world is not None else getattr(car, "world", None)  # a local simulator's
    cfg.check()
    route = repeat_laps(np.asarray(path, dtype=float), cfg.laps)
    shortest = max(cfg.goal_tolerance, cfg.lookahead) + 0.05  # where the lab's end zone begins at 0
    if Polyline(route).length <= shortest:
        raise InputError(f"the path is {Polyline(route).length:.3f} m long; a path to follow must be longer than the "
                         f"look-ahead or the goal tolerance + 0.05 m ({shortest:.2f} m here)")
    truth0 = car.truth()
    if cfg.pose == "truth" and truth0 is None:
        raise InputError("--pose truth needs the simulator (a real car has no ground truth)")
    start = (truth0.x, truth0.y, truth0.yaw) if truth0 is not None else (route[0, 0], route[0, 1], _heading(route))
    lab = PathFollowingLab(route, cfg, car.params, car.throttle_limit, start, car.truth, blocks)
    watch = WorldWatch.for_car(car, world)
    model = watch.wrap(lab) if watch is not None else lab
    max_time = cfg.max_time or (1.5 * lab.poly.length / cfg.speed + 10.0)
    log = run_loop(car, model, max_time, cfg.rate, on_tick=on_tick)
    cols = log.arrays(LOG_COLUMNS)
    metrics = score_run(cols, route, cfg, truth=truth0 is not None, stopped=log.stopped_early and not
                        (watch and watch.event))
    metrics["config"] = asdict(cfg)
    # The goal is the end of the path as the car itself knows it (its own pose estimate: all a real
    # car can know); in a simulator the truth also counts, and where the two disagree the run says
    # by how much dead reckoning drifted (collisions and leaving the world end a run either way).
    reached_true = metrics["completion"] >= 0.999 or metrics["stopped_at_goal"]
    metrics["reached_by_estimate"] = bool(lab.arrived)
    if lab.arrived and not reached_true and "pose_drift_m" in metrics:
        metrics.setdefault("notes", []).append(
            f"the car's own estimate reached the end of the path, but it truly stopped "
            f"{metrics['final_distance_to_goal_m']:.2f} m from it: dead reckoning drifted "
            f"{metrics['pose_drift_m']:.2f} m ({100 * metrics['pose_drift_per_m']:.1f} cm per metre driven)")
    finish(metrics, log, lab, watch, goal=reached_true or lab.arrived,
           goal_text="the car did not reach the end of the path")
    return Result("path-follow", metrics, logs={"log.csv": _log_columns(cols)}, figures={})


def lookahead_sweep(runs: list[Result], label: str) -> Result:
    """The runs of a look-ahead sweep (sheet 4.2.2 Tasks 3-4) ranked by what the look-ahead controls:
    the runs that reached their goal first, then by the RMS cross-track error of the car's own pose
    estimate against the path (``rms_cross_track_estimate_m``: the error pure pursuit sees and
    corrects; the true error, ``rms_cross_track_m``, adds the dead reckoning's drift, which no
    look-ahead can see, and is shown beside it). Without an estimate (``--pose truth``) the true
    error ranks. ``best`` is the first; the sweep's goal: the best reached its own."""

    def key(r: Result) -> tuple[bool, float]:
        m = r.metrics
        return (not m.get("goal_reached", True), m.get("rms_cross_track_estimate_m", m["rms_cross_track_m"]))

    ranked = sorted(runs, key=key)
    summaries = []
    for r in ranked:
        m = {k: v for k, v in r.metrics.items() if k != "config"}
        m["lookahead"] = r.metrics["config"]["lookahead"]
        summaries.append(m)
    best = summaries[0]
    metrics = {"experiment": "path-follow", "path": label, "sweep": "lookahead", "runs": summaries, "best": best,
               "goal_reached": bool(best.get("goal_reached", True)),
               "failure": None if best.get("goal_reached", True) else "no look-ahead of the sweep reached the goal"}
    sweep = Result("path-follow sweep", metrics, data={"ranked": ranked})
    sweep.logs = {f"log_lookahead_{r.metrics['config']['lookahead']:g}.csv": r.logs["log.csv"] for r in runs}
    return sweep


def _heading(path: np.ndarray) -> float:
    d = path[1] - path[0]
    return math.atan2(d[1], d[0])


def score_run(cols: dict[str, np.ndarray], route: np.ndarray, cfg: FollowConfig, truth: bool, stopped: bool) -> dict:
    """The run's metrics: tracking against the reference, speed tracking, stop, drift.

    ``completion`` is the fraction of the path's length reached; a car that stopped within the
    goal tolerance of the last point has reached all of it. With the truth, ``pose_drift_m`` is
    the estimate's distance from the true pose at the end and ``pose_drift_per_m`` that over the
    distance driven.
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
        # the tracking as the car itself sees it (its estimate against the path): the controller's
        # own quality, apart from the drift of the pose it was given
        est_errors = cross_track_errors(np.c_[cols["est_x"], cols["est_y"]], route)
        metrics["rms_cross_track_estimate_m"] = float(np.sqrt(np.mean(est_errors**2)))
        metrics["distance_driven_m"] = float(step_len.sum())
        metrics["pose_drift_per_m"] = float(drift[-1] / step_len.sum()) if step_len.sum() > 0 else 0.0
    return metrics


#: The columns of the run's log.csv (and all that score_run reads), in order.
LOG_COLUMNS = ("t", "target_x", "target_y", "est_x", "est_y", "est_yaw", "true_x", "true_y", "true_yaw",
               "throttle", "steering", "v_ref", "v_meas", "true_speed")


def _log_columns(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: cols[k] for k in LOG_COLUMNS if k in cols}
