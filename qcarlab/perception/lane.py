"""Lane detection (lab sheet 5.3, the lane example's green part): pick the image region, threshold
the yellow centre line in HSV, fit a straight line to it, draw it in red; and the obstacle window.

    >>> from qcarlab.perception.lane import detect_lane
    >>> det = detect_lane(frame.color, lane="right")          # an RGBDFrame from car.read_rgbd()
    >>> det.source, det.fit.slope, det.fit.intercept           # 'yellow', -1.41, 660.3 (u = m v + b)

One function per block of the lane example (numpy in -> numpy out, no car):

1. :func:`image_selector`: the region of interest for the selected lane. Driving in the **right**
   lane the yellow centre line is on the car's *left*, so the left part of the lower image is kept
   (and the right part for the left lane). Rows above :data:`ROW_MIN` (beyond ~1.1 m of floor,
   where the walls and the other lane's edge begin) are never used.
2. ``color_thresholding_hsv`` (shared with the stop-sign lab, :mod:`qcarlab.perception.stop_sign`):
   HSV threshold, default yellow :data:`YELLOW_HSV_MIN` .. :data:`YELLOW_HSV_MAX` (OpenCV hue
   0..179 = degrees / 2; yellow is 60 deg = 30, the track's paint is 25).
3. :func:`linear_poly_fit`: least-squares line through the mask's pixels, **column as a function
   of row**, ``u = slope * v + intercept`` (lane lines are near-vertical in the image, where
   ``v = m u + b`` would be ill-conditioned). Fewer than ``min_pixels`` pixels: no fit.
4. :func:`lane_mask`: the colour image with the tracked line's pixels painted red (Figure 58).
5. :func:`draw_box` / :func:`calculate_distance`: the obstacle window (DESIGN.md section 3): rows
   around the image middle, 120 px wide, centred on column ``320 - 520 delta``; the mean of the
   depths in 0.06..2 m inside it (0.0 = nothing there).

Backup line (qcarlab's addition): the D435's 69 deg field of view does not see the yellow line on
the *inside* of the track's 1 m curves (it is more than 27 deg to the side as soon as it is in
front of the bumper). :func:`white_line_mask` finds the white edge line on the other side of the
lane (low saturation, the brightest pixels of the region) and :func:`detect_lane` falls back to it
when the yellow line has too few pixels; the steering then aims the same lane centre from the
other side.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from qcarlab.errors import InputError
from qcarlab.perception.stop_sign import check_hsv, color_thresholding_hsv

__all__ = [
    "LANES",
    "YELLOW_HSV_MAX",
    "YELLOW_HSV_MIN",
    "LaneDetection",
    "LineFit",
    "calculate_distance",
    "color_thresholding_hsv",
    "detect_lane",
    "draw_box",
    "image_selector",
    "lane_image",
    "lane_mask",
    "linear_poly_fit",
    "white_line_mask",
]

LANES = ("right", "left")
#: Yellow: hue 15..40 (30..80 deg), saturation and value from 80 (the dim end of the track reads
#: V ~ 135, real photos' faded paint S ~ 100).
YELLOW_HSV_MIN = (15, 80, 80)
YELLOW_HSV_MAX = (40, 255, 255)
ROW_MIN = 320  # px: lowest row index used (480-row image): floor within ~1.1 m of the camera
MIN_PIXELS = 150  # px: fewer line pixels than this is "no line"
WHITE_S_MAX = 50  # white: saturation at most this ...
WHITE_V_MIN = 110  # ... and value at least this and at least 0.8 x the region's 99th percentile
BOX_WIDTH = 120  # px, obstacle window
BOX_HALF_HEIGHT = 20  # px, obstacle window rows: middle +- this
BOX_GAIN = 520.0  # px per rad of steering: the window's column shift
DEPTH_RANGE = (0.06, 2.0)  # m, depths that count in the obstacle window


def _check_lane(lane: str) -> str:
    if lane not in LANES:
        raise InputError(f"lane must be one of {', '.join(LANES)}, got {lane!r}")
    return lane


def image_selector(image: np.ndarray, lane: str = "right", row_min: int = ROW_MIN,
                   line: str = "yellow") -> np.ndarray:
    """Zero everything outside the region where the tracked line is expected; same shape.

    Rows ``row_min`` and below (nearer floor). ``line="yellow"``: the centre line, on the car's
    left in the right lane (columns 0 .. 0.85 W) and on its right in the left lane (0.15 W .. W).
    ``line="white"``: the edge line on the other side, whole width (in the curves it sweeps across
    the image). Works on a colour image or a mask.
    """
    _check_lane(lane)
    img = np.asarray(image)
    if img.ndim not in (2, 3):
        raise InputError(f"image_selector: expected an image (H, W) or (H, W, 3), got shape {img.shape}")
    h, w = img.shape[:2]
    out = np.zeros_like(img)
    r0 = min(max(0, int(row_min)), h)
    if line == "yellow":
        c0, c1 = (0, int(0.85 * w)) if lane == "right" else (int(0.15 * w), w)
    else:
        c0, c1 = 0, w
    out[r0:, c0:c1] = img[r0:, c0:c1]
    return out


def white_line_mask(image_bgr: np.ndarray, s_max: int = WHITE_S_MAX, v_min: int = WHITE_V_MIN,
                    row_min: int = ROW_MIN) -> np.ndarray:
    """Mask of white paint: saturation <= ``s_max`` and value >= max(``v_min``, 0.8 x the 99th
    percentile of the value of the unsaturated floor pixels (rows ``row_min`` and below, not the
    walls)): adaptive, so the dim end of the track
    still finds its white line and the bright corner does not take the grey concrete for it."""
    img = np.asarray(image_bgr)
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    s, v = hsv[..., 1], hsv[..., 2]
    grey = (s <= s_max) & (v > 0)
    floor = grey[row_min:]
    if not floor.any():
        return np.zeros(img.shape[:2], np.uint8)
    level = max(float(v_min), 0.8 * float(np.percentile(v[row_min:][floor], 99)))
    return ((grey & (v >= level)).astype(np.uint8)) * 255


@dataclass(frozen=True)
class LineFit:
    """A straight line in the image, ``u = slope * v + intercept`` (u column, v row, pixels),
    fitted to ``pixels`` pixels whose rows span ``rows``."""

    slope: float
    intercept: float
    pixels: int
    rows: tuple[int, int]

    def column_at(self, v: float) -> float:
        return self.slope * v + self.intercept


def linear_poly_fit(mask: np.ndarray, min_pixels: int = MIN_PIXELS) -> LineFit | None:
    """Least-squares line ``u = slope * v + intercept`` through the mask's non-zero pixels.

    Each row counts once (its mean column), so a wide, near blob does not outweigh the thin far
    part of the line; fewer than ``min_pixels`` pixels or fewer than 2 rows: None.
    """
    m = np.asarray(mask)
    if m.ndim != 2:
        raise InputError(f"linear_poly_fit: expected a 2-D mask, got shape {m.shape}")
    nz = m != 0
    count = int(nz.sum())
    if count < max(2, int(min_pixels)):
        return None
    per_row = nz.sum(axis=1)
    rows = np.nonzero(per_row)[0]
    if len(rows) < 2:
        return None
    cols = np.arange(m.shape[1], dtype=np.float64)
    mean_u = (nz[rows] @ cols) / per_row[rows]
    v = rows.astype(np.float64)
    slope, intercept = np.polyfit(v, mean_u, 1)
    return LineFit(float(slope), float(intercept), count, (int(rows[0]), int(rows[-1])))


def lane_mask(image_bgr: np.ndarray, mask: np.ndarray, color: Sequence[int] = (0, 0, 255)) -> np.ndarray:
    """The colour image with the pixels of ``mask`` painted red (BGR ``color``): the sheet's Figure 58."""
    out = np.ascontiguousarray(image_bgr).copy()
    out[np.asarray(mask) != 0] = color
    return out


