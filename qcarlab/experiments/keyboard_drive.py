"""Keyboard driving (sheet 3.4): the state machine, the key decoder, the terminal mode and the loop.

The pieces, from pure to impure:

- :class:`DriveState` and :func:`apply_key`: what a key does. Keys move *targets* (throttle,
  steering) by a step; the applied values follow their targets at a limited rate (the ramp), so a
  held key or a burst of key repeats never jerks the car. Space brakes (throttle 0 at once, brake
  lamp on); lamps toggle; ``q`` or Ctrl-C ends the drive. A terminal reports no key releases, so
  a target stays where the keys put it (``c`` centres the steering, space stops the motor)::

      >>> s = DriveState(DriveConfig(max_throttle=0.15))
      >>> s = apply_key(s, "w")            # target throttle +0.03
      >>> s = apply_key(s, None, dt=0.05)  # ramp at 0.3 duty/s: applied +0.015
      >>> round(s.throttle, 3), round(s.target_throttle, 3)
      (0.015, 0.03)

- :class:`KeyDecoder`: bytes from a terminal -> key names (``"up"``, ``"left"``, ``"space"``,
  ``"ctrl-c"``, ``"w"``, ...), arrow escape sequences included, split reads handled.
- :func:`cbreak_terminal`: a context manager that puts a TTY in non-canonical, no-echo,
  no-signal mode (Ctrl-C and Ctrl-Z arrive as keys, so the car is never left running by a
  suspended process) and always restores the saved settings.
- :func:`keyboard_drive`: the loop. Every tick (50 Hz) it reads the keys, updates the state,
  writes the command (a served car's watchdog stops a car that gets no command for 0.25 s, so
  the loop writes every tick even when nothing changes), reads the car and hands a :class:`Frame`
  to ``on_frame`` (the terminal view). Whatever ends the loop, the car is stopped.
- :func:`world_map`: a small raster of a simulator world (floor colours, walls, obstacles) for a
  character-cell map, with the car placed on it by :meth:`MapGrid.pixel_of`.
"""

from __future__ import annotations

import math
import os
import select
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from qcarlab.car.base import Car, Command, Readout, Truth
from qcarlab.car.lamps import lamps_named
from qcarlab.control.speed import basic_speed_estimation
from qcarlab.errors import InputError, NotBuiltError
from qcarlab.experiments.loop import STOP, Step, run_loop

try:
    import termios
except ImportError:  # Windows: no POSIX terminals (keyboard-drive runs in WSL there)
    termios = None  # type: ignore[assignment]

__all__ = [
    "ACTIONS",
    "DriveConfig",
    "DriveState",
    "DriveSummary",
    "Frame",
    "KEYMAP",
    "KeyDecoder",
    "MapGrid",
    "apply_key",
    "cbreak_terminal",
    "keyboard_drive",
    "lamps",
    "nearest_obstacle",
    "world_map",
]

# --------------------------------------------------------------------------------------------
# the state machine
# --------------------------------------------------------------------------------------------
#: key name -> action. Letters are matched case-insensitively (Caps Lock does not matter).
KEYMAP: dict[str, str] = {
    "w": "faster",
    "up": "faster",
    "s": "slower",
    "down": "slower",
    "a": "left",
    "left": "left",
    "d": "right",
    "right": "right",
    "c": "centre",
    "space": "brake",
    "h": "headlamps",
    "z": "indicator_left",
    ",": "indicator_left",
    "x": "indicator_right",
    ".": "indicator_right",
    "e": "hazard",
    "q": "quit",
    "ctrl-d": "quit",
    "ctrl-c": "interrupt",
    "ctrl-\\": "interrupt",
}
ACTIONS = frozenset(KEYMAP.values())

