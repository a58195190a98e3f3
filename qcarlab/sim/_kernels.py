"""The sensors' inner loops: ray casting over a label raster, LIDAR scans, camera columns.

Compiled with numba when it is installed (``cache=True``: compiled once per machine, a few
seconds, then loaded from ``__pycache__``); without numba the same code runs as plain Python,
correct but some hundred times slower (:data:`HAVE_NUMBA` tells which).

Ray casting (all distances in raster cells inside, metres outside): from a free cell whose
distance-transform value is D (cells to the nearest occupied cell centre), nothing occupied lies
closer than D - sqrt(2) to any point of the cell, so the ray jumps that far at once; near
occupied cells (D <= 2.5) it walks cell by cell (Amanatides-Woo) and stops exactly on the
boundary of the first occupied cell. A hit on a polygon or circle is then refined against the
shape itself, so vector worlds are exact and ROS maps are exact to their cells.
"""

from __future__ import annotations

import math
import sys

import numpy as np

from qcarlab.jit import COMPILE_NOTICE, HAVE_NUMBA, njit  # noqa: F401  (COMPILE_NOTICE: read by tests)
from qcarlab.jit import JIT as _JIT

#: A helper that takes arrays and runs in a hot loop (a row of a frame, a column): inlined into its
#: caller by numba, which passes each array argument of a call that is not inlined with a reference
#: count taken and given back (two atomic operations an array a call: 9 % of a frame's composing,
#: a fifth of finding its columns' layers, 8 % of a LIDAR scan marched over a ROS map, measured)
_INLINE = {**_JIT, "inline": "always"}
from qcarlab.sim.edge_scan import edge_table  # noqa: F401  (the camera's and the LIDAR's edge rows)

KMAX = 8  # hits kept per camera column

#: The raster's cell map is one uint16 per cell (2 bytes: a 1000 x 1000 map is 2 MB and stays in
#: cache): an occupied cell holds OCC + the label of the shape covering it (up to MAX_LABELS
#: shapes); a free cell its distance-transform value in units of DT_UNIT cells, rounded down
#: (so a jump is never longer than the exact value allows) and capped at OCC - 1.
OCC = 0x8000
MAX_LABELS = 0x8000
DT_UNIT = 0.125
SKIP_FROM = 20  # free cells with D > 2.5 cells: jump
WALK_UNTIL = 24  # walking near the shapes: jump again from a cell with D > 3 cells

#: A raster of a ROS map's walls alone (one shape of grid kind) is also kept for the LIDAR as 8 x 8-cell tiles
#: of one byte a cell (``Raster.tiles``): TILE_OCC = occupied, else the distance value in units
#: of TILE_UNIT cells, rounded down and capped at 254 (63.5 cells: 3.2 m on a 5 cm map).
TILE_OCC = 255
TILE_UNIT = 0.25
TILE_SKIP_FROM = 10  # D > 2.5 cells
TILE_WALK_UNTIL = 12  # D > 3 cells
BIG = 1e30
LITTLE_ENDIAN = sys.byteorder == "little"


def pack_bgr(b: int, g: int, r: int) -> int:
    """A BGRA pixel (alpha 255) as the uint32 the camera kernels write (see :func:`_pack`)."""
    return int(np.array([b, g, r, 255], np.uint8).view(np.uint32)[0])


@njit(**_INLINE)
def dda_axis(d, i, p, t):
    """Grid traversal (Amanatides-Woo) along one axis of a ray with direction component ``d``,
    at cell ``i`` and position ``p`` (cells) at ray parameter ``t``: returns the cell step (-1, 0,
    1), the ray length per cell, and the ray parameter of the next cell boundary."""
    if d > 0.0:
        return 1, 1.0 / d, t + (i + 1 - p) / d
    if d < 0.0:
        return -1, -1.0 / d, t + (i - p) / d
    return 0, BIG, BIG


@njit(**_INLINE)
def _enter_box(px, py, dx, dy, nx, ny):
    """Ray parameter (cells) where a ray from (px, py) enters the grid box, or -1 if it never does."""
    t0 = 0.0
    t1 = BIG
    if dx != 0.0:
        a = (0.0 - px) / dx
        b = (nx - px) / dx
        if a > b:
            a, b = b, a
        t0 = max(t0, a)
        t1 = min(t1, b)
    elif px < 0.0 or px >= nx:
        return -1.0
    if dy != 0.0:
        a = (0.0 - py) / dy
        b = (ny - py) / dy
        if a > b:
            a, b = b, a
        t0 = max(t0, a)
        t1 = min(t1, b)
    elif py < 0.0 or py >= ny:
        return -1.0
    if t0 > t1:
        return -1.0
    return t0


@njit(**_JIT)
def march(px, py, dx, dy, t, tmax, cells):
    """First occupied cell along a ray (cell units). Returns (t, label, side, steps).

    ``cells`` is the raster's uint16 cell map (see :data:`OCC`). ``side`` is 1 when the ray
    entered the cell through an x face, 2 through a y face, 0 when it started inside; ``label``
    is -1 when nothing is hit before ``tmax`` or the grid's edge; ``steps`` counts the cells
    looked at (each lookup of the outer loop and each step of the walk).

    Away from the shapes (a free cell whose distance value D > 2.5 cells) the ray jumps
    D - 1.4143 at once; near them it walks cell by cell and, on entering a cell with D > 3,
    jumps again *from that cell* (the boundary point lies in it, so the bound holds there).
    Every lookup is therefore followed by a step to a new cell or a jump of at least 1.2 cells:
    a ray costs at most about 3 steps per cell of its length, whatever its direction, even
    along a cell boundary (where a restart from ``floor(x)`` could land back in the cell it
    had just left, the stall this replaced).
    """
    ny, nx = cells.shape
    steps = 0
    x = px + t * dx
    y = py + t * dy
    if x < 0.0 or y < 0.0 or x >= nx or y >= ny:
        te = _enter_box(px, py, dx, dy, nx, ny)
        if te < 0.0 or te > tmax:
            return tmax, -1, 0, steps
        if te > t:
            t = te + 1e-7
    while t < tmax:
        x = px + t * dx
        y = py + t * dy
        if not (x >= 0.0 and y >= 0.0 and x < nx and y < ny):
            return tmax, -1, 0, steps
        ix = int(x)  # = floor: x >= 0 (truncation is off the loop's critical path, floor is not)
        iy = int(y)
        c = int(cells[iy, ix])
        steps += 1
        if c >= OCC:
            return t, c - OCC, 0, steps
        if c > SKIP_FROM:
            t += c * DT_UNIT - 1.4143
            continue
        # walk cell by cell until clear of the shapes again
        sx, tdx, tmx = dda_axis(dx, ix, x, t)
        sy, tdy, tmy = dda_axis(dy, iy, y, t)
        while True:
            steps += 1
            if tmx < tmy:
                t = tmx
                tmx += tdx
                ix += sx
                side = 1
            else:
                t = tmy
                tmy += tdy
                iy += sy
                side = 2
            if t >= tmax or ix < 0 or iy < 0 or ix >= nx or iy >= ny:
                return tmax, -1, 0, steps
            c = int(cells[iy, ix])
            if c >= OCC:
                return t, c - OCC, side, steps
            if c > WALK_UNTIL:
                t += c * DT_UNIT - 1.4143
                break
    return tmax, -1, 0, steps


@njit(**_INLINE)
def _tile_at(tiles, ix, iy, ntx):
    return int(tiles[(((iy >> 3) * ntx + (ix >> 3)) << 6) + ((iy & 7) << 3) + (ix & 7)])


@njit(**_JIT)
def march_tiles(px, py, dx, dy, t, tmax, tiles, nx, ny, ntx):
    """:func:`march` over a one-shape raster stored as 8 x 8-cell tiles of one byte a cell (see
    :data:`TILE_OCC`): a tile is one 64-byte cache line, so a ray's next cells are mostly in a
    line it has already fetched, and the map is a quarter the size (the ROS maps' LIDAR raster:
    the map stays in the cache between scans while a simulation also renders camera frames).
    Returns (t, label, steps), label 0 for a hit, -1 for none."""
    steps = 0
    x = px + t * dx
    y = py + t * dy
    if x < 0.0 or y < 0.0 or x >= nx or y >= ny:
        te = _enter_box(px, py, dx, dy, nx, ny)
        if te < 0.0 or te > tmax:
            return tmax, -1, steps
        if te > t:
            t = te + 1e-7
    while t < tmax:
        x = px + t * dx
        y = py + t * dy
        if not (x >= 0.0 and y >= 0.0 and x < nx and y < ny):
            return tmax, -1, steps
        ix = int(x)  # = floor: x >= 0 (truncation is off the loop's critical path, floor is not)
        iy = int(y)
        c = _tile_at(tiles, ix, iy, ntx)
        steps += 1
        if c == TILE_OCC:
            return t, 0, steps
        if c > TILE_SKIP_FROM:
            t += c * TILE_UNIT - 1.4143
            continue
        sx, tdx, tmx = dda_axis(dx, ix, x, t)
        sy, tdy, tmy = dda_axis(dy, iy, y, t)
        while True:
            steps += 1
            if tmx < tmy:
                t = tmx
                tmx += tdx
                ix += sx
            else:
                t = tmy
                tmy += tdy
                iy += sy
            if t >= tmax or ix < 0 or iy < 0 or ix >= nx or iy >= ny:
                return tmax, -1, steps
            c = _tile_at(tiles, ix, iy, ntx)
            if c == TILE_OCC:
                return t, 0, steps
            if c > TILE_WALK_UNTIL:
                t += c * TILE_UNIT - 1.4143
                break
    return tmax, -1, steps


@njit(**_INLINE)
def _start_in_grid(px, py, dx, dy, t, tmax, nx, ny):
    """Where :func:`march` and :func:`march_tiles` start: t, moved to where the ray enters the
    grid when it starts outside (tmax when it never does before tmax)."""
    x = px + t * dx
    y = py + t * dy
    if x < 0.0 or y < 0.0 or x >= nx or y >= ny:
        te = _enter_box(px, py, dx, dy, nx, ny)
        if te < 0.0 or te > tmax:
            return tmax
        if te > t:
            return te + 1e-7
    return t


