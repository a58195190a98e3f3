"""Both lines of the ego lane in any camera image (``qcarlab detect lanes``): photos, video, the
car's own frames, at any resolution.

    >>> from qcarlab.perception.lane_lines import detect_lane_lines
    >>> lines = detect_lane_lines(cv2.imread("road.jpg"))
    >>> lines.left.endpoints(lines.height), lines.right, lines.confidence

The lab's blocks (:mod:`qcarlab.perception.lane`), used on both colours at once:

1. the region: rows from ``roi_top`` (a fraction of the height, default 0.6: below the horizon of
   a level camera), the whole width; cropped before the one HSV conversion;
2. yellow paint (``color_thresholding_hsv`` with the profile's range) and white paint
   (:func:`~qcarlab.perception.lane.white_from_hsv`: unsaturated, bright for this frame, brighter
   than the road beside it);
3. the blobs of each mask shaped like a line (:func:`~qcarlab.perception.components.line_components`),
   collinear ones merged (a dashed line is one line), each group a straight line ``u = slope v +
   intercept`` (its major axis; pixels, full image);
4. the ego lane: the lines met at the bottom row of the image left of the image centre (the
   nearest one to the centre is the left line) and right of it (the nearest is the right line).
   Groups with fewer than ``min_pixels`` pixels (at 640 x 480, scaled with the area) are noise.

``confidence`` of a line is the share of the region's rows it spans (1 from half of them up);
the frame's is the mean over its two lines (a missing line counts 0).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from qcarlab.errors import InputError
from qcarlab.perception.components import (
    MAX_THICKNESS,
    BlobMap,
    LineBlob,
    blob_pixels,
    group_collinear,
    line_components,
)
from qcarlab.perception.lane import (
    WHITE_CONTRAST,
    WHITE_S_MAX,
    WHITE_V_MIN,
    YELLOW_HSV_MAX,
    YELLOW_HSV_MIN,
    _check_bgr,
    _scaled,
    white_from_hsv,
)
from qcarlab.perception.stop_sign import check_hsv, in_hsv_range

__all__ = ["ROI_TOP", "LaneLine", "LaneLines", "detect_lane_lines", "lane_lines_image"]

ROI_TOP = 0.6  # the region starts at 60 % of the height
MIN_LINE_PIXELS = 150  # px at 640 x 480 (scaled with the area): a smaller group is noise
GROUP_TOLERANCE = 0.02  # of the width: a dash this close to a line's axis is part of it
MAX_BEND = 0.02  # of the width: a row's mean this close to the fitted line is on it ...
MIN_STRAIGHT = 0.5  # ... and a line has this share of its rows on it
MIN_LEAN = 0.15  # |du/dv|: the left line leans right going up (slope <= -0.15), the right one left


@dataclass(frozen=True)
class LaneLine:
    """One lane line: ``u = slope v + intercept`` (pixels, full image), the rows its paint spans,
    its pixel count, which paint (``"yellow"`` or ``"white"``) and the line's confidence."""

    slope: float
    intercept: float
    rows: tuple[int, int]
    pixels: int
    source: str
    confidence: float

    def column_at(self, v: float) -> float:
        return self.slope * v + self.intercept

    def endpoints(self, height: int) -> list[list[float]]:
        """``[[x0, y0], [x1, y1]]``: on the bottom row (extended down to it) and at the top of the
        paint seen, (x0, y0) nearest the bottom of the image."""
        y0, y1 = height - 1, self.rows[0]
        return [[round(self.column_at(y0), 1), y0], [round(self.column_at(y1), 1), y1]]


@dataclass(frozen=True)
class LaneLines:
    """What :func:`detect_lane_lines` found in a ``width`` x ``height`` image."""

    left: LaneLine | None
    right: LaneLine | None
    width: int
    height: int
    roi_top: int  # first row of the region
    confidence: float
    yellow_pixels: int = 0
    white_pixels: int = 0
    candidates: tuple[LaneLine, ...] = field(default=(), repr=False, compare=False)
    masks: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)  # region's

    def as_dict(self) -> dict:
        """The ``qcarlab detect lanes --json`` fields (without file and frame)."""
        return {
            "width": self.width,
            "height": self.height,
            "left": self.left.endpoints(self.height) if self.left else None,
            "right": self.right.endpoints(self.height) if self.right else None,
            "confidence": round(self.confidence, 3),
        }


