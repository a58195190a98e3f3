"""A LIDAR scan of a world of polygons and circles, per edge, in numpy: no numba to load.

The same scan as the compiled :func:`qcarlab.sim._kernels.lidar_scan_edges`, the same operations
on the same numbers (so the same ranges, bit for bit), written over arrays: a lone lab run (600
scans a minute) is done before loading numba's cache (some 0.35 s, more with numba's import)
would have paid for itself, so :class:`qcarlab.sim.lidar.Lidar` scans here first and switches to
the compiled kernel after :data:`qcarlab.sim.lidar.SWITCH_AFTER` scans.

Beam ``i`` looks along the body angle ``a0 + i da`` (direction ``(cos_b[i], sin_b[i])``, turned by
the sensor's yaw into ``(dx_i, dy_i)``). An edge ``a -> b`` (relative to the sensor) spans the
beams between its ends' bearings (the short way round, one beam of slack each side); for each
such pair, with ``e = b - a``::

    den = dx ey - dy ex,   sn = ax dy - ay dx,   t = (ax ey - ay ex) / den

is a hit at range ``t`` when ``0 <= sn < den`` (``den > 0``; mirrored for ``den < 0``) and
``t >= 0``. A circle (centre ``q``, radius ``r``) likewise: ``b = -(q . d)``,
``t = -b - sqrt(b^2 - (|q|^2 - r^2))``. Each beam keeps its nearest hit; from inside a shape
(even-odd rule along +x, or within a circle) every beam reads 0 m. The balls (circles cut by the
scan plane) and the noise, limits and no-return rule are then :func:`readings`.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

__all__ = ["BIG", "KIND_CIRCLE", "KIND_GRID", "KIND_POLYGON", "Shapes", "edge_table", "readings", "scan_edges",
           "shape_tables"]

BIG = 1e30  # no hit (as the compiled kernels')
KIND_GRID, KIND_POLYGON, KIND_CIRCLE = 0, 1, 2  # (as qcarlab.sim.raster's shape tables)
TWO_PI = 2.0 * math.pi


class Shapes(NamedTuple):
    """A raster's shape tables without the raster (:class:`qcarlab.sim.raster.Raster`'s fields of
    the same names, in its order: a ROS map's grid first, then the shapes)."""

    kinds: np.ndarray  # int32 (L,)
    poly_start: np.ndarray  # int32 (L,)
    poly_count: np.ndarray  # int32 (L,)
    verts: np.ndarray  # float64 (V, 2)
    circles: np.ndarray  # float64 (L, 3)


def shape_tables(world: Any, z: float) -> Shapes:
    """The shapes the horizontal plane at height ``z`` (m) cuts (``z0 <= z < height``), as
    :func:`qcarlab.sim.raster.build_raster` ``(world, z)`` tabulates them, without drawing its cells
    (which a scan of a vector world never reads)."""
    kinds, pstart, pcount, circles, verts = [], [], [], [], []
    nverts = 0
    if world.grid is not None:
        kinds.append(KIND_GRID)
        pstart.append(0)
        pcount.append(0)
        circles.append((0.0, 0.0, 0.0))
    for s in world.static_solids():
        if not s.z0 <= z < s.height:
            continue
        if s.kind == "polygon":
            kinds.append(KIND_POLYGON)
            pstart.append(nverts)
            pcount.append(len(s.points))
            verts.append(s.points)
            nverts += len(s.points)
            circles.append((0.0, 0.0, 0.0))
        else:
            kinds.append(KIND_CIRCLE)
            pstart.append(0)
            pcount.append(0)
            circles.append((s.center[0], s.center[1], s.radius))
    return Shapes(np.array(kinds, np.int32), np.array(pstart, np.int32), np.array(pcount, np.int32),
                  np.vstack(verts).astype(np.float64) if verts else np.zeros((0, 2)),
                  np.array(circles, np.float64).reshape(-1, 3))


