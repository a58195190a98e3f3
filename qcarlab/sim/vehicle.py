"""The simulated QCar's body: kinematic bicycle, steering servo, DC motor + ESC + gear train, battery.

The sub-steps are scalar float arithmetic on one float64 state buffer, read into locals once a
control step: plain Python (some 5 us for a 10 ms step of five sub-steps) or the same code
compiled (about 1 us with the call) once a process has loaded it (:func:`load_compiled`: a server,
a gym env, the grader's warm process), has made enough steps to repay loading it, or is asked to
(:data:`COMPILED`); the simulator runs hundreds of times faster than real time.

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

**Realism** (:mod:`qcarlab.sim.realism`, ``--realism lab``): the servo's dead-band, backlash
and trim act on the command before the lag; the tyres slip, v_ground = v_wheel (1 - s0 -
k_scrub |v psi'| / g), and understeer, tan(delta_eff) = tan(delta) L / (L + K_us v^2). With the
ideal profile (all 0) the step is the exact model above.

**Battery.** 3S LiPo: open-circuit voltage from the state of charge (a LiPo cell's discharge
curve), minus the internal resistance times the current (idle draw + d * i), drained by
coulomb counting. Below the shutdown voltage the ESC cuts the motor.
"""

from __future__ import annotations

import math
import sys
from collections import deque
from array import array

import numpy as np

from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.sim.realism import IDEAL, Realism, Servo

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


_FIELDS = ("t", "x", "y", "yaw", "v", "yaw_rate", "accel", "delta", "omega", "motor_angle", "current",
           "battery_voltage", "soc", "distance", "wheel_distance")
(_T, _X, _Y, _YAW, _V, _YAW_RATE, _ACCEL, _DELTA, _OMEGA, _MOTOR_ANGLE, _CURRENT, _VBAT, _SOC, _DIST,
 _WDIST) = range(len(_FIELDS))
_SHUTDOWN = len(_FIELDS)  # 1.0 once the battery has cut the motor


class VehicleState:
    """The body's state. Angles in rad, distances in m, speeds in m/s, motor speed in rad/s.

    The numbers live in one float64 buffer (``buffer``) that the compiled physics step updates
    in place; the attributes read and write it (Python floats).
    """

    __slots__ = ("buffer", "_a")

    def __init__(self, **values: float):
        self._a = array("d", bytes(8 * (len(_FIELDS) + 1)))
        self.buffer = np.frombuffer(self._a, dtype=np.float64)  # the same memory, for the kernel
        self.yaw = -math.pi / 2.0
        self.soc = 0.9
        for k, v in values.items():
            setattr(self, k, v)

    def __repr__(self) -> str:
        return "VehicleState(" + ", ".join(f"{k}={getattr(self, k)!r}" for k in _FIELDS) + ")"

    def values(self) -> list[float]:
        """Every field at once, in the order t, x, y, yaw, v, yaw_rate, accel, delta, omega,
        motor_angle, current, battery_voltage, soc, distance, wheel_distance (then the shutdown
        flag): one call instead of an attribute lookup each, for the simulator's hot paths."""
        return self._a.tolist()


def _field(i: int, doc: str) -> property:
    def get(self: VehicleState) -> float:
        return self._a[i]

    def put(self: VehicleState, value: float) -> None:
        self._a[i] = value

    return property(get, put, doc=doc)


for _i, (_name, _doc) in enumerate(zip(_FIELDS, (
    "s", "m", "m", "rad", "ground speed of the centre along its direction of motion (m/s; 0 on the stand)",
    "rad/s", "longitudinal acceleration of the body, m/s^2", "wheel angle after the servo (rad)",
    "motor shaft speed (rad/s)", "accumulated motor shaft angle (rad; drives the encoder)", "motor current, A",
    "battery terminal voltage, V", "battery state of charge (0..1)", "ground distance driven (m)",
    "distance turned by the wheels (m, signed)",
))):
    setattr(VehicleState, _name, _field(_i, _doc))


# the step's constants, one float64 array (indices below), so that the compiled step takes arrays
(_P_DT, _P_TAU, _P_RBAT, _P_IDLE, _P_VCUT, _P_KTR, _P_J, _P_K, _P_C, _P_KB, _P_R, _P_G, _P_CAP, _P_L,
 _P_STAND, _P_CELLS, _P_SLIP, _P_SCRUB, _P_KUS) = range(19)
# (the LiPo table is read by the step as the module's tuples: compiled, numba bakes them in as
# constants, so a call passes two arrays and three floats, not four arrays)

