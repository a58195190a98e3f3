"""Realism profiles: the imperfections of a real QCar, one YAML file each (``--realism lab|ideal|FILE``).

A real car answers the lab sheet's questions ("Is the path followed precisely?", "tune the
look-ahead") with drift, lag and oscillation; a perfect simulator hides them. A profile names
every imperfection the simulator adds on top of the car's parameters (:class:`QCarParams`, whose
own noise -- IMU white noise, 5 mm LIDAR noise, the cameras' sensor noise, encoder quantisation --
is in both profiles), each with its value, unit and source in the YAML:

**Actuation** (:class:`Servo`, applied to every steering command)::

    servo     = command        if |command - servo| > deadband  else servo     (dead-band)
    wheels    = servo - b/2    if servo - wheels > b/2                        (backlash b)
              = servo + b/2    if wheels - servo > b/2
    delta_cmd = wheels + steering_offset                                      (trim offset)
    applied steering_delay s later (the PWM frame and the servo's electronics), then the servo's lag

and to every throttle command (the ESC)::

    duty = 0 if |command| < esc_deadband else command                         (neutral dead-band)
    applied throttle_delay s later (the PWM frame and the ESC's electronics)

so a speed loop tuned too hard rings or chatters on a lab car, as on the real one.

**Tyres** (in the physics step, :mod:`qcarlab.sim.vehicle`): the ground speed is the wheels'
less the slip, which grows with the lateral acceleration (scrub in turns), and the car turns less
than the bicycle model says (understeer)::

    v_ground = v_wheel (1 - slip_ratio - scrub_per_g |v psi'| / g)
    tan(delta_eff) = tan(delta) L / (L + understeer_gradient v^2)

**Gyro:** a constant bias drawn per run (``gyro_bias_sd``) plus a random walk
(``gyro_bias_walk``, rad/s per sqrt(s)), both per axis, on top of the parameters' bias and noise.

**LIDAR:** range noise proportional to the range (``lidar_range_noise``, a fraction, 1 sigma) and
beams that return nothing (``lidar_dropout``, read 0 as the device reports them).

**Cameras:** the auto-exposure's gain wanders (``exposure_sd`` about 1 with time constant
``exposure_tau``), and turning smears the image sideways: a horizontal box blur of
``|psi'| t_exp f`` pixels (``motion_blur_exposure`` = t_exp, f the camera's focal length in px).

Slow processes (the gyro's walk, the exposure) are sampled at knots a fixed simulated time apart
and interpolated (:class:`KnotProcess`), so their values depend only on the seed and the time,
never on how often a program reads the sensors: the runs stay deterministic under ``--seed``.
The ``ideal`` profile has every value 0: the simulator as it was before profiles existed, number
for number (the unit tests' default; the CLI's is ``lab``).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from qcarlab.errors import InputError

PROFILES_DIR = Path(__file__).resolve().parents[1] / "realism"


@dataclass(frozen=True)
class Realism:
    """One realism profile; every field 0 is the ideal simulator. Units in the field comments."""

    name: str = "ideal"
    steering_offset: float = 0.0  # rad, wheel angle at a zero command (trim)
    steering_backlash: float = 0.0  # rad, total play between the servo and the wheels
    servo_deadband: float = 0.0  # rad, command change the servo ignores
    steering_delay: float = 0.0  # s, from the command to the servo moving
    throttle_delay: float = 0.0  # s, from the command to the ESC's output
    esc_deadband: float = 0.0  # duty fraction about neutral the ESC gives no output for
    slip_ratio: float = 0.0  # fraction of the wheel speed lost to longitudinal slip
    scrub_per_g: float = 0.0  # extra slip per g of lateral acceleration (tyre scrub in turns)
    understeer_gradient: float = 0.0  # rad per (m/s^2): tan(delta_eff) = tan(delta) L / (L + K v^2)
    gyro_bias_sd: float = 0.0  # rad/s, per axis, drawn once per run
    gyro_bias_walk: float = 0.0  # rad/s per sqrt(s), per axis
    lidar_range_noise: float = 0.0  # fraction of the range, 1 sigma
    lidar_dropout: float = 0.0  # probability a beam returns nothing
    exposure_sd: float = 0.0  # fraction, 1 sigma of the auto-exposure gain about 1
    exposure_tau: float = 2.0  # s, how slowly the gain wanders
    motion_blur_exposure: float = 0.0  # s, exposure time that smears a turning image
    sources: dict[str, str] = field(default_factory=dict, compare=False, repr=False)
    description: str = field(default="", compare=False, repr=False)

    @property
    def ideal(self) -> bool:
        """True when the profile adds nothing (every imperfection 0)."""
        return all(getattr(self, f) == 0.0 for f in _IMPERFECTIONS)

    @property
    def servo(self) -> bool:
        return self.steering_offset != 0.0 or self.steering_backlash != 0.0 or self.servo_deadband != 0.0

    @property
    def esc(self) -> bool:
        return self.throttle_delay != 0.0 or self.esc_deadband != 0.0

    @property
    def tyres(self) -> bool:
        return self.slip_ratio != 0.0 or self.scrub_per_g != 0.0 or self.understeer_gradient != 0.0

    @property
    def camera(self) -> bool:
        return self.exposure_sd != 0.0 or self.motion_blur_exposure != 0.0

    @property
    def lidar(self) -> bool:
        return self.lidar_range_noise != 0.0 or self.lidar_dropout != 0.0

    def values(self) -> dict[str, float]:
        """The imperfections as field -> value (for results.json and the recordings)."""
        return {f: getattr(self, f) for f in _NUMBERS}


_NUMBERS = [f.name for f in fields(Realism) if f.type in ("float", float)]
_IMPERFECTIONS = [n for n in _NUMBERS if n != "exposure_tau"]
_FRACTIONS = {"slip_ratio", "lidar_dropout"}  # must stay below 1
IDEAL = Realism()


def profile_names() -> list[str]:
    """The shipped profiles (``qcarlab/realism/*.yaml``)."""
    return sorted(p.stem for p in PROFILES_DIR.glob("*.yaml"))


def load_realism(spec: str | Path | Realism | None) -> Realism:
    """A profile by name (``lab``, ``ideal``), from a YAML file, or as given; None is ideal.

    The YAML maps each imperfection to ``{value, unit, source}`` (or a bare number); unknown keys,
    negative or non-finite values are refused with the file and key named (InputError, exit 2).
    """
    if spec is None:
        return IDEAL
    if isinstance(spec, Realism):
        return spec
    text = str(spec)
    path = Path(text)
    if path.suffix.lower() not in (".yaml", ".yml"):
        shipped = PROFILES_DIR / f"{text}.yaml"
        if not shipped.is_file():
            raise InputError(f"--realism {text!r}: expected one of {', '.join(profile_names())} or a profile YAML file")
        path = shipped
    elif not path.is_file():
        raise InputError(f"--realism {text}: no such file")
    from qcarlab.yamlio import load_yaml

    data = load_yaml(path, "realism profile")
    if not isinstance(data, dict):
        raise InputError(f"{path}: a realism profile is a mapping of imperfection: {{value, unit, source}}")
    return realism_from_mapping(data, str(path), default_name=path.stem)


def realism_from_mapping(data: dict[str, Any], source: str = "realism profile", default_name: str = "custom") -> Realism:
    """Build a :class:`Realism` from a profile's mapping (see :func:`load_realism`)."""
    values: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for key, entry in data.items():
        if key in ("name", "description"):
            values[key] = str(entry)
            continue
        if key not in _NUMBERS:
            raise InputError(f"{source}: unknown imperfection {key!r} (known: {', '.join(_NUMBERS)})")
        if isinstance(entry, dict):
            unknown = set(entry) - {"value", "unit", "source"}
            if unknown or "value" not in entry:
                raise InputError(f"{source}: {key}: expected {{value, unit, source}}, got keys {sorted(entry)}")
            sources[key] = str(entry.get("source", ""))
            entry = entry["value"]
        if isinstance(entry, bool) or not isinstance(entry, (int, float)) or not math.isfinite(entry) or entry < 0:
            raise InputError(f"{source}: {key} must be a non-negative number, got {entry!r}")
        if key in _FRACTIONS and entry >= 1.0:
            raise InputError(f"{source}: {key} is a fraction below 1, got {entry!r}")
        if key == "exposure_tau" and entry <= 0.0:
            raise InputError(f"{source}: exposure_tau must be a positive time in s, got {entry!r}")
        values[key] = float(entry)
    values.setdefault("name", default_name)
    return Realism(**values, sources=sources)


class KnotProcess:
    """``dims`` scalar random processes sampled at knots ``h`` s of simulated time apart, linear
    between knots; ``at(t)`` depends only on the generator's seed and ``t``.

    ``kind="walk"``: x_0 = 0, x_{k+1} = x_k + sigma sqrt(h) n_k (a random walk, sigma per sqrt(s));
    ``kind="ou"``: stationary Ornstein-Uhlenbeck of standard deviation sigma and time constant tau,
    x_{k+1} = a x_k + sigma sqrt(1 - a^2) n_k, a = exp(-h / tau). The knots are drawn BLOCK at a time.
    """

    BLOCK = 256

    def __init__(self, rng: np.random.Generator, sigma: float, h: float, kind: str = "walk",
                 tau: float = 1.0, dims: int = 1):
        self.rng, self.sigma, self.h, self.kind, self.dims = rng, float(sigma), float(h), kind, dims
        self.a = math.exp(-h / tau) if kind == "ou" else 1.0
        if kind == "ou":
            x0 = rng.standard_normal(dims) * self.sigma
        else:
            x0 = np.zeros(dims)
        self.knots = x0.reshape(1, dims)

    def _extend(self, k: int) -> None:
        while len(self.knots) <= k + 1:
            n = self.rng.standard_normal((self.BLOCK, self.dims))
            last = self.knots[-1].copy()
            if self.kind == "walk":
                new = last + np.cumsum(n * (self.sigma * math.sqrt(self.h)), axis=0)
            else:
                b = self.sigma * math.sqrt(1.0 - self.a * self.a)
                new = np.empty_like(n)
                for i in range(self.BLOCK):
                    last = self.a * last + b * n[i]
                    new[i] = last
            self.knots = np.concatenate([self.knots, new])

    def at(self, t: float) -> np.ndarray:
        """The processes' values at simulated time ``t`` (s, >= 0), shape (dims,)."""
        s = max(t, 0.0) / self.h
        k = int(s)
        if k + 1 >= len(self.knots):
            self._extend(k)
        u = s - k
        a = self.knots[k]
        return a + u * (self.knots[k + 1] - a)


class Servo:
    """The steering servo's dead-band, the linkage's backlash and the trim offset (module docstring)."""

    __slots__ = ("deadband", "half_play", "offset", "servo", "wheels")

    def __init__(self, realism: Realism):
        self.deadband = realism.servo_deadband
        self.half_play = 0.5 * realism.steering_backlash
        self.offset = realism.steering_offset
        self.servo = 0.0
        self.wheels = 0.0

    def __call__(self, command: float) -> float:
        """The wheel angle the servo drives to for a (clamped) steering command, rad."""
        if abs(command - self.servo) > self.deadband:
            self.servo = command
        s, half = self.servo, self.half_play
        if s - self.wheels > half:
            self.wheels = s - half
        elif self.wheels - s > half:
            self.wheels = s + half
        return self.wheels + self.offset


class LidarEffects:
    """Range-proportional noise and dropouts on a finished scan (in place on its ranges)."""

    def __init__(self, realism: Realism, rng: np.random.Generator, r_min: float, r_max: float):
        self.frac, self.dropout, self.rng, self.r_min, self.r_max = (
            realism.lidar_range_noise, realism.lidar_dropout, rng, r_min, r_max)
        self._z = self._u = np.zeros(0)

    def __call__(self, ranges: np.ndarray) -> np.ndarray:
        """ranges (float64, in place): each return times 1 + frac z, z ~ N(0, 1), clipped to the
        device's range; then each beam 0 with probability ``dropout``. Compiled
        (:func:`~qcarlab.sim._kernels.lidar_effects`) once the kernels are loaded, else the same
        numbers in numpy (a lone run's scans do not load numba)."""
        n = len(ranges)
        if len(self._z) != n:  # scratch reused scan after scan (the draws go straight into it)
            self._z, self._u = np.empty(n), np.empty(n)
        z = self.rng.standard_normal(out=self._z)
        u = self.rng.random(out=self._u)
        kernels = sys.modules.get("qcarlab.sim._kernels")
        if kernels is not None:
            kernels.lidar_effects(ranges, z, u, self.frac, self.dropout, self.r_min, self.r_max)
            return ranges
        if self.frac > 0.0:
            ret = ranges > 0.0
            ranges[ret] = np.minimum(np.maximum(ranges[ret] * (1.0 + self.frac * z[ret]), self.r_min), self.r_max)
        if self.dropout > 0.0:
            ranges[u < self.dropout] = 0.0
        return ranges


class CameraEffects:
    """Auto-exposure gain and motion blur on finished colour images (in place, uint8 BGR)."""

    KNOT = 0.1  # s between the exposure process's knots

    def __init__(self, realism: Realism, rng: np.random.Generator):
        self.t_exp = realism.motion_blur_exposure
        self._gain = (KnotProcess(rng, realism.exposure_sd, self.KNOT, "ou", realism.exposure_tau)
                      if realism.exposure_sd > 0.0 else None)

    def gain(self, t: float) -> float:
        """The auto-exposure's gain at time ``t`` (1 = the ideal frame's brightness)."""
        return 1.0 if self._gain is None else max(0.0, 1.0 + float(self._gain.at(t)[0]))

    def blur_px(self, yaw_rate: float, focal_px: float) -> int:
        """Horizontal smear in pixels while turning at ``yaw_rate`` (rad/s): |psi'| t_exp f."""
        return int(round(abs(yaw_rate) * self.t_exp * focal_px))

    def apply(self, img: np.ndarray, gain: float, blur: int) -> np.ndarray:
        """img = saturate(round(gain img)), then a 1 x ``blur`` box filter (``blur`` >= 2), in place."""
        import cv2

        if gain != 1.0:
            cv2.convertScaleAbs(img, dst=img, alpha=gain)
        if blur >= 2:
            box_blur(img, blur)
        return img


MAX_BLUR_PX = 255  # the kernel's window sums are uint16: 255 b < 2^16


def box_blur(img: np.ndarray, b: int) -> np.ndarray:
    """A 1 x ``b`` box filter along the rows of a (H, W, 3) uint8 image, in place (the motion
    blur): out = floor(mean of the b pixels around + 1/2), mirrored at the ends as ``cv2.blur``
    (:func:`~qcarlab.sim._kernels.box_blur_rows`; b is capped at W and at
    MAX_BLUR_PX, a smear of 52 rad/s at the D435's 616 px focal length). For an odd b it is
    ``cv2.blur``'s numbers exactly, and b = 3 and 5 go to ``cv2.blur``, which has a fast path for
    them; for every other b ``cv2.blur`` took 0.4 ms a 640 x 480 frame, the kernel 0.09-0.14 ms.
    (For an even b ``cv2.blur`` rounds some halves up by one more: an approximation of its own.)"""
    import cv2

    from qcarlab.sim import _kernels

    h, w = img.shape[:2]
    b = min(int(b), w, MAX_BLUR_PX)
    if b < 2:
        return img
    out = img if img.flags.c_contiguous else np.ascontiguousarray(img)
    if b in (3, 5):
        cv2.blur(out, (b, 1), dst=out)
    else:
        _kernels.box_blur_rows(out.reshape(h, -1), b)
    if out is not img:
        img[...] = out
    return img
