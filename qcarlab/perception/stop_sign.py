"""Stop-sign detection (lab sheet 5.1, the *RGBD Imaging* model): HSV red threshold, Image Find
Objects, depth at the sign.

    >>> from qcarlab.perception.stop_sign import detect_stop_sign
    >>> det = detect_stop_sign(frame.color, frame.depth)      # an RGBDFrame from car.read_rgbd()
    >>> det.found, det.centre, det.distance                    # True, (564.2, 116.0), 0.40 (m)

The three blocks of the sheet, one function each, numpy in -> numpy out:

1. :func:`color_thresholding_hsv`: BGR -> HSV, keep the pixels inside ``hsv_min .. hsv_max``
   (the sheet: hue of red = 0, saturation and value 100..255). **Hue is OpenCV's 0..179 scale
   (degrees / 2).** Red sits on both sides of 0, so a range whose ``H_min > H_max`` wraps round:
   ``170,100,100 .. 10,255,255`` keeps hues 170..179 *and* 0..10 (two ``cv2.inRange`` calls).
2. :func:`find_objects`: the QUARC *Image Find Objects* block: the connected blobs of the mask
   (``cv2.connectedComponentsWithStats``, 8-connected); the largest one of at least
   ``min_area`` pixels gives the centroid (u, v), the bounding box (x, y, w, h) and the area.
   With ``shape_check`` the largest one shaped like a stop sign (:mod:`~qcarlab.perception.sign_shape`);
   :func:`detect_stop_sign` checks by default.
3. :func:`calculate_distance`: the depth at the centre: the median of the valid (non-zero)
   depths in a small square window around it (the D435 reads 0 where it has no data), 0 when
   there is none, so the sheet's ``stopSign`` block sees 0 = "no sign".

:func:`detect_stop_sign` chains them into a :class:`StopSignDetection`;
:func:`detection_image` draws the sheet's Figure 49 (colour with the box | mask | depth).
Nothing here touches a car: these run on frames from the simulator, a real D435 or a file.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from qcarlab.errors import InputError

__all__ = [
    "RED_HSV_MAX",
    "RED_HSV_MIN",
    "ImageObject",
    "StopSignDetection",
    "calculate_distance",
    "depth_at",
    "color_thresholding_hsv",
    "detect_stop_sign",
    "DETECTION_OVERLAYS",
    "detection_image",
    "detection_panels",
    "find_objects",
]

#: The sheet's red: hue 0 +- 10 (OpenCV units, +-20 deg), saturation and value 100..255.
RED_HSV_MIN = (170, 100, 100)
RED_HSV_MAX = (10, 255, 255)
MIN_AREA = 150  # px: smaller red blobs are not a sign (a 0.12 m sign is ~500 px at 2.5 m)
WINDOW = 5  # px: half-size of the depth window (an 11 x 11 square)


def check_hsv(triple: Sequence[float], name: str = "hsv") -> tuple[int, int, int]:
    """An (H, S, V) triple as ints, H in 0..179 (OpenCV), S and V in 0..255; else InputError."""
    try:
        values = [float(v) for v in triple]
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected three numbers H,S,V, got {triple!r}") from None
    if len(values) != 3:
        raise InputError(f"{name}: expected three numbers H,S,V, got {len(values)}")
    h, s, v = values
    if not all(float(x).is_integer() for x in values):
        raise InputError(f"{name}: H,S,V must be whole numbers, got {triple!r}")
    if not 0 <= h <= 179:
        raise InputError(f"{name}: hue {h:g} is outside 0..179 (OpenCV hue = degrees / 2)")
    for label, x in (("saturation", s), ("value", v)):
        if not 0 <= x <= 255:
            raise InputError(f"{name}: {label} {x:g} is outside 0..255")
    return int(h), int(s), int(v)


def color_thresholding_hsv(
    image_bgr: np.ndarray,
    hsv_min: Sequence[int] = RED_HSV_MIN,
    hsv_max: Sequence[int] = RED_HSV_MAX,
) -> np.ndarray:
    """Binary mask (uint8, 255 = kept) of the pixels whose HSV lies in ``hsv_min .. hsv_max``.

    H in OpenCV's 0..179, S and V in 0..255. When ``hsv_min[0] > hsv_max[0]`` the hue range wraps
    through 0 (red): hues ``>= hsv_min[0]`` or ``<= hsv_max[0]``.
    """
    lo, hi = check_hsv(hsv_min, "hsv_min"), check_hsv(hsv_max, "hsv_max")
    if lo[1] > hi[1] or lo[2] > hi[2]:
        raise InputError(f"hsv_min {lo} is above hsv_max {hi} in saturation or value")
    img = np.asarray(image_bgr)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise InputError(f"expected a BGR uint8 image (H, W, 3), got {img.dtype} {img.shape}")
    if lo[2] > 0 and img.shape[0] > 8 and not (img[0].any() and img[-1].any()):
        # black (V = 0) is never kept: rows that are all black above and below (image_selector's
        # zeros) need no conversion (a camera's frame, lit top and bottom, is not looked through)
        rows = np.flatnonzero(img.reshape(img.shape[0], -1).max(axis=1))
        if len(rows) == 0:
            return np.zeros(img.shape[:2], np.uint8)
        r0, r1 = int(rows[0]), int(rows[-1]) + 1
        if r1 - r0 < img.shape[0]:
            out = np.zeros(img.shape[:2], np.uint8)
            out[r0:r1] = in_hsv_range(cv2.cvtColor(img[r0:r1], cv2.COLOR_BGR2HSV), lo, hi)
            return out
    return in_hsv_range(cv2.cvtColor(img, cv2.COLOR_BGR2HSV), lo, hi)


def in_hsv_range(hsv: np.ndarray, lo: Sequence[int], hi: Sequence[int]) -> np.ndarray:
    """``cv2.inRange`` on an HSV image with the hue wrapping through 0 when ``lo[0] > hi[0]``
    (``lo``/``hi`` already checked); uint8 mask, 255 = inside."""
    lo, hi = tuple(int(x) for x in lo), tuple(int(x) for x in hi)
    if lo[0] <= hi[0]:
        return cv2.inRange(hsv, lo, hi)
    upper = cv2.inRange(hsv, lo, (179, hi[1], hi[2]))
    lower = cv2.inRange(hsv, (0, lo[1], lo[2]), hi)
    return cv2.bitwise_or(upper, lower)


@dataclass(frozen=True)
class ImageObject:
    """One blob of a binary mask: centroid (u, v) px, bounding box (x, y, w, h) px, area px."""

    centroid: tuple[float, float]
    bbox: tuple[int, int, int, int]
    area: int


def find_objects(mask: np.ndarray, min_area: int = MIN_AREA, shape_check: bool = False) -> ImageObject | None:
    """The largest 8-connected blob of ``mask`` (non-zero pixels) with at least ``min_area``
    pixels, or None: QUARC's *Image Find Objects* block (centroid, bounding box, area).

    With ``shape_check`` the largest blob *shaped like a stop sign*
    (:func:`qcarlab.perception.sign_shape.sign_shape_ok`: aspect, extent, solidity), so a red
    car or a tail light is passed over for the sign behind it. A blob cut by the image edge
    passes (a sign filling the corner of the view as the car stops before it), and the letters
    are not asked for (a plain red octagon is the lab's sign too).
    """
    m = np.asarray(mask)
    if m.ndim != 2:
        raise InputError(f"find_objects: expected a 2-D mask, got shape {m.shape}")
    if m.dtype != np.uint8:
        m = (m != 0).astype(np.uint8)
    x0 = y0 = 0
    if not shape_check:  # label only the box around the red pixels (same blobs, same order): a tenth of the work
        x0, y0, bw, bh = cv2.boundingRect(m)
        if bw == 0:
            return None
        m = m[y0:y0 + bh, x0:x0 + bw]
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return None
    areas = stats[1:, cv2.CC_STAT_AREA]
    order = np.argsort(-areas, kind="stable") + 1
    for best in order:
        area = int(stats[best, cv2.CC_STAT_AREA])
        if area < max(1, int(min_area)):
            return None
        x, y, w, h = (int(stats[best, k]) for k in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH,
                                                     cv2.CC_STAT_HEIGHT))
        if shape_check:
            from qcarlab.perception.sign_shape import blob_shape, sign_shape_ok

            if not sign_shape_ok(blob_shape(labels, int(best), (x, y, w, h), area), judge_cut=False,
                                 letters=False):
                continue
        cu, cv = centroids[best]
        return ImageObject((float(cu) + x0, float(cv) + y0), (x + x0, y + y0, w, h), area)
    return None


def depth_at(
    depth: np.ndarray,
    where: Sequence[float],
    window: int = WINDOW,
    mask: np.ndarray | None = None,
) -> float:
    """Distance (m) to what is at ``where`` in the aligned depth image; 0.0 when unknown.

    ``where`` is a centre (u, v) or a bounding box (x, y, w, h), whose centre is used. The
    result is the median of the valid (> 0) depths in the (2 window + 1)^2 square around the
    centre, clipped to the image; with ``mask`` only the pixels the mask keeps count.
    """
    d = np.asarray(depth)
    if d.ndim != 2:
        raise InputError(f"depth_at: expected a 2-D depth image, got shape {d.shape}")
    if len(where) == 4:
        x, y, w, h = (float(v) for v in where)
        u, v = x + (w - 1) / 2.0, y + (h - 1) / 2.0
    elif len(where) == 2:
        u, v = (float(c) for c in where)
    else:
        raise InputError(f"depth_at: expected (u, v) or (x, y, w, h), got {where!r}")
    if not (np.isfinite(u) and np.isfinite(v)):
        return 0.0
    H, W = d.shape
    ui, vi, r = round(u), round(v), max(0, int(window))
    u0, u1, v0, v1 = max(0, ui - r), min(W, ui + r + 1), max(0, vi - r), min(H, vi + r + 1)
    if u0 >= u1 or v0 >= v1:
        return 0.0
    patch = d[v0:v1, u0:u1]
    ok = np.isfinite(patch) & (patch > 0)
    if mask is not None:
        ok &= np.asarray(mask)[v0:v1, u0:u1] != 0
    if not ok.any():
        return 0.0
    return float(np.median(patch[ok]))


#: The sheet's block name (RGBD Imaging's distance block): the depth at the sign.
calculate_distance = depth_at


@dataclass(frozen=True)
class StopSignDetection:
    """What :func:`detect_stop_sign` found. ``distance`` is the D435's z-depth from the camera (m),
    0.0 when no sign or no depth there; ``centre``/``bbox`` in pixels (None when not found)."""

    found: bool
    centre: tuple[float, float] | None = None
    bbox: tuple[int, int, int, int] | None = None
    area: int = 0
    distance: float = 0.0
    mask: np.ndarray | None = field(default=None, repr=False, compare=False)

    def as_dict(self) -> dict:
        return {"found": self.found, "centre_px": self.centre, "bbox_px": self.bbox, "area_px": self.area,
                "distance_m": self.distance}


def detect_stop_sign(
    color: np.ndarray,
    depth: np.ndarray,
    hsv_min: Sequence[int] = RED_HSV_MIN,
    hsv_max: Sequence[int] = RED_HSV_MAX,
    min_area: int = MIN_AREA,
    window: int = WINDOW,
    shape_check: bool = True,
) -> StopSignDetection:
    """The sheet's *RGBD Imaging* chain: red mask -> largest blob -> median depth at its centroid.

    Only the red pixels of the window count, so the white letters and border never lend their
    depth (they are on the plate anyway) and a blob cut by the image edge still reads the plate.
    With ``shape_check`` (qcarlab's addition, on by default) the largest blob shaped like a sign
    (:func:`find_objects`), not a red car or a red floor. All the signs in a frame, the dim
    pass and the Hough-circle method: :func:`qcarlab.perception.stop_signs.detect_stop_signs`.
    """
    mask = color_thresholding_hsv(color, hsv_min, hsv_max)
    obj = find_objects(mask, min_area, shape_check)
    if obj is None:
        return StopSignDetection(False, mask=mask)
    dist = calculate_distance(depth, obj.centroid, window, mask=mask)
    if dist == 0.0:  # no red pixel with depth right at the centroid: fall back to the whole window
        dist = calculate_distance(depth, obj.centroid, window)
    return StopSignDetection(True, obj.centroid, obj.bbox, obj.area, dist, mask=mask)


DETECTION_OVERLAYS = (("the detected sign's box", "lime", "box"), ("its centre (the distance is read there)", "lime", "cross"))
"""What :func:`detection_panels` draws, as (meaning, matplotlib colour, kind) for a figure's legend."""


def detection_panels(color: np.ndarray, detection: StopSignDetection, depth: np.ndarray | None = None,
                     max_depth: float = 3.0) -> list[tuple[np.ndarray, str]]:
    """The sheet's Figure 49 as (BGR image, title) panels: colour with the detection box and centre,
    the thresholded mask (white = red enough), and (with ``depth``) the depth image, black at 0 m to
    white at ``max_depth``, dark purple where there is no depth."""
    img = np.ascontiguousarray(color).copy()
    h, w = img.shape[:2]
    mask = detection.mask if detection.mask is not None else np.zeros((h, w), np.uint8)
    panels = [img, cv2.cvtColor(mask, cv2.COLOR_GRAY2BGR)]
    if depth is not None:
        d = np.asarray(depth, dtype=np.float32)
        grey = np.clip(d / max_depth * 255.0, 0, 255).astype(np.uint8)
        grey[d <= 0] = 0
        dimg = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
        dimg[d <= 0] = (80, 0, 80)  # no data: dark purple
        panels.append(dimg)
    if detection.found and detection.bbox is not None:
        x, y, bw, bh = detection.bbox
        cu, cv = (round(c) for c in detection.centre)
        for p in panels:
            cv2.rectangle(p, (x, y), (x + bw - 1, y + bh - 1), (0, 255, 0), 2)
            cv2.drawMarker(p, (cu, cv), (0, 255, 0), cv2.MARKER_CROSS, 18, 2)
        text = f"stop sign {detection.distance:.2f} m" if detection.distance > 0 else "stop sign (no depth)"
    else:
        text = "no stop sign"
    labels = ["colour: " + text, "HSV threshold (mask: white = red enough)",
              f"depth: black 0 m to white {max_depth:g} m, purple = no data"]
    return list(zip(panels, labels))


def detection_image(color: np.ndarray, detection: StopSignDetection, depth: np.ndarray | None = None,
                    max_depth: float = 3.0) -> np.ndarray:
    """:func:`detection_panels` side by side, each under a caption bar (for recordings and live
    frames; ``detection.png`` is a figure with a legend). BGR uint8."""
    panels = detection_panels(color, detection, depth, max_depth)
    h, w = panels[0][0].shape[:2]
    out = []
    for p, label in panels:
        if label.startswith("depth"):
            label = "depth (darker = closer)"
        bar = np.full((28, w, 3), 255, np.uint8)
        cv2.putText(bar, label, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
        out.append(np.vstack([bar, p]))
        out.append(np.full((h + 28, 6, 3), 255, np.uint8))
    return np.hstack(out[:-1])