@njit(**_INLINE)
def march_tiles_pair(px, py, dxa, dya, dxb, dyb, t0, tmax, tiles, nx, ny, ntx):
    """:func:`march_tiles` of two rays from the same point at once, a step of each in turn: a
    ray's steps form one dependency chain (position, cell, lookup, jump) that leaves the core
    mostly waiting, and two independent chains interleave. The same numbers as two calls
    (t, label and cells looked at of each): returns (ta, laba, tb, labb, steps)."""
    steps = 0
    ta = _start_in_grid(px, py, dxa, dya, t0, tmax, nx, ny)
    tb = _start_in_grid(px, py, dxb, dyb, t0, tmax, nx, ny)
    # mode 0: jumping, 1: walking cell by cell, 2: done
    ma = 0
    mb = 0
    la = -1
    lb = -1
    ixa = iya = sxa = sya = 0
    ixb = iyb = sxb = syb = 0
    tdxa = tdya = tmxa = tmya = 0.0
    tdxb = tdyb = tmxb = tmyb = 0.0
    while ma != 2 or mb != 2:
        if ma == 0:
            x = px + ta * dxa
            y = py + ta * dya
            if not (ta < tmax and x >= 0.0 and y >= 0.0 and x < nx and y < ny):
                ma = 2
                ta = tmax
            else:
                ixa = int(x)
                iya = int(y)
                c = _tile_at(tiles, ixa, iya, ntx)
                steps += 1
                if c == TILE_OCC:
                    ma = 2
                    la = 0
                elif c > TILE_SKIP_FROM:
                    ta += c * TILE_UNIT - 1.4143
                else:
                    sxa, tdxa, tmxa = dda_axis(dxa, ixa, x, ta)
                    sya, tdya, tmya = dda_axis(dya, iya, y, ta)
                    ma = 1
        elif ma == 1:
            steps += 1
            if tmxa < tmya:
                ta = tmxa
                tmxa += tdxa
                ixa += sxa
            else:
                ta = tmya
                tmya += tdya
                iya += sya
            if ta >= tmax or ixa < 0 or iya < 0 or ixa >= nx or iya >= ny:
                ma = 2
                ta = tmax
            else:
                c = _tile_at(tiles, ixa, iya, ntx)
                if c == TILE_OCC:
                    ma = 2
                    la = 0
                elif c > TILE_WALK_UNTIL:
                    ta += c * TILE_UNIT - 1.4143
                    ma = 0
        if mb == 0:
            x = px + tb * dxb
            y = py + tb * dyb
            if not (tb < tmax and x >= 0.0 and y >= 0.0 and x < nx and y < ny):
                mb = 2
                tb = tmax
            else:
                ixb = int(x)
                iyb = int(y)
                c = _tile_at(tiles, ixb, iyb, ntx)
                steps += 1
                if c == TILE_OCC:
                    mb = 2
                    lb = 0
                elif c > TILE_SKIP_FROM:
                    tb += c * TILE_UNIT - 1.4143
                else:
                    sxb, tdxb, tmxb = dda_axis(dxb, ixb, x, tb)
                    syb, tdyb, tmyb = dda_axis(dyb, iyb, y, tb)
                    mb = 1
        elif mb == 1:
            steps += 1
            if tmxb < tmyb:
                tb = tmxb
                tmxb += tdxb
                ixb += sxb
            else:
                tb = tmyb
                tmyb += tdyb
                iyb += syb
            if tb >= tmax or ixb < 0 or iyb < 0 or ixb >= nx or iyb >= ny:
                mb = 2
                tb = tmax
            else:
                c = _tile_at(tiles, ixb, iyb, ntx)
                if c == TILE_OCC:
                    mb = 2
                    lb = 0
                elif c > TILE_WALK_UNTIL:
                    tb += c * TILE_UNIT - 1.4143
                    mb = 0
    return ta, la, tb, lb, steps


@njit(**_INLINE)
def march_pair(px, py, dxa, dya, dxb, dyb, t0, tmax, cells):
    """:func:`march` of two rays from the same point at once (see :func:`march_tiles_pair`): the
    same t, label and cells looked at as two calls; returns (ta, laba, tb, labb, steps)."""
    ny, nx = cells.shape
    steps = 0
    ta = _start_in_grid(px, py, dxa, dya, t0, tmax, nx, ny)
    tb = _start_in_grid(px, py, dxb, dyb, t0, tmax, nx, ny)
    # mode 0: jumping, 1: walking cell by cell, 2: done
    ma = 0
    mb = 0
    la = -1
    lb = -1
    ixa = iya = sxa = sya = 0
    ixb = iyb = sxb = syb = 0
    tdxa = tdya = tmxa = tmya = 0.0
    tdxb = tdyb = tmxb = tmyb = 0.0
    while ma != 2 or mb != 2:
        if ma == 0:
            x = px + ta * dxa
            y = py + ta * dya
            if not (ta < tmax and x >= 0.0 and y >= 0.0 and x < nx and y < ny):
                ma = 2
                ta = tmax
            else:
                ixa = int(x)
                iya = int(y)
                c = int(cells[iya, ixa])
                steps += 1
                if c >= OCC:
                    ma = 2
                    la = c - OCC
                elif c > SKIP_FROM:
                    ta += c * DT_UNIT - 1.4143
                else:
                    sxa, tdxa, tmxa = dda_axis(dxa, ixa, x, ta)
                    sya, tdya, tmya = dda_axis(dya, iya, y, ta)
                    ma = 1
        elif ma == 1:
            steps += 1
            if tmxa < tmya:
                ta = tmxa
                tmxa += tdxa
                ixa += sxa
            else:
                ta = tmya
                tmya += tdya
                iya += sya
            if ta >= tmax or ixa < 0 or iya < 0 or ixa >= nx or iya >= ny:
                ma = 2
                ta = tmax
            else:
                c = int(cells[iya, ixa])
                if c >= OCC:
                    ma = 2
                    la = c - OCC
                elif c > WALK_UNTIL:
                    ta += c * DT_UNIT - 1.4143
                    ma = 0
        if mb == 0:
            x = px + tb * dxb
            y = py + tb * dyb
            if not (tb < tmax and x >= 0.0 and y >= 0.0 and x < nx and y < ny):
                mb = 2
                tb = tmax
            else:
                ixb = int(x)
                iyb = int(y)
                c = int(cells[iyb, ixb])
                steps += 1
                if c >= OCC:
                    mb = 2
                    lb = c - OCC
                elif c > SKIP_FROM:
                    tb += c * DT_UNIT - 1.4143
                else:
                    sxb, tdxb, tmxb = dda_axis(dxb, ixb, x, tb)
                    syb, tdyb, tmyb = dda_axis(dyb, iyb, y, tb)
                    mb = 1
        elif mb == 1:
            steps += 1
            if tmxb < tmyb:
                tb = tmxb
                tmxb += tdxb
                ixb += sxb
            else:
                tb = tmyb
                tmyb += tdyb
                iyb += syb
            if tb >= tmax or ixb < 0 or iyb < 0 or ixb >= nx or iyb >= ny:
                mb = 2
                tb = tmax
            else:
                c = int(cells[iyb, ixb])
                if c >= OCC:
                    mb = 2
                    lb = c - OCC
                elif c > WALK_UNTIL:
                    tb += c * DT_UNIT - 1.4143
                    mb = 0
    return ta, la, tb, lb, steps


@njit(**_JIT)
def skip(px, py, dx, dy, t, tmax, cells, lab):
    """Walk on through the cells of shape ``lab`` from ``t``; returns (t_exit, label_after)."""
    ny, nx = cells.shape
    x = px + t * dx
    y = py + t * dy
    ix = int(math.floor(x))
    iy = int(math.floor(y))
    sx, tdx, tmx = dda_axis(dx, ix, x, t)
    sy, tdy, tmy = dda_axis(dy, iy, y, t)
    code = OCC + lab
    while True:
        if tmx < tmy:
            t = tmx
            tmx += tdx
            ix += sx
        else:
            t = tmy
            tmy += tdy
            iy += sy
        if t >= tmax or ix < 0 or iy < 0 or ix >= nx or iy >= ny:
            return t, -1
        c = int(cells[iy, ix])
        if c != code:
            return t, (c - OCC if c >= OCC else -1)


@njit(**_JIT)
def exact(lab, ox, oy, dx, dy, tguess, tol, kinds, pstart, pcount, verts, circles):
    """Exact (t_in, t_out, nx, ny) in metres of a ray against shape ``lab`` near ``tguess``.

    ``t_in`` is -1 when the ray misses the shape there (the raster's cells then stand).
    (nx, ny) is the outward surface normal where the ray enters.
    """
    k = kinds[lab]
    if k == 2:
        cx = circles[lab, 0]
        cy = circles[lab, 1]
        r = circles[lab, 2]
        fx = ox - cx
        fy = oy - cy
        b = fx * dx + fy * dy
        c = fx * fx + fy * fy - r * r
        disc = b * b - c
        if disc < 0.0:
            return -1.0, -1.0, 0.0, 0.0
        s = math.sqrt(disc)
        t0 = -b - s
        t1 = -b + s
        if t0 < tguess - tol or t0 > tguess + tol:
            return -1.0, -1.0, 0.0, 0.0
        hx = ox + t0 * dx - cx
        hy = oy + t0 * dy - cy
        return t0, t1, hx / r, hy / r
    if k != 1:
        return -1.0, -1.0, 0.0, 0.0
    p0 = pstart[lab]
    n = pcount[lab]
    # one pass over the edges: tin = the nearest crossing at or beyond tguess - tol, tout = the
    # nearest crossing beyond tin (+ 1e-9)
    lo = tguess - tol
    tin = BIG
    tout = BIG
    exin = 0.0
    eyin = 0.0
    for j in range(n):
        jb = j + 1 if j + 1 < n else 0
        ax = verts[p0 + j, 0]
        ay = verts[p0 + j, 1]
        ex = verts[p0 + jb, 0] - ax
        ey = verts[p0 + jb, 1] - ay
        den = dx * ey - dy * ex
        if den == 0.0:
            continue
        wx = ax - ox
        wy = ay - oy
        # the crossing's place along the edge, ss = sn / den in [0, 1], tested without dividing
        sn = wx * dy - wy * dx
        if (den > 0.0 and (sn < 0.0 or sn > den)) or (den < 0.0 and (sn > 0.0 or sn < den)):
            continue
        tt = (wx * ey - wy * ex) / den
        if tt < lo:
            continue
        if tt < tin:
            if tin > tt + 1e-9:
                tout = tin
            tin = tt
            exin = ex
            eyin = ey
        elif tt > tin + 1e-9 and tt < tout:
            tout = tt
    if tin > tguess + tol:
        return -1.0, -1.0, 0.0, 0.0
    ln = math.sqrt(exin * exin + eyin * eyin)
    nxin = eyin / ln
    nyin = -exin / ln
    if nxin * dx + nyin * dy > 0.0:
        nxin = -nxin
        nyin = -nyin
    if tout >= BIG:
        tout = tin
    return tin, tout, nxin, nyin