@dataclass(frozen=True)
class DriveConfig:
    """Limits, steps and ramps of keyboard driving (throttle as duty fraction, steering in rad)."""

    max_throttle: float = 0.15
    throttle_step: float = 0.03  # per key press
    throttle_ramp: float = 0.3  # duty/s: how fast the applied throttle follows its target
    max_steering: float = 0.5  # the servo's +-0.5 rad (QCarParams.max_steering)
    steering_step: float = 0.1  # rad per key press
    steering_ramp: float = 1.5  # rad/s
    blink_hz: float = 1.5  # indicators and hazard lamps

    def __post_init__(self) -> None:
        checks = (
            ("max throttle", self.max_throttle, 1.0),
            ("throttle step", self.throttle_step, 1.0),
            ("throttle ramp", self.throttle_ramp, 100.0),
            ("max steering", self.max_steering, math.pi / 2),
            ("steering step", self.steering_step, math.pi / 2),
            ("steering ramp", self.steering_ramp, 100.0),
            ("blink rate", self.blink_hz, 50.0),
        )
        for name, value, top in checks:
            if not (isinstance(value, (int, float)) and math.isfinite(value) and 0.0 < value <= top):
                raise InputError(f"keyboard-drive: {name} must be a number in (0, {top:g}], got {value!r}")


@dataclass(frozen=True)
class DriveState:
    """Where the keys have put the car. ``throttle``/``steering`` are what is applied this tick."""

    config: DriveConfig = field(default_factory=DriveConfig)
    target_throttle: float = 0.0
    target_steering: float = 0.0
    throttle: float = 0.0
    steering: float = 0.0
    braking: bool = False
    headlamps: bool = False
    indicator: str = "off"  # off | left | right | hazard
    quit: str | None = None  # None while driving; "quit" (q) or "interrupted" (Ctrl-C)
    t: float = 0.0  # s of driving (sum of the dt given), drives the indicators' blinking
    last_key: str = ""


