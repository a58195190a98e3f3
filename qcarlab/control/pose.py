"""Where am I? Dead-reckoning pose estimators for path following (sheet 4.1.1, Figure 34).

The car knows its speed (encoder through ``basic_speed_estimation``) and the steering it
commanded; it has no steering sensor. :class:`BicyclePoseEstimator` integrates the sheet's
kinematic bicycle model::

    X' = v cos(psi + beta),  Y' = v sin(psi + beta),  psi' = v cos(beta) tan(delta) / L,
    beta = atan(tan(delta) / 2)

with the wheel angle ``delta`` estimated from the command through the servo's first-order lag
(tau = 0.16 s): without it the estimate turns earlier than the car does and drifts. With
``yaw_rate`` given (``mode="gyro"``), psi' is the gyro's z rate instead, so the heading no longer
depends on the steering model (but integrates the gyro's bias).
"""

from __future__ import annotations

import math

from qcarlab.constants import DEFAULT_PARAMS, QCarParams


class BicyclePoseEstimator:
    """The ``pose_estimator`` block: integrates speed and steering (or gyro yaw rate) into a pose
    (x, y, yaw) of the car's centre. Stateful only through the servo model (the wheel angle)::

        est = BicyclePoseEstimator(params)
        pose = est(pose, speed, steering_cmd, dt, yaw_rate=None)   # every tick
    """

    def __init__(self, params: QCarParams = DEFAULT_PARAMS, model_servo: bool = True):
        self.params = params
        self.model_servo = model_servo
        self.reset()

    def reset(self) -> None:
        self.delta = 0.0
        self._dt = self._servo_a = math.nan  # the servo factor's tick length (none yet)

    def __call__(
        self,
        pose: tuple[float, float, float],
        speed: float,
        steering_cmd: float,
        dt: float,
        yaw_rate: float | None = None,
    ) -> tuple[float, float, float]:
        """The pose ``dt`` s after ``pose`` at the measured ``speed`` with the commanded steering."""
        if self.model_servo:
            if dt != self._dt:  # the servo's step factor 1 - exp(-dt / tau), once per tick length
                self._dt, self._servo_a = dt, 1.0 - math.exp(-dt / self.params.steering_tau)
            delta = self.delta = self.delta + (steering_cmd - self.delta) * self._servo_a
        else:
            delta = self.delta = steering_cmd
        x, y, yaw = pose
        tan_d = math.tan(delta)
        beta = math.atan(0.5 * tan_d)
        r = speed * math.cos(beta) * tan_d / self.params.wheelbase if yaw_rate is None else yaw_rate
        heading = yaw + beta + 0.5 * r * dt  # midpoint heading over the step
        return (x + speed * dt * math.cos(heading), y + speed * dt * math.sin(heading),
                (yaw + r * dt + math.pi) % (2.0 * math.pi) - math.pi)
