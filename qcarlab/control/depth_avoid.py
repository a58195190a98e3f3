"""The race-car report's state machine on its three depth windows (shared seeds 003), as the
``depth_avoid`` block: ``(left, middle, right)`` distances in, ``(speed, steering)`` out. Pure
state, no I/O: the windows come from :func:`qcarlab.perception.depth_windows.depth_windows`.

The report's states and rules, in order of priority, once per depth frame::

    no data (every window 0)             -> stop       (the report: no data, Stop)
    all three < back_distance            -> back        (the collision recovery: "the car is
                                                          running across an obstacle")
    back:      until middle > back_clear -> straight     (reverse at back_speed, wheels straight)
    straight:  middle < turn_distance    -> turn-left if left >= right else turn-right
               left - right > balance    -> straight-left   (the right wall is near: small left turn)
               right - left > balance    -> straight-right
    straight-left/right: |left - right| < balance / 2 -> straight (hysteresis);
                         middle < turn_distance       -> turn, as from straight
    turn-left/right:     middle > clear_distance + reaction * closing -> straight

The turn distance grows with how fast the middle distance shrinks (one addition to the report, for
its rolling ball: a ball rolling at the car closes at 1 m/s plus the car's speed, and the car
must start its swerve while the ball is still far)::

    closing = median of the last three (middle_prev - middle) / frame_period, >= 0
    turn_at = turn_distance + reaction * closing           (reaction 1 s; frames 1/30 s apart)

Speeds: ``desired`` going straight or gently, ``turn_speed_factor * desired`` in a turn,
``-back_speed`` backing up, 0 in stop. Steering: 0 straight, ``+-gentle_steering`` (0.15 rad) in
straight-left/right, ``+-turn_steering`` (0.5 rad) in a turn (+ = left). A window with no data
(0: nothing valid, e.g. nearer than the camera's 0.1 m) counts as near, so an obstacle right at
the lens is not taken for open space.
"""

from __future__ import annotations

__all__ = ["DEPTH_STATES", "DepthAvoid"]

DEPTH_STATES = ("stop", "straight", "straight-left", "straight-right", "turn-left", "turn-right", "back")


class DepthAvoid:
    """The report's state machine (see the module docstring); ``state`` shows the current state,
    ``backups`` counts the times it backed up. Call it as the block:
    ``depth_avoid(left, middle, right, desired_speed) -> (speed_cmd, steering_cmd)``."""

    def __init__(
        self,
        turn_distance: float = 1.0,
        clear_distance: float = 1.6,
        balance: float = 0.5,
        back_distance: float = 0.35,
        back_clear: float = 0.8,
        gentle_steering: float = 0.15,
        turn_steering: float = 0.5,
        turn_speed_factor: float = 0.6,
        back_speed: float = 0.2,
        reaction: float = 1.0,
        frame_period: float = 1.0 / 30.0,
    ):
        if not (0.0 < back_distance < turn_distance < clear_distance):
            raise ValueError("depth_avoid: need 0 < back_distance < turn_distance < clear_distance")
        self.turn_distance, self.clear_distance = turn_distance, clear_distance
        self.balance, self.back_distance, self.back_clear = balance, back_distance, back_clear
        self.gentle_steering, self.turn_steering = gentle_steering, turn_steering
        self.turn_speed_factor, self.back_speed = turn_speed_factor, back_speed
        self.reaction, self.frame_period = reaction, frame_period
        self.reset()

    def reset(self) -> None:
        self.state = "straight"
        self.backups = 0
        self._prev: float | None = None
        self._rates = [0.0, 0.0, 0.0]
        self.turn_at = self.turn_distance

    def _turn(self, left: float, right: float) -> str:
        return "turn-left" if left >= right else "turn-right"

    def __call__(self, left: float, middle: float, right: float, desired_speed: float) -> tuple[float, float]:
        """One decision per depth frame: ``(speed m/s, steering rad)``."""
        ws = [float(v) if v == v and v > 0.0 else 0.0 for v in (left, middle, right)]  # NaN, <= 0: no data
        l, m, r = ws
        if l == m == r == 0.0:
            self.state = "stop"
            return 0.0, 0.0
        if self._prev is not None and m > 0.0:
            self._rates = self._rates[1:] + [max(0.0, min((self._prev - m) / self.frame_period, 5.0))]
        self._prev = m if m > 0.0 else self._prev
        turn_at = self.turn_at = self.turn_distance + self.reaction * sorted(self._rates)[1]
        st = self.state
        if st != "back" and max(ws) < self.back_distance:
            self.state = "back"
            self.backups += 1
        elif st == "back":
            if m > self.back_clear:
                self.state = "straight"
        elif st in ("turn-left", "turn-right"):
            if m > self.clear_distance + (turn_at - self.turn_distance):
                self.state = "straight"
        elif st in ("straight-left", "straight-right"):
            if m < turn_at:
                self.state = self._turn(l, r)
            elif abs(l - r) < self.balance / 2.0:
                self.state = "straight"
        if self.state in ("straight", "stop"):
            if m < turn_at:
                self.state = self._turn(l, r)
            elif l - r > self.balance:
                self.state = "straight-left"
            elif r - l > self.balance:
                self.state = "straight-right"
            else:
                self.state = "straight"
        v = float(desired_speed)
        return {
            "back": (-abs(self.back_speed), 0.0),
            "straight": (v, 0.0),
            "straight-left": (v, self.gentle_steering),
            "straight-right": (v, -self.gentle_steering),
            "turn-left": (v * self.turn_speed_factor, self.turn_steering),
            "turn-right": (v * self.turn_speed_factor, -self.turn_steering),
        }[self.state]
