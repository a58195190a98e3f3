"""Moving obstacles in LIDAR scans (sheet 6.1 Task 4; the race-car report's rolling ball): how the
car moved between two scans, the small objects a scan holds, and tracks of them with their speed
over the ground. Pure: numpy in, numbers out; no car, no I/O.

A wall or a box does not move, a rolling ball does; but seen from a moving car everything moves.
To tell them apart, the car's own motion between two scans is taken out first, from the scans
themselves (:func:`scan_motion`: the walls are matched, so no odometry is needed and the result
holds whatever the tyres and the steering do). The small objects (:func:`scan_clusters`: a few
returns standing in front of what is behind them, at most 0.5 m across) are then followed from
scan to scan (:class:`Tracker`); a track's velocity is the least-squares slope of its last
positions, all expressed in the newest scan's frame, so it is the velocity over the ground.

Frames: the car's body frame about its centre (x forward, y left, REP-103), as
:func:`qcarlab.control.lidar_avoid.scan_points` gives the returns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from qcarlab.beams import derived

# (the compiled kernels, qcarlab.control._kernels, are imported where first called: see dodge.py)

__all__ = ["Cluster", "Motion", "PreparedScan", "Track", "Tracker", "prepare_scan", "scan_clusters", "scan_motion"]


@dataclass(frozen=True)
class Motion:
    """The car's motion from the previous scan to this one, in the previous scan's frame: it moved
    by (``dx``, ``dy``) m and turned by ``dyaw`` rad; a point ``q`` of this scan's frame is the point
    ``R(dyaw) q + (dx, dy)`` of the previous one. ``matched``: returns that agreed (0 = the guess)."""

    dx: float
    dy: float
    dyaw: float
    matched: int = 0

    def to_current(self, pts: np.ndarray) -> np.ndarray:
        """Points of the previous frame, (m, 2), in the current one: ``R(-dyaw) (p - (dx, dy))``."""
        c, s = math.cos(self.dyaw), math.sin(self.dyaw)
        p = np.asarray(pts, dtype=float).reshape(-1, 2) - (self.dx, self.dy)
        return np.column_stack((c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1]))


@dataclass(frozen=True)
class PreparedScan:
    """A scan made ready for :func:`scan_motion`: the valid returns sorted by bearing in
    [-pi, pi) (``bearings``, ``ranges``, ``points`` (m, 2)) and each return's local line normal
    from its two neighbours (``normals``; ``normal_ok`` False where a neighbour is far: an edge)."""

    bearings: np.ndarray
    ranges: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    normal_ok: np.ndarray
    _table: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def table(self) -> tuple:
        """The returns as :func:`scan_motion` reads the older scan of a match, made once: the
        bearings after a leading ``-inf`` (so ``searchsorted`` gives ``k + 1`` for a bearing just
        below return ``k``'s), then x, y, the normal's x, y and ``normal_ok``, each a contiguous
        array from the last return round to the first (``[n-1, 0, 1, ..., n-1, 0]``): entry
        ``k + 1`` is return ``k`` (mod n), entry ``k`` the one before it."""
        if self._table is None:
            P, N = self.points, self.normals
            wrap = lambda v: np.concatenate((v[-1:], v, v[:1]))  # noqa: E731
            object.__setattr__(self, "_table", (
                np.concatenate(((-math.inf,), self.bearings)), wrap(P[:, 0]), wrap(P[:, 1]), wrap(N[:, 0]),
                wrap(N[:, 1]), wrap(self.normal_ok)))
        return self._table


def prepare_scan(ranges, angles) -> PreparedScan:
    """:class:`PreparedScan` of one scan (ranges m, 0 = none; angles rad): done once a scan, as
    the newer scan of one match and the older one of the next."""
    r, a, px, py, _ = _sorted_returns(ranges, angles)
    P = np.column_stack((px, py))
    if len(P) < 3:
        return PreparedScan(a, r, P, np.zeros_like(P), np.zeros(len(P), dtype=bool))
    # each return's neighbours (the last wraps to the first): the numbers np.roll gives
    xn, yn = np.concatenate((px[1:], px[:1])), np.concatenate((py[1:], py[:1]))
    xp, yp = np.concatenate((px[-1:], px[:-1])), np.concatenate((py[-1:], py[:-1]))
    near = 0.05 + 0.03 * r
    ok_n = (np.hypot(xn - px, yn - py) < near) & (np.hypot(xp - px, yp - py) < near)
    tx, ty = xn - xp, yn - yp
    tl = np.hypot(tx, ty)
    ok_n &= tl > 1e-6
    tl = np.where(tl > 1e-6, tl, 1.0)
    return PreparedScan(a, r, P, np.column_stack((-ty / tl, tx / tl)), ok_n)


def _sorted_returns(ranges, angles) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The valid returns (range finite and > 0, bearing finite) in order of bearing in [-pi, pi)
    (a stable sort: the scan's order on a tie): their ranges, bearings, x, y and their indices in
    the scan. The same numbers as sorting each scan's valid returns and taking their cos and sin
    (:func:`_bearings`: those of every beam, once for a scan's fixed angles)."""
    r = np.asarray(ranges, dtype=float)
    a, cos_a, sin_a, finite, order = _bearings(angles)
    ok = np.isfinite(r) & (r > 0.0) & finite
    sel = order[ok[order]]
    rs = r[sel]
    return rs, a[sel], rs * cos_a[sel], rs * sin_a[sel], sel


def _bearings(angles) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A scan's beam angles (rad) wrapped to [-pi, pi), their cos and sin, which are finite, and
    the beams in order of bearing (a stable sort); once for a LIDAR's fixed angles
    (:func:`qcarlab.beams.derived`)."""
    return derived(np.asarray(angles, dtype=float), "bearings", _make_bearings)


def _make_bearings(angles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    a = np.remainder(angles + math.pi, 2.0 * math.pi) - math.pi
    return a, np.cos(a), np.sin(a), np.isfinite(a), np.argsort(a, kind="stable")


def _prepared(scan) -> PreparedScan:
    if isinstance(scan, PreparedScan):
        return scan
    if hasattr(scan, "ranges") and hasattr(scan, "angles"):
        return prepare_scan(scan.ranges, scan.angles)
    ranges, angles = scan
    return prepare_scan(ranges, angles)


def scan_motion(prev, scan, guess: tuple[float, float, float] = (0.0, 0.0, 0.0), iterations: int = 12,
                prior: tuple[float, float, float] = (2.0, 2.0, 0.5)) -> Motion:
    """The car's motion between two scans, by point-to-line matching of the newer scan's returns
    against the older one's (projective ICP). ``prev`` and ``scan``: each a ``(ranges, angles)``
    pair (m, 0 = none; rad, body frame), a :class:`~qcarlab.sensors.LidarScan` or a
    :class:`PreparedScan`.

    Each return ``q`` (a few hundred of them, evenly taken) is moved by the current estimate
    ``T = (dx, dy, dyaw)`` into the previous frame, ``p = R(dyaw) q + (dx, dy)``, and paired with
    the previous return at the nearer of the two bearings either side of ``p``'s (the scans come
    sorted by bearing, so no search tree is needed); the residual is its distance to that
    return's local line (normal ``n`` from its two neighbours), ``e = n . (p - p_prev)``.
    Gauss-Newton on ``sum w e^2 + (T - guess)' P (T - guess)`` with Huber weights ``w`` (2 cm)
    and pairs farther apart than a shrinking gate (0.3 m down to 8 cm) dropped; the weak prior
    ``P`` (``prior``, per m^2 / rad^2) towards ``guess`` only matters along a direction the walls
    leave open (down a long corridor with nothing at its end). Returns the ``guess``
    (``matched`` 0) when fewer than 20 returns pair up, or when a step is not finite (a singular
    system: only with a zero prior). Compiled
    (:func:`qcarlab.control._kernels.match_scans`: the 3 x 3 normal equations by Cholesky).
    """
    from qcarlab.control._kernels import match_scans

    old, new = _prepared(prev), _prepared(scan)
    Q = new.points
    if len(Q) > 400:  # a few hundred returns are plenty for three unknowns
        Q = Q[::2]
    g = [float(v) for v in guess]
    if len(old.points) < 20 or len(Q) < 20:
        return Motion(g[0], g[1], g[2], 0)
    # the older scan's returns, wrapped round (PreparedScan.table): k + 1 is return k, k the one before
    pa, Px, Py, Nx, Ny, ok_n = old.table()
    p = [float(v) for v in prior]
    x0, x1, x2, matched = match_scans(pa, Px, Py, Nx, Ny, ok_n, np.ascontiguousarray(Q[:, 0]),
                                      np.ascontiguousarray(Q[:, 1]), g[0], g[1], g[2], int(iterations), p[0], p[1], p[2])
    return Motion(float(x0), float(x1), float(x2), int(matched))


@dataclass(frozen=True)
class Cluster:
    """A small object in a scan: its centre (m, body frame), size across (m), returns, and the
    indices of its returns among :func:`scan_points`' points (the valid returns in scan order)."""

    x: float
    y: float
    extent: float
    n: int
    index: np.ndarray = field(repr=False)

    @property
    def range(self) -> float:
        return math.hypot(self.x, self.y)


