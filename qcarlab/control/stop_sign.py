"""Stopping at a stop sign (lab sheet 5.2): the sheet's ``stopSign`` block and an improved one.

:func:`stop_sign` is the MATLAB function of the sheet's Figure 51, filled in (Task 1)::

    function speedCmd = stopSign(distanceToSign, desiredSpeed)
    if distanceToSign > 0.05 && distanceToSign < 0.40
        speedCmd = 0;                 % stop the car
    else
        speedCmd = desiredSpeed;      % go at the desired speed
    end

0.05, not 0: the camera reads 0 when it does not see the sign.

Its faults (Task 4, "suggest improvements"), which :class:`StopSignBehaviour` addresses:

- it brakes only once inside 0.40 m, from full speed, so the stopping point depends on the speed
  (the car rolls on by v^2 / 2a) and at higher speeds ends up past the sign;
- the moment the sign leaves the camera's view (too close, off to the side) or a frame misses it,
  the distance reads 0 and the car **drives off again at full speed**;
- once stopped it stays stopped for ever: there is no "stop, wait, go";
- a sign seen once and then lost is forgotten at once.

:class:`StopSignBehaviour` is a small state machine (``reset()`` / ``step()``)::

    drive ──sign within slow_distance──> approach ──d <= stop_distance──> stopping
      ^                                                                      │ |v| < 0.01 m/s
      └──sign out of view for rearm_time── leaving <──hold seconds── holding <┘

- **approach**: v_ref = min(v_desired, sqrt(2 decel (d - stop_distance))), at least ``creep``:
  the car arrives slowly at the same place whatever its cruising speed;
- between frames, and when the sign is lost close up, the distance is **dead-reckoned** from the
  encoder speed (d -= v dt) instead of dropping to 0;
- **holding**: stands still for ``hold`` seconds (the team report's 3 s stop);
- **leaving**: drives on at v_desired and ignores that sign until it has been out of view for
  ``rearm_time`` seconds; then the next sign counts again.
"""

from __future__ import annotations

import math

__all__ = ["FAR", "NEAR", "StopSignBehaviour", "StopSignHold", "stop_sign"]

NEAR = 0.05  # m: below this the reading is "no sign" (the camera reads 0 without data)
FAR = 0.40  # m: the sheet stops the car inside 0.05 .. 0.40 m
STANDSTILL = 0.01  # m/s


def stop_sign(distance_to_sign: float, desired_speed: float, near: float = NEAR, far: float = FAR) -> float:
    """The sheet's ``stopSign``: 0 when ``near < distance_to_sign < far`` (m), else ``desired_speed``."""
    if near < distance_to_sign < far:
        return 0.0
    return desired_speed


