"""Basic I/O test (lab sheet 3.3): hold a throttle, steering and lamps, and read every sensor.

On the stand (the sheet's Task 1) the wheels turn and the encoder counts while the car stays
put; on the floor it drives. Speed is estimated from the encoder through
``basic_speed_estimation``; a simulated car also reports its own ground truth to compare with.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from qcarlab.car.base import Car, Command, Readout
from qcarlab.car.lamps import lamps_on
from qcarlab.control.speed import basic_speed_estimation
from qcarlab.experiments.loop import run_loop
from qcarlab.experiments.result import Result


def io_test(
    car: Car,
    throttle: float,
    steering: float,
    leds: tuple[float, ...],
    duration: float,
    rate: float = 100.0,
    on_tick: Callable[[float, Readout, Command], None] | None = None,
) -> Result:
    """Drive with a constant command for ``duration`` s; summarise the sensors."""
    command = car.validate(throttle, steering, leds)  # refuse NaN before anything moves
    truth0 = car.truth()
    start = car.read()
    log = run_loop(car, lambda t, r: command, duration, rate, on_tick=on_tick)
    end = car.read()
    elapsed = end.t - start.t
    counts = end.encoder_counts - start.encoder_counts
    p = car.params
    cols = log.arrays()
    speed = basic_speed_estimation(cols["tach"], p)
    metrics = {
        "experiment": "io-test",
        "command": {"throttle": command.throttle, "steering": command.steering, "leds": lamps_on(command.leds)},
        "duration_s": elapsed,
        "rate_hz": rate,
        "mean_speed_mps": basic_speed_estimation(counts / elapsed, p),
        "max_speed_mps": float(np.max(np.abs(speed))),
        "distance_m": counts * p.speed_per_count,
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
    return Result("io-test", metrics, logs={"log.csv": columns})