#: Which implementation of the sub-steps runs: None (default) = the numba-compiled one once it is
#: loaded (:func:`load_compiled`: a simulated car does when it builds a camera, whose kernels have
#: loaded numba; the warm processes at their start), or once numba is loaded in the process and
#: the process has made :data:`SWITCH_AFTER` plain-Python steps, else plain Python; True = always
#: compiled (loads numba: some 0.5 s at the first step of a process, worth it for long sweeps);
#: False = always plain Python. Both are the same code on the same numbers: the same results.
COMPILED: bool | None = None
#: Plain-Python steps after which a process with numba loaded switches to the compiled step:
#: loading it costs 30-150 ms (more when it is numba's first function in the process) and it saves
#: some 4 us a step, so a lab's lone run (a stop-sign run: 800 steps; 60 s of avoid: 6,000) keeps
#: plain Python, a long one (a sweep in one process, a gym env's training) switches.
SWITCH_AFTER = 20_000
_compiled_advance = None
_python_steps = 0
_MODULES = sys.modules


def _advance(s, p, duty, delta_cmd, dt):
    """``dt`` seconds of the body in ceil(dt / physics_dt) equal sub-steps, in place on the
    state buffer ``s`` (see :class:`VehicleState`); the equations are the module docstring's.
    Plain Python on an ``array('d')`` and the constants as a list, or compiled with numba on the
    same buffer as a numpy array (see :data:`COMPILED`): the state is read into locals once,
    stepped, and written back once."""
    n = max(1, math.ceil(dt / p[_P_DT] - 1e-9))
    h = dt / n
    delta = s[_DELTA]
    current = s[_CURRENT]
    omega = s[_OMEGA]
    motor_angle = s[_MOTOR_ANGLE]
    v_cur = s[_V]
    wdist = s[_WDIST]
    soc = s[_SOC]
    x = s[_X]
    y = s[_Y]
    yaw = s[_YAW]
    yaw_rate = s[_YAW_RATE]
    accel = s[_ACCEL]
    dist = s[_DIST]
    t = s[_T]
    vbat = s[_VBAT]
    shutdown = s[_SHUTDOWN] != 0.0
    # the open-circuit voltage moves by microvolts within a control step: evaluate it once
    # (a LiPo cell's discharge curve, piecewise linear, as cell_voltage)
    socs, volts = _SOC_POINTS, _CELL_VOLTS
    q = min(max(soc, 0.0), 1.0)
    cell = volts[len(volts) - 1]
    for i in range(1, len(socs)):
        if q <= socs[i]:
            s0 = socs[i - 1]
            v0 = volts[i - 1]
            cell = v0 + (volts[i] - v0) * (q - s0) / (socs[i] - s0)
            break
    ocv = p[_P_CELLS] * cell
    servo_a = 1.0 - math.exp(-h / p[_P_TAU])
    kt_r = p[_P_KTR]
    J = p[_P_J]
    kk = p[_P_K]
    cc = p[_P_C]
    kb = p[_P_KB]
    rm = p[_P_R]
    g = p[_P_G]
    rbat = p[_P_RBAT]
    idle = p[_P_IDLE]
    vcut = p[_P_VCUT]
    cap = p[_P_CAP]
    wheelbase = p[_P_L]
    stand = p[_P_STAND] != 0.0
    slip0 = p[_P_SLIP]
    scrub = p[_P_SCRUB]  # per m/s^2 of lateral acceleration
    kus = p[_P_KUS]
    tyres = slip0 != 0.0 or scrub != 0.0 or kus != 0.0  # a realism profile's tyres (ideal: exact as before)
    for _ in range(n):
        # steering servo (exact first-order lag)
        delta += (delta_cmd - delta) * servo_a
        # battery terminal voltage from the last step's current
        vbat = ocv - rbat * (idle + abs(duty * current))
        if vbat < vcut:
            shutdown = True
        vm = 0.0 if shutdown else duty * vbat
        # motor + load, semi-implicit with Coulomb friction that sticks at zero
        w = omega
        drive = kt_r * vm
        if w == 0.0 and abs(drive) <= cc:
            w_new = 0.0
        else:
            sgn = (1.0 if w > 0.0 else -1.0) if w != 0.0 else (1.0 if drive > 0.0 else -1.0)
            w_new = (J * w + h * (drive - sgn * cc)) / (J + h * kk)
            if w != 0.0 and w_new * sgn < 0.0:
                w_new = 0.0
        current = (vm - kb * w_new) / rm
        motor_angle += 0.5 * (w + w_new) * h
        omega = w_new
        v_old = v_cur
        v_wheel = w_new * g
        wdist += 0.5 * (w + w_new) * g * h
        soc -= (idle + abs(duty * current)) * h / cap
        if stand:
            v_cur = 0.0
            yaw_rate = 0.0
            accel = 0.0
        else:
            if tyres:  # slip (more in turns: scrub) takes ground speed off the wheels' speed
                v_wheel *= 1.0 - slip0 - scrub * abs(v_old * yaw_rate)
            v = 0.5 * (v_old + v_wheel)  # mean speed over the step
            tan_d = math.tan(delta)
            if tyres and kus != 0.0:  # understeer: the car turns wider than the bicycle model
                tan_d *= wheelbase / (wheelbase + kus * v * v)
            beta = math.atan(0.5 * tan_d)
            r = v * math.cos(beta) * tan_d / wheelbase  # yaw rate
            heading = yaw + beta
            turn = r * h
            if abs(turn) < 1e-9:
                x += v * h * math.cos(heading)
                y += v * h * math.sin(heading)
            else:
                rad = v / r
                x += rad * (math.sin(heading + turn) - math.sin(heading))
                y += rad * (math.cos(heading) - math.cos(heading + turn))
            yaw = (yaw + turn + math.pi) % (2.0 * math.pi) - math.pi
            yaw_rate = r
            dist += abs(v) * h
            accel = (v_wheel - v_old) / h
            v_cur = v_wheel
        t += h
    s[_DELTA] = delta
    s[_CURRENT] = current
    s[_OMEGA] = omega
    s[_MOTOR_ANGLE] = motor_angle
    s[_V] = v_cur
    s[_WDIST] = wdist
    s[_SOC] = soc
    s[_X] = x
    s[_Y] = y
    s[_YAW] = yaw
    s[_YAW_RATE] = yaw_rate
    s[_ACCEL] = accel
    s[_DIST] = dist
    s[_T] = t
    s[_VBAT] = vbat
    s[_SHUTDOWN] = 1.0 if shutdown else 0.0


