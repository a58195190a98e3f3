"""Stop signs in any camera image (``qcarlab detect stop-sign``): every sign in the frame with a box
and a score, by one of two methods.

    >>> from qcarlab.perception.stop_signs import detect_stop_signs
    >>> [s.as_dict() for s in detect_stop_signs(cv2.imread("lab.jpg"), method="hough")]
    [{'box': [271, 113, 32, 34], 'score': 0.71}]

``method="hsv"`` (the sheet's, sheet 5.1): red with the hue wrapping through 0
(``color_thresholding_hsv``), the blobs of the mask (``find_objects``, all of them, not only the
largest), each checked for a stop sign's shape (:mod:`qcarlab.perception.sign_shape`: aspect,
extent, solidity, the letters; a score of at least :data:`MIN_SCORE`). With the default range the sheet's floors come first (S and V
from 100); when no blob passes, a dim pass with S from 60 and V from 40 (hue 168..15) looks
again: a sign in the shade or against the light reads V 70..110 on the car's CSI cameras. A
range given by the user is used as it is, alone.

``method="hough"`` (the race-car report's, seed 003): circles in the grey image
(``cv2.HoughCircles``, 5x5 Gaussian blur first; at half size when the image is 400 px or more
on its short side: the accumulator's cost grows with the radii searched), and for each of the
:data:`MAX_CIRCLES` best-voted the share of red pixels (the dim range) inside 0.85 of its
radius; a circle wholly in view with at least :data:`MIN_RED_SHARE` red is a sign
(the letters and the rim are white: a sign's share is 0.6..0.95; a big circle must keep some
white: at most :data:`~qcarlab.perception.sign_shape.MAX_RED_FILL`), and at most
:data:`MAX_RED_AROUND` red in a ring just outside it (1.1..1.35 radii): a sign stands out from
what is behind it, a circle drawn on a red-brown floor does not. The score is the red share.

Overlapping detections keep the best (a box whose centre lies in a better one is dropped).
With ``depth`` (aligned, metres) each sign gets the sheet's ``calculate_distance`` at its centre.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from qcarlab.errors import InputError
from qcarlab.perception.sign_shape import ASPECT, LETTER_SIZE, MAX_RED_FILL, blob_shape, sign_score, sign_shape_ok
from qcarlab.perception.stop_sign import (
    RED_HSV_MAX,
    RED_HSV_MIN,
    WINDOW,
    calculate_distance,
    check_hsv,
    in_hsv_range,
)

__all__ = ["DIM_HSV_MAX", "DIM_HSV_MIN", "METHODS", "MIN_RED_SHARE", "SignBox", "circle_hough", "detect_stop_signs",
           "red_share", "sign_blobs", "signs_image"]

METHODS = ("hsv", "hough")
DIM_HSV_MIN = (168, 60, 40)  # the dim pass: red or orange-red, weakly saturated, dark
DIM_HSV_MAX = (15, 255, 255)
MIN_AREA = 150  # px, the sheet's (more on an image larger than 640 x 480, scaled with the area)
MIN_SCORE = 0.7  # hsv: a blob must score this on sign_score (cut blobs can, just)
MIN_RED_SHARE = 0.5  # hough: the share of red inside a circle that makes it a sign ...
RING = (1.1, 1.35)  # ... and round it (this ring, in radii) at most
MAX_CIRCLES = 40  # hough: the best-voted circles looked at
MAX_RED_AROUND = 0.3  # this share: a sign stands out from what is behind it, a red floor does not


@dataclass(frozen=True)
class SignBox:
    """One stop sign: box (x, y, w, h) px, centre (u, v) px, score 0..1, red pixels, the method
    and (with a depth image) the distance in m (0.0 = no depth there)."""

    bbox: tuple[int, int, int, int]
    centre: tuple[float, float]
    score: float
    area: int
    method: str
    distance: float | None = None

    def as_dict(self) -> dict:
        out = {"box": list(self.bbox), "score": round(float(self.score), 3)}
        if self.distance is not None:
            out["distance"] = round(float(self.distance), 3)
        return out


def _check_image(color: np.ndarray) -> np.ndarray:
    img = np.asarray(color)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8 or min(img.shape[:2]) < 8:
        raise InputError(f"expected a BGR uint8 image (H, W, 3) at least 8 px a side, got {img.dtype} {img.shape}")
    return img


def _min_area(min_area: int | None, h: int, w: int) -> int:
    if min_area is not None:
        return max(1, int(min_area))
    return max(MIN_AREA, int(round(MIN_AREA * h * w / (640.0 * 480.0))))


def _suppress(found: list[SignBox]) -> list[SignBox]:
    """Best first; a box whose centre lies inside a kept one is dropped."""
    kept: list[SignBox] = []
    for s in sorted(found, key=lambda s: -s.score):
        u, v = s.centre
        if any(k.bbox[0] <= u <= k.bbox[0] + k.bbox[2] and k.bbox[1] <= v <= k.bbox[1] + k.bbox[3] for k in kept):
            continue
        kept.append(s)
    return kept


def sign_blobs(mask: np.ndarray, min_area: int) -> list[SignBox]:
    """The blobs of a red ``mask`` with at least ``min_area`` pixels shaped like a stop sign."""
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    found = []
    H, W = mask.shape
    for k in np.nonzero(stats[1:, cv2.CC_STAT_AREA] >= min_area)[0] + 1:
        x, y, w, h, area = (int(v) for v in stats[k])
        cut = x <= 0 or y <= 0 or x + w >= W or y + h >= H
        if not cut and not ASPECT[0] <= w / h <= ASPECT[1]:  # cheap first: no outline needed
            continue
        shape = blob_shape(labels, int(k), (x, y, w, h), area)
        if sign_shape_ok(shape) and sign_score(shape) >= MIN_SCORE:
            found.append(SignBox((x, y, w, h), (float(centroids[k][0]), float(centroids[k][1])), sign_score(shape),
                                 area, "hsv"))
    return _suppress(found)


def circle_hough(color: np.ndarray) -> np.ndarray:
    """The race-car report's Circle Hough Transform: the circles of a BGR image as an (n, 3) array of
    (u, v, r) px, best-voted first (``cv2.HoughCircles`` on the grey image after a 5x5 Gaussian blur,
    at half size when the image is 400 px or more on its short side); (0, 3) when there is none."""
    img = np.asarray(color)
    h, w = img.shape[:2]
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    k = 2 if min(h, w) >= 400 else 1  # the accumulator is costly: big images are searched at half size
    if k > 1:
        grey = cv2.resize(grey, (w // k, h // k), interpolation=cv2.INTER_AREA)
    grey = cv2.GaussianBlur(grey, (5, 5), 1.5)
    side = min(grey.shape)
    r_min = max(5, side // 50)
    circles = cv2.HoughCircles(grey, cv2.HOUGH_GRADIENT, dp=1.2, minDist=max(8, side // 12), param1=120,
                               param2=22, minRadius=r_min, maxRadius=max(r_min + 1, side // 2))
    if circles is None:
        return np.zeros((0, 3))
    return np.asarray(circles, np.float64).reshape(-1, 3) * k


def red_share(color: np.ndarray, circle, hsv_min: Sequence[int] = DIM_HSV_MIN,
              hsv_max: Sequence[int] = DIM_HSV_MAX) -> float:
    """The report's colour check: the share (0..1) of the pixels within 0.85 radii of ``circle``
    ((u, v, r) px) whose HSV is red (``hsv_min``..``hsv_max``, the hue wrapping through 0); 0 for a
    circle not wholly in view. A stop sign's is 0.6..0.95 (its letters and rim are white)."""
    img = np.asarray(color)
    h, w = img.shape[:2]
    cx, cy, r = (float(c) for c in circle[:3])
    if not (r > 0 and cx - r >= -1 and cy - r >= -1 and cx + r <= w and cy + r <= h):
        return 0.0
    R = 0.85 * r
    x0, y0 = max(0, int(cx - R)), max(0, int(cy - R))
    x1, y1 = min(w, int(np.ceil(cx + R)) + 1), min(h, int(np.ceil(cy + R)) + 1)
    if x1 - x0 < 1 or y1 - y0 < 1:
        return 0.0
    red = in_hsv_range(cv2.cvtColor(np.ascontiguousarray(img[y0:y1, x0:x1]), cv2.COLOR_BGR2HSV), hsv_min, hsv_max)
    disc = ((np.arange(y0, y1) - cy) ** 2)[:, None] + ((np.arange(x0, x1) - cx) ** 2)[None, :] <= R * R
    n = int(np.count_nonzero(disc))
    return float(np.count_nonzero((red != 0) & disc)) / n if n else 0.0


