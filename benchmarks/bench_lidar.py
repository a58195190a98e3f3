"""The simulated LIDAR side by side with f1tenth_gym's, inside a simulator loop; and its worst case.

    python benchmarks/bench_lidar.py            # about a minute
    python benchmarks/bench_lidar.py --quick    # fewer poses and batches, noisier

Targets (issue 12):

- on the ROS maps berlin and stata_basement (../shared/data/maps), 1080 beams over 4.7 rad and
  360 beams over 2 pi, a scan taken *inside a simulator loop* (between scans the loop steps the
  car's physics ten times and renders three RGBD frames in the same world, as a 100 Hz loop with
  the LIDAR at 10 Hz and the camera at 30 Hz does, so both scanners find the cache as they would
  in a run) is at least 2x as fast as f1tenth_gym's ``ScanSimulator2D.scan`` on the same map, the
  same poses and the same beam count, the two timed in alternating batches (mean scan time of
  each, noise draws included; the ratio is printed);
- the accuracy is unchanged: both are compared with an independent exact traversal of the
  occupancy grid written here in numpy (every x and y cell boundary the beam crosses, the first
  occupied cell entered); qcarlab's median error was 0.25 mm or less, f1tenth's about 24 mm;
- every time is the CPU time of the scanning thread (``time.thread_time``), not the wall time:
  on a machine shared with other jobs the wall time counts their turns on the core too;
- the worst case of the raster march: poses on cell corners all over a room with boxes, beams
  along cell boundaries (yaw 0, so beams 0, 200, 400 and 600 of 800 run exactly along grid
  lines): no scan over 3x the median scan time. The number of cells each scan looked at is
  printed too (it is what the regression test bounds, tests/test_lidar.py). (Such a world of
  boxes is scanned per edge by default; the march is forced here, as for a ROS map.)

f1tenth_gym's model is imported from ../shared/peers/f1tenth_laser_models.py (it needs scipy and
Pillow: ``pip install -e ".[bench]"``; its kernels are compiled at each run, nothing is written
into ../shared); without it, or without ../shared, its columns are skipped. The machine and its load average are printed with the figures.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import load_note, machine  # noqa: E402

from qcarlab.car.sim import SimCar  # noqa: E402
from qcarlab.sim.camera import RGBDCamera  # noqa: E402
from qcarlab.sim.lidar import Lidar  # noqa: E402
from qcarlab.sim.world import load_world, world_from_dict  # noqa: E402

SHARED = ROOT.parent / "shared"
MAPS = SHARED / "data" / "maps"
PEER = SHARED / "peers" / "f1tenth_laser_models.py"
RMAX = 12.0


def load_peer():
    """f1tenth_gym's laser model module, or (None, reason)."""
    if not PEER.is_file():
        return None, f"{PEER} not found"
    import numba

    # ../shared is read-only: compile the peer's kernels without numba's on-disk cache (its
    # functions ask for one next to the file) and write no bytecode there
    njit = numba.njit

    def njit_no_cache(*args, **kwargs):
        kwargs["cache"] = False
        return njit(*args, **kwargs)

    numba.njit = njit_no_cache
    dont_write = sys.dont_write_bytecode
    sys.dont_write_bytecode = True
    try:
        spec = importlib.util.spec_from_file_location("f1tenth_laser_models", PEER)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)  # type: ignore[union-attr]
    except ImportError as e:
        return None, f"f1tenth's model needs {e.name} (pip install -e '.[bench]': scipy, pillow)"
    finally:
        numba.njit = njit
        sys.dont_write_bytecode = dont_write
    return mod, ""


