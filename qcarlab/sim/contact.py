"""Contact between the simulated car and its world: collisions and leaving the world, from the true pose.

The simulator does not model contact, so it is checked from the true pose: the exact distance
between the car's footprint (a ``length`` x ``width`` = 0.425 x 0.192 m rectangle about its
centre) and every solid of the world that reaches below the car's roof (walls, boxes, posts, sign
plates: :meth:`World.static_solids <qcarlab.sim.world.World.static_solids>`) and every ball at
that instant (as a circle of the ball's radius). Polygons are compared edge by edge (a
separating-axis test for crossing, else the nearest vertex-edge distance, which is exact for
disjoint convex pieces), circles by the distance from their centre to the rectangle. A distance
of 0 is a collision.

- :class:`Clearance`: the distance itself, at any pose;
- :class:`Contact`: the collision or the exit at a pose, cheap to ask every tick: after a check
  that found the nearest solid ``c`` m away, the next full check waits until the footprint may
  have moved ``c`` (displacement plus half-diagonal x heading change), so a car in open space
  costs one hypot a check. :meth:`SimCar.contact <qcarlab.car.sim.SimCar.contact>` asks it about
  the car's own pose (the referee of the labs, :mod:`qcarlab.experiments.safety`, and the
  gymnasium environment, :mod:`qcarlab.gym`, end a run with it).

    >>> from qcarlab.sim.world import load_world
    >>> from qcarlab.sim.contact import Contact
    >>> Contact(load_world("hallway")).check(0.0, 0.0, -1.5708) is None     # the start is free
    True
"""

from __future__ import annotations

import math
import sys
from typing import Any, NamedTuple

import numpy as np

from qcarlab.constants import DEFAULT_PARAMS, QCarParams

__all__ = ["Clearance", "Contact", "ContactEvent"]


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

    def __call__(self, x: float, y: float, yaw: float, t: float = 0.0,
                 balls: bool = True) -> tuple[float, tuple[float, float] | None]:
        """The clearance at pose (x, y, yaw) and time ``t`` (the balls' positions; ``balls=False``
        leaves them out) and the centre of the nearest piece."""
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
        if balls:
            return self._nearer(self.circles_at(t), x, y, c, s, best, where)
        return self._nearer(self.circles, x, y, c, s, best, where)

    def circles_at(self, t: float) -> np.ndarray:
        """The static circles (posts) and the balls at ``t``, (n, 3): x, y, radius."""
        balls = self.world.obstacles_at(t)
        if not balls:
            return self.circles
        return np.vstack([self.circles, [(b.x, b.y, b.radius) for b in balls]])

    def balls(self, x: float, y: float, yaw: float, t: float = 0.0) -> tuple[float, tuple[float, float] | None]:
        """The clearance to the balls alone at ``t`` (``inf`` when there are none)."""
        balls = self.world.obstacles_at(t)
        if not balls:
            return math.inf, None
        return self._nearer(np.array([(b.x, b.y, b.radius) for b in balls], dtype=float), x, y,
                            math.cos(yaw), math.sin(yaw), math.inf, None)

    def _nearer(self, circles: np.ndarray, x: float, y: float, c: float, s: float, best: float,
                where: tuple[float, float] | None) -> tuple[float, tuple[float, float] | None]:
        """(best, where) or the nearest of ``circles``, when strictly nearer."""
        if len(circles):
            q = self._to_body(circles[:, :2], x, y, c, s)
            d = np.maximum(self._point_rect(q) - circles[:, 2], 0.0)
            k = int(np.argmin(d))
            if d[k] < best:
                best, where = float(d[k]), (float(circles[k, 0]), float(circles[k, 1]))
        return best, where


class ContactEvent(NamedTuple):
    """A collision (``kind`` = "collision") or the car leaving the world (``"left_world"``)."""

    kind: str
    x: float  # the car's centre, m
    y: float
    yaw: float  # rad
    t: float  # the simulator's time, s
    obstacle: tuple[float, float] | None = None  # a collision: the centre of the piece touched


class Contact:
    """The collision or the exit of a car at a pose in ``world``: ``check(x, y, yaw, t)``.

    Leaving the world is leaving the box that holds its floor and every static shape
    (:attr:`World.bounds <qcarlab.sim.world.World.bounds>`). ``min_clearance`` is the smallest
    clearance (m) a full check found so far. Built for one run: the skip between full checks
    assumes the poses asked about follow a path (call :meth:`forget` after a jump).
    """

    def __init__(self, world: Any, params: QCarParams = DEFAULT_PARAMS):
        self.world = world
        self.clearance = Clearance(world, params)
        self.dynamic = bool(world.balls)
        self.half_diag = math.hypot(params.length, params.width) / 2.0
        self.box = tuple(world.bounds)
        self.min_clearance = math.inf
        self._at: tuple[float, float, float] | None = None  # pose of the last full check
        self._free = 0.0  # the clearance found there

    def forget(self) -> None:
        """Forget the last full check (the next pose asked about need not follow the last)."""
        self._at, self._free = None, 0.0

    def check(self, x: float, y: float, yaw: float, t: float = 0.0) -> ContactEvent | None:
        """The collision or exit of the car's footprint at (x, y, yaw) at time ``t`` (the balls'
        positions), or None when it is free and inside the world."""
        x0, y0, x1, y1 = self.box
        if not (x0 <= x <= x1 and y0 <= y <= y1):
            return ContactEvent("left_world", x, y, yaw, t)
        if self._at is not None:
            ax, ay, ayaw = self._at
            dyaw = abs(math.atan2(math.sin(yaw - ayaw), math.cos(yaw - ayaw)))
            if math.hypot(x - ax, y - ay) + self.half_diag * dyaw < self._free:
                if not self.dynamic:
                    return None
                clear, where = self.clearance.balls(x, y, yaw, t)  # the static solids are farther
                if clear < self.min_clearance:
                    self.min_clearance = clear
                return ContactEvent("collision", x, y, yaw, t, where) if clear <= 0.0 else None
        clear, where = self.clearance(x, y, yaw, t, balls=False)
        self._at, self._free = (x, y, yaw), clear
        if self.dynamic:  # the balls, nearer only when strictly nearer (as Clearance with them)
            ball, at = self.clearance.balls(x, y, yaw, t)
            if ball < clear:
                clear, where = ball, at
        if clear < self.min_clearance:
            self.min_clearance = clear
        if clear <= 0.0:
            return ContactEvent("collision", x, y, yaw, t, where)
        return None
