"""An HSV range for a lane line, and the sheet's sliders for it (mean and window per channel).

    >>> HsvProfile((17, 85, 70), (38, 255, 255)).sliders
    ((27.5, 21), (170.0, 170), (162.5, 185))

The file format (``--hsv FILE``) is :mod:`qcarlab.hsv_profile`; the tuner is
:mod:`qcarlab.perception.tuner`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from qcarlab.errors import InputError
from qcarlab.perception.lane import WHITE_S_MAX, WHITE_V_MIN, YELLOW_HSV_MAX, YELLOW_HSV_MIN
from qcarlab.perception.stop_sign import check_hsv

__all__ = ["CHANNELS", "TOP", "HsvProfile"]

CHANNELS = ("hue", "saturation", "value")
TOP = (179, 255, 255)  # the largest value of each channel


@dataclass(frozen=True)
class HsvProfile:
    """A yellow range ``hsv_min .. hsv_max`` and the white finder's thresholds."""

    hsv_min: tuple[int, int, int] = YELLOW_HSV_MIN
    hsv_max: tuple[int, int, int] = YELLOW_HSV_MAX
    white_s_max: int = WHITE_S_MAX
    white_v_min: int = WHITE_V_MIN
    tuned_on: tuple[str, ...] = field(default=(), compare=False)
    score: float | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        lo, hi = check_hsv(self.hsv_min, "hsv_min"), check_hsv(self.hsv_max, "hsv_max")
        if any(a > b for a, b in zip(lo, hi)):
            raise InputError(f"hsv_min {lo} is above hsv_max {hi}")
        object.__setattr__(self, "hsv_min", lo)
        object.__setattr__(self, "hsv_max", hi)

    @property
    def sliders(self) -> tuple[tuple[float, int], ...]:
        """``((mean, window), ...)`` for H, S, V: the sheet's sliders for this range."""
        return tuple(((a + b) / 2.0, b - a) for a, b in zip(self.hsv_min, self.hsv_max))

    @classmethod
    def from_sliders(cls, sliders, **kw) -> HsvProfile:
        """The range of the sheet's sliders ``((mean, window), ...)`` for H, S, V: ``mean -+
        window / 2``, clipped to each channel's range."""
        lo, hi = [], []
        for (mean, window), top in zip(sliders, TOP):
            half = max(0.0, float(window)) / 2.0
            lo.append(int(min(top, max(0, round(mean - half)))))
            hi.append(int(min(top, max(0, round(mean + half)))))
        return cls(tuple(lo), tuple(hi), **kw)

    def with_sliders(self, sliders) -> HsvProfile:
        return HsvProfile.from_sliders(sliders, white_s_max=self.white_s_max, white_v_min=self.white_v_min,
                                       tuned_on=self.tuned_on, score=self.score)

    def lane_kwargs(self) -> dict:
        """Keyword arguments for ``detect_lane`` / ``detect_lane_lines``."""
        return {"hsv_min": self.hsv_min, "hsv_max": self.hsv_max, "white_s_max": self.white_s_max,
                "white_v_min": self.white_v_min}