def _hough(img: np.ndarray, red: np.ndarray, min_area: int) -> list[SignBox]:
    h, w = img.shape[:2]
    circles = circle_hough(img)
    found = []
    # OpenCV returns the circles best-voted first: the first MAX_CIRCLES are plenty for the signs
    for cx, cy, r in circles[:MAX_CIRCLES]:
        if cx - r < -1 or cy - r < -1 or cx + r > w or cy + r > h:  # the whole sign must be in view
            continue
        R = RING[1] * r
        x0, y0 = max(0, int(cx - R)), max(0, int(cy - R))
        x1, y1 = min(w, int(np.ceil(cx + R)) + 1), min(h, int(np.ceil(cy + R)) + 1)
        if x1 - x0 < 3 or y1 - y0 < 3:
            continue
        dy = (np.arange(y0, y1) - cy) ** 2
        dx = (np.arange(x0, x1) - cx) ** 2
        d2 = dy[:, None] + dx[None, :]
        red_here = red[y0:y1, x0:x1] != 0
        disc = d2 <= (0.85 * r) ** 2
        ring = (d2 >= (RING[0] * r) ** 2) & (d2 <= R * R)
        n_disc = int(np.count_nonzero(disc))
        if n_disc == 0:
            continue
        red_in = int(np.count_nonzero(red_here & disc))
        share = red_in / n_disc
        if share < MIN_RED_SHARE or (2 * r >= LETTER_SIZE and share > MAX_RED_FILL):
            continue
        around = np.count_nonzero(red_here & ring) / max(1, int(np.count_nonzero(ring)))
        if around > MAX_RED_AROUND:
            continue
        box = (int(round(cx - r)), int(round(cy - r)), int(round(2 * r)), int(round(2 * r)))
        found.append(SignBox(box, (float(cx), float(cy)), round(share, 3), red_in, "hough"))
    return _suppress(found)