def _clip(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


def _toward(value: float, target: float, max_change: float) -> float:
    if abs(target - value) <= max_change:
        return target
    return value + math.copysign(max_change, target - value)


def _stepped(value: float, step: float, limit: float) -> float:
    # round to a whole number of steps (no drift from float sums), then keep within the limit
    return _clip(round(round(value / step) * step, 9), limit)


def apply_key(state: DriveState, key: str | None, dt: float = 0.0) -> DriveState:
    """Apply one key (None: no key) and then let ``dt`` seconds of ramping pass. Pure.

    Unknown keys only update ``last_key``. Once ``quit`` is set, further keys change nothing.
    """
    if not (math.isfinite(dt) and dt >= 0.0):
        raise InputError(f"dt must be a non-negative number of seconds, got {dt!r}")
    cfg = state.config
    s = state
    if key is not None and s.quit is None:
        action = KEYMAP.get(key.lower() if len(key) == 1 else key)
        s = replace(s, last_key=key)
        if action == "faster":
            s = replace(s, target_throttle=_stepped(s.target_throttle + cfg.throttle_step, cfg.throttle_step, cfg.max_throttle), braking=False)
        elif action == "slower":
            s = replace(s, target_throttle=_stepped(s.target_throttle - cfg.throttle_step, cfg.throttle_step, cfg.max_throttle), braking=False)
        elif action == "left":
            s = replace(s, target_steering=_stepped(s.target_steering + cfg.steering_step, cfg.steering_step, cfg.max_steering))
        elif action == "right":
            s = replace(s, target_steering=_stepped(s.target_steering - cfg.steering_step, cfg.steering_step, cfg.max_steering))
        elif action == "centre":
            s = replace(s, target_steering=0.0)
        elif action == "brake":
            s = replace(s, target_throttle=0.0, throttle=0.0, braking=True)
        elif action == "headlamps":
            s = replace(s, headlamps=not s.headlamps)
        elif action in ("indicator_left", "indicator_right", "hazard"):
            want = {"indicator_left": "left", "indicator_right": "right", "hazard": "hazard"}[action]
            s = replace(s, indicator="off" if s.indicator == want else want)
        elif action == "quit":
            s = replace(s, quit="quit")
        elif action == "interrupt":
            s = replace(s, quit="interrupted")
    if s.quit is not None:  # quitting: the command goes to zero at once
        s = replace(s, target_throttle=0.0, throttle=0.0)
    if dt > 0.0:
        s = replace(
            s,
            throttle=_clip(_toward(s.throttle, s.target_throttle, cfg.throttle_ramp * dt), cfg.max_throttle),
            steering=_clip(_toward(s.steering, s.target_steering, cfg.steering_ramp * dt), cfg.max_steering),
            t=s.t + dt,
        )
    return s


def lamps(state: DriveState) -> list[str]:
    """The lamps the state lights now (names for :func:`qcarlab.car.lamps.parse_lamps`).

    Headlamps as toggled; the brake lamp while braking; the reverse lamp while the applied
    throttle is negative; indicators and hazard lamps blink at ``blink_hz`` (on in the first half
    of each period).
    """
    out = []
    if state.braking:
        out.append("brake")
    if state.throttle < 0.0:
        out.append("reverse")
    if state.headlamps:
        out.append("headlamps")
    if state.indicator != "off" and (state.t * state.config.blink_hz) % 1.0 < 0.5:
        out.append({"left": "left-indicators", "right": "right-indicators", "hazard": "hazard"}[state.indicator])
    return out


# --------------------------------------------------------------------------------------------
# keys from a terminal
# --------------------------------------------------------------------------------------------
_ARROWS = {"A": "up", "B": "down", "C": "right", "D": "left"}
_CONTROL = {
    0x03: "ctrl-c",
    0x04: "ctrl-d",
    0x1A: "ctrl-z",
    0x1C: "ctrl-\\",
    0x0D: "enter",
    0x0A: "enter",
    0x09: "tab",
    0x7F: "backspace",
    0x08: "backspace",
}


class KeyDecoder:
    """Turn the bytes a terminal sends into key names; keeps an incomplete escape sequence.

    Arrows arrive as ``ESC [ A`` (or ``ESC O A`` in application mode, ``ESC [ 1 ; 5 A`` with a
    modifier); other escape sequences (function keys, ...) are dropped. A lone ESC becomes
    ``"escape"`` once ``esc_timeout`` s pass without the rest of a sequence.
    """

    def __init__(self, esc_timeout: float = 0.05):
        self.esc_timeout = esc_timeout
        self._buf = b""
        self._since = 0.0

    def feed(self, data: bytes, now: float) -> list[str]:
        """The keys completed by ``data`` (may be empty: call it every tick for the ESC timeout)."""
        had_pending = bool(self._buf)
        buf = self._buf + data
        keys: list[str] = []
        i = 0
        while i < len(buf):
            b = buf[i]
            if b == 0x1B:
                n = self._escape_length(buf, i)
                if n == 0:  # incomplete: wait for more, unless it has waited long enough
                    if had_pending and i == 0 and now - self._since >= self.esc_timeout:
                        keys.append("escape")
                        i += 1
                        continue
                    break
                seq = buf[i : i + n]
                if n > 1 and chr(seq[-1]) in _ARROWS and seq[1:2] in (b"[", b"O"):
                    keys.append(_ARROWS[chr(seq[-1])])
                elif n == 1:
                    keys.append("escape")
                i += n
            elif b in _CONTROL:
                keys.append(_CONTROL[b])
                i += 1
            elif b == 0x20:
                keys.append("space")
                i += 1
            elif 0x20 < b < 0x7F:
                keys.append(chr(b).lower())
                i += 1
            else:  # other control bytes, UTF-8 continuation bytes: ignored
                i += 1
        rest = buf[i:]
        if rest and (not had_pending or i > 0):  # a new incomplete sequence starts waiting now
            self._since = now
        self._buf = rest
        return keys

    @staticmethod
    def _escape_length(buf: bytes, i: int) -> int:
        """Length of the escape sequence at ``buf[i]``; 0 when it is not complete yet."""
        if i + 1 >= len(buf):
            return 0
        nxt = buf[i + 1]
        if nxt == 0x1B:  # ESC ESC: the first one was a lone escape
            return 1
        if nxt == ord("O"):  # SS3: ESC O X
            return 3 if i + 2 < len(buf) else 0
        if nxt != ord("["):  # Alt+key: ESC then the key (reported as "escape", then the key)
            return 1
        j = i + 2
        while j < len(buf):
            c = buf[j]
            if 0x40 <= c <= 0x7E:  # final byte of a CSI sequence
                return j - i + 1
            if not 0x20 <= c <= 0x3F:  # not a parameter/intermediate byte: a broken sequence
                return j - i
            j += 1
        return 0


@contextmanager
def cbreak_terminal(fd: int) -> Iterator[list[Any]]:
    """Put the TTY ``fd`` in key-at-a-time mode for the block; always restore it afterwards.

    Off: canonical input, echo, signals from keys (Ctrl-C, Ctrl-Z, Ctrl-\\ arrive as bytes, so a
    suspended process can never leave the car driving), XON/XOFF flow control (Ctrl-S would
    freeze the output), CR->NL. Reads return at once (VMIN = VTIME = 0). Output processing stays
    on, so printing works as usual. Keys typed before the block are dropped. Yields the saved
    settings.
    """
    if termios is None:
        raise NotBuiltError("keyboard-drive needs a POSIX terminal (Linux, macOS; on Windows run it in WSL)")
    saved = termios.tcgetattr(fd)
    mode = termios.tcgetattr(fd)
    mode[0] &= ~(termios.IXON | termios.ICRNL)
    mode[3] &= ~(termios.ECHO | termios.ICANON | termios.ISIG | termios.IEXTEN)
    mode[6][termios.VMIN] = 0
    mode[6][termios.VTIME] = 0
    termios.tcsetattr(fd, termios.TCSAFLUSH, mode)  # keys typed before now must not drive the car
    try:
        yield saved
    finally:
        # TCSAFLUSH also drops keys typed but not read, so they do not spill into the shell
        try:
            termios.tcsetattr(fd, termios.TCSAFLUSH, saved)
        except termios.error:  # the terminal is gone (hang-up): nothing left to restore
            pass


def read_keys(fd: int, decoder: KeyDecoder, now: float) -> list[str] | None:
    """The keys waiting on ``fd`` (never blocks); None when the terminal is gone (end of file)."""
    data = b""
    while True:
        ready, _, _ = select.select([fd], [], [], 0.0)
        if not ready:
            break
        try:
            chunk = os.read(fd, 1024)
        except OSError:  # EIO after a hang-up
            return None
        if not chunk:
            return None if not data else decoder.feed(data, now)
        data += chunk
        if len(chunk) < 1024:
            break
    return decoder.feed(data, now)


# --------------------------------------------------------------------------------------------
# the loop
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Frame:
    """What the terminal view shows: one snapshot of the loop (SI units)."""

    t: float  # s since the drive began
    state: DriveState
    readout: Readout
    speed: float  # m/s from the encoder (basic_speed_estimation)
    lamps: tuple[str, ...]
    lidar: tuple[float, float] | str  # (range m, bearing rad) of the nearest return, or "n/a"/"none"
    truth: Truth | None
    distance: float  # m driven (encoder)
    rate: float  # achieved loop rate, Hz


@dataclass
class DriveSummary:
    """How the drive went; ``reason`` is quit | interrupted (Ctrl-C, SIGINT) | terminal closed |
    signal (SIGTERM, SIGHUP) | collision (a simulated car hit a wall or an obstacle, or left its world)."""

    reason: str
    duration_s: float
    distance_m: float  # wheel distance from the encoder speed, |v| dt
    top_speed_mps: float
    final_speed_mps: float
    ticks: int
    keys: int
    truth_distance_m: float | None = None
    heading_change_rad: float | None = None
    battery_v: float | None = None
    signal: int | None = None  # the signal that ended the drive, if one did
    collision: str | None = None  # a simulated car that hit a solid or left its world: what happened (reason "collision")

    def line(self) -> str:
        """One line for the terminal, e.g. after quitting."""
        text = (
            f"keyboard-drive: drove {self.distance_m:.2f} m in {self.duration_s:.1f} s (encoder), "
            f"top speed {self.top_speed_mps:.2f} m/s, final speed {self.final_speed_mps:.2f} m/s"
        )
        if self.truth_distance_m is not None and self.heading_change_rad is not None:
            text += (
                f"; truth: {self.truth_distance_m:.2f} m over the ground, "
                f"heading change {math.degrees(self.heading_change_rad):+.0f} deg"
            )
        return text + "; the car is stopped"

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def nearest_obstacle(scan: Any) -> tuple[float, float] | str:
    """(range m, bearing rad CCW from forward) of the nearest LIDAR return, or "none"."""
    ranges = np.asarray(scan.ranges, dtype=float)
    ok = np.isfinite(ranges) & (ranges > 0.0)
    if not ok.any():
        return "none"
    k = int(np.flatnonzero(ok)[np.argmin(ranges[ok])])
    bearing = math.atan2(math.sin(float(scan.angles[k])), math.cos(float(scan.angles[k])))
    return float(ranges[k]), bearing


class _Signals:
    """SIGINT/SIGTERM/SIGHUP end the drive at the next tick (main thread only); restored on exit."""

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> _Signals:
        if threading.current_thread() is threading.main_thread():
            for name in ("SIGINT", "SIGTERM", "SIGHUP"):
                sig = getattr(signal, name, None)
                if sig is None:
                    continue
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, _frame: Any) -> None:
        self.received = signum

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


