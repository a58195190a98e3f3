"""Did the run stay safe? Collisions with the world and leaving it, from the simulator's truth.

The simulator does not model contact, so a run checks it itself from the true pose: the exact
distance between the car's footprint (a ``length`` x ``width`` = 0.425 x 0.192 m rectangle about
its centre) and every solid of the world that reaches below the car's roof (walls, boxes, posts,
sign plates: :meth:`World.static_solids`) and every ball at that instant (as a circle of the
ball's radius). Polygons are compared edge by edge (a separating-axis test for crossing, else the
nearest vertex-edge distance, which is exact for disjoint convex pieces), circles by the distance
from their centre to the rectangle. A distance of 0 is a collision.

:class:`WorldWatch` wraps any lab model: before each tick it ends the run (a goal missed) when the
car touches a solid or leaves the world's bounds. It is cheap: after a check that found the
nearest solid ``c`` m away, the next full check waits until the footprint may have moved ``c``
(displacement plus half-diagonal x heading change), so a car in open space costs one hypot a tick.
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np

from qcarlab.constants import QCarParams
from qcarlab.experiments.loop import STOP


class Clearance:
    """Distance (m) from the car's footprint rectangle to the nearest solid or ball of ``world``.

    ``clearance(x, y, yaw, t)`` -> (distance, (x, y) of the nearest obstacle point's piece centre);
    0 when they touch or overlap. Static geometry is flattened into edge arrays once.
    """

    def __init__(self, world: Any, params: QCarParams):
        self.a, self.b = params.length / 2.0, params.width / 2.0
        starts, ends, owner, circles = [], [], [], []
        self.pieces: list[tuple[float, float]] = []  # centre of each polygon / circle (reporting)
        for s in world.static_solids():
            if s.z0 >= params.height:  # entirely above the car's roof
                continue
            if s.kind == "polygon" and s.points is not None:
                p = np.asarray(s.points, dtype=float)
                k = len(self.pieces)
                starts.append(p)
                ends.append(np.roll(p, -1, axis=0))
                owner.append(np.full(len(p), k))
                self.pieces.append((float(p[:, 0].mean()), float(p[:, 1].mean())))
            elif s.center is not None:
                circles.append((s.center[0], s.center[1], s.radius))
        self.p0 = np.vstack(starts) if starts else np.zeros((0, 2))
        self.p1 = np.vstack(ends) if ends else np.zeros((0, 2))
        self.owner = np.concatenate(owner) if owner else np.zeros(0, int)
        self.n_poly = len(self.pieces)
        self.circles = np.asarray(circles, dtype=float).reshape(-1, 3)
        self.world = world
        self._first_edge = np.cumsum([0] + [len(p) for p in starts[:-1]]).astype(np.int64) if starts \
            else np.zeros(0, np.int64)
        self._corners = np.array([[self.a, self.b], [-self.a, self.b], [-self.a, -self.b], [self.a, -self.b]])

    def _to_body(self, pts: np.ndarray, x: float, y: float, c: float, s: float) -> np.ndarray:
        dx, dy = pts[:, 0] - x, pts[:, 1] - y
        return np.column_stack((c * dx + s * dy, -s * dx + c * dy))

    def _point_rect(self, q: np.ndarray) -> np.ndarray:
        return np.hypot(np.maximum(np.abs(q[:, 0]) - self.a, 0.0), np.maximum(np.abs(q[:, 1]) - self.b, 0.0))

    def __call__(self, x: float, y: float, yaw: float, t: float = 0.0) -> tuple[float, tuple[float, float] | None]:
        c, s = math.cos(yaw), math.sin(yaw)
        best, where = math.inf, None
        if len(self.p0) and "numba" in sys.modules:  # compiled (numba is loaded already: the sensors use it)
            from qcarlab.sim._kernels import polygon_clearance

            best, k = polygon_clearance(self.p0, self.p1, self._first_edge, self.n_poly, self._corners, self.a, self.b,
                                        x, y, c, s)
            where = self.pieces[k] if k >= 0 else None
        elif len(self.p0):
            A = self._to_body(self.p0, x, y, c, s)
            B = self._to_body(self.p1, x, y, c, s)
            m, h = (A + B) / 2.0, (B - A) / 2.0
            # separating axes of a segment against the rectangle: x, y and the segment's normal
            sep = (np.abs(m[:, 0]) > self.a + np.abs(h[:, 0])) | (np.abs(m[:, 1]) > self.b + np.abs(h[:, 1])) \
                | (np.abs(h[:, 0] * m[:, 1] - h[:, 1] * m[:, 0]) > self.a * np.abs(h[:, 1]) + self.b * np.abs(h[:, 0]))
            d = np.minimum(self._point_rect(A), self._point_rect(B))
            ab = B - A
            L2 = np.maximum((ab * ab).sum(axis=1), 1e-18)
            # each corner of the footprint against each edge, the four corners at once
            rel = (self._corners[:, None, :] - A) * ab
            u = np.clip(rel.sum(axis=2) / L2, 0.0, 1.0)
            d = np.minimum(d, np.hypot(A[:, 0] + u * ab[:, 0] - self._corners[:, 0:1],
                                       A[:, 1] + u * ab[:, 1] - self._corners[:, 1:2]).min(axis=0))
            d = np.where(sep, d, 0.0)
            # the car's centre inside a polygon (no edge crossing it): even-odd rule per polygon
            crosses = ((A[:, 1] > 0.0) != (B[:, 1] > 0.0))
            with np.errstate(divide="ignore", invalid="ignore"):
                xint = A[:, 0] + (0.0 - A[:, 1]) * ab[:, 0] / ab[:, 1]
            hits = np.bincount(self.owner[crosses & (xint > 0.0)], minlength=self.n_poly)
            per_poly = np.minimum.reduceat(d, self._first_edge)  # each polygon's edges are consecutive
            per_poly[hits % 2 == 1] = 0.0
            k = int(np.argmin(per_poly))
            best, where = float(per_poly[k]), self.pieces[k]
        circles = self.circles
        balls = self.world.obstacles_at(t)
        if balls:
            circles = np.vstack([circles, [(b.x, b.y, b.radius) for b in balls]])
        if len(circles):
            q = self._to_body(circles[:, :2], x, y, c, s)
            d = np.maximum(self._point_rect(q) - circles[:, 2], 0.0)
            k = int(np.argmin(d))
            if d[k] < best:
                best, where = float(d[k]), (float(circles[k, 0]), float(circles[k, 1]))
        return best, where




class WorldWatch:
    """Ends a run when the car collides with the world or leaves it (simulated cars in a local world)."""

    def __init__(self, world: Any, params: QCarParams, truth):
        self.world, self.truth = world, truth
        self.clearance = Clearance(world, params)
        self.dynamic = bool(world.balls)
        self.half_diag = math.hypot(params.length, params.width) / 2.0
        x0, y0, x1, y1 = world.bounds
        self.box = (x0, y0, x1, y1)
        self.event: dict[str, Any] | None = None
        self.min_clearance = math.inf
        self._at: tuple[float, float, float] | None = None  # pose of the last full check
        self._free = 0.0  # the clearance found there

    @classmethod
    def for_car(cls, car: Any, world: Any) -> WorldWatch | None:
        if world is None or car.truth() is None:
            return None
        return cls(world, car.params, car.truth)

    def check(self, t: float) -> dict[str, Any] | None:
        """The collision or exit at this tick, or None (``t`` is the run's time, for the report)."""
        tr = self.truth()
        x0, y0, x1, y1 = self.box
        if not (x0 <= tr.x <= x1 and y0 <= tr.y <= y1):
            self.event = {"kind": "left_world", "what": f"the car left the world at ({tr.x:.2f}, {tr.y:.2f}) m, "
                          f"t = {t:.2f} s", "t": t, "x": tr.x, "y": tr.y, "yaw": tr.yaw}
            return self.event
        if self._at is not None and not self.dynamic:
            ax, ay, ayaw = self._at
            dyaw = abs(math.atan2(math.sin(tr.yaw - ayaw), math.cos(tr.yaw - ayaw)))
            if math.hypot(tr.x - ax, tr.y - ay) + self.half_diag * dyaw < self._free:
                return None
        clear, where = self.clearance(tr.x, tr.y, tr.yaw, tr.t)
        self._at, self._free = (tr.x, tr.y, tr.yaw), clear
        self.min_clearance = min(self.min_clearance, clear)
        if clear <= 0.0:
            at = f" near ({where[0]:.2f}, {where[1]:.2f})" if where else ""
            self.event = {"kind": "collision", "what": f"collision at ({tr.x:.2f}, {tr.y:.2f}) m{at}, t = {t:.2f} s",
                          "t": t, "x": tr.x, "y": tr.y, "yaw": tr.yaw, "obstacle": list(where) if where else None}
            return self.event
        return None

    def wrap(self, model: Any) -> _Watched:
        return _Watched(model, self)


class _Watched:
    """A lab model whose run ends (STOP) at the first collision or exit."""

    def __init__(self, model: Any, watch: WorldWatch):
        self.model, self.watch = model, watch

    def start(self, car: Any, dt: float) -> None:
        start = getattr(self.model, "start", None)
        if callable(start):
            start(car, dt)

    def step(self, t: float, readout: Any, dt: float) -> Any:
        if self.watch.event is not None or self.watch.check(t) is not None:
            return STOP
        return self.model.step(t, readout, dt)