@njit(**_JIT)
def lidar_scan(ox, oy, yaw, cos_b, sin_b, rmax, x0, y0, res, cells, tiles, ntx, kinds, pstart, pcount, verts,
               circles, balls, noise, rmin, near_mode, out):
    """Ranges (m) of every beam into ``out``; returns the number of cells looked at (see :func:`march`).

    ``tiles`` (with ``ntx`` tiles a row), when not empty, is the same raster as ``cells`` in the
    one-byte tiled form of a one-shape raster (see :func:`march_tiles`), which is then marched.

    ``balls``: (m, 3) circles (x, y, radius) cut by the scan plane, intersected analytically.
    ``near_mode`` < 0: exact distances, ``inf`` where nothing is hit within ``rmax``. Otherwise
    the device's reading: the distance plus ``noise[i]`` (when ``noise`` has one value per beam),
    0 beyond ``rmax`` or with no return, and nearer than ``rmin`` 0 (``near_mode`` 0) or ``rmin``
    (``near_mode`` 1).
    """
    noisy = noise.shape[0] == cos_b.shape[0]
    inv = 1.0 / res
    px = (ox - x0) * inv
    py = (oy - y0) * inv
    cyaw = math.cos(yaw)
    syaw = math.sin(yaw)
    tmax = rmax * inv + 2.0
    tol = 2.5 * res
    total = 0
    tiled = tiles.shape[0] > 0
    ny, nx = cells.shape
    # every beam's first look is at the LIDAR's own cell: when that is clear of the shapes, its
    # jump is the same for all beams (the same arithmetic as march's first step): take it once
    t0 = 0.0
    if 0.0 <= px < nx and 0.0 <= py < ny:
        ix0 = int(math.floor(px))
        iy0 = int(math.floor(py))
        if tiled:
            c0 = _tile_at(tiles, ix0, iy0, ntx)
            if c0 != TILE_OCC and c0 > TILE_SKIP_FROM:
                t0 = 0.0 + (c0 * TILE_UNIT - 1.4143)
                total += 1
        else:
            c0 = int(cells[iy0, ix0])
            if c0 < OCC and c0 > SKIP_FROM:
                t0 = 0.0 + (c0 * DT_UNIT - 1.4143)
                total += 1
    nbeams = cos_b.shape[0]
    hit_t = np.empty(nbeams)
    hit_l = np.empty(nbeams, np.int64)
    i = 0
    # two beams at a time (march_tiles_pair, march_pair: the same numbers, the latencies overlap)
    while i + 1 < nbeams:
        dxa = cos_b[i] * cyaw - sin_b[i] * syaw
        dya = sin_b[i] * cyaw + cos_b[i] * syaw
        dxb = cos_b[i + 1] * cyaw - sin_b[i + 1] * syaw
        dyb = sin_b[i + 1] * cyaw + cos_b[i + 1] * syaw
        if tiled:
            ta, la, tb, lb, steps = march_tiles_pair(px, py, dxa, dya, dxb, dyb, t0, tmax, tiles, nx, ny, ntx)
        else:
            ta, la, tb, lb, steps = march_pair(px, py, dxa, dya, dxb, dyb, t0, tmax, cells)
        hit_t[i] = ta
        hit_l[i] = la
        hit_t[i + 1] = tb
        hit_l[i + 1] = lb
        total += steps
        i += 2
    while i < nbeams:
        dx = cos_b[i] * cyaw - sin_b[i] * syaw
        dy = sin_b[i] * cyaw + cos_b[i] * syaw
        if tiled:
            t, lab, steps = march_tiles(px, py, dx, dy, t0, tmax, tiles, nx, ny, ntx)
        else:
            t, lab, side, steps = march(px, py, dx, dy, t0, tmax, cells)
        hit_t[i] = t
        hit_l[i] = lab
        total += steps
        i += 1
    for i in range(nbeams):
        dx = cos_b[i] * cyaw - sin_b[i] * syaw
        dy = sin_b[i] * cyaw + cos_b[i] * syaw
        t = hit_t[i]
        lab = hit_l[i]
        r = BIG
        if lab >= 0:
            r = t * res
            if kinds[lab] != 0:
                te, to, nx_, ny_ = exact(lab, ox, oy, dx, dy, r, tol, kinds, pstart, pcount, verts, circles)
                if te >= 0.0:
                    r = te
        out[i] = _reading(r, ox, oy, dx, dy, balls, noise[i] if noisy else 0.0, rmax, rmin, near_mode)
    return total


@njit(**_JIT)
def lidar_effects(ranges, z, u, frac, dropout, rmin, rmax):
    """The realism profile's LIDAR effects in place (:class:`~qcarlab.sim.realism.LidarEffects`):
    each return (range > 0) times 1 + frac z[i], clipped to rmin..rmax (frac > 0); then 0 where
    u[i] < dropout. One pass; the numbers of the numpy expressions it replaced."""
    for i in range(ranges.shape[0]):
        r = ranges[i]
        if frac > 0.0 and r > 0.0:
            r = min(max(r * (1.0 + frac * z[i]), rmin), rmax)
        if dropout > 0.0 and u[i] < dropout:
            r = 0.0
        ranges[i] = r


@njit(**_INLINE)
def _reading(r, ox, oy, dx, dy, balls, noise, rmax, rmin, near_mode):
    """A beam's reading from the distance ``r`` (m) of its first static hit (BIG: none): the
    nearer of it and the balls (circles (x, y, radius) cut by the scan plane), then as
    :func:`lidar_scan` tells (``near_mode``: -1 exact, inf for none; else noise and limits)."""
    for j in range(balls.shape[0]):
        fx = ox - balls[j, 0]
        fy = oy - balls[j, 1]
        b = fx * dx + fy * dy
        c = fx * fx + fy * fy - balls[j, 2] * balls[j, 2]
        disc = b * b - c
        if disc >= 0.0:
            tb = -b - math.sqrt(disc)
            if 0.0 <= tb < r:
                r = tb
    if near_mode < 0:
        return r if r <= rmax else np.inf
    if r > rmax:
        return 0.0
    r += noise
    if r > rmax:
        return 0.0
    if r < rmin:
        return rmin if near_mode == 1 else 0.0
    return r


@njit(**_JIT)
def lidar_scan_edges(ox, oy, yaw, cos_b, sin_b, a0, da, full, rmax, edges, kinds, circles, balls, noise, rmin,
                     near_mode, out):
    """:func:`lidar_scan` for a world of polygons and circles alone, found per *edge*: beam i looks
    along body angle a0 + i da (``full``: a whole turn, da = 2 pi / beams; else a sector), with
    direction (cos_b[i], sin_b[i]); each polygon edge (``edges``, see :func:`edge_table`) is
    intersected with just the beams whose angles it spans (an edge's points a + s (b - a), s in
    [0, 1)), each circle likewise, and a beam keeps its nearest crossing. From inside a shape
    every beam's first hit is at 0 (as the raster's march finds it). Returns the number of
    beam-edge intersections computed (the work it took)."""
    n = cos_b.shape[0]
    cyaw = math.cos(yaw)
    syaw = math.sin(yaw)
    noisy = noise.shape[0] == n
    dist = np.full(n, BIG)
    work = 0
    twopi = 2.0 * math.pi
    # inside a polygon (even-odd rule along +x) or a circle: every beam hits at 0
    inside = False
    crossings = 0
    last = -1.0
    for e in range(edges.shape[0]):
        lab = edges[e, 4]
        if lab != last:
            if crossings % 2 == 1:
                inside = True
            crossings = 0
            last = lab
        ay = edges[e, 1] - oy
        by = edges[e, 3] - oy
        if (ay > 0.0) != (by > 0.0):
            ax = edges[e, 0] - ox
            bx = edges[e, 2] - ox
            if ax + (0.0 - ay) * (bx - ax) / (by - ay) > 0.0:
                crossings += 1
    if crossings % 2 == 1:
        inside = True
    for lab in range(kinds.shape[0]):
        if kinds[lab] == 2:
            qx = circles[lab, 0] - ox
            qy = circles[lab, 1] - oy
            if qx * qx + qy * qy < circles[lab, 2] * circles[lab, 2]:
                inside = True
    if inside:
        for i in range(n):
            dist[i] = 0.0
    else:
        for e in range(edges.shape[0]):
            ax = edges[e, 0] - ox
            ay = edges[e, 1] - oy
            bx = edges[e, 2] - ox
            by = edges[e, 3] - oy
            # the beams between the ends' angles (the short way round: the edge misses the sensor)
            pa = math.atan2(ay, ax) - yaw
            pb = math.atan2(by, bx) - yaw
            w = (pb - pa) % twopi
            if w > math.pi:
                lo = pb
                w = twopi - w
            else:
                lo = pa
            lo = (lo - a0) % twopi  # from beam 0's angle, in [0, 2 pi)
            ex = bx - ax
            ey = by - ay
            for shift in range(2 if not full else 1):
                base = lo - shift * twopi
                k0 = int(math.floor(base / da)) - 1
                k1 = int(math.floor((base + w) / da)) + 1
                if not full:
                    k0 = max(k0, 0)
                    k1 = min(k1, n - 1)
                for kk in range(k0, k1 + 1):
                    i = kk % n if full else kk
                    dx = cos_b[i] * cyaw - sin_b[i] * syaw
                    dy = sin_b[i] * cyaw + cos_b[i] * syaw
                    work += 1
                    den = dx * ey - dy * ex
                    if den == 0.0:
                        continue
                    sn = ax * dy - ay * dx
                    if den > 0.0:
                        if sn < 0.0 or sn >= den:
                            continue
                    elif sn > 0.0 or sn <= den:
                        continue
                    tt = (ax * ey - ay * ex) / den
                    if 0.0 <= tt < dist[i]:
                        dist[i] = tt
        for lab in range(kinds.shape[0]):
            if kinds[lab] != 2:
                continue
            qx = circles[lab, 0] - ox
            qy = circles[lab, 1] - oy
            r = circles[lab, 2]
            d = math.sqrt(qx * qx + qy * qy)
            th = (math.atan2(qy, qx) - yaw - a0) % twopi
            al = math.asin(min(r / d, 1.0))
            for shift in range(2 if not full else 1):
                base = th - al - shift * twopi
                k0 = int(math.floor(base / da)) - 1
                k1 = int(math.floor((base + 2.0 * al) / da)) + 1
                if not full:
                    k0 = max(k0, 0)
                    k1 = min(k1, n - 1)
                for kk in range(k0, k1 + 1):
                    i = kk % n if full else kk
                    dx = cos_b[i] * cyaw - sin_b[i] * syaw
                    dy = sin_b[i] * cyaw + cos_b[i] * syaw
                    work += 1
                    b = -(qx * dx + qy * dy)
                    disc = b * b - (qx * qx + qy * qy - r * r)
                    if disc < 0.0:
                        continue
                    tt = -b - math.sqrt(disc)
                    if 0.0 <= tt < dist[i]:
                        dist[i] = tt
    for i in range(n):
        dx = cos_b[i] * cyaw - sin_b[i] * syaw
        dy = sin_b[i] * cyaw + cos_b[i] * syaw
        out[i] = _reading(dist[i], ox, oy, dx, dy, balls, noise[i] if noisy else 0.0, rmax, rmin, near_mode)
    return work


@njit(**_JIT)
def _row_of(z, d, cam_z, k, fy, cy):
    return cy - (z - cam_z) * k * fy / d


@njit(**_JIT)
def _pack(b, g, r):
    """Channel values (floats, clipped to 0..255) as one BGRA uint32 pixel, alpha 255."""
    ib = int(min(max(b, 0.0), 255.0))
    ig = int(min(max(g, 0.0), 255.0))
    ir = int(min(max(r, 0.0), 255.0))
    if LITTLE_ENDIAN:
        return np.uint32(ib | (ig << 8) | (ir << 16) | (255 << 24))
    return np.uint32((ib << 24) | (ig << 16) | (ir << 8) | 255)


