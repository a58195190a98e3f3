"""The sheet's HSV tuning (section 5.3.2), the pure part: sliders, keys, the line-fit quality a
range gives, and an automatic tuner. The terminal around it is :mod:`qcarlab.cli.hsv_tune`.

The sheet's userInput block has a mean value and a window size per channel (H, S, V): the range
is ``mean -+ window / 2``. :class:`TunerState` holds the six sliders, which one is selected and
which frame is shown; :func:`apply_key` moves them (pure: state in, state out).

The quality of a range on a frame (:func:`frame_quality`) is what the sheet asks for, "only the
yellow line must be detected, no other objects of the room": in the lane region, the share of
the masked pixels that belong to the tracked line (``purity``, 1 when nothing else is yellow)
times the share of the region's rows the line spans up to half of them (``coverage``, 1 for a
line seen from the bumper to the middle of the region). :func:`auto_tune` maximises the mean
quality over the frames by coordinate ascent on the six bounds (steps 16, 8, 4, 2, 1), from the
start range (or, when that does not find the line, from the best of a coarse grid of hue
windows and floors); where the quality is flat it does not move (the result stays near the
sheet's defaults unless the frames need otherwise). The frames are tuned at half resolution
when they are wider than 400 px (the quality hardly changes; four times fewer pixels).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from qcarlab.perception.hsv_range import TOP, HsvProfile
from qcarlab.perception.lane import MIN_PIXELS, _check_bgr, _scaled, region_columns, region_row, track_line
from qcarlab.perception.stop_sign import in_hsv_range

__all__ = ["SLIDERS", "Quality", "TuneFrames", "TunerState", "apply_key", "auto_tune", "frame_quality"]

#: the six sliders, in the order the tuner lists them: (channel index, "mean" | "window")
SLIDERS = ((0, "mean"), (0, "window"), (1, "mean"), (1, "window"), (2, "mean"), (2, "window"))
NAMES = ("H", "S", "V")


@dataclass(frozen=True)
class Quality:
    """What a range gives on one frame: pixels kept in the region, the tracked line's pixels, the
    rows it spans, its fit (slope, intercept of u = slope v + intercept) and the quality 0..1."""

    pixels: int
    line_pixels: int
    rows: tuple[int, int] | None
    slope: float | None
    intercept: float | None
    quality: float


class TuneFrames:
    """The frames a range is tuned on, each cropped to the lane region and converted to HSV once.

    ``lane`` ("right"/"left") takes the lab's region (rows from 2/3 of the height, the yellow
    line's side); None takes the whole width from ``roi_top`` of the height (a photo)."""

    def __init__(self, frames: Sequence[np.ndarray], lane: str | None = "right", roi_top: float = 0.6,
                 names: Sequence[str] | None = None):
        if not frames:
            raise ValueError("TuneFrames needs at least one frame")
        self.frames = [_check_bgr(f) for f in frames]
        self.names = list(names) if names is not None else [f"frame {i}" for i in range(len(frames))]
        self.lane = lane
        self.crops: list[tuple[np.ndarray, int, int, int, int]] = []  # (hsv, row0, col0, min px, width)
        for img in self.frames:
            h, w = img.shape[:2]
            r0 = region_row(h) if lane is not None else min(h - 1, int(round(roi_top * h)))
            c0, c1 = region_columns(w, lane, "yellow") if lane is not None else (0, w)
            crop = np.ascontiguousarray(img[r0:, c0:c1])
            k = 2 if w > 400 else 1
            if k > 1:
                crop = cv2.resize(crop, (crop.shape[1] // k, crop.shape[0] // k), interpolation=cv2.INTER_AREA)
            hsv = cv2.cvtColor(crop, cv2.COLOR_BGR2HSV)
            self.crops.append((hsv, r0 // k, c0 // k, _scaled(MIN_PIXELS, h // k, w // k), w // k))

    def __len__(self) -> int:
        return len(self.frames)

    def mask(self, i: int, profile: HsvProfile) -> np.ndarray:
        """The region's mask of frame ``i`` (region-sized, at the tuning resolution)."""
        return in_hsv_range(self.crops[i][0], profile.hsv_min, profile.hsv_max)

    def quality(self, i: int, profile: HsvProfile) -> Quality:
        hsv, r0, c0, need, width = self.crops[i]
        return frame_quality(self.mask(i, profile), r0, c0, width, need)

    def mean_quality(self, profile: HsvProfile) -> float:
        return float(np.mean([self.quality(i, profile).quality for i in range(len(self))]))


def frame_quality(mask: np.ndarray, row0: int, col0: int, width: int, min_pixels: int) -> Quality:
    """The quality of one region's ``mask`` (module docstring)."""
    pixels = int(cv2.countNonZero(mask))
    if pixels < min_pixels:
        return Quality(pixels, 0, None, None, None, 0.0)
    fit, line = track_line(mask, min_pixels, width, row0, col0)
    if fit is None:
        return Quality(pixels, 0, None, None, None, 0.0)
    line_pixels = int(cv2.countNonZero(line))
    purity = line_pixels / pixels
    coverage = min(1.0, (fit.rows[1] - fit.rows[0] + 1) / max(1.0, 0.5 * mask.shape[0]))
    return Quality(pixels, line_pixels, fit.rows, fit.slope, fit.intercept, purity * coverage)


# ---------------------------------------------------------------------------------- the sliders
@dataclass(frozen=True)
class TunerState:
    """The tuner: the sliders as a profile, the selected slider (index into :data:`SLIDERS`),
    the frame shown, and whether the user asked to save or quit."""

    profile: HsvProfile
    selected: int = 0
    frame: int = 0
    frames: int = 1
    done: str | None = None  # "save" | "quit" | "auto"

    def slider_value(self, k: int) -> float:
        ch, part = SLIDERS[k]
        mean, window = self.profile.sliders[ch]
        return mean if part == "mean" else window


def move_slider(profile: HsvProfile, k: int, delta: float) -> HsvProfile:
    """``profile`` with slider ``k`` moved by ``delta`` (a mean keeps its window, clipped at the
    channel's ends; a window grows or shrinks round its mean)."""
    ch, part = SLIDERS[k]
    sliders = [list(s) for s in profile.sliders]
    mean, window = sliders[ch]
    top = TOP[ch]
    if part == "mean":
        mean = min(float(top), max(0.0, mean + delta))
    else:
        window = min(float(top), max(0.0, window + delta))
    sliders[ch] = [mean, window]
    return profile.with_sliders([tuple(s) for s in sliders])


def apply_key(state: TunerState, key: str) -> TunerState:
    """One key: up/down (k/j) select a slider, left/right (h/l) move it by 1, ``[``/``]`` by 10,
    tab/n and p the frame, ``r`` resets to the defaults, ``a`` asks for the automatic tuner,
    ``s``/enter save and finish, ``q``/escape/ctrl-c finish without saving."""
    if key in ("up", "k"):
        return replace(state, selected=(state.selected - 1) % len(SLIDERS))
    if key in ("down", "j"):
        return replace(state, selected=(state.selected + 1) % len(SLIDERS))
    steps = {"left": -1, "h": -1, "right": 1, "l": 1, "[": -10, "]": 10}
    if key in steps:
        return replace(state, profile=move_slider(state.profile, state.selected, steps[key]))
    if key in ("tab", "n"):
        return replace(state, frame=(state.frame + 1) % state.frames)
    if key == "p":
        return replace(state, frame=(state.frame - 1) % state.frames)
    if key == "r":
        return replace(state, profile=HsvProfile(white_s_max=state.profile.white_s_max,
                                                 white_v_min=state.profile.white_v_min))
    if key == "a":
        return replace(state, done="auto")
    if key in ("s", "enter"):
        return replace(state, done="save")
    if key in ("q", "escape", "ctrl-c", "ctrl-d"):
        return replace(state, done="quit")
    return state


# ---------------------------------------------------------------------------------- auto tuner
def _score(frames: TuneFrames, lo: list[int], hi: list[int], anchor: HsvProfile, cache: dict) -> float:
    key = (tuple(lo), tuple(hi))
    if key not in cache:
        if any(a > b for a, b in zip(lo, hi)):
            cache[key] = -1.0
        else:
            q = frames.mean_quality(HsvProfile(tuple(lo), tuple(hi)))
            # equal quality: the range nearest the anchor wins (a hair: 1e-5 per channel range)
            moved = sum(abs(a - b) / t for a, b, t in zip(lo + hi, anchor.hsv_min + anchor.hsv_max, TOP + TOP))
            cache[key] = q - 1e-5 * moved
    return cache[key]


def _grid(frames: TuneFrames, anchor: HsvProfile, cache: dict) -> tuple[list[int], list[int]]:
    """The best of a coarse grid: hue centres every 6 (windows 14 and 24), S and V floors."""
    best, arg = -2.0, None
    for centre in range(3, 180, 6):
        for window in (14, 24):
            for s_min in (40, 80, 120):
                for v_min in (40, 100):
                    lo = [max(0, centre - window // 2), s_min, v_min]
                    hi = [min(179, centre + window // 2), 255, 255]
                    sc = _score(frames, lo, hi, anchor, cache)
                    if sc > best:
                        best, arg = sc, (lo, hi)
    return arg


def auto_tune(frames: TuneFrames, start: HsvProfile | None = None, max_rounds: int = 6) -> HsvProfile:
    """The range with the best mean :func:`frame_quality` over ``frames`` (module docstring):
    from ``start`` (default: the defaults) when that finds the line at all, else from the best
    of a coarse grid; then coordinate ascent on the six bounds. Where the quality is flat the
    bounds stay nearest ``start`` (nearest the defaults when it came from the grid). The result carries its ``score``."""
    start = start or HsvProfile()
    cache: dict = {}
    lo, hi = list(start.hsv_min), list(start.hsv_max)
    anchor = start
    best = _score(frames, lo, hi, anchor, cache)
    if best < 0.5:  # the start does not find the line: from the grid, anchored to the defaults
        anchor, cache = HsvProfile(), {}
        glo, ghi = _grid(frames, anchor, cache)
        if frames.mean_quality(HsvProfile(tuple(glo), tuple(ghi))) > frames.mean_quality(start):
            lo, hi = glo, ghi
        best = _score(frames, lo, hi, anchor, cache)
    for step in (16, 8, 4, 2, 1):
        for _ in range(max_rounds):
            improved = False
            for bound in (lo, hi):
                for ch in range(3):
                    for d in (-step, step):
                        trial = bound[ch] + d
                        if not 0 <= trial <= TOP[ch]:
                            continue
                        old = bound[ch]
                        bound[ch] = trial
                        sc = _score(frames, lo, hi, anchor, cache)
                        if sc > best + 1e-12:
                            best, improved = sc, True
                        else:
                            bound[ch] = old
            if not improved:
                break
    quality = frames.mean_quality(HsvProfile(tuple(lo), tuple(hi)))
    return HsvProfile(tuple(lo), tuple(hi), start.white_s_max, start.white_v_min,
                      tuple(frames.names), round(quality, 3))