def detect_stop_signs(
    color: np.ndarray,
    method: str = "hsv",
    hsv_min: Sequence[int] | None = None,
    hsv_max: Sequence[int] | None = None,
    min_area: int | None = None,
    depth: np.ndarray | None = None,
    window: int = WINDOW,
) -> list[SignBox]:
    """Every stop sign in a BGR image, best first (module docstring). ``hsv_min``/``hsv_max``:
    the red range (default: the sheet's, then the dim pass); ``min_area`` px (default 150, scaled
    up with the area of a larger image); ``depth`` adds each sign's distance."""
    if method not in METHODS:
        raise InputError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    img = _check_image(color)
    h, w = img.shape[:2]
    area = _min_area(min_area, h, w)
    custom = hsv_min is not None or hsv_max is not None
    lo = check_hsv(hsv_min if hsv_min is not None else RED_HSV_MIN, "hsv_min")
    hi = check_hsv(hsv_max if hsv_max is not None else RED_HSV_MAX, "hsv_max")
    if lo[1] > hi[1] or lo[2] > hi[2]:
        raise InputError(f"hsv_min {lo} is above hsv_max {hi} in saturation or value")
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    if method == "hsv":
        mask = in_hsv_range(hsv, lo, hi)
        found = sign_blobs(mask, area)
        if not found and not custom:
            mask = in_hsv_range(hsv, DIM_HSV_MIN, DIM_HSV_MAX)
            found = sign_blobs(mask, area)
    else:
        mask = in_hsv_range(hsv, lo, hi) if custom else in_hsv_range(hsv, DIM_HSV_MIN, DIM_HSV_MAX)
        found = _hough(img, mask, area)
    if depth is not None:
        d = np.asarray(depth)
        if d.shape[:2] != (h, w):
            raise InputError(f"the depth image is {d.shape[1]}x{d.shape[0]}, the colour image {w}x{h}: they must be aligned")
        out = []
        for s in found:
            dist = calculate_distance(d, s.centre, window, mask=mask)
            if dist == 0.0:
                dist = calculate_distance(d, s.centre, window)
            out.append(SignBox(s.bbox, s.centre, s.score, s.area, s.method, dist))
        found = out
    return found


def signs_image(frame: np.ndarray, signs: list[SignBox], method: str) -> np.ndarray:
    """The frame with a box, score (and distance) per sign, and a caption bar. BGR uint8."""
    img = np.ascontiguousarray(frame).copy()
    h, w = img.shape[:2]
    thick = max(2, w // 320)
    for s in signs:
        x, y, bw, bh = s.bbox
        cv2.rectangle(img, (x, y), (x + bw - 1, y + bh - 1), (0, 255, 0), thick)
        label = f"{s.score:.2f}" + (f" {s.distance:.2f} m" if s.distance else "")
        cv2.putText(img, label, (x, max(12, y - 4)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 255, 0), 1, cv2.LINE_AA)
    bar = np.full((28, w, 3), 255, np.uint8)
    text = f"{len(signs)} stop sign{'s' if len(signs) != 1 else ''} ({method})" if signs else f"no stop sign ({method})"
    cv2.putText(bar, text, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, img])