def scan_clusters(ranges, angles, lidar_x: float = 0.0, jump: float = 0.10, jump_per_m: float = 0.03,
                  max_extent: float = 0.5, min_points: int = 3, background: float = 0.15) -> list[Cluster]:
    """The small, free-standing objects of a scan (a ball, a post, a bin; not a wall).

    The valid returns, in order of bearing, are split wherever two neighbours are farther apart
    than ``jump + jump_per_m * r`` (m). A piece is a small object when it has at least
    ``min_points`` returns, spans at most ``max_extent`` m (its bounding box's diagonal), and
    stands in front of what is beside it: the returns just outside it on both sides are
    ``background`` m farther, or there are none within three beams. That last test drops the
    pieces a wall falls into when seen at a grazing angle (its nearer part continues beside).

    The centre of a round object is behind its visible face: a half circle of radius ``rho``
    seen from afar has its returns' mean ``pi rho / 4`` nearer than its centre, so the centre is
    the mean pushed back along its bearing by ``pi/4 * extent/2``. ``lidar_x`` shifts the points to
    the car's centre as :func:`~qcarlab.control.lidar_avoid.scan_points` does.
    """
    r = np.asarray(ranges, dtype=float)
    ok = np.isfinite(r) & (r > 0.0)
    _, _, _, finite, _ = _bearings(angles)
    if not finite[ok].all():
        return []  # angles that are not numbers: nothing to cluster (scan_points would misplace them)
    rv, av, px, py, sel = _sorted_returns(r, angles)
    if len(rv) < min_points:
        return []
    pos = (np.cumsum(ok) - 1)[sel]  # index into scan_points' array (the valid returns in scan order)
    pts = np.column_stack((px, py))
    m = len(rv)
    # to the next return (the last wraps to the first)
    step = np.hypot(np.concatenate((px[1:], px[:1])) - px, np.concatenate((py[1:], py[:1])) - py)
    brk = step > jump + jump_per_m * np.minimum(rv, np.concatenate((rv[1:], rv[:1])))
    if not brk.any():
        return []
    # pieces: from after one break to the next; rotate so the first piece starts at index 0
    start = (int(np.flatnonzero(brk)[-1]) + 1) % m
    roll = np.concatenate((np.arange(start, m), np.arange(start)))
    brk_r = brk[roll]
    ends = np.flatnonzero(brk_r)
    beam = 2.0 * math.pi / max(len(r), 1)
    out: list[Cluster] = []
    # each piece's bounding box at once (the last piece ends at the last return: ends[-1] = m - 1)
    starts = np.concatenate(((0,), ends[:-1] + 1))
    xs, ys = px[roll], py[roll]
    span_x = np.maximum.reduceat(xs, starts) - np.minimum.reduceat(xs, starts)  # np.ptp's numbers
    span_y = np.maximum.reduceat(ys, starts) - np.minimum.reduceat(ys, starts)
    for lo, hi, wx, wy in zip(starts.tolist(), ends.tolist(), span_x.tolist(), span_y.tolist()):
        if hi + 1 - lo < min_points:
            continue
        extent = math.hypot(wx, wy)
        if extent > max_extent:
            continue
        sel = roll[lo:hi + 1]
        p = pts[sel]
        near = float(rv[sel].min())
        fg = True
        for j, k in ((sel[0], (sel[0] - 1) % m), (sel[-1], (sel[-1] + 1) % m)):
            gap = abs(math.remainder(float(av[k] - av[j]), 2.0 * math.pi))
            if gap <= 3.5 * beam and rv[k] < near + background:
                fg = False
        if not fg:
            continue
        cx, cy = float(p[:, 0].mean()), float(p[:, 1].mean())
        rc = math.hypot(cx, cy)
        push = math.pi / 4.0 * extent / 2.0
        if rc > 1e-9:
            cx, cy = cx * (1.0 + push / rc), cy * (1.0 + push / rc)
        out.append(Cluster(cx + lidar_x, cy, extent, len(sel), np.sort(pos[sel])))
    return out


