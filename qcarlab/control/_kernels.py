"""The obstacle-avoidance controller's inner loops, compiled (:mod:`qcarlab.jit`): the scan
matching of :func:`~qcarlab.control.moving_obstacles.scan_motion` and the model drive of
:func:`~qcarlab.control.dodge.rollout`, with the steering law they share
(:func:`offset_steer`), and the LIDAR strategies' free distance along an arc (:func:`free_distance`).
Scalars and float64 (and bool) arrays in, numbers out; the equations are those of the functions'
docstrings. Each runs a few hundred small steps per LIDAR scan: written as loops over
scalars they cost microseconds where a numpy call per step cost a millisecond.
"""

from __future__ import annotations

import math

import numpy as np

from qcarlab.jit import JIT, njit


@njit(**JIT)
def offset_steer(y, psi, v, offset, wheelbase, max_steering, look_min, look_time, psi_max, k_psi):
    """One car's steering (rad) towards the line ``offset`` m to the left, from lateral position
    ``y`` (m) and heading ``psi`` (rad) in the line's frame, at speed ``v`` (m/s, signed): the law
    of :func:`qcarlab.control.dodge.offset_steering`."""
    sgn = -1.0 if v < 0.0 else 1.0
    look = max(look_min, look_time * abs(v))
    psi_d = sgn * min(max(math.atan((offset - y) / look), -psi_max), psi_max)
    err = (psi_d - psi + math.pi) % (2.0 * math.pi) - math.pi
    v_eff = sgn * max(abs(v), 0.15)
    return min(max(math.atan(wheelbase * k_psi * err / v_eff), -max_steering), max_steering)


@njit(**JIT)
def drive_paths(v0, delta0, vref, off, free, ox, oy, ex, ey, heading, wheelbase, max_steering, tau, horizon_steps,
                dt, accel, hold, look_min, look_time, psi_max, k_psi):
    """The kinematic bicycle about the centre (``beta = atan(tan(delta) / 2)``) driven ``horizon_steps``
    steps of ``dt`` s from the origin (heading 0, speed ``v0``, wheels at ``delta0``) by each of the
    k manoeuvres (speed ``vref[j]``, target line ``off[j]`` m left of the line through (ox, oy)
    along (ex, ey) at ``heading``; ``free[j]``: wheels straight): the steering law every ``hold``
    steps and held, the servo's first-order lag ``tau`` s, the speed ramp ``accel`` m/s^2.
    Returns the poses ``xs, ys, yaws`` (steps, k): m, m, rad."""
    k = vref.shape[0]
    xs = np.empty((horizon_steps, k))
    ys = np.empty((horizon_steps, k))
    yaws = np.empty((horizon_steps, k))
    servo = 1.0 - math.exp(-dt / tau)
    dv = accel * dt
    for j in range(k):
        x = 0.0
        y = 0.0
        yaw = 0.0
        v = v0
        d = delta0
        cmd = 0.0
        for i in range(horizon_steps):
            if i % hold == 0:  # a new command on each scan, held between them as the car does
                if free[j]:
                    cmd = 0.0
                else:
                    lateral = (x - ox) * -ey + (y - oy) * ex
                    cmd = offset_steer(lateral, yaw - heading, v if abs(v) > 0.05 else vref[j], off[j], wheelbase,
                                       max_steering, look_min, look_time, psi_max, k_psi)
            d += (cmd - d) * servo
            v += min(max(vref[j] - v, -dv), dv)
            tan_d = math.tan(d)
            beta = math.atan(0.5 * tan_d)
            course = yaw + beta
            x += v * math.cos(course) * dt
            y += v * math.sin(course) * dt
            yaw += v * math.cos(beta) * tan_d / wheelbase * dt
            xs[i, j] = x
            ys[i, j] = y
            yaws[i, j] = yaw
    return xs, ys, yaws