class KeyboardDriveLab:
    """Keyboard drive (sheet 3.4) as a model of the one loop: keys in, command out, every tick.

    ``keys(t)`` gives the keys pressed since the last call (None: end of input); the step applies
    them and ramps the command by the tick's real ``dt``; it ends the run (STOP) on q, Ctrl-C, the
    end of input or a signal, and says why in ``reason``.
    """

    def __init__(self, car: Car, config: DriveConfig, keys: Callable[[float], list[str] | None],
                 on_frame: Callable[[Frame], None] | None, sigs: _Signals, rate: float,
                 lidar_period: float, truth_period: float):
        self.car, self.keys, self.on_frame, self.sigs = car, keys, on_frame, sigs
        self.lidar_period, self.truth_period = lidar_period, truth_period
        self.state = DriveState(config)
        self.params = car.params
        self.lidar_ok, self.nearest = True, "n/a"
        self.truth0 = self.truth = car.truth()
        self.distance = self.top = self.speed = 0.0
        self.n_keys = self.ticks = 0
        self.reason = "quit"
        self.wall0 = time.monotonic()
        self.last_lidar = self.last_truth = self.wall0
        self.recent: deque[float] = deque(maxlen=max(2, int(rate)))  # tick times of the last second
        self.rate = rate
        self.t_car: float | None = None
        self.readout: Readout | None = None

    def read_lidar(self) -> None:
        if not self.lidar_ok:
            return
        try:
            self.nearest = nearest_obstacle(self.car.read_lidar())
        except NotBuiltError:
            self.lidar_ok, self.nearest = False, "n/a"

    def step(self, t: float, r: Readout, dt: float) -> Step | object:
        now = time.monotonic()
        pressed = self.keys(now - self.wall0)
        if pressed is None:
            self.reason = "terminal closed"
            return STOP
        state = self.state
        for key in pressed:
            self.n_keys += 1
            state = apply_key(state, key)
        if state.quit is not None:
            self.state, self.reason = state, state.quit
            return STOP
        if self.sigs.received is not None:
            self.reason = "interrupted" if self.sigs.received == signal.SIGINT else "signal"
            return STOP
        state = self.state = apply_key(state, None, min(dt, 5.0 / self.rate) if self.ticks else 0.0)
        self.recent.append(now)
        recent = self.recent
        rate_est = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 and recent[-1] > recent[0] \
            else self.rate
        self.readout = r
        self.speed = speed = float(basic_speed_estimation(r.tach, self.params))
        if self.t_car is not None:
            self.distance += abs(speed) * max(0.0, r.t - self.t_car)
        self.t_car = r.t
        self.top = max(self.top, abs(speed))
        if now - self.last_lidar >= self.lidar_period:
            self.last_lidar = now
            self.read_lidar()
        if self.truth0 is not None and now - self.last_truth >= self.truth_period:
            self.last_truth = now
            self.truth = self.car.truth()
        self.ticks += 1
        names = tuple(lamps(state))
        if self.on_frame is not None:
            self.on_frame(Frame(now - self.wall0, state, r, speed, names, self.nearest, self.truth, self.distance,
                                rate_est))
        return Step(Command(state.throttle, state.steering, lamps_named(names)))


