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

try:  # pragma: no cover - which branch runs depends on the install
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False

    def njit(*args, **kwargs):  # type: ignore[no-redef]
        if args and callable(args[0]):
            return args[0]
        return lambda f: f


_JIT = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}

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


@njit(**_JIT)
def dda_axis(d, i, p, t):
    """Grid traversal (Amanatides-Woo) along one axis of a ray with direction component ``d``,
    at cell ``i`` and position ``p`` (cells) at ray parameter ``t``: returns the cell step (-1, 0,
    1), the ray length per cell, and the ray parameter of the next cell boundary."""
    if d > 0.0:
        return 1, 1.0 / d, t + (i + 1 - p) / d
    if d < 0.0:
        return -1, -1.0 / d, t + (i - p) / d
    return 0, BIG, BIG


@njit(**_JIT)
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
        ix = int(math.floor(x))
        iy = int(math.floor(y))
        if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
            return tmax, -1, 0, steps
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


@njit(**_JIT)
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
        ix = int(math.floor(x))
        iy = int(math.floor(y))
        if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
            return tmax, -1, steps
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
    nb = balls.shape[0]
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
    for i in range(cos_b.shape[0]):
        dx = cos_b[i] * cyaw - sin_b[i] * syaw
        dy = sin_b[i] * cyaw + cos_b[i] * syaw
        if tiled:
            t, lab, steps = march_tiles(px, py, dx, dy, t0, tmax, tiles, nx, ny, ntx)
        else:
            t, lab, side, steps = march(px, py, dx, dy, t0, tmax, cells)
        total += steps
        r = BIG
        if lab >= 0:
            r = t * res
            if kinds[lab] != 0:
                te, to, nx_, ny_ = exact(lab, ox, oy, dx, dy, r, tol, kinds, pstart, pcount, verts, circles)
                if te >= 0.0:
                    r = te
        for j in range(nb):
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
            out[i] = r if r <= rmax else np.inf
            continue
        if r > rmax:
            out[i] = 0.0
            continue
        if noisy:
            r += noise[i]
        if r > rmax:
            r = 0.0
        elif r < rmin:
            r = rmin if near_mode == 1 else 0.0
        out[i] = r
    return total


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
    float32 are *transposed* images (one row per image column). With ``markers`` each column's
    colour is first cleared to 0, "nothing drawn here" (every drawn pixel has alpha 255, and a
    depth), and its depth left as it was: :func:`finish_frame` puts the background and the floor
    there later.
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


@njit(**_JIT)
def _finish_depth_row(row, noise, nv, nb, noisy, c, lo, hi):
    W = row.shape[0]
    if noisy:
        nrow = noise[nv, nb : nb + W]
        for u in range(W):
            d = row[u]
            d = np.float32(0.0) if d > hi else d
            d = d + c * (d * d * nrow[u])
            row[u] = np.float32(0.0) if (d > hi) | (d <= lo) else d
    else:
        for u in range(W):
            d = row[u]
            row[u] = np.float32(0.0) if (d > hi) | (d <= lo) else d


@njit(**_JIT)
def finish_depth(depth, noise, na, nb, coef, dmin, dmax):
    """The depth image as the D435 reports it, in place: ``depth`` (H, W) float32 z-depth (inf =
    nothing) -> 0 beyond ``dmax``, plus noise ``coef * z^2 * noise[na + v, nb + u]`` (when
    ``noise`` is not empty), then 0 beyond ``dmax`` and at or nearer than ``dmin``.

    One pass, row by row over contiguous slices so that LLVM vectorises it (about 4x the three
    OpenCV passes it replaces).
    """
    noisy = noise.shape[0] > 0
    c = np.float32(coef)
    lo = np.float32(dmin)
    hi = np.float32(dmax)
    for v in range(depth.shape[0]):
        _finish_depth_row(depth[v], noise, na + v, nb, noisy, c, lo, hi)


@njit(**_JIT)
def finish_frame(color, depth, v0, r0, bg, floor, row_depth, finish, noise, na, nb, coef, dmin, dmax):
    """Rows v0.. of an upright frame drawn with markers (see :func:`render_columns`), in place.

    ``color`` (n, W) uint32 and ``depth`` (n, W) float32: where nothing was drawn (colour 0; the
    depth there is whatever the buffer held) the background ``bg`` with no depth (0) above row
    ``r0``, the floor below it: colour from ``floor`` (uint32, (H - r0, W), upright, row 0 =
    image row r0) and depth ``row_depth[v]`` (float32 (H,): a level pinhole sees the floor at
    one z-depth along each row). Then, if ``finish``, the depth as the D435 reports it, as
    :func:`finish_depth` (noise window rows from ``na + v0``, columns from ``nb``). Row by row,
    each row finished while in cache; each loop tests the array it writes, the form LLVM
    vectorises.
    """
    n, W = color.shape
    noisy = noise.shape[0] > 0
    c = np.float32(coef)
    lo = np.float32(dmin)
    hi = np.float32(dmax)
    zero = np.float32(0.0)
    for i in range(n):
        v = v0 + i
        crow = color[i]
        drow = depth[i]
        if v < r0:
            for u in range(W):
                drow[u] = zero if crow[u] == 0 else drow[u]
            for u in range(W):
                x = crow[u]
                crow[u] = bg if x == 0 else x
        else:
            fz = row_depth[v]
            frow = floor[v - r0]
            for u in range(W):
                drow[u] = fz if crow[u] == 0 else drow[u]
            for u in range(W):
                x = crow[u]
                crow[u] = frow[u] if x == 0 else x
        if finish:
            _finish_depth_row(drow, noise, na + v, nb, noisy, c, lo, hi)
