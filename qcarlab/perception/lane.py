"""Lane detection (lab sheet 5.3, the lane example's green part): pick the image region, threshold
the yellow centre line in HSV, fit a straight line to it, draw it in red; and the obstacle window.

    >>> from qcarlab.perception.lane import detect_lane
    >>> det = detect_lane(frame.color, lane="right")          # an RGBDFrame from car.read_rgbd()
    >>> det.source, det.fit.slope, det.fit.intercept           # 'yellow', -1.41, 660.3 (u = m v + b)

One function per block of the lane example (numpy in -> numpy out, no car):

1. :func:`image_selector`: the region of interest for the selected lane. Driving in the **right**
   lane the yellow centre line is on the car's *left*, so the left part of the lower image is kept
   (and the right part for the left lane). The region starts at :data:`ROW_FRACTION` of the image
   height (row 320 of 480: beyond ~1.1 m of floor the walls and the other lane's edge begin); a
   fraction, so a 540- or 720-row photo gets the same part of its view. An int ``row_min`` is
   still a pixel row.
2. ``color_thresholding_hsv`` (shared with the stop-sign lab, :mod:`qcarlab.perception.stop_sign`):
   HSV threshold, default yellow :data:`YELLOW_HSV_MIN` .. :data:`YELLOW_HSV_MAX` (OpenCV hue
   0..179 = degrees / 2; yellow is 60 deg = 30: road paint reads 17..24, the Quanser mat 26..33,
   the simulator's paint 25). Saturation from 85 keeps faded road paint (S 75..165) but not dry
   grass (S 60..75); hue from 17 keeps paint but not a brown box (hue 13..15).
3. :func:`line_components` (:mod:`qcarlab.perception.components`): the mask's blobs shaped like
   a line (long, thin, not flat); the tracked line is the largest one with the blobs collinear
   with it (a dashed line's dashes). Grass, boxes and the floor never enter the fit.
4. :func:`linear_poly_fit`: least-squares line through the line's pixels, **column as a function
   of row**, ``u = slope * v + intercept`` (lane lines are near-vertical in the image, where
   ``v = m u + b`` would be ill-conditioned). Fewer than ``min_pixels`` pixels: no fit.
5. :func:`lane_mask`: the colour image with the tracked line's pixels painted red (Figure 58).
6. :func:`draw_box` / :func:`calculate_distance`: the obstacle window (DESIGN.md section 3): rows
   around the image middle, 120 px wide, centred on column ``320 - 520 delta``; the mean of the
   depths in 0.06..2 m inside it (0.0 = nothing there).

Backup line (qcarlab's addition): the D435's 69 deg field of view does not see the yellow line on
the *inside* of the track's 1 m curves (it is more than 27 deg to the side as soon as it is in
front of the bumper). :func:`white_line_mask` finds white paint (low saturation, the brightest
pixels of the floor; optionally brighter than the floor beside it, ``white_contrast``) and
:func:`detect_lane` falls back to it when the yellow line is not found; when no white blob is
shaped like a line either (a plain light floor is one wide blob: too thick), the answer is
"no line". The steering then aims the same lane
centre from the other side.

:func:`detect_lane` crops the region first and converts it to HSV once for both colours;
the white level comes from a histogram, not a sort. Both lane lines of the ego lane (for
``qcarlab detect lanes`` on photos and video) are :func:`qcarlab.perception.lane_lines.detect_lane_lines`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from qcarlab.errors import InputError
from qcarlab.perception.components import MAX_THICKNESS, group_collinear, line_components, mask_of
from qcarlab.perception.stop_sign import check_hsv, color_thresholding_hsv, in_hsv_range

__all__ = [
    "LANES",
    "ROW_FRACTION",
    "YELLOW_HSV_MAX",
    "YELLOW_HSV_MIN",
    "LaneDetection",
    "LineFit",
    "calculate_distance",
    "color_thresholding_hsv",
    "detect_lane",
    "draw_box",
    "image_selector",
    "LANE_OVERLAYS",
    "lane_caption",
    "lane_image",
    "lane_overlay",
    "lane_mask",
    "line_components",
    "linear_poly_fit",
    "white_line_mask",
    "edge_line_mask",
    "edge_line_side",
    "LaneBand",
    "white_edge_mask",
]

LANES = ("right", "left")
#: Yellow paint: hue 17..38 (34..76 deg), saturation from 85, value from 70 (module docstring).
YELLOW_HSV_MIN = (17, 85, 70)
YELLOW_HSV_MAX = (38, 255, 255)
ROW_FRACTION = 2.0 / 3.0  # the region starts this far down the image (row 320 of 480)
ROW_MIN = 320  # px: the same for a 480-row image (kept for callers that pass pixel rows)
YELLOW_SIDE = 0.85  # the yellow line's region: columns 0 .. 0.85 W (right lane) or 0.15 W .. W
MIN_PIXELS = 150  # px at 640 x 480 (scaled with the image area): fewer line pixels is "no line"
WHITE_S_MAX = 80  # white: saturation at most this (the QCar 1 RGB reads its white paint at S 55..75) ...
WHITE_V_MIN = 110  # ... value at least this and at least 0.8 x the floor's 99th percentile ...
WHITE_CONTRAST = 0  # optional: a top-hat (value above the floor round it) of at least this; 0 = off
BOX_WIDTH = 120  # px, obstacle window
BOX_HALF_HEIGHT = 20  # px, obstacle window rows: middle +- this
BOX_GAIN = 520.0  # px per rad of steering: the window's column shift
DEPTH_RANGE = (0.06, 2.0)  # m, depths that count in the obstacle window
GROUP_TOLERANCE = 0.03  # blobs within 3 % of the width of a line's path belong to it (dashes)


def _check_lane(lane: str) -> str:
    if lane not in LANES:
        raise InputError(f"lane must be one of {', '.join(LANES)}, got {lane!r}")
    return lane


def region_row(height: int, row_min: float | int | None = None) -> int:
    """The first row of the region: ``row_min`` as a pixel row (int), a fraction of ``height``
    (float in [0, 1)) or, None, :data:`ROW_FRACTION`; clipped to the image."""
    if row_min is None:
        row_min = ROW_FRACTION
    if isinstance(row_min, float) and 0.0 <= row_min < 1.0:
        r = int(round(row_min * height))
    else:
        try:
            r = int(row_min)
        except (TypeError, ValueError):
            raise InputError(f"row_min must be a pixel row or a fraction of the height, got {row_min!r}") from None
    return min(max(0, r), height)


def region_columns(width: int, lane: str, line: str) -> tuple[int, int]:
    """Columns ``c0 .. c1`` (c1 exclusive) where ``line`` ("yellow" or "white") is looked for."""
    if line == "yellow":
        return (0, int(YELLOW_SIDE * width)) if lane == "right" else (int((1.0 - YELLOW_SIDE) * width), width)
    # the lane's own edge line: the whole width but the far side of the yellow line's region
    return (int((1.0 - YELLOW_SIDE) * width), width) if lane == "right" else (0, int(YELLOW_SIDE * width))


def image_selector(image: np.ndarray, lane: str = "right", row_min: float | int | None = None,
                   line: str = "yellow") -> np.ndarray:
    """Zero everything outside the region where the tracked line is expected; same shape.

    Rows from ``row_min`` (a fraction of the height, default :data:`ROW_FRACTION`, or an int
    pixel row) down. ``line="yellow"``: the centre line, on the car's left in the right lane
    (columns 0 .. 0.85 W) and on its right in the left lane (0.15 W .. W). ``line="white"``: the
    edge line on the other side, whole width (in the curves it sweeps across the image). Works
    on a colour image or a mask.
    """
    _check_lane(lane)
    img = np.asarray(image)
    if img.ndim not in (2, 3):
        raise InputError(f"image_selector: expected an image (H, W) or (H, W, 3), got shape {img.shape}")
    h, w = img.shape[:2]
    out = np.zeros_like(img)
    r0 = region_row(h, row_min)
    c0, c1 = region_columns(w, lane, "yellow") if line == "yellow" else (0, w)
    out[r0:, c0:c1] = img[r0:, c0:c1]
    return out


def white_level(hsv: np.ndarray, grey: np.ndarray, v_min: int = WHITE_V_MIN) -> int:
    """The value a white pixel needs: max(``v_min``, 0.8 x the 99th percentile of V over the
    ``grey`` (unsaturated) pixels of the HSV image, or of V itself when ``hsv`` has one channel),
    from a 256-bin histogram (no sort); 256 (nothing is white) when no pixel is grey."""
    if hsv.ndim == 2 and grey is not None:
        # V where grey, 0 elsewhere, unmasked, those zeros taken off bin 0: the same counts, some
        # 20 % faster than a masked calcHist
        kept = cv2.copyTo(hsv, grey)
        hist = cv2.calcHist([kept], [0], None, [256], [0, 256]).ravel()
        hist[0] -= kept.size - cv2.countNonZero(grey)
    else:
        hist = cv2.calcHist([hsv], [2 if hsv.ndim == 3 else 0], grey, [256], [0, 256]).ravel()
    total = hist.sum()
    if total <= 0:
        return 256
    p99 = int(np.searchsorted(np.cumsum(hist), 0.99 * total))
    return int(max(float(v_min), 0.8 * p99))


def white_from_hsv(hsv: np.ndarray, s_max: int = WHITE_S_MAX, v_min: int = WHITE_V_MIN,
                   contrast: int = WHITE_CONTRAST, width: int | None = None) -> np.ndarray:
    """White paint in an HSV image (a region of the floor), uint8 mask: saturation <= ``s_max``,
    value >= :func:`white_level`, and (``contrast`` > 0; off by default: the line-shape checks
    already reject a plain floor, and it costs a third of the chain) a white top-hat of at least
    ``contrast``:

        top_hat = V - opening(V, k x k square),  k = width / 8 (80 px at 640)

    The opening wipes out every bright structure narrower than k in some direction (a painted
    line, whatever its angle) and keeps wide ones (a light floor, a wall): a line stands out from
    the floor beside it, a plain floor or the bright side of an edge does not."""
    # grey = S <= s_max, bright = grey and V >= level: inRange(hsv, (0, 0, level), (179, s_max, 255))
    # for OpenCV's hue (0..179), at a third of its cost (two thresholds of single channels)
    _, grey = cv2.threshold(cv2.extractChannel(hsv, 1), int(s_max), 255, cv2.THRESH_BINARY_INV)
    v = cv2.extractChannel(hsv, 2)
    level = white_level(v, grey, v_min)
    if level > 255:
        return np.zeros(hsv.shape[:2], np.uint8)
    _, bright = cv2.threshold(v, level - 1, 255, cv2.THRESH_BINARY)
    cv2.bitwise_and(bright, grey, dst=bright)
    if contrast > 0 and cv2.countNonZero(bright):
        k = max(3, ((width or v.shape[1]) // 8) | 1)
        top_hat = cv2.morphologyEx(v, cv2.MORPH_TOPHAT, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
        bright = cv2.bitwise_and(bright, cv2.inRange(top_hat, int(contrast), 255))
    return bright


def white_line_mask(image_bgr: np.ndarray, s_max: int = WHITE_S_MAX, v_min: int = WHITE_V_MIN,
                    row_min: float | int | None = None, contrast: int = WHITE_CONTRAST) -> np.ndarray:
    """Mask (uint8, full image) of white paint on the floor (rows from ``row_min`` down, a
    fraction or a pixel row): low saturation (<= ``s_max``), value >= max(``v_min``, 0.8 x the
    99th percentile of the unsaturated floor pixels) -- adaptive, so the dim end of the track
    still finds its white line and the bright corner does not take the grey concrete for it --
    and, with ``contrast`` > 0, that much brighter than the floor round it (a top-hat)."""
    img = np.asarray(image_bgr)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise InputError(f"expected a BGR uint8 image (H, W, 3), got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    r0 = region_row(h, row_min)
    out = np.zeros((h, w), np.uint8)
    if r0 < h:
        out[r0:] = white_from_hsv(cv2.cvtColor(img[r0:], cv2.COLOR_BGR2HSV), s_max, v_min, contrast, w)
    return out


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


def _fit_points(v: np.ndarray, u: np.ndarray, min_pixels: int) -> LineFit | None:
    """The per-row-mean least-squares line through pixels at rows ``v``, columns ``u``."""
    count = len(v)
    if count < max(2, int(min_pixels)):
        return None
    v0 = int(v.min())
    vv = v - v0
    per_row = np.bincount(vv)
    rows = np.nonzero(per_row)[0]
    if len(rows) < 2:
        return None
    mean_u = np.bincount(vv, weights=u)[rows] / per_row[rows]
    r = rows.astype(np.float64)
    rm, um = r.mean(), mean_u.mean()
    slope = float(np.dot(r - rm, mean_u - um) / np.dot(r - rm, r - rm))
    intercept = float(um - slope * (rm + v0))
    return LineFit(slope, intercept, count, (int(rows[0]) + v0, int(rows[-1]) + v0))


def _fit_rows(nz: np.ndarray, min_pixels: int, row0: int = 0, col0: int = 0) -> LineFit | None:
    """The per-row-mean least-squares line (:func:`_fit_points`) of a mask's pixels, the mask's
    (0, 0) being (``row0``, ``col0``) of the image; row counts and column sums by matrix
    products over the mask's bounding box (no list of pixels)."""
    m = nz.view(np.uint8) if nz.dtype == bool else nz
    count = int(cv2.countNonZero(m))
    if count < max(2, int(min_pixels)):
        return None
    x, y, w, h = cv2.boundingRect(m)
    sub = (m[y:y + h, x:x + w] != 0).astype(np.float32)
    # each row's count and column sum in one matrix product (whole numbers below 2^24: exact in
    # float32, in any order; a third of the time of a sum and a product)
    weights = np.empty((w, 2), np.float32)
    weights[:, 0] = 1.0
    weights[:, 1] = np.arange(w, dtype=np.float32)
    sums = sub @ weights
    per_row = sums[:, 0]
    rows = np.nonzero(per_row)[0]
    n = len(rows)
    if n < 2:
        return None
    mean_u = sums[rows, 1].astype(np.float64) / per_row[rows]
    r = rows.astype(np.float64)
    rm, um = np.add.reduce(r) / n, np.add.reduce(mean_u) / n  # (r.mean(), mean_u.mean())
    slope = float(np.dot(r - rm, mean_u - um) / np.dot(r - rm, r - rm))
    v0, u0 = y + row0, x + col0
    intercept = float(um + u0 - slope * (rm + v0))
    return LineFit(slope, intercept, count, (int(rows[0]) + v0, int(rows[-1]) + v0))


