"""Speed blocks of the lab: speed estimation from the encoder, the feed-forward PI speed controller,
and the speed reduction in turns. Names follow the lab sheets (lane example blocks 6 and 9, path
following Figure 43).
"""

from __future__ import annotations

import math

from qcarlab.constants import DEFAULT_PARAMS, QCarParams

#: The speed controller's gains, Quanser's defaults (sheet 4.2.3): written here once.
KP, KI, KFF = 0.3, 1.0, 0.1


def basic_speed_estimation(counts_per_s, params: QCarParams = DEFAULT_PARAMS):
    """Car speed (m/s) from the motor encoder's rate (counts/s): the four scaling terms of block 9.

        rotations/s = counts/s / 2880           (720 lines x 4 quadrature per motor revolution)
        wheel rev/s = rotations/s * 0.09537     (gear train (13*19)/(70*37))
        wheel rad/s = wheel rev/s * 2 pi
        v           = wheel rad/s * 0.033       (tyre radius)

    i.e. v = counts/s * 6.866e-6 m/s. Works on floats and numpy arrays alike.
    """
    motor_rps = counts_per_s / params.encoder_cpr
    wheel_rps = motor_rps * params.gear_ratio
    wheel_rad_s = wheel_rps * (2.0 * math.pi)
    return wheel_rad_s * params.wheel_radius


def speed_estimation(params: QCarParams = DEFAULT_PARAMS):
    """:func:`basic_speed_estimation` bound to ``params``: ``f(counts_per_s) -> m/s``, the same
    four terms in the same order (so the same numbers), with the parameters looked up once."""
    cpr, gear, radius = params.encoder_cpr, params.gear_ratio, params.wheel_radius
    two_pi = 2.0 * math.pi

    def speed(counts_per_s):
        return counts_per_s / cpr * gear * two_pi * radius

    speed.__doc__ = basic_speed_estimation.__doc__
    return speed


def turn_speed_handling(desired_speed: float, steering: float, enable: bool = True) -> float:
    """Slow down in turns (block 6): v_ref * clip(cos(delta)^8, 0.5, 1) when enabled, else v_ref."""
    if not enable:
        return desired_speed
    return desired_speed * min(1.0, max(0.5, math.cos(steering) ** 8))


class SpeedController:
    """``speed_controller``: feed-forward PI from desired speed to throttle (sheet Figure 43).

        e = v_ref - v
        throttle = clip(K_ff v_ref + K_p e + K_i integral(e dt), +-throttle_limit)

    The integral term K_i integral(e dt) is clamped to +-``integral_limit`` (anti-windup) and held at zero while the
    controller is not armed. Defaults are Quanser's: K_ff = 0.1, K_p = 0.3, K_i = 1.

    A car asked to stand still (v_ref = 0) that is at rest (|v| < ``rest_speed``) gets throttle 0
    and a reset integrator: otherwise the integral built up while braking backs the car away.
    """

    def __init__(
        self,
        kp: float = KP,
        ki: float = KI,
        kff: float = KFF,
        throttle_limit: float = DEFAULT_PARAMS.throttle_limit,
        integral_limit: float = 0.4,
        rest_speed: float = 0.01,
    ):
        for name, value in (("kp", kp), ("ki", ki), ("kff", kff)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a non-negative number, got {value}")
        self.kp, self.ki, self.kff = kp, ki, kff
        self.throttle_limit = throttle_limit
        self.integral_limit = integral_limit
        self.rest_speed = rest_speed
        self.integral = 0.0

    def reset(self) -> None:
        self.integral = 0.0

    def __call__(self, desired_speed: float, measured_speed: float, dt: float, armed: bool = True) -> float:
        if not armed or (desired_speed == 0.0 and abs(measured_speed) < self.rest_speed):
            self.integral = 0.0
            return 0.0
        e = desired_speed - measured_speed
        lim = self.integral_limit
        i = self.integral + self.ki * e * dt
        i = i if i > -lim else -lim  # min(lim, max(-lim, i)) written out (it runs every tick)
        i = i if i < lim else lim
        self.integral = i
        u = self.kff * desired_speed + self.kp * e + i
        lim = self.throttle_limit
        return lim if u > lim else (-lim if u < -lim else u)


#: The sheet's block name for the class (a stateful block: ``speed_controller(v_ref, v, dt)``).
speed_controller = SpeedController
