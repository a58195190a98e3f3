"""The one control loop every lab uses: read the sensors, call the lab's step, write, wait.

    def step(t, readout):             # the lab's logic, pure or a small stateful object
        return Command(0.1, 0.0)      # or the STOP sentinel to end the run early

    log = run_loop(car, step, duration=5.0, rate=100.0)

The clock follows the car: a stepped simulator is advanced by exactly 1/rate per tick (as fast
as the CPU allows, deterministic); anything else (a real car, a realtime simulator, a TCP car) is
paced against the wall clock with deadlines that do not drift. Whatever happens, a run that ends
(normally, by an exception, by Ctrl-C) leaves the car stopped.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from qcarlab.car.base import Car, Command, Readout
from qcarlab.errors import InputError

STOP = object()  # returned by a step function to end the run


@dataclass
class LoopLog:
    """What the loop saw and did, one row per tick (SI units)."""

    columns: dict[str, list[float]] = field(default_factory=dict)
    ticks: int = 0
    stopped_early: bool = False

    def add(self, **values: float) -> None:
        for key, value in values.items():
            self.columns.setdefault(key, []).append(value)

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(v) for k, v in self.columns.items()}


def check_rate(rate: float) -> float:
    if not (math.isfinite(rate) and 1.0 <= rate <= 2000.0):
        raise InputError(f"--rate must be between 1 and 2000 Hz, got {rate}")
    return float(rate)


def run_loop(
    car: Car,
    step: Callable[[float, Readout], Command | object],
    duration: float,
    rate: float = 100.0,
    on_tick: Callable[[float, Readout, Command], None] | None = None,
    record_truth: bool = True,
) -> LoopLog:
    """Run ``step`` at ``rate`` Hz for ``duration`` s (or until it returns STOP); return the log.

    Each tick logs: t, the applied throttle and steering, encoder counts, tach (counts/s),
    motor current, battery voltage, gyro z and, on a simulator, the true pose and speed.
    """
    if not (math.isfinite(duration) and duration > 0.0):
        raise InputError(f"duration must be a positive number of seconds, got {duration}")
    dt = 1.0 / check_rate(rate)
    n_ticks = max(1, round(duration * rate))
    log = LoopLog()
    has_truth = record_truth and car.truth() is not None
    stepped = car.stepped
    t0 = car.time
    wall0 = time.monotonic()
    recorder = getattr(car, "recorder", None)  # --record/--live (qcarlab.recording): the lab's values too
    try:
        for k in range(n_ticks):
            if getattr(car, "ended", False):  # --car replay: the recording has run out
                log.stopped_early = True
                break
            readout = car.read()
            t = readout.t - t0
            out = step(t, readout)
            if out is STOP:
                log.stopped_early = True
                break
            cmd = car.write(out.throttle, out.steering, out.leds)
            row = dict(
                t=t,
                throttle=cmd.throttle,
                steering=cmd.steering,
                encoder_counts=readout.encoder_counts,
                tach=readout.tach,
                motor_current=readout.motor_current,
                battery_voltage=readout.battery_voltage,
                gyro_z=float(readout.gyro[2]),
            )
            if has_truth:
                tr = car.truth()
                row.update(true_x=tr.x, true_y=tr.y, true_yaw=tr.yaw, true_speed=tr.speed, true_steering=tr.steering)
            log.add(**row)
            if recorder is not None and getattr(out, "log", None):  # the lab's own values (a step's ``log``)
                recorder.log_values(readout.t, {"t": t, **out.log})
            log.ticks += 1
            if on_tick is not None:
                on_tick(t, readout, cmd)
            if stepped:
                car.advance(dt)
            else:
                delay = wall0 + (k + 1) * dt - time.monotonic()
                if delay > 0.0:
                    time.sleep(delay)
    finally:
        car.stop()
    return log