def _compiled():
    """The numba-compiled :func:`_advance` when :data:`COMPILED` asks for it, else None."""
    use = COMPILED
    if use is None:
        use = _compiled_advance is not None or ("numba" in sys.modules and _python_steps >= SWITCH_AFTER)
    if not use:
        return None
    return load_compiled()


def load_compiled():
    """The numba-compiled :func:`_advance`, used from now on in this process (unless
    :data:`COMPILED` is False); None without numba. Its first call loads it from numba's cache."""
    global _compiled_advance
    if _compiled_advance is None:
        from qcarlab.sim._kernels import HAVE_NUMBA, njit

        if not HAVE_NUMBA:
            return None
        _compiled_advance = njit(cache=True, nogil=True, error_model="numpy")(_advance)
    return _compiled_advance


class Vehicle:
    """One simulated QCar body. ``command(d, delta)`` sets the inputs, ``step(dt)`` advances time.

    ``auto_switch`` (default True): this body may switch the process to the compiled step after
    :data:`SWITCH_AFTER` plain-Python steps; a real-time car turns it off, so that loading the
    compiled step (tens of ms) never lands in one of its steps (it runs compiled only once
    something has loaded it: :func:`load_compiled`).
    """

    auto_switch = True

    def __init__(
        self,
        params: QCarParams = DEFAULT_PARAMS,
        on_stand: bool = False,
        pose: tuple[float, float, float] = (0.0, 0.0, -math.pi / 2.0),
        realism: Realism | None = None,
    ):
        self.p = params
        self.realism = realism = realism if realism is not None else IDEAL
        self._servo = Servo(realism) if realism.servo else None
        self._delay_ns = round(realism.steering_delay * 1e9)
        self._pending: deque[tuple[int, float]] = deque()  # (due time in ns, wheel target) with a delay
        self._duty_delay_ns = round(realism.throttle_delay * 1e9)
        self._esc_deadband = realism.esc_deadband
        self._pending_duty: deque[tuple[int, float]] = deque()  # (due time in ns, duty) with a delay
        self.on_stand = bool(on_stand)
        p = params
        self.state = VehicleState(x=pose[0], y=pose[1], yaw=pose[2], soc=p.battery_soc0)
        self.state.battery_voltage = p.battery_cells * cell_voltage(p.battery_soc0)
        self.duty = 0.0
        self.delta_cmd = 0.0
        # constants of the step, computed once
        g = p.gear_ratio * p.wheel_radius  # m of travel per rad of motor shaft
        self._g = g
        reflected = 0.0 if self.on_stand else p.mass * g**2
        rolling = 0.0 if self.on_stand else p.rolling_resistance * p.mass * p.gravity * g
        k = np.zeros(19)
        k[_P_DT] = p.physics_dt
        k[_P_TAU] = p.steering_tau
        k[_P_RBAT] = p.battery_resistance
        k[_P_IDLE] = p.idle_current
        k[_P_VCUT] = p.battery_shutdown_v
        k[_P_KTR] = p.motor_kt / p.motor_resistance
        k[_P_J] = p.drivetrain_inertia + reflected
        k[_P_K] = p.motor_kt * p.motor_kb / p.motor_resistance + p.motor_damping
        k[_P_C] = p.motor_friction + rolling
        k[_P_KB] = p.motor_kb
        k[_P_R] = p.motor_resistance
        k[_P_G] = g
        k[_P_CAP] = p.battery_capacity_ah * 3600.0
        k[_P_L] = p.wheelbase
        k[_P_STAND] = 1.0 if self.on_stand else 0.0
        k[_P_CELLS] = p.battery_cells
        k[_P_SLIP] = realism.slip_ratio
        k[_P_SCRUB] = realism.scrub_per_g / p.gravity
        k[_P_KUS] = realism.understeer_gradient
        self._k = k
        self._kl = k.tolist()  # the same constants for the plain-Python step (faster to index)
        self._max_steering = p.max_steering
        self._t_s, self._t_ns = math.nan, 0  # the state's t as last written by the step, and in ns
        self._dt, self._dt_ns = math.nan, 0  # the last step's dt, and in ns

    @property
    def shutdown(self) -> bool:
        """True once the battery fell below the shutdown voltage (the ESC cut the motor)."""
        return self.state._a[_SHUTDOWN] != 0.0

    def command(self, duty: float, delta: float) -> None:
        """Set the PWM duty fraction and the steering command (rad); the servo clamps to +-max (and
        a realism profile's servo adds its dead-band, backlash and trim, and its delay: the wheels'
        target changes ``steering_delay`` s after the command; its ESC ignores a duty within
        ``esc_deadband`` of neutral and passes the rest on ``throttle_delay`` s after the command)."""
        if abs(duty) < self._esc_deadband:
            duty = 0.0
        if self._duty_delay_ns:
            t = self.state._a[_T]
            self._pending_duty.append(((self._t_ns if t == self._t_s else round(t * 1e9)) + self._duty_delay_ns, duty))
        else:
            self.duty = duty
        m = self._max_steering
        delta = m if delta > m else (-m if delta < -m else delta)
        target = delta if self._servo is None else self._servo(delta)
        if self._delay_ns:
            t = self.state._a[_T]  # the time in ns: the step's count while t is as it left it
            self._pending.append(((self._t_ns if t == self._t_s else round(t * 1e9)) + self._delay_ns, target))
        else:
            self.delta_cmd = target

    def step(self, dt: float) -> None:
        """Advance by ``dt`` seconds in physics steps of at most ``params.physics_dt`` (split where a
        delayed steering command takes effect)."""
        if dt <= 0.0:
            return
        pending, duties = self._pending, self._pending_duty
        if pending or duties:
            t = self.state._a[_T]  # (the counts in ns as _advance keeps them)
            t_ns = self._t_ns if t == self._t_s else round(t * 1e9)
            end_ns = t_ns + (self._dt_ns if dt == self._dt else round(dt * 1e9))
            while (pending and pending[0][0] < end_ns) or (duties and duties[0][0] < end_ns):
                steer = bool(pending) and pending[0][0] < end_ns and (not duties or pending[0][0] <= duties[0][0])
                due, value = (pending if steer else duties).popleft()
                if due > t_ns:
                    self._advance((due - t_ns) / 1e9)
                    t_ns = due
                if steer:
                    self.delta_cmd = value
                else:
                    self.duty = value
            if end_ns > t_ns:
                self._advance((end_ns - t_ns) / 1e9)
            return
        self._advance(dt)

    def _advance(self, dt: float) -> None:
        global _python_steps
        # simulated time moves by dt rounded to the nanosecond, so that 100 steps of 10 ms make
        # exactly 1 s (the sub-steps' own sum drifts in the last bits); the count in ns is kept
        # beside the state's t (recounted when t was set from outside) and dt's for the last dt
        state = self.state
        a = state._a
        t = a[_T]
        if t != self._t_s:
            self._t_ns = round(t * 1e9)
        if dt != self._dt:
            self._dt, self._dt_ns = dt, round(dt * 1e9)
        t_ns = self._t_ns + self._dt_ns
        use = COMPILED  # (_compiled(), written out: this runs every step)
        if use is None:
            use = _compiled_advance is not None or (_python_steps >= SWITCH_AFTER and self.auto_switch
                                                    and "numba" in _MODULES)
        kernel = (_compiled_advance or _compiled()) if use else None
        if kernel is not None:
            kernel(state.buffer, self._k, float(self.duty), float(self.delta_cmd), float(dt))
        else:
            _python_steps += 1
            _advance(a, self._kl, self.duty, self.delta_cmd, dt)
        self._t_ns = t_ns
        a[_T] = self._t_s = t_ns / 1e9

    @property
    def wheel_speed(self) -> float:
        """Tyre surface speed (m/s), what the encoder measures."""
        return self.state._a[_OMEGA] * self._g