def free_poses(world, count: int, rng: np.random.Generator, clearance: float = 0.3):
    """Random poses on free cells at least ``clearance`` from any wall (a car's place)."""
    import cv2

    g = world.grid
    free = (~g.occupied & ~g.unknown).astype(np.uint8)
    clear = cv2.distanceTransform(free, cv2.DIST_L2, 5) * g.resolution
    rows, cols = np.nonzero(clear >= clearance)
    k = rng.choice(len(rows), count)
    xs = g.origin[0] + (cols[k] + rng.uniform(0, 1, count)) * g.resolution
    ys = g.origin[1] + (rows[k] + rng.uniform(0, 1, count)) * g.resolution
    return [(float(x), float(y), float(a)) for x, y, a in zip(xs, ys, rng.uniform(-math.pi, math.pi, count))]


def reference_ranges(grid, x: float, y: float, angles: np.ndarray, rmax: float = RMAX) -> np.ndarray:
    """Exact ranges by an independent traversal: for each beam, every crossing of a vertical
    (x = origin + i res) and horizontal grid line up to ``rmax``, sorted; the first crossing
    into an occupied cell gives the range (inf: none). Numpy, no shared code with the kernels."""
    res = grid.resolution
    ny, nx = grid.occupied.shape
    px = (x - grid.origin[0]) / res
    py = (y - grid.origin[1]) / res
    tmax = rmax / res
    out = np.full(len(angles), np.inf)
    for b, a in enumerate(angles):
        dx, dy = math.cos(a), math.sin(a)
        ts = [np.zeros(1)]
        for p, d in ((px, dx), (py, dy)):
            if abs(d) > 1e-12:
                k = np.arange(math.floor(p) + 1, math.floor(p + tmax * d) + 1) if d > 0 else np.arange(math.ceil(p) - 1, math.ceil(p + tmax * d) - 1, -1)
                ts.append((k - p) / d)
        t = np.sort(np.concatenate(ts))
        t = t[t <= tmax]
        mid = t + 1e-7  # just past each crossing: the cell entered there
        ix = np.floor(px + mid * dx).astype(int)
        iy = np.floor(py + mid * dy).astype(int)
        inside = (ix >= 0) & (iy >= 0) & (ix < nx) & (iy < ny)
        hit = np.zeros(len(t), bool)
        hit[inside] = grid.occupied[iy[inside], ix[inside]]
        hit &= inside
        if hit.any():
            out[b] = t[np.argmax(hit)] * res
    return out


def f1tenth_angles(sim, yaw: float) -> np.ndarray:
    """The directions f1tenth's scan really uses: its angle index is truncated to a 2000-entry
    table (``linspace(0, 2 pi, 2000)``) and stepped by a fractional increment."""
    ti = sim.theta_dis * (yaw - sim.fov / 2.0) / (2.0 * np.pi)
    ti = math.fmod(ti, sim.theta_dis)
    while ti < 0:
        ti += sim.theta_dis
    out = []
    for _ in range(sim.num_beams):
        out.append(np.linspace(0.0, 2 * np.pi, num=sim.theta_dis)[int(ti)])
        ti += sim.theta_index_increment
        while ti >= sim.theta_dis:
            ti -= sim.theta_dis
    return np.array(out)


def accuracy(world, lidar: Lidar, sim, poses) -> tuple[float, float | None]:
    """Median |range - reference| (m) of qcarlab and of f1tenth over beams with a return."""
    ours, theirs = [], []
    for x, y, yaw in poses:
        r = lidar.true_ranges((x, y, yaw))
        sx, sy, _ = lidar.sensor_pose((x, y, yaw))  # the LIDAR sits lidar_x ahead of the car's centre
        ref = reference_ranges(world.grid, sx, sy, lidar.angles + yaw)
        ok = np.isfinite(ref) & (ref < RMAX - 0.1)
        ours.append(np.abs(r[ok] - ref[ok]))
        if sim is not None:
            f = sim.scan(np.array([x, y, yaw]), None)
            ref = reference_ranges(world.grid, x, y, f1tenth_angles(sim, yaw))
            ok = np.isfinite(ref) & (ref < RMAX - 0.1)
            theirs.append(np.abs(f[ok] - ref[ok]))
    return float(np.median(np.concatenate(ours))), (float(np.median(np.concatenate(theirs))) if theirs else None)