@njit(**JIT)
def match_scans(pa, px_old, py_old, nx_old, ny_old, ok_old, qx, qy, g0, g1, g2, iterations, p0, p1, p2):
    """Projective point-to-line ICP of the newer scan's returns (qx, qy) against the older scan's
    table (:meth:`~qcarlab.control.moving_obstacles.PreparedScan.table`: bearings after a leading
    -inf, then x, y, normal and normal_ok wrapped round), from the guess (g0, g1, g2), with the prior
    weights (p0, p1, p2): Gauss-Newton with Huber weights (2 cm) and a gate shrinking from 0.3 m to
    8 cm (see :func:`~qcarlab.control.moving_obstacles.scan_motion`). Returns (dx, dy, dyaw, matched);
    matched 0 (and the guess) when fewer than 20 returns pair up or a step is not finite."""
    n = qx.shape[0]
    m = pa.shape[0]
    x0 = g0
    x1 = g1
    x2 = g2
    matched = 0
    cur = min(1, m)  # where the last search ended: the returns come in bearing order, the next is a step or two on
    for it in range(iterations):
        c = math.cos(x2)
        s = math.sin(x2)
        gate = max(0.08, 0.3 * 0.7**it)
        h00 = p0
        h01 = 0.0
        h02 = 0.0
        h11 = p1
        h12 = 0.0
        h22 = p2
        b0 = p0 * (x0 - g0)
        b1 = p1 * (x1 - g1)
        b2 = p2 * (x2 - g2)
        matched = 0
        for i in range(n):
            px = c * qx[i] - s * qy[i] + x0
            py = s * qx[i] + c * qy[i] + x1
            # the return at or after p's bearing, + 1: np.searchsorted(pa, bearing)'s index (the first
            # pa[k] >= bearing; NaN after all), walked to from the last one instead of bisected
            bearing = math.atan2(py, px)
            if bearing != bearing:
                cur = m
            else:
                while cur < m and pa[cur] < bearing:
                    cur += 1
                while cur > 0 and pa[cur - 1] >= bearing:
                    cur -= 1
            k = cur
            d1 = math.hypot(px - px_old[k], py - py_old[k])
            d0 = math.hypot(px - px_old[k - 1], py - py_old[k - 1])
            if d0 < d1:
                k -= 1
                d1 = d0
            if not (ok_old[k] and d1 < gate):
                continue
            matched += 1
            nx = nx_old[k]
            ny = ny_old[k]
            e = nx * (px - px_old[k]) + ny * (py - py_old[k])
            w = min(1.0, 0.02 / max(abs(e), 1e-9))
            j2 = ny * (px - x0) - nx * (py - x1)
            h00 += w * nx * nx
            h01 += w * nx * ny
            h02 += w * nx * j2
            h11 += w * ny * ny
            h12 += w * ny * j2
            h22 += w * j2 * j2
            b0 += w * e * nx
            b1 += w * e * ny
            b2 += w * e * j2
        if matched < 20:
            return g0, g1, g2, 0
        # H step = -b, H symmetric positive definite (the prior's diagonal): Cholesky, H = L L'
        l00 = math.sqrt(h00)
        l10 = h01 / l00
        l20 = h02 / l00
        l11 = math.sqrt(h11 - l10 * l10)
        l21 = (h12 - l20 * l10) / l11
        l22 = math.sqrt(h22 - l20 * l20 - l21 * l21)
        z0 = -b0 / l00
        z1 = (-b1 - l10 * z0) / l11
        z2 = (-b2 - l20 * z0 - l21 * z1) / l22
        s2 = z2 / l22
        s1 = (z1 - l21 * s2) / l11
        s0 = (z0 - l10 * s1 - l20 * s2) / l00
        if not (math.isfinite(s0) and math.isfinite(s1) and math.isfinite(s2)):
            return g0, g1, g2, 0
        x0 += s0
        x1 += s1
        x2 += s2
        if abs(s0) + abs(s1) < 2e-4 and abs(s2) < 2e-4 and gate <= 0.1:
            break
    return x0, x1, x2, matched


@njit(**JIT)
def free_distance(px, py, steering, half_len, w, wheelbase, horizon):
    """How far (m) the car's centre drives forward with the wheels at ``steering`` before its
    footprint (half length ``half_len``, half width ``w`` with the margin) meets one of the points
    (``px``, ``py``: body frame about the centre), capped at ``horizon``: the corridor ahead when
    straight, else the first touch along the turning annulus, the equations of
    :func:`qcarlab.control.lidar_avoid.free_distance`, one pass over the points."""
    n = px.shape[0]
    best = math.inf
    if abs(steering) < 1e-3:
        for i in range(n):
            if abs(py[i]) <= w and px[i] >= half_len:
                best = min(best, px[i] - half_len)
        return horizon if best == math.inf else min(horizon, best)
    R = wheelbase / math.tan(abs(steering))
    mirror = -1.0 if steering < 0.0 else 1.0  # right turns mirrored into left turns
    a = wheelbase / 2.0 + half_len
    r_in = R - w
    r_out = math.hypot(R + w, a)
    inner = math.hypot(a, r_in)
    for i in range(n):
        xr = px[i] + wheelbase / 2.0  # rear-axle frame
        ry = R - mirror * py[i]
        rho = math.hypot(xr, ry)
        if rho >= r_in and rho <= r_out:
            phi = math.atan2(xr, ry)  # 0 at the rear axle, + ahead
            if rho <= inner:
                lead = math.acos(min(max(r_in / rho, -1.0), 1.0))
            else:
                lead = math.asin(min(max(a / rho, -1.0), 1.0))
            if phi >= lead:
                best = min(best, phi - lead)
    return horizon if best == math.inf else min(horizon, best * math.hypot(R, wheelbase / 2.0))


def warm() -> None:
    """Each kernel called once with the types the controller passes: loaded from numba's cache, or
    compiled (some seconds, once per machine) and cached. A warm start (:mod:`qcarlab.zygote`) calls
    it, so that a student's process forked from it, which cannot write the cache, never compiles."""
    offset_steer(0.0, 0.0, 0.5, 0.3, 0.256, 0.5, 0.35, 0.9, 0.5, 2.5)
    one = np.zeros(1)
    drive_paths(0.5, 0.0, one, one, np.zeros(1, dtype=np.bool_), 0.0, 0.0, 1.0, 0.0, 0.0, 0.256, 0.5, 0.1, 2, 0.05, 2.0, 2,
                0.35, 0.9, 0.5, 2.5)
    table = np.array([-math.inf, 0.0, 1.0])
    match_scans(table, np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4, dtype=np.bool_), one, one, 0.0, 0.0,
                0.0, 1, 2.0, 2.0, 0.5)
    free_distance(one, one, 0.1, 0.2, 0.1, 0.256, 3.0)