@dataclass
class Track:
    """One small object followed over scans: its positions (m, in the newest scan's frame) at times
    ``t`` (s), its size across (m) and how many scans in a row missed it."""

    id: int
    t: list[float]
    xy: list[np.ndarray]
    extent: float
    misses: int = 0
    cluster: Cluster | None = None  # this scan's, None when missed
    _fit: tuple | None = field(default=None, repr=False, compare=False)  # fit()'s, until the next update
    run: int = 0  # positions the last fit used

    def fit(self, max_residual: float = 0.03) -> tuple[np.ndarray, np.ndarray, float]:
        """``(position now, velocity, rms residual)``: the straight line ``p(t) = p0 + v t``
        fitted by least squares to the longest run of the newest kept positions (at least three)
        that it fits to ``max_residual`` m (an object that has just started to roll is fitted on
        its rolling part only; :attr:`run` says how many positions); the newest position and zero
        velocity below two positions."""
        if self._fit is not None and self._fit[0] == max_residual:
            return self._fit[1]
        out, self.run = self._fit_now(max_residual)
        self._fit = (max_residual, out)
        return out

    def _fit_now(self, max_residual: float) -> tuple[tuple[np.ndarray, np.ndarray, float], int]:
        if len(self.t) < 2:
            return (self.xy[-1], np.zeros(2), 0.0), len(self.t)
        t_all = np.asarray(self.t) - self.t[-1]
        xy_all = np.asarray(self.xy)
        for k in range(len(t_all), 1, -1):
            t, xy = t_all[-k:], xy_all[-k:]
            A = np.column_stack((np.ones_like(t), t))
            sol, *_ = np.linalg.lstsq(A, xy, rcond=None)
            res = xy - A @ sol
            rms = float(math.sqrt(np.mean(np.sum(res * res, axis=1))))
            if rms <= max_residual or k <= 3:
                return (sol[0], sol[1], rms), k
        return (sol[0], sol[1], rms), 2  # pragma: no cover (k = 3 returns above)

    def velocity(self) -> tuple[np.ndarray, float]:
        """Velocity over the ground (m/s, newest frame) and the fit's RMS residual (m): :meth:`fit`."""
        _, v, rms = self.fit()
        return v, rms

    def position(self) -> np.ndarray:
        """Where the object is now (the fitted line at the newest time)."""
        return self.fit()[0]