def in_loop(world, scanners: dict, poses, batches: int) -> dict[str, float]:
    """Mean scan time (s) of each scanner inside a loop that, before every scan, steps a SimCar
    ten times (100 Hz) and renders three RGBD frames in the same world; alternating batches."""
    car = SimCar(seed=0, world=world)
    cam = RGBDCamera(world, rng=np.random.default_rng(4))
    times: dict[str, list[float]] = {k: [] for k in scanners}
    names = list(scanners)
    for b in range(batches):
        order = names if b % 2 == 0 else names[::-1]
        for name in order:
            scan = scanners[name]
            for i, pose in enumerate(poses):
                for _ in range(10):
                    car.write(0.05, 0.0)
                    car.advance(0.01)
                    car.read()
                for j in range(3):
                    cam.render(pose, j / 30.0)
                t = time.thread_time()
                scan(pose)
                times[name].append(time.thread_time() - t)
    return {k: statistics.fmean(v) for k, v in times.items()}


def tight(scanners: dict, poses, batches: int) -> dict[str, float]:
    """Median scan time (s) of each scanner, scans back to back (alternating batches)."""
    out: dict[str, list[float]] = {k: [] for k in scanners}
    names = list(scanners)
    for b in range(batches):
        for name in (names if b % 2 == 0 else names[::-1]):
            scan = scanners[name]
            t = time.thread_time()
            for pose in poses:
                scan(pose)
            out[name].append((time.thread_time() - t) / len(poses))
    return {k: statistics.median(v) for k, v in out.items()}


