"""The race-car report's depth windows (shared seeds 003): three small windows of the RealSense
depth image, at its left, middle and right, each reduced to one distance. Pure: an image in,
three numbers out.

    left, middle, right = depth_windows(frame.depth)        # metres; 0 = no data in that window

The report: "we create three small square windows, located at left, middle and right of the
image, then we calculate the mean of the depth value for each square window to represent the
distance from the car to the left wall, the front, and the right wall". For the rolling ball it
"adjust[ed] and add[ed] some detection area" ("the rolling ball is much smaller than a wall or a
door"): the windows lie in the band around the horizon of the level D435 (0.14 m up), where a
wall, a door and a 0.24 m ball all show, and the middle distance is the nearer of the middle
window and an added small window at its centre (``BALL``: 0.10 x 0.12 of the image), in which a
ball 3 m away already fills half the pixels instead of a tenth.

Each window is a rectangle in fractions of the image (``u0, u1`` across, ``v0, v1`` down); its
distance is the mean of the pixels whose depth is valid (``near < d < far``; the D435 reads 0
for no data), or 0 when fewer than ``min_valid`` of the window's pixels are valid. The middle
windows tile the band (thirds, the middle one 40 % wide): at 1 m the middle window spans
+-0.21 m, the car's width and 11 cm either side, so nothing in the car's way falls between them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from qcarlab.errors import InputError

__all__ = ["BALL", "LEFT", "MIDDLE", "RIGHT", "WINDOWS", "depth_windows", "window_boxes"]

#: (u0, u1, v0, v1) as fractions of the image width and height
LEFT = (0.0, 0.3, 0.42, 0.58)
MIDDLE = (0.3, 0.7, 0.42, 0.58)
RIGHT = (0.7, 1.0, 0.42, 0.58)
BALL = (0.45, 0.55, 0.44, 0.56)  # the added detection area at the middle
WINDOWS = (LEFT, MIDDLE, RIGHT, BALL)  # the fourth and any further ones add to the middle
NEAR, FAR = 0.1, 10.0  # m: the D435's valid range
MIN_VALID = 0.2  # fraction of a window's pixels that must have depth


def window_boxes(shape: Sequence[int], windows: Sequence[Sequence[float]] = WINDOWS) -> list[tuple[int, int, int, int]]:
    """The windows as pixel boxes ``(x0, y0, x1, y1)`` (x1, y1 exclusive) of an image of ``shape``."""
    h, w = int(shape[0]), int(shape[1])
    out = []
    for u0, u1, v0, v1 in windows:
        x0, x1 = int(round(u0 * w)), max(int(round(u1 * w)), int(round(u0 * w)) + 1)
        y0, y1 = int(round(v0 * h)), max(int(round(v1 * h)), int(round(v0 * h)) + 1)
        out.append((x0, y0, min(x1, w), min(y1, h)))
    return out


def depth_windows(depth: np.ndarray, windows: Sequence[Sequence[float]] = WINDOWS, near: float = NEAR,
                  far: float = FAR, min_valid: float = MIN_VALID) -> tuple[float, float, float]:
    """``(left, middle, right)``: for each window, the mean depth (m) of its valid pixels::

        d_k = mean{ depth[v, u] : (u, v) in window k, near < depth[v, u] < far }

    or 0.0 (no data) when fewer than ``min_valid`` of the window's pixels are valid. Windows after
    the third are added detection areas of the middle: ``middle`` is the smallest non-zero
    distance of the middle window and those.
    """
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2 or d.size == 0:
        raise InputError(f"depth_windows: expected a 2-D depth image, got shape {d.shape}")
    out = []
    for x0, y0, x1, y1 in window_boxes(d.shape, windows):
        patch = d[y0:y1, x0:x1]
        ok = (patch > near) & (patch < far)
        n = int(np.count_nonzero(ok))
        out.append(float(patch[ok].mean()) if n and n >= min_valid * patch.size else 0.0)
    if len(out) < 3:
        raise InputError(f"depth_windows: expected at least three windows, got {len(out)}")
    middle = [v for v in [out[1], *out[3:]] if v > 0.0]
    return out[0], min(middle) if middle else 0.0, out[2]
