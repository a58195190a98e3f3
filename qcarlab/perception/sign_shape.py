"""Is this red blob shaped like a stop sign? Measures of one blob of a mask, and the check.

A stop sign is a red octagon (a disc from afar) with white letters. For the blob's outline (its
outer contour, holes filled) of ``filled`` pixels inside a ``w`` x ``h`` bounding box:

    aspect   = w / h                    # 1 face-on; a sign seen 50 deg to the side: 0.64
    extent   = filled / (w h)           # octagon 0.83, disc 0.79, rectangle 1, triangle 0.5
    solidity = filled / hull pixels     # convex shapes 1; a car's outline, a floor patch less
    red_fill = red pixels / filled      # the letters are holes: < 1 on a near sign

:func:`sign_shape_ok` keeps ``aspect`` in 0.6..1.6, ``extent`` in 0.62..0.95 and ``solidity``
>= 0.88; a blob at least :data:`LETTER_SIZE` px across must also have its letters (``red_fill``
<= 0.97): a red traffic light's lamp, a car's red body panel or a colour map's red is a solid
blob. A blob cut by the image edge is judged on what shows (convex, compact, letters when big;
not its aspect), so a sign leaving the view is still read while a red floor is not.
:func:`sign_score` ranks candidates in 0..1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["BlobShape", "blob_shape", "sign_score", "sign_shape_ok"]

ASPECT = (0.6, 1.6)
EXTENT = (0.62, 0.95)
MIN_SOLIDITY = 0.88
LETTER_SIZE = 40  # px: a blob this wide and tall shows the letters as holes
MAX_RED_FILL = 0.97


@dataclass(frozen=True)
class BlobShape:
    """The shape measures of one blob (module docstring) and whether it touches the image edge."""

    bbox: tuple[int, int, int, int]
    area: int  # red pixels
    filled: int
    hull: int
    cut: bool

    @property
    def aspect(self) -> float:
        return self.bbox[2] / max(1, self.bbox[3])

    @property
    def extent(self) -> float:
        return self.filled / max(1, self.bbox[2] * self.bbox[3])

    @property
    def solidity(self) -> float:
        return self.filled / max(1, self.hull)

    @property
    def red_fill(self) -> float:
        return self.area / max(1, self.filled)


def blob_shape(labels: np.ndarray, label: int, bbox: tuple[int, int, int, int], area: int) -> BlobShape:
    """The :class:`BlobShape` of blob ``label`` of a label image (``cv2.connectedComponents``),
    whose bounding box is ``bbox`` (x, y, w, h) and red pixel count ``area``."""
    x, y, w, h = (int(v) for v in bbox)
    H, W = labels.shape
    sub = np.zeros((h + 2, w + 2), np.uint8)  # a 1 px margin: contours never touch the crop edge
    sub[1:-1, 1:-1][labels[y:y + h, x:x + w] == label] = 255
    contours, _ = cv2.findContours(sub, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cut = x <= 0 or y <= 0 or x + w >= W or y + h >= H
    if not contours:
        return BlobShape((x, y, w, h), int(area), int(area), int(area), cut)
    outline = max(contours, key=cv2.contourArea)
    canvas = np.zeros_like(sub)
    cv2.drawContours(canvas, [outline], -1, 255, cv2.FILLED)
    filled = int(cv2.countNonZero(canvas))
    canvas[:] = 0
    cv2.fillConvexPoly(canvas, cv2.convexHull(outline), 255)
    hull = int(cv2.countNonZero(canvas))
    return BlobShape((x, y, w, h), int(area), max(filled, int(area)), max(hull, filled, int(area)), cut)


def sign_shape_ok(s: BlobShape, judge_cut: bool = True, letters: bool = True) -> bool:
    """True when the blob is shaped like a stop sign (module docstring). A blob cut by the image
    edge is judged on what shows: convex and compact (solidity, extent), letters when it is big;
    its aspect is whatever the edge left. ``judge_cut=False`` lets every cut blob pass (the
    lab's ``detect_stop_sign``: a sign filling the corner of the view as the car stops in front
    of it shows neither its outline nor its letters); ``letters=False`` does not ask for the
    letters (a plain red octagon, as a student may print for the lab, passes)."""
    if s.cut and not judge_cut:
        return True
    if not (EXTENT[0] <= s.extent <= EXTENT[1] or (s.cut and s.extent > EXTENT[1])):
        return False
    if not s.cut and not ASPECT[0] <= s.aspect <= ASPECT[1]:
        return False
    if s.solidity < MIN_SOLIDITY:
        return False
    if letters and min(s.bbox[2], s.bbox[3]) >= LETTER_SIZE and s.red_fill > MAX_RED_FILL:
        return False
    return True


def sign_score(s: BlobShape) -> float:
    """0..1: how sign-like (aspect near 1, extent near an octagon's 0.83, solidity near 1); the
    mean of the three closeness terms (a cut blob's aspect term is 0.5: unknown)."""
    a = 0.5 if s.cut else 1.0 - min(1.0, abs(math.log(max(s.aspect, 1e-6))) / math.log(ASPECT[1]))
    e = 1.0 - min(1.0, abs(s.extent - 0.81) / 0.19)
    return round((a + e + max(0.0, min(1.0, s.solidity))) / 3.0, 3)
