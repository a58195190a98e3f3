"""A top-down picture of a world: floor, painted lines, walls, obstacles, signs, balls, the car.

    >>> import cv2
    >>> from qcarlab.sim.world import load_world
    >>> from qcarlab.sim.render import render_topdown
    >>> img = render_topdown(load_world("track"), px_per_m=100)
    >>> cv2.imwrite("track.png", img)

The image is BGR uint8 with +Y up and +X to the right (as the sheet's plots); ``px_per_m``
pixels per metre; a 1 m scale bar in the bottom-left corner. Optional overlays: ``path`` (an
(N, 2) reference path, drawn magenta) and ``poses`` (an (N, 2) or (N, 3) driven trajectory,
drawn red, with the car's outline at the last pose). The start pose is the green car outline.
:func:`world_to_pixel` maps world points to the image's pixel coordinates for further drawing.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from qcarlab.constants import DEFAULT_PARAMS
from qcarlab.sim.world import World, load_world

__all__ = ["render_topdown", "world_to_pixel"]

MARGIN = 0.25  # m around the world's bounds
_SHIFT = 4
_ONE = 1 << _SHIFT
PATH_COLOR = (200, 40, 200)  # BGR magenta
TRAJ_COLOR = (30, 30, 220)  # BGR red
START_COLOR = (60, 170, 40)  # BGR green


def _frame(world: World, px_per_m: float) -> tuple[float, float, int, int]:
    xmin, ymin, xmax, ymax = world.bounds
    x0, y1 = xmin - MARGIN, ymax + MARGIN
    w = int(math.ceil((xmax - xmin + 2 * MARGIN) * px_per_m))
    h = int(math.ceil((ymax - ymin + 2 * MARGIN) * px_per_m))
    return x0, y1, w, h


def world_to_pixel(world: World, points: Any, px_per_m: float = 100.0) -> np.ndarray:
    """(N, 2) world points -> (N, 2) float pixel coordinates (col, row) of :func:`render_topdown`'s image."""
    x0, y1, _, _ = _frame(world, px_per_m)
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    return np.column_stack(((p[:, 0] - x0) * px_per_m - 0.5, (y1 - p[:, 1]) * px_per_m - 0.5))


def _car_outline(x: float, y: float, yaw: float, length: float, width: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], float) * [length / 2, width / 2]
    return np.column_stack((x + local[:, 0] * c - local[:, 1] * s, y + local[:, 0] * s + local[:, 1] * c))


def _darker(color: tuple[int, int, int], f: float = 0.6) -> tuple[int, int, int]:
    return tuple(int(c * f) for c in color)  # type: ignore[return-value]


