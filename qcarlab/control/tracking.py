"""How far the car is from its reference path, and how far along it it has got.

Pure geometry on a reference polyline ``path`` of shape ``(N, 2)`` (metres):

- :func:`cross_track_errors`: distance from each driven point to the polyline (vectorised, in
  chunks so that 3000 points against a 911-point path stay within a few MB).
- :func:`progress_along`: arc-length position of each point's projection on the polyline, by
  default following the points in order and only moving forward (the butterfly starts, crosses
  itself and ends at the origin, so a plain nearest-point search would be ambiguous there).
- :class:`Polyline`: the precomputed polyline the followers share (projection with a bounded
  forward search, point at an arc length).

Used by ``experiments`` for the metrics (``rms_cross_track_m``, ``completion``) and by
``control.steering`` for the look-ahead target search. No I/O, no car.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["Polyline", "cross_track_errors", "progress_along"]

_CHUNK_ELEMENTS = 1 << 19  # points x segments per chunk (about 4 MB per float64 temporary)


class Polyline:
    """A reference polyline with its segments and cumulative arc length precomputed (O(N) once).

    ``cum[k]`` is the arc length at vertex ``k``; segment ``j`` runs from vertex ``j`` to ``j+1``.
    Zero-length segments (repeated points) are allowed. Per-call methods are O(window).
    """

    def __init__(self, path: np.ndarray) -> None:
        p = np.asarray(path, dtype=float)
        if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
            raise ValueError(f"a path must have shape (N >= 2, 2), got {p.shape}")
        self.points = p
        self.n = len(p)
        seg = np.diff(p, axis=0)
        self.seglen = np.hypot(seg[:, 0], seg[:, 1])
        self.cum = np.concatenate([[0.0], np.cumsum(self.seglen)])
        self.length = float(self.cum[-1])
        # plain Python lists: the per-tick walks touch a handful of elements, where scalar code
        # beats numpy's per-call overhead by an order of magnitude
        self._x = p[:, 0].tolist()
        self._y = p[:, 1].tolist()
        self._cum = self.cum.tolist()
        self._len = self.seglen.tolist()
        # each segment's (dx, dy, dx^2 + dy^2), the same float64 operations as computing them per
        # call (elementwise IEEE arithmetic: the same bits), so the walks only index them
        self._dx = seg[:, 0].tolist()
        self._dy = seg[:, 1].tolist()
        self._dxa, self._dya = seg[:, 0].copy(), seg[:, 1].copy()
        self._l2a = seg[:, 0] * seg[:, 0] + seg[:, 1] * seg[:, 1]
        self._l2 = self._l2a.tolist()

    # -- scalar helpers ------------------------------------------------------------------------
    def segment_projection(self, j: int, px: float, py: float) -> tuple[float, float]:
        """Closest point of segment ``j`` to ``(px, py)``: returns ``(t, distance)``, t in [0, 1]."""
        ax, ay = self._x[j], self._y[j]
        dx, dy = self._x[j + 1] - ax, self._y[j + 1] - ay
        l2 = dx * dx + dy * dy
        t = 0.0 if l2 == 0.0 else min(1.0, max(0.0, ((px - ax) * dx + (py - ay) * dy) / l2))
        return t, math.hypot(px - ax - t * dx, py - ay - t * dy)

    def walk_forward(self, j: int, px: float, py: float, max_segments: int) -> tuple[int, float, float]:
        """Project ``(px, py)`` on the path searching forward from segment ``j`` only.

        Walks from segment ``j`` to the next while the distance does not increase (the first
        local minimum ahead), at most ``max_segments`` segments. Returns ``(j, t, distance)``.
        Never moves backward and never jumps to a distant branch of a self-crossing path.
        Each segment is :meth:`segment_projection`, written out here (this runs every tick).
        """
        xs, ys, dxs, dys, l2s = self._x, self._y, self._dx, self._dy, self._l2
        last = j + max_segments
        if last > self.n - 2:  # (builtin min and max cost more than the comparison, every tick)
            last = self.n - 2
        ax, ay, dx, dy, l2 = xs[j], ys[j], dxs[j], dys[j], l2s[j]
        if l2 == 0.0:
            t = 0.0
        else:  # t = min(1, max(0, u)), written out
            u = ((px - ax) * dx + (py - ay) * dy) / l2
            t = (u if u < 1.0 else 1.0) if u > 0.0 else 0.0
        d = math.hypot(px - ax - t * dx, py - ay - t * dy)
        hypot = math.hypot
        while j < last:
            k = j + 1
            ax, ay, dx, dy, l2 = xs[k], ys[k], dxs[k], dys[k], l2s[k]
            if l2 == 0.0:
                tn = 0.0
            else:
                u = ((px - ax) * dx + (py - ay) * dy) / l2
                tn = (u if u < 1.0 else 1.0) if u > 0.0 else 0.0
            dn = hypot(px - ax - tn * dx, py - ay - tn * dy)
            if dn > d + 1e-12:
                break
            j, t, d = k, tn, dn
        return j, t, d

    def point_at(self, s: float) -> tuple[np.ndarray, int]:
        """The point at arc length ``s`` (clamped to [0, length]) and its segment index."""
        s = min(max(s, 0.0), self.length)
        j = int(np.searchsorted(self.cum, s, side="right")) - 1
        j = min(max(j, 0), self.n - 2)
        t = 0.0 if self._len[j] == 0.0 else min(1.0, (s - self._cum[j]) / self._len[j])
        a = self.points[j]
        return a + t * (self.points[j + 1] - a), j

    def walk_trajectory(self, points: np.ndarray) -> np.ndarray:
        """The segment of each point of a trajectory as :meth:`walk_forward` finds it, each walk
        starting where the previous one ended (from segment 0, no window): ``j_i = walk(j_{i-1}, p_i)``.

        Blocks of ``WALK_BLOCK`` points are compared with a window of ``WALK_WINDOW`` segments
        at once, vectorised: the walk from ``j`` stops at the first ``j`` whose next segment is
        farther, ``d_{j+1} > d_j + 1e-12``. numpy's hypot may differ from ``math.hypot`` in the
        last bit, so a comparison within 1e-13 (1 + d) of that threshold (or with a NaN) is
        decided by the scalar code, which makes the result the same as walking point by point.
        """
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        n_pts = len(pts)
        js = np.zeros(n_pts, dtype=np.intp)
        last = self.n - 2
        if last == 0 or n_pts == 0:
            return js
        ax_all, ay_all = self.points[:-1, 0], self.points[:-1, 1]
        xs, ys = pts[:, 0].tolist(), pts[:, 1].tolist()
        block, window = self.WALK_BLOCK, self.WALK_WINDOW
        i = j = 0
        while i < n_pts:
            i1 = min(i + block, n_pts)
            j0, j1 = j, min(j + window, last)  # the walk's decisions at segments j0 .. j1 - 1
            seg = slice(j0, j1 + 1)
            ax, ay, dx, dy, l2 = ax_all[seg], ay_all[seg], self._dxa[seg], self._dya[seg], self._l2a[seg]
            qx, qy = pts[i:i1, 0:1], pts[i:i1, 1:2]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = ((qx - ax) * dx + (qy - ay) * dy) / l2
            t = np.where(l2 == 0.0, 0.0, np.where(u > 0.0, np.where(u < 1.0, u, 1.0), 0.0))
            d = np.hypot(qx - ax - t * dx, qy - ay - t * dy)
            here, ahead = d[:, :-1], d[:, 1:]
            thr = here + 1e-12
            eps = 1e-13 * (1.0 + here)
            # 1: the walk stops there, 0: it moves on, 2: too close to call here (the scalar decides)
            code = np.where(ahead > thr + eps, 1, np.where(ahead < thr - eps, 0, 2))
            if j1 == last:  # the last segment: the walk always stops
                code = np.concatenate([code, np.ones((len(code), 1), dtype=code.dtype)], axis=1)
            width = code.shape[1]
            rows = code.tolist()
            k = j - j0
            for r in range(i1 - i):
                row = rows[r]
                while k < width:
                    c = row[k]
                    if c == 0 or (c == 2 and not self._stops(j0 + k, xs[i + r], ys[i + r])):
                        k += 1
                    else:
                        break
                if k == width:  # past the window: a new block from this point, where its walk got to
                    i += r
                    break
                js[i + r] = j0 + k
            else:
                i = i1
            j = j0 + k
        return js

    WALK_BLOCK = 256  # points per block of walk_trajectory
    WALK_WINDOW = 8  # segments per block (a block of a driven path passes a few; more: the next block)

    def _stops(self, j: int, px: float, py: float) -> bool:
        """walk_forward's decision at segment ``j`` (not the last): stop, the next one is farther."""
        _, d = self.segment_projection(j, px, py)
        _, dn = self.segment_projection(j + 1, px, py)
        return dn > d + 1e-12

    # -- vectorised ----------------------------------------------------------------------------
    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance to the polyline and arc length of the nearest point, for each of ``points``.

        For each point ``q`` and segment ``j`` (from ``a_j`` along ``d_j``)::

            t_j = clip(((q - a_j) . d_j) / |d_j|^2, 0, 1)     (0 for an empty segment)
            e   = min_j |a_j + t_j d_j - q|,   s = cum_j + t_j |d_j|   at the first minimising j

        Vectorised over blocks of ``BLOCK`` consecutive points. A block only looks at the
        segments that can hold one of its points' nearest: with ``c`` the block's centre, ``R``
        its radius and ``D_j`` the distance from ``c`` to segment ``j``, every point is within
        ``D_min + R`` of the path and at least ``D_j - R`` from segment ``j`` (the distance to a
        set moves no faster than the point), so only segments with ``D_j <= D_min + 2 R`` (plus
        a rounding margin) can win. Those are evaluated exactly as all of them would be, so the
        result is the same, bit for bit, at a fraction of the work for a driven trajectory
        (its consecutive points are millimetres apart).
        """
        q = np.asarray(points, dtype=float).reshape(-1, 2)
        ax, ay = self.points[:-1, 0], self.points[:-1, 1]
        dx, dy = np.diff(self.points[:, 0]), np.diff(self.points[:, 1])
        l2 = self.seglen**2
        # t = ((q - a) . d) / |d|^2 = (q . d) / |d|^2 - (a . d) / |d|^2, zero for empty segments
        inv = np.divide(1.0, l2, out=np.zeros_like(l2), where=l2 > 0.0)
        ux, uy = dx * inv, dy * inv
        c0 = (ax * dx + ay * dy) * inv
        n = len(q)
        dist = np.empty(n)
        s = np.empty(n)
        if n == 0:
            return dist, s
        nseg = len(ax)
        # every block's centre, radius and candidate segments at once (the same operations on
        # each block as one block at a time), a few blocks' rows at a time (the temporaries small)
        starts = np.arange(0, n, self.BLOCK)
        step = max(1, _CHUNK_ELEMENTS // max(nseg, 1))
        for b0 in range(0, len(starts), step):
            first = starts[b0 : b0 + step]
            lo, hi = int(first[0]), int(min(n, first[-1] + self.BLOCK))
            qb = q[lo:hi]
            at = first - lo
            centre = (np.minimum.reduceat(qb, at, axis=0) + np.maximum.reduceat(qb, at, axis=0)) / 2.0
            own = np.repeat(centre, np.diff(np.append(at, hi - lo)), axis=0)  # each point's block centre
            radius = np.maximum.reduceat(np.hypot(qb[:, 0] - own[:, 0], qb[:, 1] - own[:, 1]), at)
            cx, cy = centre[:, 0:1], centre[:, 1:2]
            t = np.clip(cx * ux + cy * uy - c0, 0.0, 1.0)
            dc = np.hypot(ax + t * dx - cx, ay + t * dy - cy)
            bound = dc.min(axis=1) + 2.0 * radius
            bound += 1e-9 * (1.0 + bound + np.abs(centre[:, 0]) + np.abs(centre[:, 1]))  # rounding margin: more, never fewer
            inside = dc <= bound[:, None]
            wide = (inside.sum(axis=1) == nseg).tolist()
            for k, i in enumerate(first.tolist()):
                cand = slice(None) if wide[k] else np.flatnonzero(inside[k])  # (all of them: a wide block)
                self._nearest_rows(q[i : i + self.BLOCK], dist[i : i + self.BLOCK], s[i : i + self.BLOCK], cand,
                                   ax, ay, dx, dy, ux, uy, c0)
        return dist, s

    BLOCK = 128  # points per block of :meth:`nearest` (about half a metre of a driven path at 0.5 m/s, 100 Hz)

    def _nearest_rows(self, q, dist_out, s_out, cand, ax, ay, dx, dy, ux, uy, c0) -> None:
        """``nearest`` of the points ``q`` against the segments ``cand``, into the outputs."""
        ax, ay, dx, dy, ux, uy, c0 = ax[cand], ay[cand], dx[cand], dy[cand], ux[cand], uy[cand], c0[cand]
        cum, seglen = self.cum[:-1][cand], self.seglen[cand]
        rows = max(1, _CHUNK_ELEMENTS // max(len(ax), 1))
        for i in range(0, len(q), rows):
            qx, qy = q[i : i + rows, 0:1], q[i : i + rows, 1:2]
            t = qx * ux + qy * uy
            t -= c0
            np.clip(t, 0.0, 1.0, out=t)
            ex = ax + t * dx
            ex -= qx
            ey = ay + t * dy
            ey -= qy
            ex *= ex
            ey *= ey
            ex += ey
            k = np.argmin(ex, axis=1)
            r = np.arange(len(k))
            dist_out[i : i + rows] = np.sqrt(ex[r, k])
            s_out[i : i + rows] = cum[k] + t[r, k] * seglen[k]


def cross_track_errors(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Distance (m) from each point ``(M, 2)`` to the reference polyline ``path`` ``(N, 2)``.

    ``e_i = min_j |p_i - proj_j(p_i)|`` where ``proj_j`` is the closest point of segment ``j``
    (the segment parameter clipped to [0, 1]). Returns shape ``(M,)``. A one-point path gives
    the distance to that point.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    ref = np.asarray(path, dtype=float).reshape(-1, 2)
    if len(ref) == 0:
        raise ValueError("the reference path is empty")
    if len(ref) == 1:
        return np.hypot(*(pts - ref[0]).T)
    return Polyline(ref).nearest(pts)[0]


def progress_along(points: np.ndarray, path: np.ndarray, ordered: bool = True) -> np.ndarray:
    """Arc length (m) along ``path`` of each point's projection on it, shape ``(M,)``.

    ``ordered=True`` (default) treats ``points`` as a trajectory driven in order: each projection
    is searched forward from the previous one (the first local minimum of the distance ahead), so
    progress never decreases and a self-crossing path (the butterfly) cannot jump between its
    branches; completion is then ``progress[-1] / path_length``. ``ordered=False`` takes the
    globally nearest point of each (ties to the earliest).
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    poly = Polyline(path)
    if not ordered:
        return poly.nearest(pts)[1]
    if len(pts) == 0:
        return np.zeros(0)
    step = np.hypot(np.diff(pts[:, 0]), np.diff(pts[:, 1]))
    seg = poly.seglen[poly.seglen > 0.0]
    if len(step) and len(seg) and np.median(seg) >= 16.0 * np.median(step):
        js = poly.walk_trajectory(pts)  # a block of points passes a few segments: vectorised
    else:  # segments as short as a few steps: point by point (the same walks)
        found: list[int] = []
        j, walk, n, append = 0, poly.walk_forward, poly.n, found.append
        for px, py in pts.tolist():
            j = walk(j, px, py, n)[0]
            append(j)
        js = np.array(found, dtype=np.intp)
    # each point's arc length on its segment, t = min(1, max(0, u)) as walk_forward computes it
    dx, dy, l2 = poly._dxa[js], poly._dya[js], poly._l2a[js]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = ((pts[:, 0] - poly.points[js, 0]) * dx + (pts[:, 1] - poly.points[js, 1]) * dy) / l2
    t = np.where(l2 == 0.0, 0.0, np.where(u > 0.0, np.where(u < 1.0, u, 1.0), 0.0))
    s = poly.cum[js] + t * poly.seglen[js]
    return np.fmax.accumulate(np.concatenate(([0.0], s)))[1:]  # never decreasing (from 0)