@njit(**_JIT)
def render_columns(
    color, depth, floor_depth, sky, sky_rows, markers, ox, oy, cam_z, yaw, cos_c, sin_c, kcol, fy, cy, max_dist,
    x0, y0, res, cells, kinds, heights, colors, pstart, pcount, verts, circles,
    gain, gx0, gy0, gres, balls, light_x, light_y,
):
    """Draw the walls, obstacles and balls of every column of a level camera over the floor.

    ``color`` (W, H) uint32 (packed BGRA pixels, see :func:`pack_bgr`) and ``depth`` (W, H)
    float32 are *transposed* images (one row per image column) of a cylindrical view (the CSI
    cameras; the RGBD camera is drawn by :func:`column_layers` and :func:`compose_rows`). With
    ``markers`` each column's colour is first cleared to 0, "nothing drawn here" (every drawn
    pixel has alpha 255, and a depth), and its depth left as it was, for a caller to fill.
    Otherwise ``color`` already holds the floor below row ``sky_rows``, and each column first
    gets the background ``sky`` (a packed pixel) above that row and the depth of the floor
    (``floor_depth``, same shape, inf above the horizon). Then this paints, far to near, each
    column's visible bands. Column u looks along body azimuth (cos_c[u], sin_c[u]); a point at
    horizontal distance d along it and height z is at row cy - (z - cam_z) * kcol[u] * fy / d and
    has depth d / kcol[u] (the z-depth of a pinhole; kcol = 1 for a cylindrical panorama).
    ``balls``: (m, 6) x, y, radius, B, G, R of spheres resting on the floor.
    """
    W = color.shape[0]
    H = color.shape[1]
    inv = 1.0 / res
    px = (ox - x0) * inv
    py = (oy - y0) * inv
    cyaw = math.cos(yaw)
    syaw = math.sin(yaw)
    tmax = max_dist * inv
    tol = 2.5 * res
    gny, gnx = gain.shape
    nb = balls.shape[0]
    hd = np.empty(KMAX + 8)  # entry distance (m)
    ho = np.empty(KMAX + 8)  # exit distance (m)
    hl = np.empty(KMAX + 8, np.int64)  # label, or -2 - ball index
    hnx = np.empty(KMAX + 8)
    hny = np.empty(KMAX + 8)
    for u in range(W):
        if markers:
            color[u, :] = 0  # (the depth of undrawn pixels is left as it was: colour 0 tells)
        else:
            color[u, :sky_rows] = sky
            drow = depth[u]
            frow = floor_depth[u]
            for v in range(H):  # a loop: numba copies a slice assignment through a temporary
                drow[v] = frow[v]
        dx = cos_c[u] * cyaw - sin_c[u] * syaw
        dy = sin_c[u] * cyaw + cos_c[u] * syaw
        k = kcol[u]
        n = 0
        t = 0.0
        vcover = float(H)
        while n < KMAX:
            t, lab, side, _ = march(px, py, dx, dy, t, tmax, cells)
            if lab < 0:
                break
            din = t * res
            # grid walls: shade as if facing the ray (the cells' staircase would stripe them)
            nxv = -dx
            nyv = -dy
            ts = t  # where the walk through the shape's cells starts
            te = -1.0
            to = 0.0
            ex_ = 0.0
            ey_ = 0.0
            if kinds[lab] != 0:
                te, to, ex_, ey_ = exact(lab, ox, oy, dx, dy, din, tol, kinds, pstart, pcount, verts, circles)
                if te >= 0.0:
                    # the exact exit is known: walk only the last cells before it (a thick wall
                    # would otherwise cost a step per cell)
                    ts = max(t, to * inv - 2.0)
            t2, nextlab = skip(px, py, dx, dy, ts, tmax, cells, lab)
            dout = t2 * res
            if te >= 0.0:
                din = te
                nxv = ex_
                nyv = ey_
                if abs(to - dout) < tol:
                    dout = to
            if din < 1e-3:
                din = 1e-3
            hd[n] = din
            ho[n] = max(dout, din)
            hl[n] = lab
            hnx[n] = nxv
            hny[n] = nyv
            n += 1
            h = heights[lab]
            if h >= cam_z:
                vtop = _row_of(h, din, cam_z, k, fy, cy)
            else:
                vtop = _row_of(h, max(dout, din), cam_z, k, fy, cy)
            if vtop < vcover:
                vcover = vtop
            if vcover <= 0.0:
                break
            t = t2 + 1e-4  # just past the exit boundary (so rounding cannot land back inside)
        # balls: spheres cut by this column's vertical plane
        for j in range(nb):
            if n >= KMAX + 8:
                break
            fx = balls[j, 0] - ox
            fy_ = balls[j, 1] - oy
            dc = fx * dx + fy_ * dy
            e = abs(fx * dy - fy_ * dx)
            r = balls[j, 2]
            if dc <= 0.0 or e >= r:
                continue
            if n > 0 and dc - r > hd[n - 1] and vcover <= 0.0:
                continue
            hd[n] = dc
            ho[n] = dc
            hl[n] = -2 - j
            hnx[n] = e
            hny[n] = 0.0
            n += 1
        # painter's order: far to near (insertion sort by entry distance, descending)
        for a in range(1, n):
            b = a
            while b > 0 and hd[b] > hd[b - 1]:
                hd[b], hd[b - 1] = hd[b - 1], hd[b]
                ho[b], ho[b - 1] = ho[b - 1], ho[b]
                hl[b], hl[b - 1] = hl[b - 1], hl[b]
                hnx[b], hnx[b - 1] = hnx[b - 1], hnx[b]
                hny[b], hny[b - 1] = hny[b - 1], hny[b]
                b -= 1
        for a in range(n):
            lab = hl[a]
            din = hd[a]
            if lab <= -2:  # a ball
                j = -2 - lab
                r = balls[j, 2]
                e = hnx[a]
                rs = math.sqrt(r * r - e * e)
                vt = _row_of(r + rs, din, cam_z, k, fy, cy)
                vb = _row_of(r - rs, din, cam_z, k, fy, cy)
                r0 = max(int(math.ceil(vt)), 0)
                r1 = min(int(math.floor(vb)), H - 1)
                hx = ox + dx * din
                hy = oy + dy * din
                gi = int((hy - gy0) / gres)
                gj = int((hx - gx0) / gres)
                g = gain[gi, gj] if 0 <= gi < gny and 0 <= gj < gnx else 1.0
                zdep = max((din - rs) / k, 1e-6)  # > 0 even from inside the ball (0 = nothing)
                for v in range(r0, r1 + 1):
                    z = cam_z - (v - cy) * din / (k * fy)
                    q = (z - r) / r
                    lat = e / r
                    s2 = 1.0 - q * q - lat * lat
                    sh = (0.35 + 0.65 * math.sqrt(s2) if s2 > 0.0 else 0.35) * g
                    color[u, v] = _pack(balls[j, 3] * sh, balls[j, 4] * sh, balls[j, 5] * sh)
                    depth[u, v] = zdep
                continue
            h = heights[lab]
            dout = ho[a]
            hx = ox + dx * din
            hy = oy + dy * din
            gi = int((hy - gy0) / gres)
            gj = int((hx - gx0) / gres)
            g = gain[gi, gj] if 0 <= gi < gny and 0 <= gj < gnx else 1.0
            lam = abs(hnx[a] * light_x + hny[a] * light_y)
            sh = (0.72 + 0.28 * lam) * g
            # front face
            vt = _row_of(h, din, cam_z, k, fy, cy)
            vb = _row_of(0.0, din, cam_z, k, fy, cy)
            r0 = max(int(math.ceil(vt)), 0)
            r1 = min(int(math.floor(vb)), H - 1)
            cf = _pack(colors[lab, 0] * sh, colors[lab, 1] * sh, colors[lab, 2] * sh)
            zd = np.float32(din / k)
            color[u, r0 : r1 + 1] = cf  # slice fills: vectorised, about 2x the loop
            depth[u, r0 : r1 + 1] = zd
            # top face, seen from above when the shape is lower than the camera
            if h < cam_z and dout > din:
                vtt = _row_of(h, dout, cam_z, k, fy, cy)
                r0 = max(int(math.ceil(vtt)), 0)
                r1 = min(int(math.ceil(vt)) - 1, H - 1)
                ct = _pack(colors[lab, 0] * 1.12 * g, colors[lab, 1] * 1.12 * g, colors[lab, 2] * 1.12 * g)
                for v in range(r0, r1 + 1):
                    color[u, v] = ct
                    depth[u, v] = (cam_z - h) * fy / (v - cy) if v > cy else 0.0


@njit(**_INLINE)
def _finish_depth_row(row, noise, nv, nb, noisy, c, lo, hi):
    W = row.shape[0]
    if noisy:
        nrow = noise[nv, nb : nb + W]
        for u in range(W):
            d = row[u]
            d = np.float32(0.0) if d > hi else d
            d = d + c * (d * d * np.float32(nrow[u]))
            row[u] = np.float32(0.0) if (d > hi) | (d <= lo) else d
    else:
        for u in range(W):
            d = row[u]
            row[u] = np.float32(0.0) if (d > hi) | (d <= lo) else d


@njit(**_INLINE)
def _floor_depth_row(row, fz, noise, nv, nb, noisy, c, lo, hi):
    """A row that shows the floor alone, finished (:func:`_finish_depth_row` on a row of ``fz``,
    the same numbers, without filling it first)."""
    W = row.shape[0]
    d = np.float32(0.0) if fz > hi else np.float32(fz)
    if noisy:
        dd = d * d
        nrow = noise[nv, nb : nb + W]
        for u in range(W):
            e = d + c * (dd * np.float32(nrow[u]))
            row[u] = np.float32(0.0) if (e > hi) | (e <= lo) else e
    else:
        e = np.float32(0.0) if (d > hi) | (d <= lo) else d
        for u in range(W):
            row[u] = e


@njit(**_JIT)
def finish_depth(depth, noise, na, nb, coef, dmin, dmax):
    """The depth image as the D435 reports it, in place: ``depth`` (H, W) float32 z-depth (inf =
    nothing) -> 0 beyond ``dmax``, plus noise ``coef * z^2 * noise[na + v, nb + u]`` (when
    ``noise`` is not empty; int8 steps of a standard deviation times ``coef``, see
    ``camera.DEPTH_TILE_STEP``), then 0 beyond ``dmax`` and at or nearer than ``dmin``.

    One pass, row by row over contiguous slices so that LLVM vectorises it (about 4x the three
    OpenCV passes it replaces).
    """
    noisy = noise.shape[0] > 0
    c = np.float32(coef)
    lo = np.float32(dmin)
    hi = np.float32(dmax)
    for v in range(depth.shape[0]):
        _finish_depth_row(depth[v], noise, na + v, nb, noisy, c, lo, hi)


# --------------------------------------------------------------------------------------------
# the RGBD camera, row-major: layers per column, then one pass per image row
# --------------------------------------------------------------------------------------------
LMAX = 2 * (KMAX + 8)  # layers a column may hold: a front face and a top face per hit, balls
NO_ROW = 1 << 30  # an empty layer's top row


@njit(**_JIT)
def _word(b, g, r):
    """Channel values (floats, clipped to 0..255) as one packed pixel B | G << 8 | R << 16 | 255 << 24
    (an integer: the same on any byte order; as bytes on a little-endian machine, BGRA)."""
    ib = int(min(max(b, 0.0), 255.0))
    ig = int(min(max(g, 0.0), 255.0))
    ir = int(min(max(r, 0.0), 255.0))
    return np.uint32(ib | (ig << 8) | (ir << 16) | (255 << 24))


CMAX = 32  # edge crossings a column may hold in the vector path (more: the frame is marched instead)
NEAR = 1e-3  # m: crossings nearer than this to the camera are not seen
TIE = 1e-9  # m: hits this close are at the same distance (coinciding faces)