class StopSignBehaviour:
    """Slow down, stop, hold, drive on, ignore that sign: an improved ``stopSign`` (sheet Task 4).

        beh = StopSignBehaviour(desired_speed=0.3, hold=3.0)
        v_ref = beh.step(t, speed, distance)   # every control tick

    ``distance`` is the camera's distance to the sign (m) from a **new** frame, 0 when the frame
    shows no sign, or None when no new frame arrived this tick (then the last estimate is carried
    forward by dead reckoning). ``speed`` is the measured car speed (m/s, from the encoder).
    ``state`` is one of drive, approach, stopping, holding, leaving.
    """

    STATES = ("drive", "approach", "stopping", "holding", "leaving")

    def __init__(
        self,
        desired_speed: float,
        hold: float = 3.0,
        stop_distance: float = 0.30,
        slow_distance: float = 1.2,
        decel: float = 0.3,
        creep: float = 0.06,
        rearm_time: float = 1.0,
        lost_time: float = 1.5,
        near: float = NEAR,
    ):
        for name, value in (("desired_speed", desired_speed), ("stop_distance", stop_distance),
                            ("slow_distance", slow_distance), ("decel", decel), ("creep", creep)):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        for name, value in (("hold", hold), ("rearm_time", rearm_time), ("lost_time", lost_time)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a non-negative number, got {value}")
        if stop_distance <= near:
            raise ValueError(f"stop_distance {stop_distance} must be above the no-data limit {near}")
        self.desired_speed = float(desired_speed)
        self.hold = float(hold)
        self.stop_distance = float(stop_distance)
        self.slow_distance = max(float(slow_distance), self.stop_distance)
        self.decel = float(decel)
        self.creep = min(float(creep), self.desired_speed)
        self.rearm_time = float(rearm_time)
        self.lost_time = float(lost_time)
        self.near = float(near)
        self.reset()

    def reset(self) -> None:
        self.state = "drive"
        self.estimate: float | None = None  # m, dead-reckoned distance to the sign
        self._t_last: float | None = None
        self._t_seen: float | None = None  # last time a frame showed the sign
        self._t_hold: float | None = None  # when the car came to rest
        self.stops = 0

    def _seen(self, distance: float | None) -> bool:
        return distance is not None and distance > self.near

    def step(self, t: float, speed: float, distance: float | None) -> float:
        """Advance to time ``t`` (s); return the desired speed v_ref (m/s)."""
        dt = 0.0 if self._t_last is None else max(0.0, t - self._t_last)
        self._t_last = t
        if self.estimate is not None:
            self.estimate -= max(speed, 0.0) * dt
        seen = self._seen(distance)
        if seen:
            self._t_seen = t
        lost_for = math.inf if self._t_seen is None else t - self._t_seen

        if self.state == "leaving":
            if lost_for >= self.rearm_time:  # that sign is behind us: the next one counts
                self.state, self.estimate = "drive", None
            return self.desired_speed
        if self.state in ("drive", "approach") and seen:
            self.estimate = float(distance)
        if self.state == "drive":
            if self.estimate is not None and self.estimate <= self.slow_distance:
                self.state = "approach"
            else:
                if not seen and lost_for > self.lost_time:
                    self.estimate = None
                return self.desired_speed
        if self.state == "approach":
            if not seen and lost_for > self.lost_time and self.estimate > self.slow_distance:
                self.state, self.estimate = "drive", None  # a far glimpse that went away
                return self.desired_speed
            gap = self.estimate - self.stop_distance
            if gap <= 0.0:
                self.state = "stopping"
            else:
                return min(self.desired_speed, max(self.creep, math.sqrt(2.0 * self.decel * gap)))
        if self.state == "stopping":
            if abs(speed) < STANDSTILL:
                self.state, self._t_hold = "holding", t
                self.stops += 1
            return 0.0
        # holding
        if t - self._t_hold >= self.hold:
            self.state = "leaving"
            return self.desired_speed
        return 0.0


class StopSignHold:
    """The ``stop_sign_hold`` block (sheet 5.2 Task 4, the improved stopSign) as the lab calls it::

        speed_cmd = stop_sign_hold(t, distance_to_sign, new_frame, speed, desired_speed)

    every control tick: ``t`` s since the start, ``distance_to_sign`` m from the latest camera
    frame (0 = no sign in it; held between frames), ``new_frame`` True on the tick a new frame
    arrived, ``speed`` the measured speed (m/s), ``desired_speed`` m/s. The reference is
    :class:`StopSignBehaviour` (slow down, stop, hold ``hold`` s, drive on, ignore that sign),
    made at the first call with that call's desired speed; ``state`` and ``stops`` are its.
    """

    def __init__(self, hold: float = 3.0):
        self.hold = float(hold)
        self.reset()

    def reset(self) -> None:
        self._machine: StopSignBehaviour | None = None

    @property
    def state(self) -> str:
        return self._machine.state if self._machine is not None else "drive"

    @property
    def stops(self) -> int:
        return self._machine.stops if self._machine is not None else 0

    def __call__(self, t: float, distance_to_sign: float, new_frame: bool, speed: float,
                 desired_speed: float) -> float:
        if self._machine is None:
            self._machine = StopSignBehaviour(desired_speed, hold=self.hold)
        return self._machine.step(t, speed, distance_to_sign if new_frame else None)
