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
- :class:`PathClearance`: the same numbers for poses that follow a path (a run's every tick),
  for a few edges' arithmetic a tick;
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

__all__ = ["Clearance", "Contact", "ContactEvent", "PathClearance"]


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
        return _point_rect(q[:, 0], q[:, 1], self.a, self.b)

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
            _, per_poly = self._polygon_distances(x, y, c, s)
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

    def _polygon_distances(self, x, y, c, s) -> tuple[np.ndarray, np.ndarray]:
        """(every edge's distance from the footprint, every polygon's: its nearest edge's, or 0 when
        it holds the car's centre) at the pose (x, y, cos, sin of the heading); at several poses at
        once when they are arrays (P,): then (P, edges) and (P, polygons), each row as one pose's."""
        x, y = np.asarray(x, dtype=float)[..., None], np.asarray(y, dtype=float)[..., None]
        c, s = np.asarray(c, dtype=float)[..., None], np.asarray(s, dtype=float)[..., None]
        ax, ay, bx, by = self._body_ends(self.p0, self.p1, x, y, c, s)
        d = self._edge_distances(ax, ay, bx, by)
        # the car's centre inside a polygon (no edge crossing it): even-odd rule per polygon
        crosses = ((ay > 0.0) != (by > 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            xint = ax + (0.0 - ay) * (bx - ax) / (by - ay)
        hits = np.add.reduceat((crosses & (xint > 0.0)).astype(np.int64), self._first_edge, axis=-1)
        per_poly = np.minimum.reduceat(d, self._first_edge, axis=-1)  # each polygon's edges are consecutive
        per_poly[hits % 2 == 1] = 0.0
        return d, per_poly

    @staticmethod
    def _body_ends(p0: np.ndarray, p1: np.ndarray, x, y, c, s) -> tuple:
        """Edges' ends ``p0``, ``p1`` (n, 2) in the body frame of the pose (x, y, cos, sin of the
        heading; broadcasting): ``ax, ay, bx, by``."""
        dx, dy = p0[:, 0] - x, p0[:, 1] - y
        ax, ay = c * dx + s * dy, -s * dx + c * dy
        dx, dy = p1[:, 0] - x, p1[:, 1] - y
        return ax, ay, c * dx + s * dy, -s * dx + c * dy

    def _edge_distances(self, ax, ay, bx, by) -> np.ndarray:
        """Every edge's distance from the footprint (0 where they overlap), from its body-frame ends
        ``(ax, ay)``, ``(bx, by)``: separating axes of a segment against the rectangle (x, y and the
        segment's normal), then the nearest of its ends against the rectangle and of each corner
        against it."""
        a, b = self.a, self.b
        mx, my, hx, hy = (ax + bx) / 2.0, (ay + by) / 2.0, (bx - ax) / 2.0, (by - ay) / 2.0
        sep = (np.abs(mx) > a + np.abs(hx)) | (np.abs(my) > b + np.abs(hy)) \
            | (np.abs(hx * my - hy * mx) > a * np.abs(hy) + b * np.abs(hx))
        d = np.minimum(_point_rect(ax, ay, a, b), _point_rect(bx, by, a, b))
        abx, aby = bx - ax, by - ay
        L2 = np.maximum(abx * abx + aby * aby, 1e-18)
        for cx, cy in self._corners.tolist():
            u = np.clip(((cx - ax) * abx + (cy - ay) * aby) / L2, 0.0, 1.0)
            d = np.minimum(d, np.hypot(ax + u * abx - cx, ay + u * aby - cy))
        return np.where(sep, d, 0.0)


def _point_rect(qx, qy, a: float, b: float):
    """Distance from points (qx, qy) (body frame) to the footprint rectangle of half sides a, b."""
    return np.hypot(np.maximum(np.abs(qx) - a, 0.0), np.maximum(np.abs(qy) - b, 0.0))


_hypot = np.hypot  # (on two floats: the ufunc's number, which Clearance's arrays and the kernel give)


def _hypot_of(p: float, q: float) -> float:
    """``float(np.hypot(p, q))``, the ufunc's number, without calling it when one side is 0: then
    it is the other's magnitude, exactly (C's hypot(x, +-0) = fabs(x), Annex F)."""
    if q == 0.0:
        return abs(p)
    if p == 0.0:
        return abs(q)
    return float(_hypot(p, q))


class PathClearance(Clearance):
    """:class:`Clearance` for poses that follow a path (the avoid referee's every tick): the same
    distance and nearest piece, bit for bit, at any pose, from a few edges a call.

    The footprint-to-edge distance ``D_e`` moves by at most ``m = |c - c_ref| + h |yaw - yaw_ref|``
    (``h`` the footprint's half diagonal) when the pose moves from a reference pose to the car's
    centre ``c`` and heading ``yaw``: no footprint point moves farther. So ``D_e(ref) - m`` bounds
    every edge from below. At the reference (redone once ``m`` passes :attr:`REFRESH`) every edge's
    ``D_e`` is computed with :class:`Clearance`'s arrays and sorted; at a pose after it the edges
    are taken in that order and computed one by one, as the kernel's arithmetic on floats (the
    distances' hypot picked by their squares and taken with ``np.hypot``), until the next one's
    bound exceeds the nearest found: an edge not computed is farther than it (never equal, by a
    1e-9 m margin). A polygon holding the car's centre (even-odd rule, checked for the polygons
    whose box may hold it) is at 0. The polygon first in the world's order among the nearest is
    the one reported, as :class:`Clearance` (``argmin``) does; circles and balls follow as there."""

    REFRESH = 0.1  #: m: the bound's slack after which the reference pose is redone (the avoid referee measures most ticks after the run: a refresh costs more than the few more edges a longer slack leaves)

    def __init__(self, world: Any, params: QCarParams):
        super().__init__(world, params)
        self.half_diag = math.hypot(self.a, self.b)
        self._edge_rows = [(*a, *b, int(k)) for a, b, k in zip(self.p0.tolist(), self.p1.tolist(), self.owner.tolist())]
        first = self._first_edge.tolist() + [len(self.p0)]
        self._poly_edges = [self._edge_rows[first[k]:first[k + 1]] for k in range(self.n_poly)]
        self._boxes = [(float(p[:, 0].min()), float(p[:, 1].min()), float(p[:, 0].max()), float(p[:, 1].max()))
                       for p in (self.p0[first[k]:first[k + 1]] for k in range(self.n_poly))]
        self._circle_rows = [tuple(row) for row in self.circles.tolist()]
        # each edge's frame: unit direction e, the ends' positions along it, and its line's offset
        # along the normal n = e turned left (a zero-length edge: no frame, never passed over)
        self._frames = []
        for p0x, p0y, p1x, p1y, _ in self._edge_rows:
            ln = math.hypot(p1x - p0x, p1y - p0y)
            if ln > 0.0:
                ex, ey = (p1x - p0x) / ln, (p1y - p0y) / ln
                t0, t1 = ex * p0x + ey * p0y, ex * p1x + ey * p1y
                self._frames.append((ex, ey, min(t0, t1), max(t0, t1), ex * p0y - ey * p0x))
            else:
                self._frames.append((0.0, 0.0, -math.inf, math.inf, math.inf))
        self._ref: tuple[float, float, float] | None = None
        self._order: list[tuple[float, int]] = []  # (D_e at the reference, e), nearest first
        self._boxed: list[int] = []  # polygons whose box the centre may enter before the next refresh

    def __call__(self, x: float, y: float, yaw: float, t: float = 0.0,
                 balls: bool = True) -> tuple[float, tuple[float, float] | None]:
        c, s = math.cos(yaw), math.sin(yaw)
        best, where = math.inf, None
        if self.n_poly:
            ref = self._ref
            move = math.inf if ref is None else math.hypot(x - ref[0], y - ref[1]) + self.half_diag * abs(yaw - ref[2])
            if move > self.REFRESH:
                best, k = self._reference(x, y, yaw, c, s)
            else:
                best, k = self._walk(x, y, c, s, move + 1e-9)
            where = self.pieces[k]
        return self._nearest_circle(self._rows_at(t, balls), x, y, c, s, best, where)

    def _rows_at(self, t: float, balls: bool = True) -> list:
        """The circles (x, y, radius): the posts, and the balls at ``t`` when ``balls``."""
        rows = self._circle_rows
        if balls:
            moving = self.world.obstacles_at(t)
            if moving:
                rows = rows + [(float(b.x), float(b.y), float(b.radius)) for b in moving]
        return rows

    def edges_if_clear(self, x: float, y: float, yaw: float) -> list[int] | None:
        """When every polygon is surely farther than 0 from the footprint at this pose, by the
        reference pose's bound alone, the edges that may be the nearest (the rest are farther
        than one of them, by the bound: at the reference, farther than the nearest by more than
        twice the move); else None. Surely clear: the pose is within :attr:`REFRESH` of the
        reference (so a call here would not redo it: leaving the call out changes nothing after),
        no polygon's box may hold the centre, and the nearest edge at the reference less the move
        is still > 0."""
        ref = self._ref
        if ref is None or self._boxed or not self._order:
            return None
        move = math.hypot(x - ref[0], y - ref[1]) + self.half_diag * abs(yaw - ref[2])
        nearest = self._order[0][0]
        if move > self.REFRESH or nearest - move - 1e-9 <= 0.0:
            return None
        reach = nearest + 2.0 * move + 1e-9
        edges = []
        for d_ref, e in self._order:
            if d_ref > reach:
                break
            edges.append(e)
        return edges

    def circle_clearance(self, x: float, y: float, yaw: float, t: float = 0.0) -> tuple[float, tuple[float, float] | None]:
        """The nearest circle (post, or ball at ``t``): (clearance, its centre), (inf, None) if none."""
        return self._nearest_circle(self._rows_at(t), x, y, math.cos(yaw), math.sin(yaw), math.inf, None)

    def walls_at(self, x: np.ndarray, y: np.ndarray, c: np.ndarray, s: np.ndarray, edges: list[list[int]]) -> np.ndarray:
        """The polygons' clearance at many poses at once (centres ``x``, ``y``, the heading's cos and
        sin as ``math`` gives them), each pose's over its ``edges`` (:meth:`edges_if_clear`'s): the
        number :meth:`__call__` takes before the circles."""
        counts = [len(es) for es in edges]
        pose = np.repeat(np.arange(len(edges)), counts)
        e = np.fromiter((k for es in edges for k in es), dtype=np.int64, count=sum(counts))
        d = self._edge_distances(*self._body_ends(self.p0[e], self.p1[e], x[pose], y[pose], c[pose], s[pose]))
        return np.minimum.reduceat(d, np.cumsum(counts) - counts)

    def _reference(self, x: float, y: float, yaw: float, c: float, s: float) -> tuple[float, int]:
        """Every edge's distance at this pose (Clearance's arrays), kept sorted as the new
        reference; returns (the clearance to the polygons, the first nearest polygon)."""
        d, per_poly = self._polygon_distances(x, y, c, s)
        k = int(np.argmin(per_poly))
        order = np.argsort(d, kind="stable")
        self._order = list(zip(d[order].tolist(), order.tolist()))
        self._ref = (x, y, yaw)
        reach = self.REFRESH + 1e-6
        self._boxed = [j for j, (x0, y0, x1, y1) in enumerate(self._boxes)
                       if x0 - reach <= x <= x1 + reach and y0 - reach <= y <= y1 + reach]
        return float(per_poly[k]), k

    def _walk(self, x: float, y: float, c: float, s: float, slack: float) -> tuple[float, int]:
        """The edges in the reference's order until the next one's bound passes the nearest; an
        edge whose extent is farther than the nearest by its extent's gaps is passed over without its distance."""
        best, k_best = math.inf, -1
        for k in self._boxed:
            x0, y0, x1, y1 = self._boxes[k]
            if x0 - 1e-6 <= x <= x1 + 1e-6 and y0 - 1e-6 <= y <= y1 + 1e-6 and self._holds(k, x, y, c, s):
                if 0.0 < best or (0.0 == best and k < k_best):
                    best, k_best = 0.0, k
        rows, frames, a, b = self._edge_rows, self._frames, self.a, self.b
        bound2 = (best + 1e-9) * (best + 1e-9) if best < math.inf else math.inf
        for d_ref, e in self._order:
            if d_ref - slack > best:
                break
            # the gaps between the footprint's and the edge's extents along e and along n bound
            # their distance from below: sqrt(gap_e^2 + gap_n^2)
            ex, ey, t0, t1, off = frames[e]
            ce, se = ex * c + ey * s, ey * c - ex * s
            ext = a * abs(ce) + b * abs(se)
            tc = ex * x + ey * y
            ge = max(t0 - tc - ext, tc - ext - t1, 0.0)
            gn = max(abs(ex * y - ey * x - off) - (a * abs(se) + b * abs(ce)), 0.0)
            if ge * ge + gn * gn > bound2:
                continue
            d, k = self._edge(rows[e], x, y, c, s)
            if d < best or (d == best and k < k_best):
                best, k_best = d, k
                bound2 = (best + 1e-9) * (best + 1e-9)
        return best, k_best

    def _holds(self, k: int, x: float, y: float, c: float, s: float) -> bool:
        """The car's centre inside polygon ``k``: an odd number of its edges cross the body +x axis."""
        hits = 0
        for p0x, p0y, p1x, p1y, _ in self._poly_edges[k]:
            dx, dy = p0x - x, p0y - y
            ax, ay = c * dx + s * dy, -s * dx + c * dy
            dx, dy = p1x - x, p1y - y
            bx, by = c * dx + s * dy, -s * dx + c * dy
            if (ay > 0.0) != (by > 0.0) and ax + (0.0 - ay) * (bx - ax) / (by - ay) > 0.0:
                hits += 1
        return hits % 2 == 1

    def _edge(self, row: tuple, x: float, y: float, c: float, s: float) -> tuple[float, int]:
        """(the footprint's distance to one edge, its polygon): the kernel's arithmetic; of the
        six hypots (two ends to the rectangle, four corners to the edge) only those whose squares
        tie the smallest (to 1e-12) are taken, with the ufunc's hypot."""
        p0x, p0y, p1x, p1y, k = row
        a, b = self.a, self.b
        dx, dy = p0x - x, p0y - y
        ax, ay = c * dx + s * dy, -s * dx + c * dy
        dx, dy = p1x - x, p1y - y
        bx, by = c * dx + s * dy, -s * dx + c * dy
        mx, my = (ax + bx) / 2.0, (ay + by) / 2.0
        hx, hy = (bx - ax) / 2.0, (by - ay) / 2.0
        if not ((abs(mx) > a + abs(hx)) or (abs(my) > b + abs(hy)) or (abs(hx * my - hy * mx) > a * abs(hy) + b * abs(hx))):
            return 0.0, k  # the edge crosses the footprint
        p, q = abs(ax) - a, abs(ay) - b
        p, q = (p if p > 0.0 else 0.0), (q if q > 0.0 else 0.0)
        pairs = [(p * p + q * q, p, q)]
        p, q = abs(bx) - a, abs(by) - b
        p, q = (p if p > 0.0 else 0.0), (q if q > 0.0 else 0.0)
        pairs.append((p * p + q * q, p, q))
        abx, aby = bx - ax, by - ay
        l2 = max(abx * abx + aby * aby, 1e-18)
        for cx, cy in ((a, b), (-a, b), (-a, -b), (a, -b)):
            u = ((cx - ax) * abx + (cy - ay) * aby) / l2
            u = min(max(u, 0.0), 1.0)
            p, q = ax + u * abx - cx, ay + u * aby - cy
            pairs.append((p * p + q * q, p, q))
        lim = min(pairs)[0] * (1.0 + 1e-12)
        d = math.inf
        for v, p, q in pairs:  # (every pair whose square ties the smallest, in any order: the least hypot)
            if v <= lim:
                h = _hypot_of(p, q)
                if h < d:
                    d = h
        return d, k

    def _nearest_circle(self, rows: list, x: float, y: float, c: float, s: float, best: float,
                        where: tuple[float, float] | None) -> tuple[float, tuple[float, float] | None]:
        """(best, where) or the nearest circle (x, y, radius), when strictly nearer: :meth:`_nearer` on floats."""
        a, b = self.a, self.b
        d_min, at = math.inf, None
        for cx, cy, r in rows:
            dx, dy = cx - x, cy - y
            qx, qy = c * dx + s * dy, -s * dx + c * dy
            d = max(_hypot_of(max(abs(qx) - a, 0.0), max(abs(qy) - b, 0.0)) - r, 0.0)
            if d < d_min:
                d_min, at = d, (cx, cy)
        if d_min < best:
            return d_min, at
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