def _as_line(g: LineBlob, source: str, r0: int, height: int) -> LaneLine:
    span = (g.rows[1] - g.rows[0] + 1) / max(1.0, 0.5 * (height - r0))
    return LaneLine(float(g.slope), float(g.intercept), g.rows, g.pixels, source, float(min(1.0, span)))


_PAIRS = np.array([(0.05, 0.95), (0.05, 0.5), (0.5, 0.95), (0.25, 0.75), (0.05, 0.35), (0.35, 0.65), (0.65, 0.95),
                   (0.15, 0.85)])


def _line_through(v: np.ndarray, u: np.ndarray) -> tuple[float, float]:
    vm, um = v.mean(), u.mean()
    d = np.dot(v - vm, v - vm)
    slope = float(np.dot(v - vm, u - um) / d) if d > 0 else 0.0
    return slope, float(um - slope * vm)


def _row_fit(line: LaneLine, blob_map: BlobMap, blob: LineBlob, r0: int, tol: float) -> tuple[LaneLine, float]:
    """The line refitted through the mean column of each row (rows weighted alike, as the lab's
    :func:`~qcarlab.perception.lane.linear_poly_fit`), robustly: of the lines through the row
    means at eight fixed pairs of quantile rows, the one with the most rows within ``tol`` px,
    refitted to those rows. Rows where the paint touches the image's side are left out (a line
    leaving the image is cut there: its row mean is biased). Returns the line and the share of
    rows it explains: a straight line's is near 1, an L-shaped blob's (a pillar on its
    reflection) or a corner's lower."""
    v, u = blob_pixels(blob_map, blob)
    h, w = blob_map.shape
    if len(v) < 3:
        return line, 0.0
    v0 = int(v.min())
    vv = v - v0
    n = np.bincount(vv).astype(np.float64)
    su = np.bincount(vv, weights=u)
    edge = np.bincount(vv, weights=((u == 0) | (u == w - 1)).astype(np.float64), minlength=len(n))
    rows = np.nonzero((n > 0) & (edge == 0))[0]
    if len(rows) < max(3, (line.rows[1] - line.rows[0] + 1) // 4):
        rows = np.nonzero(n > 0)[0]
        if len(rows) < 3:
            return line, 0.0
    vv_, uu = rows.astype(np.float64) + (v0 + r0), su[rows] / n[rows]
    k = len(vv_) - 1
    i = (_PAIRS[:, 0] * k).astype(int)
    j = (_PAIRS[:, 1] * k).astype(int)
    ok = vv_[j] != vv_[i]
    if not ok.any():
        return line, 0.0
    i, j = i[ok], j[ok]
    m = (uu[j] - uu[i]) / (vv_[j] - vv_[i])
    b = uu[i] - m * vv_[i]
    inliers = np.abs(uu[None, :] - (m[:, None] * vv_[None, :] + b[:, None])) <= tol  # hypotheses x rows
    best = inliers[int(np.argmax(inliers.sum(axis=1)))]
    if best.sum() < 2:
        return line, 0.0
    for _ in range(2):  # refit to the inliers, then take the rows within tol of that
        slope, c = _line_through(vv_[best], uu[best])
        again = np.abs(uu - (slope * vv_ + c)) <= tol
        if again.sum() < 2:
            break
        best = again
    slope, c = _line_through(vv_[best], uu[best])
    return (LaneLine(slope, c, line.rows, line.pixels, line.source, line.confidence), float(best.mean()))


def detect_lane_lines(
    color: np.ndarray,
    hsv_min: Sequence[int] = YELLOW_HSV_MIN,
    hsv_max: Sequence[int] = YELLOW_HSV_MAX,
    roi_top: float = ROI_TOP,
    white: bool = True,
    white_s_max: int = WHITE_S_MAX,
    white_v_min: int = WHITE_V_MIN,
    white_contrast: int = WHITE_CONTRAST,
    min_pixels: int = MIN_LINE_PIXELS,
) -> LaneLines:
    """The left and right lines of the ego lane in a BGR image (module docstring); either is None
    when no line-shaped paint is on that side."""
    lo, hi = check_hsv(hsv_min, "hsv_min"), check_hsv(hsv_max, "hsv_max")
    img = _check_bgr(color)
    if not (isinstance(roi_top, (int, float)) and 0.0 <= float(roi_top) < 1.0):
        raise InputError(f"roi_top must be a fraction of the height in [0, 1), got {roi_top!r}")
    h, w = img.shape[:2]
    r0 = min(h - 1, int(round(float(roi_top) * h)))
    need = _scaled(min_pixels, h, w)
    hsv = cv2.cvtColor(img[r0:], cv2.COLOR_BGR2HSV)
    masks = [("yellow", in_hsv_range(hsv, lo, hi))]
    if white:
        masks.append(("white", white_from_hsv(hsv, white_s_max, white_v_min, white_contrast, w)))
    groups: list[tuple[LaneLine, LineBlob, int]] = []  # (line, its blobs, which mask)
    maps: list[BlobMap] = []
    counts = {"yellow": 0, "white": 0}
    for i, (name, mask) in enumerate(masks):
        counts[name] = int(cv2.countNonZero(mask))
        blobs, blob_map = line_components(mask, max(10, need // 10), MAX_THICKNESS * w, row0=r0, return_labels=True)
        maps.append(blob_map)
        # each colour on its own: a yellow and a white line are never one line
        groups += [(_as_line(g, name, r0, h), g, i) for g in group_collinear(blobs, GROUP_TOLERANCE * w)
                   if g.pixels >= need]
    cx, bottom = w / 2.0, h - 1
    # the ego lane's lines lean towards the middle going up (a pole or a pillar stands upright)
    left = [g for g in groups if g[0].column_at(bottom) < cx and g[0].slope <= -MIN_LEAN]
    right = [g for g in groups if g[0].column_at(bottom) >= cx and MIN_LEAN <= g[0].slope < np.inf]
    best = []
    for side, nearest_first in ((left, True), (right, False)):
        found = None
        for line, blob, i in sorted(side, key=lambda g: g[0].column_at(bottom), reverse=nearest_first):
            fit, share = _row_fit(line, maps[i], blob, r0, MAX_BEND * w)
            lean = -fit.slope if nearest_first else fit.slope
            if share >= MIN_STRAIGHT and lean >= MIN_LEAN:
                found = fit
                break
        best.append(found)
    best_left, best_right = best
    conf = ((best_left.confidence if best_left else 0.0) + (best_right.confidence if best_right else 0.0)) / 2.0
    return LaneLines(best_left, best_right, w, h, r0, conf, counts["yellow"], counts["white"],
                     tuple(g[0] for g in groups),
                     (masks[0][1], masks[1][1] if white else np.zeros_like(masks[0][1])))


def lane_lines_image(color: np.ndarray, lines: LaneLines, text: str | None = None) -> np.ndarray:
    """The overlay ``qcarlab detect lanes --out`` writes (the sheet's Figure 58, both lines): the
    paint the masks kept in red, the region's top edge dashed, the left line in green and the right
    in blue from the bottom row to the top of their paint, a caption bar. BGR uint8."""
    img = np.ascontiguousarray(color).copy()
    h, w = img.shape[:2]
    if lines.masks is not None:
        paint = cv2.bitwise_or(lines.masks[0], lines.masks[1])
        img[lines.roi_top:][paint != 0] = (0, 0, 255)
    for x in range(0, w, 16):
        cv2.line(img, (x, lines.roi_top), (min(w - 1, x + 7), lines.roi_top), (255, 255, 255), 1)
    thick = max(2, w // 320)
    for ln, bgr in ((lines.left, (0, 220, 0)), (lines.right, (255, 120, 0))):
        if ln is None:
            continue
        (x0, y0), (x1, y1) = ln.endpoints(h)
        cv2.line(img, (round(x0), y0), (round(x1), y1), bgr, thick, cv2.LINE_AA)
    bar = np.full((28, w, 3), 255, np.uint8)
    if text is None:
        found = [s for s, ln in (("left", lines.left), ("right", lines.right)) if ln is not None]
        text = (" and ".join(found) + f" line{'s' if len(found) > 1 else ''}" if found else "no lane line") + \
            f", confidence {lines.confidence:.2f}"
    cv2.putText(bar, text, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, img])