class Tracker:
    """Follows :func:`scan_clusters`' objects from scan to scan.

    ``update(t, motion, clusters)``: the kept positions are moved into the new scan's frame
    (:meth:`Motion.to_current`); each track is predicted to ``t`` with its velocity and paired with
    the nearest unpaired cluster within ``gate`` m of similar size (nearest pairs first); the
    unpaired clusters start tracks, a track missed ``max_misses`` scans in a row is dropped.
    :meth:`moving` gives the tracks that move over the ground at ``min_speed`` m/s or more along
    a straight line fitted to their last ``min_seen`` positions or more (residual below
    ``max_residual`` m): 0.4 s of rolling at 10 scans a second, before the direction is known
    well enough to tell which side of it the car is.
    """

    def __init__(self, gate: float = 0.35, keep: int = 10, max_misses: int = 3, min_seen: int = 5,
                 min_speed: float = 0.35, max_residual: float = 0.05):
        self.gate, self.keep, self.max_misses = gate, keep, max_misses
        self.min_seen, self.min_speed, self.max_residual = min_seen, min_speed, max_residual
        self.reset()

    def reset(self) -> None:
        self.tracks: list[Track] = []
        self._next = 0

    def update(self, t: float, motion: Motion | None, clusters: list[Cluster]) -> list[Track]:
        for tr in self.tracks:
            if motion is not None and tr.xy:
                moved = motion.to_current(np.asarray(tr.xy))
                tr.xy = [row for row in moved]
            tr.cluster = None
            tr._fit = None
        pairs = []
        for i, tr in enumerate(self.tracks):
            v, _ = tr.velocity()
            pred = tr.position() + v * (t - tr.t[-1])
            for j, c in enumerate(clusters):
                d = math.hypot(c.x - pred[0], c.y - pred[1])
                if d < self.gate and abs(c.extent - tr.extent) < 0.25:
                    pairs.append((d, i, j))
        pairs.sort()
        used_t, used_c = set(), set()
        for _, i, j in pairs:
            if i in used_t or j in used_c:
                continue
            used_t.add(i)
            used_c.add(j)
            tr, c = self.tracks[i], clusters[j]
            tr.t.append(float(t))
            tr.xy.append(np.array([c.x, c.y]))
            tr.t, tr.xy = tr.t[-self.keep:], tr.xy[-self.keep:]
            tr.extent = 0.7 * tr.extent + 0.3 * c.extent
            tr.misses = 0
            tr.cluster = c
            tr._fit = None
        for i, tr in enumerate(self.tracks):
            if i not in used_t:
                tr.misses += 1
        self.tracks = [tr for tr in self.tracks if tr.misses <= self.max_misses]
        for j, c in enumerate(clusters):
            if j not in used_c:
                self.tracks.append(Track(self._next, [float(t)], [np.array([c.x, c.y])], c.extent, 0, c))
                self._next += 1
        return self.tracks

    def moving(self) -> list[Track]:
        out = []
        for tr in self.tracks:
            if len(tr.t) < self.min_seen or tr.misses > 1:
                continue
            v, res = tr.velocity()
            if tr.run >= self.min_seen and math.hypot(v[0], v[1]) >= self.min_speed and res <= self.max_residual:
                out.append(tr)
        return out