def keyboard_drive(
    car: Car,
    config: DriveConfig = DriveConfig(),
    key_fd: int | None = None,
    on_frame: Callable[[Frame], None] | None = None,
    rate: float = 50.0,
    lidar_period: float = 0.2,
    truth_period: float = 0.1,
    keys: Callable[[float], list[str] | None] | None = None,
) -> DriveSummary:
    """Drive ``car`` from the keyboard until quit; returns the summary. The car is stopped on exit.

    Keys come from ``key_fd`` (a TTY already in :func:`cbreak_terminal` mode) or from ``keys``
    (a function of the time since start returning the keys pressed since the last call, or None
    for end of input; for tests). ``on_frame`` gets a :class:`Frame` every tick and must be quick.
    SIGINT, SIGTERM and SIGHUP end the drive like ``q`` does (reason ``interrupted`` or
    ``signal``). A :class:`~qcarlab.errors.CarError` (a lost connection) propagates after the
    stop was tried. The drive runs on the one loop of every lab, paced in real time.
    """
    if not (math.isfinite(rate) and 1.0 <= rate <= 1000.0):
        raise InputError(f"--rate must be between 1 and 1000 Hz, got {rate}")
    if key_fd is None and keys is None:
        raise InputError("keyboard_drive needs key_fd or keys")
    decoder = KeyDecoder()
    if keys is None:
        def keys(_t: float) -> list[str] | None:
            return read_keys(key_fd, decoder, time.monotonic())  # type: ignore[arg-type]

    from qcarlab.experiments.safety import WorldWatch

    # a simulated car in a local world collides like in every lab: the drive ends, the car stopped
    watch = WorldWatch.for_car(car, getattr(car, "world", None))
    with _Signals() as sigs:
        lab = KeyboardDriveLab(car, config, keys, on_frame, sigs, rate, lidar_period, truth_period)
        lab.read_lidar()  # once before driving: a first scan may be slow (compilation, a cold cache)
        lab.wall0 = time.monotonic()
        model = watch.wrap(lab) if watch is not None else lab
        log = run_loop(car, model, 7 * 24 * 3600.0, rate, record_truth=False, pace=True, keep_rows=False)
    event = watch.event if watch is not None else None
    final_truth = car.truth() if lab.truth0 is not None else None
    r = lab.readout if lab.readout is not None else car.read()
    summary = DriveSummary(
        reason="interrupted" if log.interrupted else "collision" if event is not None else lab.reason,
        duration_s=time.monotonic() - lab.wall0,
        distance_m=lab.distance,
        top_speed_mps=lab.top,
        final_speed_mps=lab.speed,
        ticks=lab.ticks,
        keys=lab.n_keys,
        battery_v=float(r.battery_voltage),
        signal=sigs.received,
        collision=event["what"] if event is not None else None,
    )
    if lab.truth0 is not None and final_truth is not None:
        summary.truth_distance_m = final_truth.distance - lab.truth0.distance
        dyaw = final_truth.yaw - lab.truth0.yaw
        summary.heading_change_rad = math.atan2(math.sin(dyaw), math.cos(dyaw))
    return summary