def render_topdown(
    world: World | str,
    px_per_m: float = 100.0,
    poses: Any = None,
    path: Any = None,
    t: float = 0.0,
    show_start: bool = True,
    scale_bar: bool = True,
) -> np.ndarray:
    """The world seen from above as a BGR image (see the module docstring); balls at time ``t``;
    ``scale_bar=False`` leaves the 1 m bar out (for figures that have axes in metres)."""
    w = world if isinstance(world, World) else load_world(world)
    ppm = float(px_per_m)
    if not (math.isfinite(ppm) and ppm > 0):
        raise ValueError(f"px_per_m must be a positive number, got {px_per_m!r}")
    x0, y1, W, H = _frame(w, ppm)
    img = np.empty((H, W, 3), np.uint8)
    img[:] = (255, 255, 255)

    def px(p: Any) -> np.ndarray:
        return np.round(world_to_pixel(w, p, ppm) * _ONE).astype(np.int32)

    # the floor texture, placed and scaled into the frame
    from qcarlab.sim.raster import floor_texture  # (it loads numba's kernels: only when a map is drawn)

    tex, (tx0, ty1, tppm) = floor_texture(w, min(ppm, 200.0))
    s = ppm / tppm
    A = np.array([[s, 0.0, (tx0 - x0) * ppm + 0.5 * s - 0.5], [0.0, s, (y1 - ty1) * ppm + 0.5 * s - 0.5]])
    cv2.warpAffine(tex, A, (W, H), dst=img, flags=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR,
                   borderMode=cv2.BORDER_TRANSPARENT)

    for sol in w.solids:
        if sol.kind == "polygon":
            pts = px(sol.points)
            cv2.fillPoly(img, [pts], sol.color, cv2.LINE_AA, _SHIFT)
            cv2.polylines(img, [pts], True, _darker(sol.color), 1, cv2.LINE_AA, _SHIFT)
        else:
            c = px([sol.center])[0]
            r = int(round(sol.radius * ppm * _ONE))
            cv2.circle(img, (int(c[0]), int(c[1])), r, sol.color, -1, cv2.LINE_AA, _SHIFT)
            cv2.circle(img, (int(c[0]), int(c[1])), r, _darker(sol.color), 1, cv2.LINE_AA, _SHIFT)

    for g in w.signs:
        ang = math.pi / 8 + np.arange(8) * math.pi / 4
        r = g.size / 2 / math.cos(math.pi / 8)
        oct_ = np.column_stack((g.x + r * np.cos(ang), g.y + r * np.sin(ang)))
        cv2.fillPoly(img, [px(oct_)], (16, 16, 200), cv2.LINE_AA, _SHIFT)
        cv2.polylines(img, [px(oct_)], True, (235, 235, 235), max(1, int(ppm * 0.01)), cv2.LINE_AA, _SHIFT)
        tip = (g.x + 1.6 * r * math.cos(g.facing), g.y + 1.6 * r * math.sin(g.facing))
        a, b = px([(g.x, g.y), tip])
        cv2.line(img, tuple(int(v) for v in a), tuple(int(v) for v in b), (16, 16, 200), max(1, int(ppm * 0.01)), cv2.LINE_AA, _SHIFT)

    for ball, c in zip(w.balls, w.obstacles_at(t)):
        ctr = px([(c.x, c.y)])[0]
        cv2.circle(img, (int(ctr[0]), int(ctr[1])), int(round(c.radius * ppm * _ONE)), c.color, -1, cv2.LINE_AA, _SHIFT)
        reach = min(ball.distance, 2.0) if ball.speed > 0 else 0.0
        if reach > 0:
            end = (c.x + reach * math.cos(ball.direction), c.y + reach * math.sin(ball.direction))
            a, b = px([(c.x, c.y), end])
            cv2.arrowedLine(img, tuple(int(v) for v in a), tuple(int(v) for v in b), _darker(c.color), 2, cv2.LINE_AA, _SHIFT, 0.1)

    p = DEFAULT_PARAMS
    if show_start:
        sx, sy, syaw = w.start
        out = _car_outline(sx, sy, syaw, p.length, p.width)
        cv2.polylines(img, [px(out)], True, START_COLOR, 2, cv2.LINE_AA, _SHIFT)
        a, b = px([(sx, sy), (sx + 0.35 * math.cos(syaw), sy + 0.35 * math.sin(syaw))])
        cv2.arrowedLine(img, tuple(int(v) for v in a), tuple(int(v) for v in b), START_COLOR, 2, cv2.LINE_AA, _SHIFT, 0.25)

    if path is not None:
        pts = np.asarray(path, dtype=float).reshape(-1, 2)
        if len(pts) >= 2:
            cv2.polylines(img, [px(pts)], False, PATH_COLOR, 2, cv2.LINE_AA, _SHIFT)

    if poses is not None:
        q = np.asarray(poses, dtype=float)
        q = q.reshape(-1, q.shape[-1]) if q.ndim > 1 else q.reshape(1, -1)
        if len(q) >= 2:
            cv2.polylines(img, [px(q[:, :2])], False, TRAJ_COLOR, 2, cv2.LINE_AA, _SHIFT)
        if len(q) and q.shape[1] >= 3:
            out = _car_outline(q[-1, 0], q[-1, 1], q[-1, 2], p.length, p.width)
            cv2.polylines(img, [px(out)], True, TRAJ_COLOR, 2, cv2.LINE_AA, _SHIFT)

    # 1 m scale bar
    bx, by = 10, H - 12
    blen = int(round(ppm))
    if scale_bar and blen < W - 20:
        cv2.rectangle(img, (bx - 3, by - 16), (bx + blen + 30, by + 6), (255, 255, 255), -1)
        cv2.line(img, (bx, by), (bx + blen, by), (0, 0, 0), 2)
        for xx in (bx, bx + blen):
            cv2.line(img, (xx, by - 5), (xx, by + 3), (0, 0, 0), 2)
        cv2.putText(img, "1 m", (bx + blen + 4, by + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return img