@njit(**_JIT)
def vector_crossings(cr_t, cr_e, ncr, ox, oy, yaw, cos_c, sin_c, fx, cx, edges, kinds, circles):
    """Where every column's ray (a level pinhole's: column u looks along body azimuth (cos_c[u],
    sin_c[u]), u = cx - fx tan(azimuth)) crosses the shapes' outlines, found per *edge*: each
    polygon edge in front of the camera is projected to the columns it spans and intersected
    with just those rays (a circle likewise). ``cr_t[u, i]`` (m along the ray) and ``cr_e[u, i]``
    (the edge's row in ``edges``, or -1 - label for a circle), ``ncr[u]`` crossings, unordered.
    An edge's points are a + s (b - a) with s in [0, 1), so a ray through a shared vertex
    crosses once. Returns False when a column has more than CMAX crossings."""
    W = cos_c.shape[0]
    cyaw = math.cos(yaw)
    syaw = math.sin(yaw)
    for u in range(W):
        ncr[u] = 0
    for e in range(edges.shape[0]):
        ax = edges[e, 0] - ox
        ay = edges[e, 1] - oy
        bx = edges[e, 2] - ox
        by = edges[e, 3] - oy
        fa = ax * cyaw + ay * syaw  # forward and left of the camera
        la = -ax * syaw + ay * cyaw
        fb = bx * cyaw + by * syaw
        lb = -bx * syaw + by * cyaw
        if fa < NEAR and fb < NEAR:
            continue
        if fa < NEAR:
            q = (NEAR - fa) / (fb - fa)
            la = la + q * (lb - la)
            fa = NEAR
        elif fb < NEAR:
            q = (NEAR - fb) / (fa - fb)
            lb = lb + q * (la - lb)
            fb = NEAR
        ua = cx - fx * la / fa
        ub = cx - fx * lb / fb
        u0 = max(int(math.floor(min(ua, ub))), 0)
        u1 = min(int(math.ceil(max(ua, ub))), W - 1)
        ex = bx - ax
        ey = by - ay
        for u in range(u0, u1 + 1):
            dx = cos_c[u] * cyaw - sin_c[u] * syaw
            dy = sin_c[u] * cyaw + cos_c[u] * syaw
            den = dx * ey - dy * ex
            if den == 0.0:
                continue
            sn = ax * dy - ay * dx  # the crossing's place along the edge: s = sn / den
            if den > 0.0:
                if sn < 0.0 or sn >= den:
                    continue
            elif sn > 0.0 or sn <= den:
                continue
            tt = (ax * ey - ay * ex) / den
            if tt < NEAR:
                continue
            c = ncr[u]
            if c >= CMAX:
                return False
            cr_t[u, c] = tt
            cr_e[u, c] = e
            ncr[u] = c + 1
    for lab in range(kinds.shape[0]):
        if kinds[lab] != 2:
            continue
        qx = circles[lab, 0] - ox
        qy = circles[lab, 1] - oy
        r = circles[lab, 2]
        fc = qx * cyaw + qy * syaw
        lc = -qx * syaw + qy * cyaw
        dist = math.sqrt(fc * fc + lc * lc)
        if fc + r < NEAR:
            continue
        if dist <= r * 1.000001 or fc - r < NEAR:  # around or beside the camera: every column
            u0 = 0
            u1 = W - 1
        else:
            th = math.atan2(lc, fc)
            al = math.asin(r / dist)
            u0 = max(int(math.floor(cx - fx * math.tan(min(th + al, 1.5707)))), 0)
            u1 = min(int(math.ceil(cx - fx * math.tan(max(th - al, -1.5707)))), W - 1)
        for u in range(u0, u1 + 1):
            dx = cos_c[u] * cyaw - sin_c[u] * syaw
            dy = sin_c[u] * cyaw + cos_c[u] * syaw
            b = -(qx * dx + qy * dy)
            cc = qx * qx + qy * qy - r * r
            disc = b * b - cc
            if disc < 0.0:
                continue
            sq = math.sqrt(disc)
            for tt in (-b - sq, -b + sq):
                if tt < NEAR:
                    continue
                c = ncr[u]
                if c >= CMAX:
                    return False
                cr_t[u, c] = tt
                cr_e[u, c] = -1 - lab
                ncr[u] = c + 1
    return True


@njit(**_INLINE)
def _vector_hits(u, dx, dy, ox, oy, cr_t, cr_e, ncr, edges, circles, hd, ho, hl, hnx, hny):
    """The crossings of column u (:func:`vector_crossings`) as hits, nearest first: per shape,
    its crossings in order pair up as (entry, exit); an odd count means the camera is inside
    (the first crossing is its exit, the entry at NEAR). Returns how many (at most KMAX + 8)."""
    m = ncr[u]
    ts = cr_t[u]
    es = cr_e[u]
    # order by (label, distance): insertion sort of a few entries
    for a in range(1, m):
        b = a
        while b > 0:
            la = es[b] if es[b] < 0 else -1 - int(edges[es[b], 4])
            lb = es[b - 1] if es[b - 1] < 0 else -1 - int(edges[es[b - 1], 4])
            if lb < la or (lb == la and ts[b - 1] <= ts[b]):
                break
            ts[b], ts[b - 1] = ts[b - 1], ts[b]
            es[b], es[b - 1] = es[b - 1], es[b]
            b -= 1
    n = 0
    i = 0
    while i < m:
        e0 = es[i]
        lab = -1 - e0 if e0 < 0 else int(edges[e0, 4])
        j = i
        while j < m and (-1 - es[j] if es[j] < 0 else int(edges[es[j], 4])) == lab:
            j += 1
        k = i
        if (j - i) % 2 == 1:  # inside the shape
            if n < KMAX + 8:
                hd[n] = NEAR
                ho[n] = ts[k]
                hl[n] = lab
                hnx[n] = -dx
                hny[n] = -dy
                n += 1
            k += 1
        while k + 1 < j:
            if n >= KMAX + 8:
                break
            tin = ts[k]
            e = es[k]
            if e >= 0:
                ex = edges[e, 2] - edges[e, 0]
                ey = edges[e, 3] - edges[e, 1]
                ln = math.sqrt(ex * ex + ey * ey)
                nxv = ey / ln
                nyv = -ex / ln
            else:
                r = circles[lab, 2]
                nxv = (ox + tin * dx - circles[lab, 0]) / r
                nyv = (oy + tin * dy - circles[lab, 1]) / r
            if nxv * dx + nyv * dy > 0.0:
                nxv = -nxv
                nyv = -nyv
            hd[n] = tin
            ho[n] = ts[k + 1]
            hl[n] = lab
            hnx[n] = nxv
            hny[n] = nyv
            n += 1
            k += 2
        i = j
    # nearest first; of two shapes entered at the same distance (faces that coincide) the one
    # drawn later into the raster (the higher label) first, as the raster's cells tell
    for a in range(1, n):
        b = a
        while b > 0 and (hd[b] < hd[b - 1] - TIE or (hd[b] <= hd[b - 1] + TIE and hl[b] > hl[b - 1])):
            hd[b], hd[b - 1] = hd[b - 1], hd[b]
            ho[b], ho[b - 1] = ho[b - 1], ho[b]
            hl[b], hl[b - 1] = hl[b - 1], hl[b]
            hnx[b], hnx[b - 1] = hnx[b - 1], hnx[b]
            hny[b], hny[b - 1] = hny[b - 1], hny[b]
            b -= 1
    return n


