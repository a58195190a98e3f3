"""The simulated QCar's body: kinematic bicycle, steering servo, DC motor + ESC + gear train, battery.

Everything is scalar float arithmetic (no numpy in the inner step) so a physics step costs a few
microseconds; the simulator runs hundreds of times faster than real time.

**Kinematic bicycle (lab sheet 4.1.1, exact form).** The reference point is the car's centre,
midway between the axles (l_r = l_f = L/2). With wheel angle delta, the slip angle at the centre
is beta = atan(tan(delta) / 2) and::

    X' = v cos(psi + beta)     Y' = v sin(psi + beta)     psi' = v cos(beta) tan(delta) / L

The sheet's form X' = v cos(psi) - (L/2) psi' sin(psi), psi' = v delta / L is its linearisation
for small angles. Over one physics step delta and v are held, so the centre moves along an exact
circular arc of radius R = L / (cos(beta) tan(delta)); integration adds no error of its own.

**Steering servo.** First-order lag towards the clamped command:
delta' = (clip(delta_cmd, +-delta_max) - delta) / tau_s, discretised exactly.

**Drive train.** The ESC puts d * V_batt across the motor (d = PWM duty fraction). With back-EMF
and the armature resistance, i = (d V_batt - K_b w) / R, torque K_t i. The motor shaft carries the
reflected inertia J = J_drive + m (G r)^2 on the floor (J_drive alone on the stand), viscous
damping b w and a Coulomb load c = c_motor + C_rr m g G r (rolling resistance on the floor only)::

    J w' = K_t (d V_batt - K_b w) / R - b w - c sign(w)

integrated semi-implicitly (unconditionally stable, sticks at w = 0 while |drive| <= c).
Wheel speed v = w G r with G the gear ratio; the encoder counts w * 2880 / (2 pi).

**Battery.** 3S LiPo: open-circuit voltage from the state of charge (a LiPo cell's discharge
curve), minus the internal resistance times the current (idle draw + d * i), drained by
coulomb counting. Below the shutdown voltage the ESC cuts the motor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from qcarlab.constants import DEFAULT_PARAMS, QCarParams

# A LiPo cell's open-circuit voltage against its state of charge (typical discharge curve).
_SOC_POINTS = (0.0, 0.05, 0.1, 0.2, 0.4, 0.6, 0.8, 0.9, 1.0)
_CELL_VOLTS = (3.27, 3.50, 3.60, 3.68, 3.77, 3.86, 4.00, 4.08, 4.20)


def cell_voltage(soc: float) -> float:
    """Open-circuit voltage of one LiPo cell at state of charge ``soc`` (0..1), piecewise linear."""
    soc = min(max(soc, 0.0), 1.0)
    for i in range(1, len(_SOC_POINTS)):
        if soc <= _SOC_POINTS[i]:
            s0, s1 = _SOC_POINTS[i - 1], _SOC_POINTS[i]
            v0, v1 = _CELL_VOLTS[i - 1], _CELL_VOLTS[i]
            return v0 + (v1 - v0) * (soc - s0) / (s1 - s0)
    return _CELL_VOLTS[-1]


def turning_radius(delta: float, wheelbase: float = DEFAULT_PARAMS.wheelbase) -> float:
    """Radius of the circle the car's centre drives at a constant wheel angle ``delta``.

    R = L / (cos(beta) tan(delta)) = sqrt((L/2)^2 + (L / tan(delta))^2), beta = atan(tan(delta)/2).
    """
    t = math.tan(abs(delta))
    return math.inf if t == 0.0 else math.hypot(wheelbase / 2.0, wheelbase / t)


@dataclass(slots=True)
class VehicleState:
    """The body's state. Angles in rad, distances in m, speeds in m/s, motor speed in rad/s."""

    t: float = 0.0
    x: float = 0.0
    y: float = 0.0
    yaw: float = -math.pi / 2.0
    v: float = 0.0  # ground speed of the centre along its direction of motion (0 on the stand)
    yaw_rate: float = 0.0
    accel: float = 0.0  # longitudinal acceleration of the body, m/s^2
    delta: float = 0.0  # wheel angle after the servo
    omega: float = 0.0  # motor shaft speed
    motor_angle: float = 0.0  # accumulated motor shaft angle (drives the encoder)
    current: float = 0.0  # motor current, A
    battery_voltage: float = 0.0  # terminal voltage, V
    soc: float = 0.9  # battery state of charge
    distance: float = 0.0  # ground distance driven
    wheel_distance: float = 0.0  # distance turned by the wheels (signed)


