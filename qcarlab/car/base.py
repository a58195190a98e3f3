"""The Car interface every backend implements: the simulator, the TCP client, the on-car driver.

A student scripts a car in five lines::

    import qcarlab
    with qcarlab.open_car("sim", seed=1) as car:
        for _ in range(100):
            car.write(0.1, 0.0, leds=["headlamps"])
            car.advance(0.01)            # simulated cars: step time; real cars: sleep
        print(car.read().encoder_counts)

``write`` validates every command: a non-finite value raises :class:`InputError`; values outside
the steering limit (+-0.5 rad) or the throttle limit (0.3 by default) are clamped and the
clamp is reported once per channel through the ``qcarlab`` logger, never silently.
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from qcarlab.car.lamps import ALL_OFF, parse_lamps
from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.errors import InputError, NotBuiltError

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Mapping

log = logging.getLogger("qcarlab")
_new_tuple = tuple.__new__  # Command(thr, ste, lamps) without the Python-level __new__ frame


# Command, Readout and Truth are made once or twice every tick: immutable named tuples (a C
# constructor, 0.2-0.3 us) rather than frozen dataclasses (about 1 us for nine fields, each set
# through object.__setattr__). Their fields are read by name; nothing indexes them.
class Command(NamedTuple):
    """What the car was told: throttle (duty fraction), steering (rad, + = left), lamps (12)."""

    throttle: float = 0.0
    steering: float = 0.0
    leds: tuple[float, ...] = ALL_OFF


class Readout(NamedTuple):
    """One read of the car's basic sensors (the sheet's HIL-Read block), SI units.

    ``tach`` is the encoder's hardware tachometer in counts/s; ``basic_speed_estimation(tach)``
    turns it into m/s. ``gyro`` and ``accel`` are body-frame (x forward, y left, z up).
    """

    t: float  # s since the car was opened
    encoder_counts: int
    tach: float  # counts/s
    motor_current: float  # A
    battery_voltage: float  # V
    gyro: np.ndarray  # (3,) rad/s
    accel: np.ndarray  # (3,) m/s^2
    steering: float = 0.0  # the last applied steering command, rad
    throttle: float = 0.0  # the last applied throttle command
    leds: tuple[float, ...] = ALL_OFF  # the lamps' state

    def to_dict(self) -> dict[str, Any]:
        return {
            "t": self.t,
            "encoder_counts": self.encoder_counts,
            "tach": self.tach,
            "motor_current": self.motor_current,
            "battery_voltage": self.battery_voltage,
            "gyro": [float(v) for v in self.gyro],
            "accel": [float(v) for v in self.accel],
            "steering": self.steering,
            "throttle": self.throttle,
            "leds": list(self.leds),
        }


@dataclass(frozen=True, slots=True)
class Pose:
    """A planar pose in the world frame: x, y (m) of the car's centre and yaw (rad, CCW from +X)."""

    x: float
    y: float
    yaw: float


class Truth(NamedTuple):
    """The simulator's ground truth (only simulated cars have one)."""

    t: float
    x: float
    y: float
    yaw: float
    speed: float  # m/s of the car's centre over the ground (0 on the stand)
    wheel_speed: float  # m/s at the tyre surface (what the encoder measures)
    steering: float  # rad, the actual wheel angle after the servo lag
    distance: float  # m driven over the ground since opened
    wheel_distance: float  # m turned by the wheels since opened


@dataclass
class Identity:
    """Who the car is: shown by ``ping`` and in results."""

    name: str
    backend: str  # "sim", "tcp", "quanser"
    capabilities: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)