@njit(**_JIT)
def column_layers(
    ltop, lbot, lcol, lza, lzb, lball, lbd, lbe, lbg, lrange, flo,
    r0, H, ox, oy, cam_z, yaw, cos_c, sin_c, kcol, fx, cx, fy, cy, max_dist,
    x0, y0, res, cells, kinds, heights, colors, pstart, pcount, verts, circles,
    gain, gx0, gy0, gres, balls, light_x, light_y, vector, edges, cr_t, cr_e, ncr,
):
    """What each column of a level pinhole sees, as *layers* for :func:`compose_rows`; returns
    how many layers the busiest column has (L).

    Column u looks along body azimuth (cos_c[u], sin_c[u]) (u = cx - fx tan(azimuth)); a point
    at horizontal distance d and height z along it is at row cy - (z - cam_z) * kcol[u] * fy / d,
    z-depth d / kcol[u]. Its walls and obstacles are found, nearest first, up to the first that
    covers the column or KMAX of them: with ``vector`` (a world of polygons and circles alone)
    analytically from its polygon edges (``edges``, see :func:`edge_table`) by
    :func:`vector_crossings` (scratch ``cr_t``, ``cr_e``, ``ncr``), else (a ROS map's grid; or
    when a column has more than CMAX crossings) by marching the raster (:func:`march`, hits
    refined by :func:`exact`, as :func:`render_columns`); then the balls cut by the column's
    plane. Each becomes layer l = 0, 1, ... of the column, far to near (painter's order): arrays
    (LMAX, W) ``ltop``/``lbot`` (the rows it covers, inclusive; an empty layer has ltop =
    NO_ROW), ``lcol`` (its packed colour, :func:`_word`), depth ``lza + lzb * fy / (v - cy)`` at
    row v (a front face: lza = d / k, lzb = 0; a top face, a horizontal plane at height h:
    lza = 0, lzb = cam_z - h), and for a ball ``lball`` = its index (else -1) with its distance
    ``lbd``, offset ``lbe`` from the column's plane and light gain ``lbg`` (shaded per pixel).
    ``lrange`` (LMAX, 4): each layer's first and last row and first and past-last column over
    all columns. ``flo`` (W,): the first row at or below ``r0`` (the first row below the
    horizon) that no layer covers: the floor is seen only from there down.
    """
    W = cos_c.shape[0]
    inv = 1.0 / res
    px = (ox - x0) * inv
    py = (oy - y0) * inv
    cyaw = math.cos(yaw)
    syaw = math.sin(yaw)
    tmax = max_dist * inv
    tol = 2.5 * res
    gny, gnx = gain.shape
    ginv = 1.0 / gres
    nb = balls.shape[0]
    hd = np.empty(KMAX + 8)  # entry distance (m)
    ho = np.empty(KMAX + 8)  # exit distance (m)
    hl = np.empty(KMAX + 8, np.int64)  # label, or -2 - ball index
    hnx = np.empty(KMAX + 8)
    hny = np.empty(KMAX + 8)
    nlay = np.zeros(W, np.int64)
    if vector:
        vector = vector_crossings(cr_t, cr_e, ncr, ox, oy, yaw, cos_c, sin_c, fx, cx, edges, kinds, circles)
    # the raster march's first look, from the camera's own cell, is the same for every column
    t0 = 0.0
    ny_, nx_ = cells.shape
    if not vector and 0.0 <= px < nx_ and 0.0 <= py < ny_:
        c0 = int(cells[int(math.floor(py)), int(math.floor(px))])
        if c0 < OCC and c0 > SKIP_FROM:
            t0 = c0 * DT_UNIT - 1.4143
    for u in range(W):
        dx = cos_c[u] * cyaw - sin_c[u] * syaw
        dy = sin_c[u] * cyaw + cos_c[u] * syaw
        k = kcol[u]
        kf = k * fy  # a point at distance d, height z is at row cy - (z - cam_z) kf / d
        n = 0
        vcover = float(H)
        if vector:
            nv = _vector_hits(u, dx, dy, ox, oy, cr_t, cr_e, ncr, edges, circles, hd, ho, hl, hnx, hny)
            # keep them up to the first that covers the column (and at most KMAX), leaving out
            # those hidden behind nearer ones: a shape standing on the floor covers its rows from
            # its top (vtop) down to where it meets the floor, and a farther one meets the floor
            # higher up, so one whose top is no higher than the nearer ones' is hidden
            i = 0
            while i < nv and n < KMAX:
                din = hd[i]
                if din > max_dist:
                    break
                h = heights[hl[i]]
                vtop = cy - (h - cam_z) * kf / (din if h >= cam_z else max(ho[i], din))
                if vtop < vcover:
                    hd[n] = hd[i]
                    ho[n] = ho[i]
                    hl[n] = hl[i]
                    hnx[n] = hnx[i]
                    hny[n] = hny[i]
                    n += 1
                    vcover = vtop
                    if vcover <= 0.0:
                        break
                i += 1
        else:
            t = t0
            while n < KMAX:
                t, lab, side, _ = march(px, py, dx, dy, t, tmax, cells)
                if lab < 0:
                    break
                din = t * res
                nxv = -dx  # grid walls: shade as if facing the ray
                nyv = -dy
                ts = t
                te = -1.0
                to = 0.0
                ex_ = 0.0
                ey_ = 0.0
                if kinds[lab] != 0:
                    te, to, ex_, ey_ = exact(lab, ox, oy, dx, dy, din, tol, kinds, pstart, pcount, verts, circles)
                    if te >= 0.0:
                        ts = max(t, to * inv - 2.0)
                t2, nextlab = skip(px, py, dx, dy, ts, tmax, cells, lab)
                dout = t2 * res
                if te >= 0.0:
                    din = te
                    nxv = ex_
                    nyv = ey_
                    if abs(to - dout) < tol:
                        dout = to
                if din < 1e-3:
                    din = 1e-3
                h = heights[lab]
                vtop = cy - (h - cam_z) * kf / (din if h >= cam_z else max(dout, din))
                if vtop < vcover:  # (else hidden behind the nearer ones, see above)
                    hd[n] = din
                    ho[n] = max(dout, din)
                    hl[n] = lab
                    hnx[n] = nxv
                    hny[n] = nyv
                    n += 1
                    vcover = vtop
                    if vcover <= 0.0:
                        break
                t = t2 + 1e-4
        for j in range(nb):
            if n >= KMAX + 8:
                break
            fx_ = balls[j, 0] - ox
            fy_ = balls[j, 1] - oy
            dc = fx_ * dx + fy_ * dy
            e = abs(fx_ * dy - fy_ * dx)
            r = balls[j, 2]
            if dc <= 0.0 or e >= r:
                continue
            if n > 0 and dc - r > hd[n - 1] and vcover <= 0.0:
                continue
            hd[n] = dc
            ho[n] = dc
            hl[n] = -2 - j
            hnx[n] = e
            hny[n] = 0.0
            n += 1
        for a in range(1, n):  # far to near (of equally far shapes the higher label last, on top)
            b = a
            while b > 0 and (hd[b] > hd[b - 1] + TIE or (hd[b] >= hd[b - 1] - TIE and hl[b] < hl[b - 1])):
                hd[b], hd[b - 1] = hd[b - 1], hd[b]
                ho[b], ho[b - 1] = ho[b - 1], ho[b]
                hl[b], hl[b - 1] = hl[b - 1], hl[b]
                hnx[b], hnx[b - 1] = hnx[b - 1], hnx[b]
                hny[b], hny[b - 1] = hny[b - 1], hny[b]
                b -= 1
        m = 0  # layers of this column
        for a in range(n):
            lab = hl[a]
            din = hd[a]
            hx = ox + dx * din
            hy = oy + dy * din
            gi = int((hy - gy0) * ginv)
            gj = int((hx - gx0) * ginv)
            g = gain[gi, gj] if 0 <= gi < gny and 0 <= gj < gnx else 1.0
            if lab <= -2:  # a ball
                j = -2 - lab
                r = balls[j, 2]
                e = hnx[a]
                rs = math.sqrt(r * r - e * e)
                q = kf / din
                top = max(int(math.ceil(cy - (r + rs - cam_z) * q)), 0)
                bot = min(int(math.floor(cy - (r - rs - cam_z) * q)), H - 1)
                if top <= bot:
                    ltop[m, u] = top
                    lbot[m, u] = bot
                    lcol[m, u] = 0
                    lza[m, u] = max((din - rs) / k, 1e-6)  # > 0 even from inside the ball
                    lzb[m, u] = 0.0
                    lball[m, u] = j
                    lbd[m, u] = din
                    lbe[m, u] = e
                    lbg[m, u] = g
                    m += 1
                continue
            h = heights[lab]
            dout = ho[a]
            lam = abs(hnx[a] * light_x + hny[a] * light_y)
            sh = (0.72 + 0.28 * lam) * g
            q = kf / din
            vt = cy - (h - cam_z) * q
            top = max(int(math.ceil(vt)), 0)
            bot = min(int(math.floor(cy + cam_z * q)), H - 1)
            if top <= bot:
                ltop[m, u] = top
                lbot[m, u] = bot
                lcol[m, u] = _word(colors[lab, 0] * sh, colors[lab, 1] * sh, colors[lab, 2] * sh)
                lza[m, u] = din / k
                lzb[m, u] = 0.0
                lball[m, u] = -1
                m += 1
            if h < cam_z and dout > din:  # the top face, seen from above
                top = max(int(math.ceil(cy - (h - cam_z) * kf / dout)), 0)
                bot = min(int(math.ceil(vt)) - 1, H - 1)
                if top <= bot:
                    ltop[m, u] = top
                    lbot[m, u] = bot
                    lcol[m, u] = _word(colors[lab, 0] * 1.12 * g, colors[lab, 1] * 1.12 * g, colors[lab, 2] * 1.12 * g)
                    lza[m, u] = 0.0
                    lzb[m, u] = cam_z - h
                    lball[m, u] = -1
                    m += 1
        nlay[u] = m
        # the first row below the horizon no layer covers
        v = r0
        moved = True
        while moved:
            moved = False
            for l in range(m):
                if ltop[l, u] <= v <= lbot[l, u]:
                    v = lbot[l, u] + 1
                    moved = True
        flo[u] = v
    L = 0
    for u in range(W):
        L = max(L, nlay[u])
    for l in range(L):
        lrange[l, 0] = NO_ROW
        lrange[l, 1] = -1
        lrange[l, 2] = W
        lrange[l, 3] = 0
    for u in range(W):
        for l in range(L):
            if l >= nlay[u]:
                ltop[l, u] = NO_ROW
                lbot[l, u] = -1
                lball[l, u] = -1
                lcol[l, u] = 0
                lza[l, u] = 0.0
                lzb[l, u] = 0.0
            else:
                lrange[l, 0] = min(lrange[l, 0], ltop[l, u])
                lrange[l, 1] = max(lrange[l, 1], lbot[l, u])
                lrange[l, 2] = min(lrange[l, 2], u)
                lrange[l, 3] = max(lrange[l, 3], u + 1)
    return L


@njit(**_JIT)
def _texel(tex, off, tw, th, ix, iy, bg):
    if ix < 0 or iy < 0 or ix >= tw or iy >= th:
        return bg
    return int(tex[off + iy * tw + ix])


@njit(**_JIT)
def _lerp2(a, b, w):
    """Two 8-bit lanes (bits 0-7 and 16-23 of a and b) blended as a + (b - a) w / 256, rounded."""
    return ((a * (256 - w) + b * w + 0x00800080) >> 8) & 0x00FF00FF


@njit(**_JIT)
def _bilinear(p00, p01, p10, p11, wx, wy):
    """Bilinear blend of four packed pixels (weights wx, wy in 0..256 for the second column / row)."""
    m = 0x00FF00FF
    rb = _lerp2(_lerp2(p00 & m, p01 & m, wx), _lerp2(p10 & m, p11 & m, wx), wy)
    ga = _lerp2(_lerp2((p00 >> 8) & m, (p01 >> 8) & m, wx), _lerp2((p10 >> 8) & m, (p11 >> 8) & m, wx), wy)
    return (rb | (ga << 8)) | 0xFF000000


@njit(**_JIT)
def _gain_word(p, lut):
    """A packed pixel's B, G, R bytes through ``lut`` (256 values: the exposure's
    saturate(rint(gain c)), see ``camera.exposure_lut``), its top byte kept."""
    q = np.uint64(p)  # (unsigned: the table is read without numba's fix-up for a negative index)
    m = np.uint64(255)
    return np.uint32((np.int64(q) & 0xFF000000) | lut[q & m] | (lut[(q >> np.uint64(8)) & m] << 8)
                     | (lut[(q >> np.uint64(16)) & m] << 16))


@njit(**_JIT)
def exposure_table(gain, out):
    """``out`` (256,) = saturate(rint(gain c)) for c = 0..255 in float32 (the exposure's table,
    ``cv2.convertScaleAbs``'s numbers)."""
    g = np.float32(gain)
    for c in range(256):
        out[c] = int(min(np.rint(np.float32(c) * g), np.float32(255.0)))


@njit(**_JIT)
def gain_words(words, lut):
    """:func:`_gain_word` on every packed pixel of ``words`` (1-D uint32), in place."""
    for i in range(words.shape[0]):
        words[i] = _gain_word(words[i], lut)