def edge_table(kinds: np.ndarray, pstart: np.ndarray, pcount: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """Every polygon edge of a raster's shape tables as one row (ax, ay, bx, by, label) for
    :func:`~qcarlab.sim._kernels.vector_crossings` and the scans (float64 (E, 5))."""
    rows = []
    for lab in range(len(kinds)):
        if kinds[lab] != 1:
            continue
        p0, n = int(pstart[lab]), int(pcount[lab])
        for j in range(n):
            a = verts[p0 + j]
            b = verts[p0 + (j + 1) % n]
            rows.append((a[0], a[1], b[0], b[1], float(lab)))
    return np.array(rows, np.float64).reshape(-1, 5)


def _beam_ranges(lo: np.ndarray, w: np.ndarray, da: float, n: int, full: bool) -> tuple[np.ndarray, np.ndarray]:
    """For spans starting ``lo`` rad from beam 0 (in [0, 2 pi)) and ``w`` rad wide: the (span,
    beam) pairs to test, as two index arrays (a whole turn: beam indices mod n; a sector: the
    span once more a turn earlier, clipped to the sector)."""
    spans, k0s, k1s = [], [], []
    for shift in range(1 if full else 2):
        base = lo - shift * TWO_PI
        k0 = np.floor(base / da).astype(np.int64) - 1
        k1 = np.floor((base + w) / da).astype(np.int64) + 1
        if not full:
            k0 = np.maximum(k0, 0)
            k1 = np.minimum(k1, n - 1)
        spans.append(np.arange(len(lo)))
        k0s.append(k0)
        k1s.append(k1)
    span, k0, k1 = (np.concatenate(x) for x in (spans, k0s, k1s)) if not full else (spans[0], k0s[0], k1s[0])
    counts = np.maximum(k1 - k0 + 1, 0)
    total = int(counts.sum())
    owner = np.repeat(span, counts)
    first = np.cumsum(counts) - counts  # where each span's pairs start
    beam = np.arange(total, dtype=np.int64) + np.repeat(k0 - first, counts)
    return owner, (beam % n if full else beam)


def _inside(ox: float, oy: float, edges: np.ndarray, kinds: np.ndarray, circles: np.ndarray) -> bool:
    """The sensor inside a polygon (an odd number of its edges crossed along +x) or a circle."""
    if len(edges):
        ay, by = edges[:, 1] - oy, edges[:, 3] - oy
        span = (ay > 0.0) != (by > 0.0)
        if span.any():
            e = edges[span]
            ax, bx = e[:, 0] - ox, e[:, 2] - ox
            ya, yb = ay[span], by[span]
            cross = ax + (0.0 - ya) * (bx - ax) / (yb - ya) > 0.0
            labels = e[cross, 4].astype(np.int64)
            if len(labels) and (np.bincount(labels) % 2 == 1).any():
                return True
    for lab in np.flatnonzero(kinds == KIND_CIRCLE):
        qx, qy = circles[lab, 0] - ox, circles[lab, 1] - oy
        if qx * qx + qy * qy < circles[lab, 2] * circles[lab, 2]:
            return True
    return False


def scan_edges(ox: float, oy: float, yaw: float, cos_b: np.ndarray, sin_b: np.ndarray, a0: float, da: float,
               full: bool, edges: np.ndarray, kinds: np.ndarray, circles: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                              np.ndarray, int]:
    """The distance (m, ``BIG`` = none) of every beam's nearest static hit from the sensor at
    (ox, oy) heading ``yaw``, the beams' world directions (dx, dy), and the beam-shape pairs
    tested (the work, as the compiled kernel counts it); see the module docstring."""
    n = cos_b.shape[0]
    cyaw, syaw = math.cos(yaw), math.sin(yaw)
    dx = cos_b * cyaw - sin_b * syaw
    dy = sin_b * cyaw + cos_b * syaw
    dist = np.full(n, BIG)
    if _inside(ox, oy, edges, kinds, circles):
        dist[:] = 0.0
        return dist, dx, dy, 0
    work = 0
    if len(edges):
        ax, ay = edges[:, 0] - ox, edges[:, 1] - oy
        bx, by = edges[:, 2] - ox, edges[:, 3] - oy
        pa = np.arctan2(ay, ax) - yaw
        pb = np.arctan2(by, bx) - yaw
        w = np.remainder(pb - pa, TWO_PI)
        wide = w > math.pi
        lo = np.remainder(np.where(wide, pb, pa) - a0, TWO_PI)
        w = np.where(wide, TWO_PI - w, w)
        e, i = _beam_ranges(lo, w, da, n, full)
        work += len(i)
        ex, ey = (bx - ax)[e], (by - ay)[e]
        axe, aye = ax[e], ay[e]
        bdx, bdy = dx[i], dy[i]
        den = bdx * ey - bdy * ex
        sn = axe * bdy - aye * bdx
        ok = np.where(den > 0.0, (sn >= 0.0) & (sn < den), (sn <= 0.0) & (sn > den)) & (den != 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            tt = (axe[ok] * ey[ok] - aye[ok] * ex[ok]) / den[ok]
        hit = tt >= 0.0
        _min_at(dist, i[ok][hit], tt[hit])
    circ = np.flatnonzero(kinds == KIND_CIRCLE)
    if len(circ):
        qx, qy, r = circles[circ, 0] - ox, circles[circ, 1] - oy, circles[circ, 2]
        d = np.sqrt(qx * qx + qy * qy)
        th = np.remainder(np.arctan2(qy, qx) - yaw - a0, TWO_PI)
        with np.errstate(divide="ignore"):
            al = np.arcsin(np.minimum(r / d, 1.0))
        c, i = _beam_ranges(th - al, 2.0 * al, da, n, full)
        work += len(i)
        cx, cy, cr = qx[c], qy[c], r[c]
        b = -(cx * dx[i] + cy * dy[i])
        disc = b * b - (cx * cx + cy * cy - cr * cr)
        ok = disc >= 0.0
        tt = -b[ok] - np.sqrt(disc[ok])
        hit = tt >= 0.0
        _min_at(dist, i[ok][hit], tt[hit])
    return dist, dx, dy, work


def _min_at(dist: np.ndarray, idx: np.ndarray, val: np.ndarray) -> None:
    """``np.minimum.at(dist, idx, val)``, the same numbers (each index's smallest value, a min being
    exact in any order): the pairs sorted by index and each index's run reduced at once, which is
    several times faster than ``minimum.at`` on a scan's few thousand pairs."""
    if not len(idx):
        return
    order = np.argsort(idx, kind="stable")
    idx = idx[order]
    starts = np.flatnonzero(np.concatenate(((True,), idx[1:] != idx[:-1])))
    at = idx[starts]
    dist[at] = np.minimum(dist[at], np.minimum.reduceat(val[order], starts))


def readings(dist: np.ndarray, ox: float, oy: float, dx: np.ndarray, dy: np.ndarray, balls: np.ndarray,
             noise: np.ndarray, rmax: float, rmin: float, near_mode: int, out: np.ndarray) -> None:
    """The beams' readings from their static hits ``dist`` (m, ``BIG``: none), into ``out``: the
    nearer of that and the balls ((x, y, radius) circles cut by the scan plane), then
    ``near_mode`` -1: exact, ``inf`` beyond ``rmax``; else plus the noise (a beam's own, when
    ``noise`` holds one a beam), 0 beyond ``rmax`` and below ``rmin`` (or ``rmin`` itself,
    ``near_mode`` 1). The compiled ``_reading``'s operations, a beam at a time."""
    r = dist.copy()
    for j in range(balls.shape[0]):
        fx, fy = ox - balls[j, 0], oy - balls[j, 1]
        b = fx * dx + fy * dy
        c = fx * fx + fy * fy - balls[j, 2] * balls[j, 2]
        disc = b * b - c
        ok = disc >= 0.0
        if ok.any():
            tb = np.full(r.shape, np.inf)
            tb[ok] = -b[ok] - np.sqrt(disc[ok])
            nearer = (tb >= 0.0) & (tb < r)
            r[nearer] = tb[nearer]
    if near_mode < 0:
        out[:] = np.where(r <= rmax, r, np.inf)
        return
    far = r > rmax
    r += noise if noise.shape[0] == r.shape[0] else 0.0
    near = r < rmin
    r[near] = rmin if near_mode == 1 else 0.0
    r[far | (r > rmax)] = 0.0
    out[:] = r