def linear_poly_fit(mask: np.ndarray, min_pixels: int = MIN_PIXELS, whole_mask: bool = False) -> LineFit | None:
    """Least-squares line ``u = slope * v + intercept`` through the tracked line's pixels.

    The line's pixels are its own blobs (:func:`track_line`): the largest blob of the mask
    shaped like a line (long, thin, not flat; :mod:`qcarlab.perception.components`) and the
    blobs collinear with it (a dashed line's dashes), so grass, a box or a second line beside it
    never enter the fit. Each row counts once (its mean column), so a wide, near blob does not
    outweigh the thin far part of the line; fewer than ``min_pixels`` line pixels or fewer than
    2 rows: None. ``whole_mask=True`` fits every non-zero pixel of the mask (the sheet's block
    as it was).
    """
    m = np.asarray(mask)
    if m.ndim != 2:
        raise InputError(f"linear_poly_fit: expected a 2-D mask, got shape {m.shape}")
    m = m if m.dtype == np.uint8 else (m != 0).astype(np.uint8) * 255
    if whole_mask:
        return _fit_rows(m, min_pixels)
    return track_line(m, min_pixels, m.shape[1])[0]


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


def obstacle_distance(depth: np.ndarray, box: Sequence[int], depth_range: tuple[float, float] = DEPTH_RANGE) -> float:
    """Mean depth (m) of the pixels of ``box`` (x0, y0, x1, y1) whose depth lies in ``depth_range``
    (0.06..2 m); 0.0 when there is none (nothing within 2 m)."""
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2:
        raise InputError(f"obstacle_distance: expected a 2-D depth image, got shape {d.shape}")
    x0, y0, x1, y1 = (int(v) for v in box)
    patch = d[y0:y1, x0:x1]
    ok = (patch > depth_range[0]) & (patch < depth_range[1])
    return float(patch[ok].mean()) if ok.any() else 0.0