class Car(ABC):
    """A QCar, real or simulated. Use it in a ``with`` block: leaving it stops the car."""

    def __init__(self, params: QCarParams = DEFAULT_PARAMS, throttle_limit: float | None = None):
        self.params = params
        limit = params.throttle_limit if throttle_limit is None else float(throttle_limit)
        if not (math.isfinite(limit) and 0.0 < limit <= 1.0):
            raise InputError(f"throttle limit must be in (0, 1], got {limit}")
        self.throttle_limit = limit
        self.steering_limit = params.max_steering
        self._clamped: set[str] = set()
        self._last_leds: tuple = (ALL_OFF, ALL_OFF)
        self.closed = False

    # --- commands -----------------------------------------------------------------------------
    def validate(
        self,
        throttle: float,
        steering: float,
        leds: str | Iterable[str] | Mapping[str, float] | None = None,
    ) -> Command:
        """Check and clamp a command; the first clamp of each channel is logged once."""
        try:
            thr, ste = float(throttle), float(steering)
        except (TypeError, ValueError):
            raise InputError(f"throttle and steering must be numbers, got {throttle!r}, {steering!r}") from None
        tl, sl = self.throttle_limit, self.steering_limit
        if not (-tl <= thr <= tl and -sl <= ste <= sl):  # NaN and inf fail these comparisons too
            if not math.isfinite(thr):
                raise InputError(f"throttle must be a finite number, got {throttle!r}")
            if not math.isfinite(ste):
                raise InputError(f"steering must be a finite number, got {steering!r}")
            thr = self._clamp("throttle", thr, tl, "")
            ste = self._clamp("steering", ste, sl, " rad")
        if leds is None:
            lamps = ALL_OFF
        else:
            last = self._last_leds
            if leds is last[0] or (isinstance(leds, (tuple, str)) and leds == last[0]):
                lamps = last[1]  # the same lamps as last tick: already checked
            else:
                lamps = parse_lamps(leds)
                self._last_leds = (leds, lamps)
        return _new_tuple(Command, (thr, ste, lamps))

    def _clamp(self, name: str, value: float, limit: float, unit: str) -> float:
        if -limit <= value <= limit:
            return value
        clamped = limit if value > 0 else -limit
        if name not in self._clamped:
            self._clamped.add(name)
            log.warning("%s %.4g%s is outside +-%.4g%s; clamped (reported once)", name, value, unit, limit, unit)
        return clamped

    def write(
        self,
        throttle: float,
        steering: float,
        leds: str | Iterable[str] | Mapping[str, float] | None = None,
    ) -> Command:
        """Send throttle (duty fraction) and steering (rad, + = left); returns what was applied."""
        cmd = self.validate(throttle, steering, leds)
        self._apply(cmd)
        return cmd

    def stop(self) -> None:
        """Throttle 0, wheels straight, brake lamp on."""
        self._apply(Command(0.0, 0.0, parse_lamps(["brake"])))

    # --- backend hooks ------------------------------------------------------------------------
    @abstractmethod
    def _apply(self, cmd: Command) -> None:
        """Send a validated command to the car."""

    @abstractmethod
    def read(self) -> Readout:
        """Read the basic sensors (encoder, tach, current, battery, IMU)."""

    @abstractmethod
    def advance(self, dt: float) -> None:
        """Let ``dt`` seconds pass: a stepped simulator steps its physics, a real car sleeps."""

    @property
    @abstractmethod
    def time(self) -> float:
        """Seconds since the car was opened (simulated time for a stepped simulator)."""

    @property
    def stepped(self) -> bool:
        """True when time only moves through :meth:`advance` (a deterministic simulator)."""
        return False

    def identity(self) -> Identity:
        return Identity(name=type(self).__name__, backend="unknown")

    def truth(self) -> Truth | None:
        """The simulator's ground truth, or None for a real car."""
        return None

    # sensors declared here, provided by backends that have them
    def read_lidar(self) -> Any:
        """The latest LIDAR scan (angles in the body frame, ranges in m, 0 = no return)."""
        raise NotBuiltError(f"{self.identity().backend} car: LIDAR is not available on this backend yet")

    def read_rgbd(self) -> Any:
        """The latest RGBD frame pair (640x480 BGR uint8, depth float32 m aligned to it)."""
        raise NotBuiltError(f"{self.identity().backend} car: the RGBD camera is not available on this backend yet")

    def read_rgbd_rows(self) -> Any:
        """:meth:`read_rgbd`'s frame for a reader of some of its rows (the lane lab: ``color_rows``,
        ``depth_rows`` where the frame has them); a car that draws its frames (the simulator) may
        draw only the rows read. This one: :meth:`read_rgbd` (a wrapper, a recorder, sees the read)."""
        return self.read_rgbd()

    def read_csi(self) -> Any:
        """The latest four CSI frames (right, rear, left, front), 820x410 BGR uint8."""
        raise NotBuiltError(f"{self.identity().backend} car: the CSI cameras are not available on this backend yet")

    def sensor_job(self, kind: str) -> Callable[[], Any]:
        """For servers: called with the car's drive lock held, returns a function that produces the
        ``kind`` frame ("lidar", "rgbd" or "csi") and is run without it, so that a slow sensor never
        holds up a command or the watchdog. This default reads at once (under the lock); backends
        whose sensors are independent of the drive I/O return the reading itself."""
        frame = getattr(self, f"read_{kind}")()
        return lambda: frame

    def prepare_sensors(self) -> None:
        """Build whatever the sensors need before the first frame (a server calls it at start)."""

    # --- lifecycle ----------------------------------------------------------------------------
    def close(self) -> None:
        if not self.closed:
            try:
                self.stop()
            finally:
                self.closed = True
                self._close()

    def _close(self) -> None:
        """Release backend resources (sockets, devices)."""

    def __enter__(self) -> Car:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
