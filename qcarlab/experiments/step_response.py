"""PI speed controller tuning (lab sheet 4.2.3): a speed step and its classic figures.

The car drives straight; at t = 0 the desired speed steps from 0 to ``speed``. From the measured
speed (encoder through ``basic_speed_estimation``):

- rise time: from 10 % to 90 % of the step,
- overshoot: (peak - step) / step, in %,
- settling time: the last time the speed is outside +-``band`` (2 %) of the step,
- steady-state error: step - mean speed over the last second.
"""

from __future__ import annotations

import numpy as np

from qcarlab.car.base import Car, Command, Readout
from qcarlab.control.speed import SpeedController, basic_speed_estimation
from qcarlab.experiments.loop import run_loop
from qcarlab.experiments.result import Result


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


def step_response(car: Car, speed: float, kp: float, ki: float, kff: float, duration: float = 6.0,
                  rate: float = 100.0) -> Result:
    """Drive a speed step of ``speed`` m/s with the feed-forward PI gains; return the figures."""
    pi = SpeedController(kp, ki, kff, throttle_limit=car.throttle_limit)
    dt = 1.0 / rate
    p = car.params

    def step(t: float, r: Readout) -> Command:
        return Command(pi(speed, basic_speed_estimation(r.tach, p), dt), 0.0)

    log = run_loop(car, step, duration, rate)
    cols = log.arrays()
    v = basic_speed_estimation(cols["tach"], p)
    metrics = {"experiment": "path-follow --step-response", "speed_step_mps": speed,
               "kp": kp, "ki": ki, "kff": kff, "duration_s": duration}
    metrics.update(step_metrics(cols["t"], v, speed))
    columns = {"t": cols["t"], "v_ref": np.full_like(v, speed), "v_meas": v, "throttle": cols["throttle"]}
    return Result("step-response", metrics, logs={"log.csv": columns})