def _stop_quietly(car: Car) -> None:
    """Stop the car; when that fails too (the connection is gone), the served car's watchdog or
    the server's drop detection stops it, and the original error is the one to report."""
    try:
        car.stop()
    except Exception:  # noqa: BLE001
        pass


# --------------------------------------------------------------------------------------------
# the map
# --------------------------------------------------------------------------------------------
@dataclass
class MapGrid:
    """A world as a small raster for a character-cell map: 2 pixels per text row (half blocks).

    ``rgb`` (2*rows, cols, 3) uint8, row 0 at the top (+Y up, +X right); ``solid`` marks pixels
    that touch a wall, obstacle or sign; pixel (col, row) covers
    x in x0 + [col, col+1) / ppm, y in y1 - [row, row+1) / ppm.
    """

    rgb: np.ndarray
    solid: np.ndarray
    x0: float
    y1: float
    ppm: float

    @property
    def cols(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def rows(self) -> int:
        """Text rows (two pixels each)."""
        return int(self.rgb.shape[0] // 2)

    def pixel_of(self, x: float, y: float) -> tuple[int, int] | None:
        """(col, pixel row) of world point (x, y), or None when it is off the map."""
        col = math.floor((x - self.x0) * self.ppm)
        row = math.floor((self.y1 - y) * self.ppm)
        if 0 <= col < self.rgb.shape[1] and 0 <= row < self.rgb.shape[0]:
            return col, row
        return None


def world_map(world: Any, cols: int = 40, rows: int = 16, supersample: int = 4) -> MapGrid:
    """Rasterise ``world`` (a :class:`qcarlab.sim.world.World`) to at most ``cols`` x ``rows`` cells.

    The floor (with its markings) is averaged down; a pixel touching any static shape (wall,
    obstacle, sign) takes that shape's colour, so thin walls stay visible.
    """
    import cv2

    if cols < 4 or rows < 2:
        raise InputError(f"map needs at least 4 x 2 cells, got {cols} x {rows}")
    xmin, ymin, xmax, ymax = world.bounds
    pad = 0.02 * max(xmax - xmin, ymax - ymin)
    x0, y1 = xmin - pad, ymax + pad
    wm, hm = (xmax - xmin) + 2 * pad, (ymax - ymin) + 2 * pad
    ppm = min(cols / wm, 2 * rows / hm)
    pw = max(1, min(cols, math.ceil(wm * ppm - 1e-9)))
    ph = max(2, min(2 * rows, math.ceil(hm * ppm - 1e-9)))
    ph += ph % 2
    k = int(supersample)
    hp = ppm * k
    W, H = pw * k, ph * k
    bg = tuple(int(c) for c in getattr(world, "background", (60, 60, 70)))
    hi = np.empty((H, W, 3), np.uint8)
    hi[:] = bg
    from qcarlab.sim.raster import floor_texture

    tex, (tx0, ty1, tppm) = floor_texture(world, min(hp, 200.0))
    sc = hp / tppm
    A = np.array([[sc, 0.0, (tx0 - x0) * hp + 0.5 * sc - 0.5], [0.0, sc, (y1 - ty1) * hp + 0.5 * sc - 0.5]])
    cv2.warpAffine(tex, A, (W, H), dst=hi, flags=cv2.INTER_AREA if sc < 1 else cv2.INTER_LINEAR,
                   borderMode=cv2.BORDER_TRANSPARENT)
    mask = np.zeros((H, W), np.uint8)
    layer = np.zeros((H, W, 3), np.uint8)

    def px(points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, float).reshape(-1, 2)
        return np.round(np.column_stack(((p[:, 0] - x0) * hp - 0.5, (y1 - p[:, 1]) * hp - 0.5)) * 16).astype(np.int32)

    for sol in world.static_solids():
        color = tuple(int(c) for c in sol.color)
        if sol.kind == "polygon" and sol.points is not None:
            for img, val in ((mask, 1), (layer, color)):
                cv2.fillPoly(img, [px(sol.points)], val, cv2.LINE_8, 4)
        elif sol.center is not None:
            c = px(np.array([sol.center]))[0]
            rad = max(16, int(round(sol.radius * hp * 16)))
            for img, val in ((mask, 1), (layer, color)):
                cv2.circle(img, (int(c[0]), int(c[1])), rad, val, -1, cv2.LINE_8, 4)
    grid = getattr(world, "grid", None)
    if grid is not None:
        xs = x0 + (np.arange(W) + 0.5) / hp
        ys = y1 - (np.arange(H) + 0.5) / hp
        gc = np.floor((xs - grid.origin[0]) / grid.resolution).astype(int)
        gr = np.floor((ys - grid.origin[1]) / grid.resolution).astype(int)
        ny, nx = grid.occupied.shape
        okc, okr = (gc >= 0) & (gc < nx), (gr >= 0) & (gr < ny)
        occ = np.zeros((H, W), bool)
        occ[np.ix_(okr, okc)] = grid.occupied[np.ix_(gr[okr], gc[okc])]
        mask[occ] = 1
        layer[occ] = grid.wall_color
    rgb = cv2.resize(hi, (pw, ph), interpolation=cv2.INTER_AREA)
    blocks = mask.reshape(ph, k, pw, k)
    count = blocks.sum(axis=(1, 3))
    solid = count > 0
    if solid.any():
        sums = (layer.astype(np.float64) * mask[:, :, None]).reshape(ph, k, pw, k, 3).sum(axis=(1, 3))
        rgb[solid] = np.clip(sums[solid] / count[solid][:, None], 0, 255).astype(np.uint8)
    return MapGrid(rgb=np.ascontiguousarray(rgb[:, :, ::-1]), solid=solid, x0=x0, y1=y1, ppm=ppm)
