"""PI speed controller tuning (lab sheet 4.2.3): a speed step through the lab's own blocks.

The model, :class:`StepResponseLab`, is the speed loop of the path-following diagram (Figure 43)
with the steering held at zero; each tick (``--rate``, 100 Hz)::

    v = basic_speed_estimation(tach)            # encoder -> m/s
    u = speed_controller(v_step, v, dt)         # feed-forward PI -> throttle

Both blocks are looked up by their sheet names, so ``blocks={"speed_controller": MyPI}`` (or
``--use``/``--block``) drives the step with the student's controller; the reference controller
takes the run's gains (``--kp``, ``--ki``, ``--kff`` or the ``lab:`` section of ``--params``).
At t = 0 the desired speed steps from 0 to ``speed``. From the measured speed (the encoder's
rate through qcarlab's own ``basic_speed_estimation``, so a student's estimate cannot flatter
its own controller):

- rise time: from 10 % to 90 % of the step,
- overshoot: (peak - step) / step, in %,
- settling time: the last time the speed is outside +-``band`` (2 %) of the step,
- steady-state error: step - mean speed over the last second.

The run's goal: the speed reached 90 % of the step. On a simulator the step starts at the back of
the room (:func:`step_start`: the world's start backed up to 0.3 m from the wall behind it) and
ends, a goal missed, when the car drives into a wall or out of the world.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from functools import partial
from typing import Any

import numpy as np

from qcarlab.car.base import Car, Command, Readout
from qcarlab.control.speed import SpeedController, basic_speed_estimation
from qcarlab.experiments.loop import Step, run_loop
from qcarlab.experiments.model import LabModel, finish
from qcarlab.experiments.path_follow import BLOCKS as PATH_BLOCKS
from qcarlab.experiments.path_follow import FollowConfig
from qcarlab.experiments.result import Result
from qcarlab.experiments.safety import Clearance, WorldWatch

#: The blocks of the speed loop: the path-following sheet's own (same names, signatures, texts).
STEP_BLOCKS = tuple(b for b in PATH_BLOCKS if b.name in ("basic_speed_estimation", "speed_controller"))


def step_metrics(t: np.ndarray, v: np.ndarray, step: float, band: float = 0.02) -> dict[str, float | None]:
    """Rise time, overshoot, settling time and steady-state error of a response ``v(t)`` to ``step``."""
    def first_at(level: float) -> float | None:
        idx = np.flatnonzero(v >= level)
        return float(t[idx[0]]) if idx.size else None

    t10, t90 = first_at(0.1 * step), first_at(0.9 * step)
    outside = np.flatnonzero(np.abs(v - step) > band * step)
    if outside.size == 0:
        settling = 0.0
    elif outside[-1] == len(v) - 1:
        settling = None  # never settled within the run
    else:
        settling = float(t[outside[-1] + 1])
    tail = v[t >= t[-1] - 1.0]
    return {
        "rise_time_s": (t90 - t10) if t10 is not None and t90 is not None else None,
        "overshoot_pct": max(0.0, float(v.max() - step) / step * 100.0),
        "settling_time_s": settling,
        "steady_state_error_mps": float(step - tail.mean()),
    }


def throttle_metrics(t: np.ndarray, u: np.ndarray, limit: float) -> dict[str, float]:
    """What the controller asks of the motor: its chatter, the RMS of the throttle's change from one
    tick to the next over the last second, ``sqrt(mean((u[k] - u[k-1])^2))`` (0 for a steady
    throttle; a loop tuned too hard for the drive train's delay and dead-band switches the throttle
    back and forth every few ticks), and the seconds it spent at the throttle limit (saturated)."""
    tail = u[t >= t[-1] - 1.0]
    du = np.diff(tail)
    return {"throttle_chatter": float(np.sqrt(np.mean(du * du))) if du.size else 0.0,
            "throttle_saturated_s": float(np.count_nonzero(np.abs(u) >= limit - 1e-9)
                                          * (float(t[1] - t[0]) if len(t) > 1 else 0.0))}


class StepResponseLab(LabModel):
    """The speed loop of the PathFollowing model (sheet 4.2.3, Figure 43), driven by a speed step."""

    lab = "path-follow"
    BLOCKS = STEP_BLOCKS

    def __init__(self, speed: float, cfg: FollowConfig, params: Any, throttle_limit: float,
                 blocks: Mapping[str, Any] | None = None):
        self.speed, self.cfg, self.p, self.throttle_limit = speed, cfg, params, throttle_limit
        super().__init__(blocks)

    def reference_blocks(self) -> dict[str, Any]:
        c = self.cfg
        return {
            "basic_speed_estimation": partial(basic_speed_estimation, params=self.p),
            "speed_controller": SpeedController(c.kp, c.ki, c.kff, throttle_limit=self.throttle_limit),
        }

    def step(self, t: float, r: Readout, dt: float) -> Step:
        v = self.basic_speed_estimation(r.tach)
        throttle = self.speed_controller(self.speed, v, dt)
        return Step(Command(throttle, 0.0), {"v_ref": self.speed, "v_est": v})


def step_start(world: Any, params: Any, margin: float = 0.3, reach: float = 20.0) -> tuple[float, float, float]:
    """Where a simulated step starts: the world's start pose, backed up along its heading until the
    car's footprint is ``margin`` m from what is behind it, so the step has the longest straight run
    the room allows (the studio: from its centre 4.7 m to the wall, from the back wall 9.1 m).

    Backs up in 5 cm steps while the footprint's clearance stays above ``margin``
    (:class:`~qcarlab.experiments.safety.Clearance`); at most ``reach`` m.
    """
    x, y, yaw = (float(v) for v in world.start)
    clearance = Clearance(world, params)
    bx, by = -math.cos(yaw), -math.sin(yaw)
    x0, y0, x1, y1 = world.bounds
    back = 0.0
    while back + 0.05 <= reach:
        px, py = x + (back + 0.05) * bx, y + (back + 0.05) * by
        inside = x0 + margin <= px <= x1 - margin and y0 + margin <= py <= y1 - margin
        if not inside or clearance(px, py, yaw)[0] <= margin:
            break
        back += 0.05
    return (round(x + back * bx, 6), round(y + back * by, 6), yaw)


def step_response(car: Car, cfg: FollowConfig, duration: float = 6.0,
                  on_tick: Callable[[float, Readout, Command], None] | None = None, *,
                  blocks: Mapping[str, Any] | None = None, world: Any = None) -> Result:
    """Drive a speed step of ``cfg.speed`` m/s for ``duration`` s; return the step's figures.

    ``blocks`` replaces ``basic_speed_estimation`` and/or ``speed_controller`` by name (other
    path-following blocks are not part of the speed loop and are ignored); ``world`` (a local
    simulator's) ends the run when the car hits a wall or leaves it.
    """
    cfg.check()
    world = world if world is not None else getattr(car, "world", None)
    mine = {k: v for k, v in (blocks or {}).items() if k in StepResponseLab.specs()}
    lab = StepResponseLab(cfg.speed, cfg, car.params, car.throttle_limit, mine)
    watch = WorldWatch.for_car(car, world)
    model = watch.wrap(lab) if watch is not None else lab
    log = run_loop(car, model, duration, cfg.rate, on_tick=on_tick)
    cols = log.arrays()
    t = cols["t"].astype(float)
    v = basic_speed_estimation(cols["tach"].astype(float), car.params)  # qcarlab's measure, not the block's
    speed = cfg.speed
    ours = "speed_controller" not in lab.student
    metrics: dict[str, Any] = {
        "experiment": "path-follow --step-response", "speed_step_mps": speed,
        "controller": "qcarlab's SpeedController" if ours else f"your speed_controller ({lab.student['speed_controller'].source})",
        "kp": cfg.kp, "ki": cfg.ki, "kff": cfg.kff, "duration_s": duration, "rate_hz": cfg.rate,
    }
    if len(t):
        metrics.update(step_metrics(t, v, speed))
        metrics.update(throttle_metrics(t, cols["throttle"].astype(float), car.throttle_limit))
    else:  # stopped before the first tick (a wall at the start)
        metrics.update({"rise_time_s": None, "overshoot_pct": 0.0, "settling_time_s": None,
                        "steady_state_error_mps": speed})
    reached = bool(len(v)) and bool(np.any(v >= 0.9 * speed))
    finish(metrics, log, lab, watch, goal=reached,
           goal_text=f"the speed never reached 90 % of the {speed:g} m/s step (max "
           f"{float(v.max()) if len(v) else 0.0:.3f} m/s)")
    columns = {"t": t, "v_ref": np.full_like(v, speed), "v_meas": v, "throttle": cols["throttle"]}
    if "v_est" in cols:
        columns["v_est"] = cols["v_est"]
    return Result("step-response", metrics, logs={"log.csv": columns})