class Vehicle:
    """One simulated QCar body. ``command(d, delta)`` sets the inputs, ``step(dt)`` advances time."""

    def __init__(
        self,
        params: QCarParams = DEFAULT_PARAMS,
        on_stand: bool = False,
        pose: tuple[float, float, float] = (0.0, 0.0, -math.pi / 2.0),
    ):
        self.p = params
        self.on_stand = bool(on_stand)
        p = params
        self.state = VehicleState(x=pose[0], y=pose[1], yaw=pose[2], soc=p.battery_soc0)
        self.state.battery_voltage = self._ocv = p.battery_cells * cell_voltage(p.battery_soc0)
        self.duty = 0.0
        self.delta_cmd = 0.0
        self.shutdown = False
        # constants of the step, computed once
        self._g = p.gear_ratio * p.wheel_radius  # m of travel per rad of motor shaft
        reflected = 0.0 if self.on_stand else p.mass * self._g**2
        self._J = p.drivetrain_inertia + reflected
        self._k = p.motor_kt * p.motor_kb / p.motor_resistance + p.motor_damping
        rolling = 0.0 if self.on_stand else p.rolling_resistance * p.mass * p.gravity * self._g
        self._c = p.motor_friction + rolling
        self._kt_r = p.motor_kt / p.motor_resistance
        self._cap_as = p.battery_capacity_ah * 3600.0
        self._dt_cached = -1.0
        self._servo_a = 0.0

    def command(self, duty: float, delta: float) -> None:
        """Set the PWM duty fraction and the steering command (rad); the servo clamps to +-max."""
        self.duty = duty
        m = self.p.max_steering
        self.delta_cmd = m if delta > m else (-m if delta < -m else delta)

    def step(self, dt: float) -> None:
        """Advance by ``dt`` seconds in physics steps of at most ``params.physics_dt``."""
        if dt <= 0.0:
            return
        n = max(1, math.ceil(dt / self.p.physics_dt - 1e-9))
        h = dt / n
        t_end = round(self.state.t + dt, 9)  # keep simulated time free of rounding drift
        # the open-circuit voltage moves by microvolts within a control step: evaluate it once
        self._ocv = self.p.battery_cells * cell_voltage(self.state.soc)
        for _ in range(n):
            self._substep(h)
        self.state.t = t_end

    def _substep(self, h: float) -> None:
        s, p = self.state, self.p
        if h != self._dt_cached:
            self._dt_cached = h
            self._servo_a = 1.0 - math.exp(-h / p.steering_tau)
        # steering servo (exact first-order lag)
        s.delta += (self.delta_cmd - s.delta) * self._servo_a
        # battery terminal voltage from the last step's current
        vbat = self._ocv - p.battery_resistance * (
            p.idle_current + abs(self.duty * s.current)
        )
        if vbat < p.battery_shutdown_v:
            self.shutdown = True
        s.battery_voltage = vbat
        vm = 0.0 if self.shutdown else self.duty * vbat
        # motor + load, semi-implicit with Coulomb friction that sticks at zero
        w = s.omega
        drive = self._kt_r * vm
        if w == 0.0 and abs(drive) <= self._c:
            w_new = 0.0
        else:
            sgn = (1.0 if w > 0.0 else -1.0) if w != 0.0 else (1.0 if drive > 0.0 else -1.0)
            w_new = (self._J * w + h * (drive - sgn * self._c)) / (self._J + h * self._k)
            if w != 0.0 and w_new * sgn < 0.0:
                w_new = 0.0
        s.current = (vm - p.motor_kb * w_new) / p.motor_resistance
        s.motor_angle += 0.5 * (w + w_new) * h
        s.omega = w_new
        v_old = s.v
        v_wheel = w_new * self._g
        s.wheel_distance += 0.5 * (w + w_new) * self._g * h
        s.soc -= (p.idle_current + abs(self.duty * s.current)) * h / self._cap_as
        if self.on_stand:
            s.v = 0.0
            s.yaw_rate = 0.0
            s.accel = 0.0
        else:
            v = 0.5 * (v_old + v_wheel)  # mean speed over the step
            tan_d = math.tan(s.delta)
            beta = math.atan(0.5 * tan_d)
            r = v * math.cos(beta) * tan_d / p.wheelbase  # yaw rate
            heading = s.yaw + beta
            turn = r * h
            if abs(turn) < 1e-9:
                s.x += v * h * math.cos(heading)
                s.y += v * h * math.sin(heading)
            else:
                rad = v / r
                s.x += rad * (math.sin(heading + turn) - math.sin(heading))
                s.y += rad * (math.cos(heading) - math.cos(heading + turn))
            s.yaw = (s.yaw + turn + math.pi) % (2.0 * math.pi) - math.pi
            s.yaw_rate = r
            s.distance += abs(v) * h
            s.accel = (v_wheel - v_old) / h
            s.v = v_wheel
        s.t += h

    @property
    def wheel_speed(self) -> float:
        """Tyre surface speed (m/s), what the encoder measures."""
        return self.state.omega * self._g