@njit(**_INLINE)
def _floor_row(crow, v, flo, tex, sq, off, tw, th, X0, dX, Y0, dY, bg, bu, b00, b01, b10, b11, bwx, bwy, lut, gain):
    """Row v of the floor into ``crow`` where ``flo[u] <= v``: bilinear samples of a texture level
    (``tex[off:]``, tw x th packed texels, see ``raster.floor_runs``) at texel (X0 + u dX,
    Y0 + u dY) / 65536 (16.16 fixed point; texel centres at integers); ``bg`` outside the
    texture.

    A sample whose block (the 2 x 2 texels it reads) is uniform reads texel (ix, iy) exactly,
    and so does every sample whose block lies in the square of uniform blocks that has (ix, iy)
    at its corner and extends the way the row moves (``sq[off:]``, its side S >= 1, the row's
    quadrant of ``FloorRuns.squares``; 0: the block is not uniform): x in [ix, ix + S) when
    dX > 0, (ix - S, ix] when dX < 0, y likewise. The samples of a row lie on a line, so the
    pixels up to the first that leaves that square are filled at once (the same numbers as
    blending each). The other samples are gathered (scratch ``bu``, ``b00``.., ``bwx``,
    ``bwy``) and blended in one vectorised pass. With a ``lut`` (not empty: the exposure
    ``gain``'s table) each sampled colour gets the exposure (:func:`_gain_word`; once per run)."""
    W = crow.shape[0]
    # 2^38 / |d|, rounded down: q * inv >> 38 is floor(q / |d|) or one less (q < 2^24), never
    # more, so a run never leaves its square (an integer multiply on the run's critical path
    # instead of two conversions and a float multiply)
    inv_x = (1 << 38) // abs(dX) if dX != 0 else 0
    inv_y = (1 << 38) // abs(dY) if dY != 0 else 0
    gained = lut.shape[0] > 0
    last_in = np.uint32(0)
    last_out = _gain_word(last_in, lut) if gained else last_in
    n = 0
    u = 0
    # (indices unsigned where they are known not to be negative: numba then reads and writes
    # without its fix-up for a negative index, a good part of the gather's time)
    twu = np.uint64(tw)
    one = np.uint64(1)
    while u < W:
        if flo[np.uint64(u)] > v:  # covered by a layer: on to the next column the floor shows in
            u += 1
            while u < W and flo[np.uint64(u)] > v:
                u += 1
            continue
        X = X0 + u * dX
        Y = Y0 + u * dY
        ix = X >> 16
        iy = Y >> 16
        if ix >= 0 and iy >= 0 and ix + 1 < tw and iy + 1 < th:
            k = np.uint64(off + iy * tw + ix)
            R = int(sq[k])
            if R > 0:
                # how many more pixels stay in the square
                m = W - 1 - u
                fx = X & 0xFFFF
                fy = Y & 0xFFFF
                if dX > 0:
                    m = min(m, (((R << 16) - fx - 1) * inv_x) >> 38)
                elif dX < 0:
                    m = min(m, (((((R - 1) << 16) + fx)) * inv_x) >> 38)
                if dY > 0:
                    m = min(m, (((R << 16) - fy - 1) * inv_y) >> 38)
                elif dY < 0:
                    m = min(m, (((((R - 1) << 16) + fy)) * inv_y) >> 38)
                w = tex[k] | np.uint32(0xFF000000)
                if gained:  # runs of one colour follow each other: one conversion per colour
                    if w != last_in:
                        last_in = w
                        last_out = _gain_word(w, lut)
                    w = last_out
                seg = crow[u : u + m + 1]  # (a loop from 0: vectorised)
                for i in range(m + 1):
                    seg[i] = w
                u += m + 1
                continue
            nn = np.uint64(n)
            b00[nn] = int(tex[k])
            b01[nn] = int(tex[k + one])
            b10[nn] = int(tex[k + twu])
            b11[nn] = int(tex[k + twu + one])
        else:
            nn = np.uint64(n)
            b00[nn] = _texel(tex, off, tw, th, ix, iy, bg)
            b01[nn] = _texel(tex, off, tw, th, ix + 1, iy, bg)
            b10[nn] = _texel(tex, off, tw, th, ix, iy + 1, bg)
            b11[nn] = _texel(tex, off, tw, th, ix + 1, iy + 1, bg)
        bwx[nn] = (X >> 8) & 255
        bwy[nn] = (Y >> 8) & 255
        bu[nn] = u
        n += 1
        u += 1
    for i in range(n):
        b00[i] = _bilinear(b00[i], b01[i], b10[i], b11[i], bwx[i], bwy[i])
    if gained:  # the table's numbers, computed (vectorised: a lookup per channel is not)
        g = np.float32(gain)
        top = np.float32(255.0)
        for i in range(n):
            q = b00[i]
            yb = min(np.rint(np.float32(q & 255) * g), top)
            yg = min(np.rint(np.float32((q >> 8) & 255) * g), top)
            yr = min(np.rint(np.float32((q >> 16) & 255) * g), top)
            b00[i] = (q & 0xFF000000) | np.int64(yb) | (np.int64(yg) << 8) | (np.int64(yr) << 16)
    for i in range(n):
        crow[bu[i]] = np.uint32(b00[i])


@njit(**_INLINE)
def _noise_row(dst, nrow):
    """A row of colour bytes in place: ``dst = saturate(dst + nrow)`` (int8 noise; empty: none),
    in 16-bit lanes (written so that LLVM vectorises it)."""
    if nrow.shape[0] > 0:
        for i in range(dst.shape[0]):
            x = np.int16(dst[i]) + np.int16(nrow[i])
            x = np.int16(x) if np.int16(x) > np.int16(0) else np.int16(0)
            x = x if x < np.int16(255) else np.int16(255)
            dst[i] = np.uint8(x)


@njit(**_INLINE)
def _noisy_copy(dst, src, nrow):
    """``dst = saturate(src + nrow)`` (bytes, int8 noise; empty: a copy): :func:`_noise_row` on a
    copy of ``src``, in one pass."""
    if nrow.shape[0] > 0:
        for i in range(dst.shape[0]):
            x = np.int16(src[i]) + np.int16(nrow[i])
            x = np.int16(x) if np.int16(x) > np.int16(0) else np.int16(0)
            x = x if x < np.int16(255) else np.int16(255)
            dst[i] = np.uint8(x)
    else:
        for i in range(dst.shape[0]):
            dst[i] = src[i]


@njit(**_JIT)
def color_noise(img, tile, a, b):
    """Colour noise on a frame in place (:func:`_noise_row` on each row): ``img`` (n, 3 w)
    uint8 B, G, R bytes, noise ``tile[a + v, 3 b + i]`` (int8)."""
    w = img.shape[1]
    for v in range(img.shape[0]):
        _noise_row(img[v], tile[a + v, 3 * b : 3 * b + w])


@njit(**_INLINE)
def _bgr_row(dst, crow, nrow):
    """A row of packed pixels as B, G, R bytes into ``dst``, then its colour noise ``nrow``."""
    W = crow.shape[0]
    src = crow.view(np.uint8)  # (B, G, R, A bytes on a little-endian machine)
    if LITTLE_ENDIAN:
        for u in range(W):
            dst[3 * u] = src[4 * u]
            dst[3 * u + 1] = src[4 * u + 1]
            dst[3 * u + 2] = src[4 * u + 2]
    else:  # pragma: no cover - big-endian machines
        for u in range(W):
            dst[3 * u] = src[4 * u + 3]
            dst[3 * u + 1] = src[4 * u + 2]
            dst[3 * u + 2] = src[4 * u + 1]
    _noise_row(dst, nrow)


@njit(**_INLINE)
def _wall_depth_row(row, d, dd, noise, nv, nb, noisy, c, lo, hi):
    """A row one front face covers from end to end (depth ``d`` per column, clipped to 0 above
    ``hi``, and ``dd`` = d d), finished: :func:`_layer_depth_row`'s numbers with its lzb = 0."""
    W = row.shape[0]
    if noisy:
        nrow = noise[nv, nb : nb + W]
        for u in range(W):
            e = d[u] + c * (dd[u] * np.float32(nrow[u]))
            row[u] = np.float32(0.0) if (e > hi) | (e <= lo) else e
    else:
        for u in range(W):
            e = d[u]
            row[u] = np.float32(0.0) if (e > hi) | (e <= lo) else e


@njit(**_INLINE)
def _layer_depth_row(row, za, zb, rf, noise, nv, nb, noisy, c, lo, hi):
    """A row one layer covers from end to end, its depth ``za + zb rf`` finished
    (:func:`_finish_depth_row` after the layer pass, the same numbers, in one pass)."""
    W = row.shape[0]
    if noisy:
        nrow = noise[nv, nb : nb + W]
        for u in range(W):
            d = za[u] + zb[u] * rf
            d = np.float32(0.0) if d > hi else d
            d = d + c * (d * d * np.float32(nrow[u]))
            row[u] = np.float32(0.0) if (d > hi) | (d <= lo) else d
    else:
        for u in range(W):
            d = za[u] + zb[u] * rf
            row[u] = np.float32(0.0) if (d > hi) | (d <= lo) else d