def draw_box(shape: Sequence[int], steering: float, width: int = BOX_WIDTH,
             half_height: int = BOX_HALF_HEIGHT, gain: float = BOX_GAIN) -> tuple[int, int, int, int]:
    """The obstacle window ``(x0, y0, x1, y1)`` (x1, y1 exclusive) in an image of ``shape``: rows
    around the middle, ``width`` px wide, centred on column ``W/2 - gain * steering * W/640``
    (the box looks where the car turns: positive steering = left), clipped to the image."""
    h, w = int(shape[0]), int(shape[1])
    centre = w / 2.0 - gain * float(steering) * (w / 640.0)
    x0 = round(centre - width / 2.0)
    x0 = min(max(0, x0), max(0, w - width))
    x1 = min(w, x0 + width)
    y0, y1 = max(0, h // 2 - half_height), min(h, h // 2 + half_height)
    return x0, y0, x1, y1


def calculate_distance(depth: np.ndarray, box: Sequence[int], depth_range: tuple[float, float] = DEPTH_RANGE) -> float:
    """Mean depth (m) of the pixels of ``box`` (x0, y0, x1, y1) whose depth lies in ``depth_range``
    (0.06..2 m); 0.0 when there is none (nothing within 2 m)."""
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2:
        raise InputError(f"calculate_distance: expected a 2-D depth image, got shape {d.shape}")
    x0, y0, x1, y1 = (int(v) for v in box)
    patch = d[y0:y1, x0:x1]
    ok = (patch > depth_range[0]) & (patch < depth_range[1])
    return float(patch[ok].mean()) if ok.any() else 0.0


@dataclass(frozen=True)
class LaneDetection:
    """What :func:`detect_lane` found: the fit of the tracked line (None = lost), which line it is
    (``"yellow"``, ``"white"`` or None) and the masks (yellow in its region, the line used)."""

    fit: LineFit | None
    source: str | None
    yellow_pixels: int = 0
    white_pixels: int = 0
    mask: np.ndarray | None = field(default=None, repr=False, compare=False)
    yellow_mask: np.ndarray | None = field(default=None, repr=False, compare=False)

    def as_dict(self) -> dict:
        f = self.fit
        return {"source": self.source, "slope": f.slope if f else None, "intercept": f.intercept if f else None,
                "yellow_pixels": self.yellow_pixels, "white_pixels": self.white_pixels}


def detect_lane(
    color: np.ndarray,
    lane: str = "right",
    hsv_min: Sequence[int] = YELLOW_HSV_MIN,
    hsv_max: Sequence[int] = YELLOW_HSV_MAX,
    min_pixels: int = MIN_PIXELS,
    white_backup: bool = True,
    row_min: int = ROW_MIN,
) -> LaneDetection:
    """imageSelector -> colorThresholdingHSV -> linearPolyFit on the yellow line; when it has fewer
    than ``min_pixels`` pixels (and ``white_backup``), the same on the white edge line."""
    _check_lane(lane)
    hsv_min, hsv_max = check_hsv(hsv_min, "hsv_min"), check_hsv(hsv_max, "hsv_max")
    yellow = image_selector(color_thresholding_hsv(color, hsv_min, hsv_max), lane, row_min, "yellow")
    fit = linear_poly_fit(yellow, min_pixels)
    ny = int(np.count_nonzero(yellow))
    if fit is not None:
        return LaneDetection(fit, "yellow", ny, 0, yellow, yellow)
    if not white_backup:
        return LaneDetection(None, None, ny, 0, yellow, yellow)
    white = image_selector(white_line_mask(color, row_min=row_min), lane, row_min, "white")
    # the lane's own edge line only: on the far side of the yellow line's region
    _h, w = white.shape
    if lane == "right":
        white[:, : int(0.15 * w)] = 0
    else:
        white[:, int(0.85 * w):] = 0
    nw = int(np.count_nonzero(white))
    fit = linear_poly_fit(white, min_pixels)
    return LaneDetection(fit, "white" if fit is not None else None, ny, nw, white if fit is not None else yellow,
                         yellow)


def lane_image(color: np.ndarray, det: LaneDetection, box: tuple[int, int, int, int] | None = None,
               text: str | None = None) -> np.ndarray:
    """The processed frame: the tracked line's pixels in red (Figure 58), the fitted line in green,
    the obstacle window (``box``) in red, a caption bar. BGR uint8."""
    img = lane_mask(color, det.mask if det.mask is not None else np.zeros(color.shape[:2], np.uint8))
    _h, w = img.shape[:2]
    if det.fit is not None:
        v0, v1 = det.fit.rows
        p0 = (round(det.fit.column_at(v0)), v0)
        p1 = (round(det.fit.column_at(v1)), v1)
        cv2.line(img, p0, p1, (0, 255, 0), 2, cv2.LINE_AA)
    if box is not None:
        cv2.rectangle(img, (box[0], box[1]), (box[2] - 1, box[3] - 1), (0, 0, 255), 2)
    bar = np.full((28, w, 3), 255, np.uint8)
    caption = text or (f"tracking the {det.source} line" if det.source else "no line found")
    cv2.putText(bar, caption, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, img])