#: The lane example's block name (obstacleDetection's calculateDistance): the obstacle window's depth.
calculate_distance = obstacle_distance


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


def _scaled(min_pixels: int, h: int, w: int) -> int:
    """``min_pixels`` (meant for 640 x 480) for an ``h`` x ``w`` image: scaled with the area."""
    return max(8, int(round(int(min_pixels) * (h * w) / (640.0 * 480.0))))


def _check_bgr(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8 or img.shape[0] < 2 or img.shape[1] < 2:
        raise InputError(f"expected a BGR uint8 image (H, W, 3), got {img.dtype} {img.shape}")
    return img


def track_line(mask: np.ndarray, min_pixels: int, width: int, row0: int = 0, col0: int = 0,
               pick: str = "largest", image_shape: tuple[int, int] | None = None):
    """The tracked line in a region's ``mask`` (at ``row0``, ``col0`` of an image ``width`` px
    wide): the largest line-shaped blob and the blobs collinear with it, fitted with
    :func:`linear_poly_fit`'s per-row means. ``(LineFit | None, its pixels as a mask)``.
    ``image_shape`` (H, W): blobs are cut by that image's edges, not the region's (the mask is a
    crop of a frame-sized mask: :class:`LaneBand`).

    ``pick="left"`` / ``"right"``: of the groups of at least ``min_pixels`` pixels, the leftmost /
    rightmost one instead (two groups compared by their axes' columns in the middle of the rows
    both cover): the road's white edge line, not a lit floor beyond it (:func:`edge_line_side`)."""
    blobs, labels = line_components(mask, max(10, min_pixels // 8), MAX_THICKNESS * width, row0=row0, col0=col0,
                                    return_labels=True, image_shape=image_shape)
    groups = group_collinear(blobs, GROUP_TOLERANCE * width)
    if not groups or groups[0].pixels < min_pixels:
        return None, None
    chosen = groups[0]
    if pick in ("left", "right"):
        big = [g for g in groups if g.pixels >= min_pixels]
        sign = 1.0 if pick == "left" else -1.0

        def ahead(a, b) -> bool:  # a is more to the ``pick`` side than b, on the rows both cover
            lo, hi = max(a.rows[0], b.rows[0]), min(a.rows[1], b.rows[1])
            v = 0.5 * (lo + hi)  # (no common rows: where the two come closest)
            return sign * (a.column_at(v) - b.column_at(v)) < 0.0

        wins = [sum(ahead(a, b) for b in big if b is not a) for a in big]
        chosen = big[int(np.argmax(wins))]
    line = mask_of(labels, chosen)
    return _fit_rows(line, min_pixels, row0, col0), line


def edge_line_side(lane: str) -> str:
    """Which of several white line candidates is the lane's own edge line: the one nearest the
    road, ``"left"`` in the right lane (the edge line is the road's right border), ``"right"`` in
    the left lane. Beyond the edge line there is only floor: where it is lit more brightly than
    the paint seen with it (the track's bright corner: concrete at V 195 beside normally lit paint
    at 235, above the white level 0.8 x 235), it makes a second, larger line-shaped blob, cut by
    the image's corner, that the largest-blob rule took for the line."""
    _check_lane(lane)
    return "left" if lane == "right" else "right"


def edge_line_mask(white: np.ndarray, lane: str = "right", min_pixels: int = MIN_PIXELS) -> np.ndarray:
    """The lane's white edge line's own pixels in a white-paint mask (uint8, same shape): the
    line-shaped blob group nearest the road (:func:`edge_line_side`); all zeros when none has
    ``min_pixels`` pixels (scaled with the image area)."""
    m = np.asarray(white)
    if m.ndim != 2:
        raise InputError(f"edge_line_mask: expected a 2-D mask, got shape {m.shape}")
    m = m if m.dtype == np.uint8 else (m != 0).astype(np.uint8) * 255
    h, w = m.shape
    _, line = track_line(m, _scaled(min_pixels, h, w), w, pick=edge_line_side(lane))
    return line if line is not None else np.zeros_like(m)


def _paste(part: np.ndarray | None, shape: tuple[int, int], r0: int, c0: int) -> np.ndarray:
    out = np.zeros(shape, np.uint8)
    if part is not None:
        out[r0:r0 + part.shape[0], c0:c0 + part.shape[1]] = part
    return out


WHITE_EDGE_SKIP = 0.15  # the white edge line's mask leaves out this much of the width on the yellow line's side


class LaneBand:
    """The lab chain's reference blocks on one colour frame of ``shape`` (H, W), from its lower
    band alone (``band``: BGR rows :func:`region_row` .. H, all the chain reads), converted to HSV
    once for both lines. Each method gives, cropped to the band (the column it starts at aside),
    what the blocks give on the whole frame (a mask of the frame's size, zeros above the band):

    - :meth:`yellow`: ``color_thresholding_hsv(image_selector(color, lane), lo, hi)``, where black
      is out of the range (:meth:`keeps_black`: else image_selector's zeros are kept),
    - :meth:`white_edge`: :func:`white_edge_mask` (the backup's white edge line),
    - :meth:`fit`: ``linear_poly_fit(mask, min_pixels)`` of such a mask, and the line's pixels
      (blobs cut by the frame's edges, not the band's),
    - :meth:`full`: the frame-sized mask of a band's mask.

        >>> band = LaneBand.of(frame.color)
        >>> yellow, c0 = band.yellow("right", YELLOW_HSV_MIN, YELLOW_HSV_MAX)
        >>> fit, line = band.fit(yellow, MIN_PIXELS, c0)
    """

    def __init__(self, band: np.ndarray, shape: tuple[int, int]):
        self.band = band
        self.h, self.w = int(shape[0]), int(shape[1])
        self.r0 = self.h - band.shape[0]
        self._hsv: np.ndarray | None = None

    @classmethod
    def of(cls, color: np.ndarray, row_min: float | int | None = None) -> LaneBand:
        """The band of a whole BGR frame (from ``row_min``, default :data:`ROW_FRACTION`)."""
        img = _check_bgr(color)
        h, w = img.shape[:2]
        return cls(img[region_row(h, row_min):], (h, w))

    @staticmethod
    def keeps_black(hsv_min: Sequence[int], hsv_max: Sequence[int]) -> bool:
        """Whether the HSV range keeps black (0, 0, 0): image_selector's zeros would be kept."""
        return bool(in_hsv_range(np.zeros((1, 1, 3), np.uint8), hsv_min, hsv_max)[0, 0])

    @property
    def hsv(self) -> np.ndarray:
        if self._hsv is None:
            self._hsv = (cv2.cvtColor(self.band, cv2.COLOR_BGR2HSV) if self.band.shape[0]
                         else np.zeros((0, self.w, 3), np.uint8))
        return self._hsv

    def yellow(self, lane: str, hsv_min: Sequence[int], hsv_max: Sequence[int]) -> tuple[np.ndarray, int]:
        """The yellow line's region thresholded (uint8 0/255) and the column it starts at."""
        c0, c1 = region_columns(self.w, _check_lane(lane), "yellow")
        return in_hsv_range(self.hsv[:, c0:c1], hsv_min, hsv_max), c0

    def white_edge(self, lane: str, s_max: int = WHITE_S_MAX,
                   v_min: int = WHITE_V_MIN) -> tuple[LineFit | None, np.ndarray | None]:
        """The lane's white edge line: its fit (with :data:`MIN_PIXELS`, scaled) and its pixels
        (band-sized, from column 0), (None, None) when none. The white paint
        (:func:`white_from_hsv`, its level from the whole band) without the
        :data:`WHITE_EDGE_SKIP` of the width on the yellow line's side, its line-shaped blob
        group nearest the road (:func:`edge_line_side`)."""
        _check_lane(lane)
        w = self.w
        if not self.band.shape[0]:
            return None, None
        white = white_from_hsv(self.hsv, s_max, v_min, WHITE_CONTRAST, w)
        if lane == "right":
            white[:, : int(WHITE_EDGE_SKIP * w)] = 0
        else:
            white[:, int((1.0 - WHITE_EDGE_SKIP) * w):] = 0
        return track_line(white, _scaled(MIN_PIXELS, self.h, w), w, self.r0, 0, pick=edge_line_side(lane),
                          image_shape=(self.h, w))

    def fit(self, mask: np.ndarray, min_pixels: int, col0: int = 0) -> tuple[LineFit | None, np.ndarray | None]:
        """``linear_poly_fit(full mask, min_pixels)`` of a band's ``mask`` (at column ``col0``),
        and the tracked line's pixels (band-sized mask or None)."""
        return track_line(mask, min_pixels, self.w, self.r0, col0, image_shape=(self.h, self.w))

    def fit_edge(self, edge: tuple[LineFit | None, np.ndarray | None], min_pixels: int) -> LineFit | None:
        """:meth:`fit` (``linear_poly_fit``) of :meth:`white_edge`'s line (``edge``: its fit and
        pixels). Tracked again, its pixels give back the outlines of the group it was picked as
        (the islands in its holes are no outlines of their own), the same blobs in the same
        order, one group again (each joins it as before) of as many pixels: while ``min_pixels``
        asks for no more than the edge was tracked with, its fit is the per-row fit of the line's
        pixels, without a second search (the edge's own fit, for as many pixels)."""
        fit, line = edge
        if line is None:
            return None
        tracked = _scaled(MIN_PIXELS, self.h, self.w)
        if int(min_pixels) > tracked:
            return self.fit(line, min_pixels)[0]
        return fit if int(min_pixels) == tracked else _fit_rows(line, min_pixels, self.r0, 0)

    def full(self, mask: np.ndarray | None, col0: int = 0) -> np.ndarray:
        """The frame-sized uint8 mask of a band's ``mask`` (at column ``col0``; None: all zeros)."""
        return _paste(mask, (self.h, self.w), self.r0, col0)


def white_edge_mask(color: np.ndarray, lane: str, s_max: int = WHITE_S_MAX, v_min: int = WHITE_V_MIN) -> np.ndarray:
    """The backup line: the lane's own white edge line (on the far side of the yellow line's
    region), the white line-shaped blob nearest the road (:func:`edge_line_mask`: a brightly lit
    floor beyond the edge line is not taken for it); uint8, the frame's size (:meth:`LaneBand.white_edge`)."""
    band = LaneBand.of(color)
    return band.full(band.white_edge(lane, s_max, v_min)[1])


def detect_lane(
    color: np.ndarray,
    lane: str = "right",
    hsv_min: Sequence[int] = YELLOW_HSV_MIN,
    hsv_max: Sequence[int] = YELLOW_HSV_MAX,
    min_pixels: int = MIN_PIXELS,
    white_backup: bool = True,
    row_min: float | int | None = None,
    white_s_max: int = WHITE_S_MAX,
    white_v_min: int = WHITE_V_MIN,
    white_contrast: int = WHITE_CONTRAST,
) -> LaneDetection:
    """imageSelector -> colorThresholdingHSV -> line blobs -> linearPolyFit on the yellow line;
    when no yellow blob is a line of ``min_pixels`` pixels (for 640 x 480; scaled with the image
    area) and ``white_backup``, the same on the white edge line; else "no line" (fit None).

    The region is cropped before the one HSV conversion both colours share.
    """
    _check_lane(lane)
    lo, hi = check_hsv(hsv_min, "hsv_min"), check_hsv(hsv_max, "hsv_max")
    img = _check_bgr(color)
    h, w = img.shape[:2]
    r0 = region_row(h, row_min)
    need = _scaled(min_pixels, h, w)
    if r0 >= h:
        empty = np.zeros((h, w), np.uint8)
        return LaneDetection(None, None, 0, 0, empty, empty)
    hsv = cv2.cvtColor(img[r0:], cv2.COLOR_BGR2HSV)
    c0, c1 = region_columns(w, lane, "yellow")
    ymask = in_hsv_range(hsv[:, c0:c1], lo, hi)
    ny = int(cv2.countNonZero(ymask))
    fit, line = track_line(ymask, need, w, r0, c0) if ny >= need else (None, None)
    yellow_full = _paste(ymask, (h, w), r0, c0)
    if fit is not None:
        return LaneDetection(fit, "yellow", ny, 0, _paste(line, (h, w), r0, c0), yellow_full)
    if not white_backup:
        return LaneDetection(None, None, ny, 0, yellow_full, yellow_full)
    c0w, c1w = region_columns(w, lane, "white")
    wmask = white_from_hsv(hsv[:, c0w:c1w], white_s_max, white_v_min, white_contrast, w)
    nw = int(cv2.countNonZero(wmask))
    fit, line = track_line(wmask, need, w, r0, c0w, pick=edge_line_side(lane)) if nw >= need else (None, None)
    if fit is None:
        return LaneDetection(None, None, ny, nw, yellow_full, yellow_full)
    return LaneDetection(fit, "white", ny, nw, _paste(line, (h, w), r0, c0w), yellow_full)


LANE_OVERLAYS = (("the tracked line's pixels (HSV mask)", "red", "pixels"),
                 ("the line fitted to them", "lime", "line"),
                 ("the obstacle window (depth averaged in it)", "red", "box"))
"""What :func:`lane_overlay` draws, as (meaning, matplotlib colour, kind) for a figure's legend."""


def lane_caption(det: LaneDetection) -> str:
    return f"tracking the {det.source} line" if det.source else "no line found"


def lane_overlay(color: np.ndarray, det: LaneDetection, box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """The processed frame without a caption: the tracked line's pixels in red (Figure 58), the
    fitted line in green, the obstacle window (``box``) in red (:data:`LANE_OVERLAYS`). BGR uint8."""
    img = lane_mask(color, det.mask if det.mask is not None else np.zeros(color.shape[:2], np.uint8))
    if det.fit is not None:
        v0, v1 = det.fit.rows
        p0 = (round(det.fit.column_at(v0)), v0)
        p1 = (round(det.fit.column_at(v1)), v1)
        cv2.line(img, p0, p1, (0, 255, 0), 2, cv2.LINE_AA)
    if box is not None:
        cv2.rectangle(img, (box[0], box[1]), (box[2] - 1, box[3] - 1), (0, 0, 255), 2)
    return img


def lane_image(color: np.ndarray, det: LaneDetection, box: tuple[int, int, int, int] | None = None,
               text: str | None = None) -> np.ndarray:
    """:func:`lane_overlay` under a caption bar (for recordings and live frames). BGR uint8."""
    img = lane_overlay(color, det, box)
    _h, w = img.shape[:2]
    bar = np.full((28, w, 3), 255, np.uint8)
    caption = text or lane_caption(det)
    cv2.putText(bar, caption, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, img])
