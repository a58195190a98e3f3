"""Basic I/O test (lab sheet 3.3): hold a throttle, steering and lamps, and read every sensor.

On the stand (the sheet's Task 1) the wheels turn and the encoder counts while the car stays
put; on the floor it drives. The model, :class:`BasicIOLab` (BasicIO.slx), holds the command and,
each tick, turns the tachometer into a speed with its one block, ``basic_speed_estimation`` (the
student may give their own: ``--use``); a simulated car also reports its ground truth to compare.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from functools import partial
from typing import Any

import numpy as np

from qcarlab.blocks import BlockSpec
from qcarlab.car.base import Car, Command, Readout
from qcarlab.car.lamps import lamps_on
from qcarlab.control.speed import basic_speed_estimation
from qcarlab.experiments.loop import Step, run_loop
from qcarlab.experiments.model import LabModel, finish
from qcarlab.experiments.result import Result

BLOCKS = (
    BlockSpec("basic_speed_estimation", "basic_speed_estimation(counts_per_s) -> speed", "counts/s -> m/s",
              "3.3 Task 2; lane example block 9", "Car speed from the motor encoder's rate.", "speed",
              fill="basicSpeedEstimation: turn the encoder's rate (counts/s) into the car's speed (m/s). The "
              "encoder has 720 lines, read in 4x quadrature (2880 counts per motor revolution); the gear "
              "ratio from the motor to the wheels is (13*19)/(70*37); the tyre radius is 0.033 m.",
              example="basic_speed_estimation(10000.0) ~ 0.0687 m/s"),
)


class BasicIOLab(LabModel):
    """BasicIO.slx (sheet 3.3): a constant command; the encoder's speed through its block."""

    lab = "io-test"
    BLOCKS = BLOCKS

    def __init__(self, command: Command, params, blocks: Mapping[str, Any] | None = None):
        self.command, self.p = command, params
        super().__init__(blocks)

    def reference_blocks(self) -> dict[str, Any]:
        return {"basic_speed_estimation": partial(basic_speed_estimation, params=self.p)}

    speed = 0.0  # m/s: the last speed the basic_speed_estimation block gave

    def step(self, t: float, r: Readout, dt: float) -> Step:
        self.speed = speed = self.basic_speed_estimation(r.tach)
        return Step(self.command, {"speed_mps": speed})


def io_test(
    car: Car,
    throttle: float,
    steering: float,
    leds: tuple[float, ...],
    duration: float,
    rate: float = 100.0,
    on_tick: Callable[[float, Readout, Command, float], None] | None = None,
    *,
    blocks: Mapping[str, Any] | None = None,
) -> Result:
    """Drive with a constant command for ``duration`` s; summarise the sensors.

    ``on_tick(t, readout, command, speed_mps)`` sees each tick, with the speed the run's
    ``basic_speed_estimation`` block (the student's, when given) made of it. The speeds and the
    distance reported come from that block too."""
    command = car.validate(throttle, steering, leds)  # refuse NaN before anything moves
    lab = BasicIOLab(command, car.params, blocks)
    truth0 = car.truth()
    start = car.read()
    tick = None if on_tick is None else (lambda t, r, cmd: on_tick(t, r, cmd, lab.speed))
    log = run_loop(car, lab, duration, rate, on_tick=tick)
    end = car.read()
    elapsed = end.t - start.t
    counts = end.encoder_counts - start.encoder_counts
    p = car.params
    cols = log.arrays()
    speed = cols["speed_mps"].astype(float)
    mean_speed = float(lab.basic_speed_estimation(counts / elapsed))  # the run's block, on the mean count rate
    metrics = {
        "experiment": "io-test",
        "command": {"throttle": command.throttle, "steering": command.steering, "leds": lamps_on(command.leds)},
        "duration_s": elapsed,
        "rate_hz": rate,
        "mean_speed_mps": mean_speed,
        "max_speed_mps": float(np.max(np.abs(speed))),
        "distance_m": mean_speed * elapsed,  # the block's mean speed over the run (it was the package's constant)
        "encoder_counts": counts,
        "tach_counts_per_s": end.tach,
        "motor_current_a": float(np.mean(cols["motor_current"])),
        "motor_current_max_a": float(np.max(np.abs(cols["motor_current"]))),
        "battery_v": float(np.mean(cols["battery_voltage"])),
        "battery_min_v": float(np.min(cols["battery_voltage"])),
        "battery_low": bool(np.min(cols["battery_voltage"]) < p.battery_low_v),
        "steering_rad": command.steering,
        "leds_on": lamps_on(command.leds),
    }
    truth1 = car.truth()
    if truth0 is not None and truth1 is not None:
        metrics["truth"] = {
            "mean_speed_mps": (truth1.distance - truth0.distance) / elapsed,
            "distance_m": truth1.distance - truth0.distance,
            "wheel_speed_mps": (truth1.wheel_distance - truth0.wheel_distance) / elapsed,
            "wheel_distance_m": truth1.wheel_distance - truth0.wheel_distance,
            "final_pose": [truth1.x, truth1.y, truth1.yaw],
        }
    columns = {"t": cols["t"], "throttle": cols["throttle"], "steering": cols["steering"],
               "encoder_counts": cols["encoder_counts"], "tach": cols["tach"], "speed_mps": speed,
               "motor_current_a": cols["motor_current"], "battery_v": cols["battery_voltage"],
               "gyro_z": cols["gyro_z"]}
    for key in ("true_x", "true_y", "true_yaw", "true_speed"):
        if key in cols:
            columns[key] = cols[key]
    finish(metrics, log, lab, None, True, "")
    return Result("io-test", metrics, logs={"log.csv": columns})