@njit(**_JIT)
def compose_rows(
    color, depth, va, vb, r0, bg, row_depth, rowf,
    ftex, fsq, ftab, row_lev, row_dist, ox, oy, yaw, fx, cx, tx0, ty1, ppm, flo,
    L, ltop, lbot, lcol, lza, lzb, lrange, lball, lbd, lbe, lbg, balls, kcol, cam_z, fy, cy,
    sg_tab, sg_d, sg_pix,
    finish, dnoise, na, nb, coef, dmin, dmax, bgr, cnoise, ca, cb, glut, gain,
):
    """Rows va..vb-1 of a level pinhole's frame, upright, in place: ``color`` (H, W) packed pixels
    (:func:`_word`), ``depth`` (H, W) float32 z-depth (inf = nothing). Each row, in cache:

    1. above row ``r0`` (the horizon) the background ``bg``, depth inf; below it the floor's
       (``bg`` beyond the floor texture too)
       depth ``row_depth[v]`` (a level pinhole sees the floor at one z-depth along a row) and,
       where ``flo[u] <= v``, its colour (:func:`_floor_row`): the floor point of pixel (u, v)
       is at forward distance ``row_dist[v]`` and left offset -(u - cx) row_dist[v] / fx of the
       camera at (ox, oy) heading ``yaw``; the texture level ``row_lev[v]`` (``ftab``: offset,
       width, height in ``ftex``; ``fsq`` the squares of uniform blocks) whose texels match the
       pixel's footprint;
    2. the L layers of :func:`column_layers`, far to near (depth ``lza + lzb rowf[v]``,
       ``rowf[v]`` = fy / (v - cy) below the horizon; balls shaded per pixel);
    3. the stop-sign sprites: ``sg_tab`` (n, 5) rows v0..v1-1, columns u0..u1-1, offset into
       ``sg_pix`` (packed pixels, alpha > 127 = the plate), drawn where nearer than the depth so
       far (``sg_d``);
    4. with ``finish``: the depth as the D435 reports it (see :func:`finish_depth`, noise window
       from row na, column nb).

    With ``bgr`` ((H, 3 W) uint8, not empty) each row's colour goes there as B, G, R bytes
    instead (``color`` is then not written: a row at a time in cache, no second pass), with the
    colour noise ``cnoise`` (int8, window from row ca, pixel column cb; (1, 0): none).

    ``glut`` (the realism profile's exposure ``gain`` as a table of 256 levels; empty = none) maps the
    colours drawn here, the floor's and the balls' (:func:`_gain_word`, once per run of the
    floor, and the background); the caller has mapped the layers' ``lcol`` and the signs'
    ``sg_pix`` (:func:`gain_words`). The colour noise comes after, as the sensor's.
    """
    W = color.shape[1]
    nballs = balls.shape[0]
    sky = _gain_word(bg, glut) if glut.shape[0] > 0 else np.uint32(bg)
    noisy = dnoise.shape[0] > 0
    c = np.float32(coef)
    lo = np.float32(dmin)
    hi = np.float32(dmax)
    inf = np.float32(np.inf)
    cyaw = math.cos(yaw)
    syaw = math.sin(yaw)
    bu = np.empty(W, np.int64)  # the floor's blended samples of a row (see _floor_row)
    b00 = np.empty(W, np.int64)
    b01 = np.empty(W, np.int64)
    b10 = np.empty(W, np.int64)
    b11 = np.empty(W, np.int64)
    bwx = np.empty(W, np.int64)
    bwy = np.empty(W, np.int64)
    to_bgr = bgr.shape[0] > 0
    cnoisy = cnoise.shape[1] > 0
    scratch = np.empty(W, np.uint32)
    flo_min = vb
    for u in range(W):
        flo_min = min(flo_min, flo[u])
    # rows from below_all on: no layer and no sign, the depth is the floor's alone
    below_all = r0
    for l in range(L):
        below_all = max(below_all, lrange[l, 1] + 1)
    for s in range(sg_tab.shape[0]):
        below_all = max(below_all, sg_tab[s, 1])
    # rows full_a..full_b: one layer (no ball) covers every column and no sign is there (a wall
    # across the view): its colours, and its depths finished, in one pass each
    full_a = vb
    full_b = -1
    if finish and L == 1 and nballs == 0 and lrange[0, 2] == 0 and lrange[0, 3] == W:
        full_a = 0
        full_b = vb
        for u in range(W):
            full_a = max(full_a, ltop[0, u])
            full_b = min(full_b, lbot[0, u])
        for s in range(sg_tab.shape[0]):
            if sg_tab[s, 0] <= full_b and sg_tab[s, 1] > full_a:
                full_b = -1
    # those rows' colours are the same in each: their B, G, R bytes made once, each row a copy
    # with its noise (a fifth of a wall row's time, measured)
    walls = max(full_a, va) <= min(full_b, vb - 1)
    wall = np.empty(3 * W if to_bgr and walls else 0, np.uint8)
    if wall.shape[0] > 0:
        _bgr_row(wall, lcol[0], cnoise[0, :0])
    # and a front face (lzb = 0) is as far in each: its depths (and their squares) once too
    flat = walls
    for u in range(W if walls else 0):
        flat &= lzb[0, u] == np.float32(0.0)
    wz = np.empty(W if flat else 0, np.float32)
    wzz = np.empty(W if flat else 0, np.float32)
    for u in range(wz.shape[0]):
        d = lza[0, u]
        wz[u] = np.float32(0.0) if d > hi else d
        wzz[u] = wz[u] * wz[u]
    for v in range(va, vb):
        crow = scratch if to_bgr else color[v]
        drow = depth[v]
        if full_a <= v <= full_b:
            if flat:
                _wall_depth_row(drow, wz, wzz, dnoise, na + v, nb, noisy, c, lo, hi)
            else:
                _layer_depth_row(drow, lza[0], lzb[0], np.float32(rowf[v]), dnoise, na + v, nb, noisy, c, lo, hi)
            if to_bgr:
                _noisy_copy(bgr[v], wall, cnoise[ca + v, 3 * cb : 3 * cb + 3 * W] if cnoisy else cnoise[0, :0])
            else:
                cs = lcol[0]
                for u in range(W):
                    crow[u] = cs[u]
            continue
        if v < r0:
            for u in range(W):
                crow[u] = sky
            for u in range(W):
                drow[u] = inf
        elif v < flo_min:
            pass  # the layers cover every pixel of the row (see column_layers' flo): no floor to draw
        else:
            fz = row_depth[v]
            if not (finish and v >= below_all):  # (else the floor's depth is finished in one pass below)
                for u in range(W):
                    drow[u] = fz
            lev = row_lev[v]
            off = ftab[lev, 0]
            tw = ftab[lev, 1]
            th = ftab[lev, 2]
            sc = ppm / (1 << lev)
            d = row_dist[v]
            lat0 = cx * d / fx  # left offset of column 0
            wx0 = ox + d * cyaw - lat0 * syaw
            wy0 = oy + d * syaw + lat0 * cyaw
            ddx = (d / fx) * syaw  # world step per column: -(d / fx) * (-sin, cos)
            ddy = -(d / fx) * cyaw
            i0 = ((wx0 - tx0) * ppm - 0.5) / (1 << lev)
            j0 = ((ty1 - wy0) * ppm - 0.5) / (1 << lev)
            X0 = int(math.floor(i0 * 65536.0 + 0.5))
            Y0 = int(math.floor(j0 * 65536.0 + 0.5))
            dX = int(math.floor(ddx * sc * 65536.0 + 0.5))
            dY = int(math.floor(-ddy * sc * 65536.0 + 0.5))
            _floor_row(crow, v, flo, ftex, fsq[(1 if dX < 0 else 0) | (2 if dY < 0 else 0)], off, tw, th, X0, dX, Y0, dY,
                       int(bg), bu, b00, b01, b10, b11, bwx, bwy, glut, gain)
        rf = np.float32(rowf[v])
        for l in range(L):
            if v < lrange[l, 0] or v > lrange[l, 1]:
                continue
            ua = lrange[l, 2]
            ub = lrange[l, 3]
            # slices from 0: a loop from an index numba cannot prove >= 0 is not vectorised
            tops = ltop[l, ua:ub]
            bots = lbot[l, ua:ub]
            cols = lcol[l, ua:ub]
            za = lza[l, ua:ub]
            zb = lzb[l, ua:ub]
            cs = crow[ua:ub]
            ds = drow[ua:ub]
            for i in range(ub - ua):
                hit = (tops[i] <= v) & (v <= bots[i])
                cs[i] = cols[i] if hit else cs[i]
                ds[i] = (za[i] + zb[i] * rf) if hit else ds[i]
            if nballs == 0:
                continue
            for u in range(ua, ub):
                j = lball[l, u]
                if j < 0 or ltop[l, u] > v or v > lbot[l, u]:
                    continue
                din = lbd[l, u]
                r = balls[j, 2]
                z = cam_z - (v - cy) * din / (kcol[u] * fy)
                qq = (z - r) / r
                lat = lbe[l, u] / r
                s2 = 1.0 - qq * qq - lat * lat
                sh = (0.35 + 0.65 * math.sqrt(s2) if s2 > 0.0 else 0.35) * lbg[l, u]
                crow[u] = _word(balls[j, 3] * sh, balls[j, 4] * sh, balls[j, 5] * sh)
                if glut.shape[0] > 0:
                    crow[u] = _gain_word(crow[u], glut)
        for s in range(sg_tab.shape[0]):
            v0 = sg_tab[s, 0]
            if v < v0 or v >= sg_tab[s, 1]:
                continue
            u0 = sg_tab[s, 2]
            u1 = sg_tab[s, 3]
            base = sg_tab[s, 4] + (v - v0) * (u1 - u0) - u0
            zs = np.float32(sg_d[s])
            for u in range(u0, u1):
                p = sg_pix[base + u]
                if (p >> 24) > 127 and drow[u] > zs:
                    crow[u] = p | np.uint32(0xFF000000)
                    drow[u] = zs
        if finish and v >= below_all:
            _floor_depth_row(drow, row_depth[v], dnoise, na + v, nb, noisy, c, lo, hi)
        elif finish:
            _finish_depth_row(drow, dnoise, na + v, nb, noisy, c, lo, hi)
        if to_bgr:
            _bgr_row(bgr[v], crow, cnoise[ca + v, 3 * cb : 3 * cb + 3 * W] if cnoisy else cnoise[0, :0])


@njit(**_JIT)
def box_blur_rows(img, b):
    """Each row of ``img`` ((H, 3 W) uint8: W pixels of 3 channels) through a 1 x ``b`` box
    filter, in place (the motion blur; 2 <= b <= W and b <= 257, so that 255 b fits a uint16):

        out[x] = floor(S[x] / b + 1/2),   S[x] = sum over i = x - b//2 .. x - b//2 + b - 1 of row[i]

    per channel, the row mirrored at its ends (OpenCV's BORDER_REFLECT_101: row[-i] = row[i]).
    The window sums by doubling: P_1 = the row, P_2m[j] = P_m[j] + P_m[j + m], and S = the sum
    of the P_2^k of b's binary digits, each shifted past the ones before: log2(b) + popcount(b)
    vector passes over the row, whatever b (``cv2.blur`` took 0.4 ms a frame for b = 2, 4, 6..).
    The division is exact in float32: S + b/2 < 2^17 is exact, and the 1e-4 added lies below
    1/b and above the two roundings' 3e-5 (tested for every S of every b)."""
    H = img.shape[0]
    n = img.shape[1]
    W = n // 3
    a = b // 2
    m = n + 3 * (b - 1)
    top = 0
    while (2 << top) <= b:
        top += 1
    lev = np.empty((top + 1, m), np.uint16)
    acc = np.empty(n, np.uint16)
    half = np.float32(0.5 * b)
    inv = np.float32(1.0 / b)
    eps = np.float32(1e-4)
    for y in range(H):
        row = img[y]
        p = lev[0]
        pa = p[3 * a :]
        for j in range(n):
            pa[j] = row[j]
        for i in range(1, a + 1):
            for c in range(3):
                p[3 * (a - i) + c] = row[3 * i + c]
        for i in range(1, b - a):
            for c in range(3):
                p[3 * (a + W - 1 + i) + c] = row[3 * (W - 1 - i) + c]
        for k in range(1, top + 1):
            q = lev[k - 1]
            d = lev[k]
            s = 3 << (k - 1)
            qs = q[s:]  # (views: an index j from a range is never negative, so the loops vectorise)
            for j in range(m - 2 * s + 3):
                d[j] = q[j] + qs[j]
        t = lev[top]
        for j in range(n):
            acc[j] = t[j]
        off = 3 << top
        for k in range(top - 1, -1, -1):
            if (b >> k) & 1:
                q = lev[k][off:]
                for j in range(n):
                    acc[j] += q[j]
                off += 3 << k
        for j in range(n):
            row[j] = np.uint8(np.int32((np.float32(acc[j]) + half) * inv + eps))


# --------------------------------------------------------------------------------------------
# the collision check (qcarlab.sim.contact.Clearance), edge by edge
# --------------------------------------------------------------------------------------------
@njit(**_JIT)
def _point_rect(qx, qy, a, b):
    return math.hypot(max(abs(qx) - a, 0.0), max(abs(qy) - b, 0.0))


@njit(**_JIT)
def polygon_clearance(p0, p1, first, n_poly, corners, a, b, x, y, c, s):
    """(distance, polygon) from the car's footprint (half sizes ``a`` x ``b``, centred on (x, y),
    heading cos ``c``, sin ``s``) to the nearest of the polygons whose edges run p0[i] -> p1[i],
    polygon k owning edges first[k] .. first[k+1]-1: Clearance's numpy arithmetic one edge at a
    time, the same operations in the same order (so the same numbers, bit for bit)."""
    n = p0.shape[0]
    best, where = math.inf, -1
    for k in range(n_poly):
        e0 = first[k]
        e1 = first[k + 1] if k + 1 < n_poly else n
        dmin = math.inf
        hits = 0
        for i in range(e0, e1):
            dx, dy = p0[i, 0] - x, p0[i, 1] - y
            ax, ay = c * dx + s * dy, -s * dx + c * dy
            dx, dy = p1[i, 0] - x, p1[i, 1] - y
            bx, by = c * dx + s * dy, -s * dx + c * dy
            mx, my = (ax + bx) / 2.0, (ay + by) / 2.0
            hx, hy = (bx - ax) / 2.0, (by - ay) / 2.0
            sep = (abs(mx) > a + abs(hx)) or (abs(my) > b + abs(hy)) \
                or (abs(hx * my - hy * mx) > a * abs(hy) + b * abs(hx))
            d = min(_point_rect(ax, ay, a, b), _point_rect(bx, by, a, b))
            abx, aby = bx - ax, by - ay
            l2 = max(abx * abx + aby * aby, 1e-18)
            dc = math.inf
            for j in range(4):
                cx, cy = corners[j, 0], corners[j, 1]
                u = ((cx - ax) * abx + (cy - ay) * aby) / l2
                u = min(max(u, 0.0), 1.0)
                dc = min(dc, math.hypot(ax + u * abx - cx, ay + u * aby - cy))
            d = min(d, dc)
            if not sep:
                d = 0.0
            if d < dmin:
                dmin = d
            if (ay > 0.0) != (by > 0.0):
                if ax + (0.0 - ay) * abx / aby > 0.0:
                    hits += 1
        if hits % 2 == 1:
            dmin = 0.0
        if dmin < best:
            best, where = dmin, k
    return best, where