def worst_case(quick: bool) -> tuple[float, float, int, int]:
    """Scan times over poses on cell corners in a 10 x 10 m room with ten boxes (5 mm cells),
    yaw 0: (median s, max s, median cells, max cells)."""
    boxes = [{"shape": "box", "center": [0.755, -0.5], "size": [0.49, 1.0]}]
    rng = np.random.default_rng(7)
    for _ in range(9):
        cx, cy = rng.integers(-16, 17, 2) * 0.25
        boxes.append({"shape": "box", "center": [float(cx), float(cy)], "size": [0.5, 0.3]})
    w = world_from_dict({"floor": {"size": [10, 10]},
                         "walls": [{"points": [[-5, -5], [5, -5], [5, 5], [-5, 5]], "closed": True}],
                         "obstacles": boxes})
    lidar = Lidar(w, beams=800)
    lidar.vector_walls = False  # the raster march (a vector world is scanned per edge by default)
    r = lidar._raster
    lidar.true_ranges((0.0, 0.0, 0.0))
    step = 0.25 if quick else 0.125
    poses = []
    for x in np.arange(-4.5, 4.51, step):
        for y in np.arange(-4.5, 4.51, step):
            # snap to the nearest cell corner of the raster
            cx = r.x0 + round((x - r.x0) / r.res) * r.res
            cy = r.y0 + round((y - r.y0) / r.res) * r.res
            col, row = int(round((cx - r.x0) / r.res)), int(round((cy - r.y0) / r.res))
            if (r.label[row - 1 : row + 1, col - 1 : col + 1] < 0).all():
                poses.append((cx, cy, 0.0))
    poses.append((0.5, 1.0, 0.0))  # the pinned stall case
    # the least CPU time of five rounds over all the poses: a scan is short and the machine
    # shared, so each pose is timed in five separate moments
    times = [math.inf] * len(poses)
    steps = [0] * len(poses)
    for _ in range(5):
        for k, pose in enumerate(poses):
            t = time.thread_time()
            lidar.true_ranges(pose)
            times[k] = min(times[k], time.thread_time() - t)
            steps[k] = lidar.last_cell_steps
    return statistics.median(times), max(times), int(statistics.median(steps)), max(steps)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer poses and batches")
    args = ap.parse_args()
    npose = 20 if args.quick else 40
    batches = 4 if args.quick else 8
    print(f"machine: {machine()}")
    print(f"load: {load_note()}")
    peer, why = load_peer()
    if peer is None:
        print(f"f1tenth_gym columns skipped: {why}")
    ok = True
    measured_peer = False  # the 2x-f1tenth target is "not measured" without the peer's columns
    print(f"{'map':<16}{'beams':>12}{'qcarlab us':>12}{'f1tenth us':>12}{'ratio':>8}   {'tight q/f us':>14}"
          f"{'ratio':>7}   {'err q mm':>9}{'err f mm':>9}")
    for name in ("berlin", "stata_basement"):
        path = MAPS / f"{name}.yaml"
        if not path.is_file():
            print(f"{name:<16} skipped: {path} not found")
            continue
        world = load_world(path)
        poses = free_poses(world, npose, np.random.default_rng(11))
        for beams, fov in ((1080, 4.7), (360, 2 * math.pi)):
            lidar = Lidar(world, beams=beams, rng=np.random.default_rng(1), fov=fov)
            scanners = {"qcarlab": lambda p, L=lidar: L.scan(p)}
            sim = None
            if peer is not None:
                sim = peer.ScanSimulator2D(beams, fov, max_range=RMAX)
                sim.set_map(str(path), ".png")
                prng = np.random.default_rng(2)
                scanners["f1tenth"] = lambda p, S=sim, g=prng: S.scan(np.array(p), g, std_dev=0.005)
            for s in scanners.values():
                s(poses[0])  # compiled / cache loaded outside the timing
            loop = in_loop(world, scanners, poses, batches)
            tt = tight(scanners, poses * 5, batches)
            err_q, err_f = accuracy(world, Lidar(world, beams=beams, fov=fov), sim, poses[: (4 if args.quick else 8)])
            label = f"{beams}/{'2pi' if fov > 6 else f'{fov:g} rad'}"
            q = loop["qcarlab"] * 1e6
            if "f1tenth" in loop:
                f = loop["f1tenth"] * 1e6
                ratio = loop["f1tenth"] / loop["qcarlab"]
                tr = tt["f1tenth"] / tt["qcarlab"]
                ok &= ratio >= 2.0
                measured_peer = True
                print(f"{name:<16}{label:>12}{q:>12.0f}{f:>12.0f}{ratio:>7.2f}x   "
                      f"{tt['qcarlab'] * 1e6:>6.0f}/{tt['f1tenth'] * 1e6:<7.0f}{tr:>6.2f}x   "
                      f"{err_q * 1000:>9.3f}{err_f * 1000:>9.2f}")
            else:
                print(f"{name:<16}{label:>12}{q:>12.0f}{'-':>12}{'-':>8}   {tt['qcarlab'] * 1e6:>6.0f}/{'-':<7}{'-':>7}"
                      f"   {err_q * 1000:>9.3f}{'-':>9}")
            ok &= err_q <= 0.00025
    print("target: in the loop >= 2x f1tenth's scan rate; median error <= 0.25 mm")
    med, worst, smed, smax = worst_case(args.quick)
    print(f"worst case (poses on cell corners, beams along cell boundaries, 800 beams): median "
          f"{med * 1e6:.0f} us, max {worst * 1e6:.0f} us = {worst / med:.2f}x the median (target <= 3x); "
          f"cells looked at: median {smed:,}, max {smax:,}")
    ok &= worst <= 3.0 * med
    if not ok:
        print("SOME TARGETS MISSED")
    elif not measured_peer:
        print("targets met: accuracy and worst case; in the loop >= 2x f1tenth: not measured (no f1tenth_gym "
              "columns: pip install 'qcarlab[bench]' and ../shared/peers beside the checkout)")
    else:
        print("all targets met")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
