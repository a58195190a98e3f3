"""Speed of the simulated sensors and of the simulated car with its sensors, on one core.

    python benchmarks/bench_sensors.py              # about a minute
    python benchmarks/bench_sensors.py --quick      # a few seconds, noisier
    python benchmarks/bench_sensors.py --all-cores  # do not pin (OpenCV's own threads)

The process pins itself to one core first (the targets are per core: a 2-core machine grades two
runs at once), unless ``--all-cores``. Prints the machine and the load average, then the median
rate over several timed batches of each sensor with its target. The LIDAR runs over the ROS map
``berlin`` (600 x 600 cells of 5 cm, from ../shared/data/maps beside the repository; marched)
from random free poses (bench_lidar.py has the side-by-side with f1tenth_gym), and in the
``track`` world (scanned per edge); the cameras in the ``track`` world from poses along the road. Noise is on (seeded), as in a simulation run. The first call of
each sensor (numba compilation or cache load, rasters) is excluded and reported separately.

Last, the whole simulated car (issue 12's target >= 60x real time on one core, under the ideal
and the lab realism profiles): ``open_car("sim", world="track", seed=0, realism=...)`` stepped at
100 Hz for 3 simulated seconds (write, advance 10 ms, read, read_lidar, read_rgbd each step; the
sensors render at their own rates, 10 and 30 Hz), as the real-time factor (simulated s / CPU s),
median of a few runs, with the share of the CPU time spent rendering RGBD frames, scanning and
in the rest (physics, the car's calls).

    python benchmarks/bench_sensors.py --quick --against /work/main   # the car beside other code

With ``--against DIR`` the car's runs alternate with the same runs of the checkout in DIR (a
subprocess each, pinned to the same core) and the ratio of the medians is printed.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import Timer, load_note, one_core  # noqa: E402

import qcarlab  # noqa: E402
from qcarlab.constants import DEFAULT_PARAMS  # noqa: E402
from qcarlab.sim import _kernels  # noqa: E402
from qcarlab.sim.camera import CSICameras, RGBDCamera  # noqa: E402
from qcarlab.sim.lidar import Lidar  # noqa: E402
from qcarlab.sim.world import load_world  # noqa: E402

BERLIN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "maps" / "berlin.yaml"


def machine() -> str:
    cpu = platform.processor() or ""
    if not cpu:
        try:
            for line in Path("/proc/cpuinfo").read_text().splitlines():
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
        except OSError:
            pass
    try:
        import numba

        nb = f"numba {numba.__version__}"
    except ImportError:
        nb = "numba not installed (pure Python kernels)"
    import cv2

    return (
        f"{cpu or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"numpy {np.__version__}, OpenCV {cv2.__version__}, {nb}"
    )


def rate(fn, n: int, batches: int) -> tuple[float, float]:
    """Median calls per CPU second and per wall second over ``batches`` batches of ``n`` calls."""
    cpu, wall = [], []
    for _ in range(batches):
        with Timer() as tm:
            for i in range(n):
                fn(i)
        cpu.append(n / max(tm.cpu, 1e-9))
        wall.append(n / tm.wall)
    return statistics.median(cpu), statistics.median(wall)


def first_call(fn) -> float:
    t = time.perf_counter()
    fn(0)
    return time.perf_counter() - t


def free_poses(world, count: int, rng: np.random.Generator) -> list[tuple[float, float, float]]:
    g = world.grid
    rows, cols = np.nonzero(~g.occupied & ~g.unknown)
    k = rng.choice(len(rows), count)
    xs = g.origin[0] + (cols[k] + 0.5) * g.resolution
    ys = g.origin[1] + (rows[k] + 0.5) * g.resolution
    yaws = rng.uniform(-math.pi, math.pi, count)
    return list(zip(xs.tolist(), ys.tolist(), yaws.tolist()))


def report(name: str, value: tuple[float, float], unit: str, target: float | None, first: float | None = None) -> None:
    cpu, wall = value
    status = "" if target is None else ("  target >= {:,.0f}: {}".format(target, "met" if cpu >= target else "NOT met"))
    extra = f"  (first call {first * 1000:.0f} ms)" if first is not None else ""
    print(f"  {name:<30} {cpu:>9,.0f} {unit} per CPU s, {wall:>9,.0f} per wall s{status}{extra}")


def simcar_factor(seconds: float = 3.0, hz: float = 100.0, realism: str = "ideal") -> tuple[float, float, float, float]:
    """Real-time factor of the stepped SimCar in ``track`` with the LIDAR and the RGBD camera per
    CPU second, the fractions of the CPU time in read_rgbd and read_lidar, and the factor per
    wall second. (Self-contained: ``--against`` runs its source in another checkout.)"""
    import time

    import qcarlab
    from _common import Timer

    with qcarlab.open_car("sim", world="track", seed=0, realism=realism) as car:
        car.read_lidar()  # sensors built (rasters, numba cache) outside the timing
        car.read_rgbd()
        dt = 1.0 / hz
        t_rgbd = t_lidar = 0.0
        clock = time.process_time
        with Timer() as tm:
            for _ in range(round(seconds * hz)):
                car.write(0.1, 0.0)
                car.advance(dt)
                car.read()
                a = clock()
                car.read_lidar()
                b = clock()
                car.read_rgbd()
                c = clock()
                t_lidar += b - a
                t_rgbd += c - b
        return seconds / tm.cpu, t_rgbd / tm.cpu, t_lidar / tm.cpu, seconds / tm.wall


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer, shorter batches")
    ap.add_argument("--all-cores", action="store_true", help="do not pin the process to one core")
    ap.add_argument("--against", metavar="DIR", help="time the SimCar runs of the checkout in DIR too, alternating")
    args = ap.parse_args()
    pin = "all cores" if args.all_cores else one_core()
    batches = 3 if args.quick else 7
    scale = 0.2 if args.quick else 1.0
    print(f"machine: {machine()}; {pin}")
    print(f"load: {load_note()}")
    if not _kernels.HAVE_NUMBA:
        print("  (without numba the kernels run as plain Python: expect rates some 100x lower)")
    rng = np.random.default_rng(0)
    p = DEFAULT_PARAMS

    print("LIDAR over berlin (600 x 600 cells), random free poses, noise on:")
    lidar_rates = {}
    if BERLIN.is_file():
        berlin = load_world(BERLIN)
        poses = free_poses(berlin, 256, rng)
        for beams, target in ((1080, 4000.0), (360, 10000.0), (p.lidar_beams, None)):
            lidar = Lidar(berlin, beams=beams, rng=np.random.default_rng(1))
            f0 = first_call(lambda i: lidar.scan(poses[i % 256]))
            r = rate(lambda i: lidar.scan(poses[i % 256]), int(4000 * scale), batches)
            lidar_rates[beams] = r[0]
            report(f"{beams} beams", r, "scans/s", target, f0)
    else:
        print(f"  skipped: {BERLIN} not found")

    track = load_world("track")
    road = [(x, -1.7, 0.0) for x in np.linspace(-1.0, 1.0, 64)]
    print("LIDAR in track (a vector world: scanned per edge), poses along the road, noise on:")
    lidar = Lidar(track, rng=np.random.default_rng(1))
    f0 = first_call(lambda i: lidar.scan(road[i % 64]))
    r = rate(lambda i: lidar.scan(road[i % 64]), int(4000 * scale), batches)
    report(f"{p.lidar_beams} beams", r, "scans/s", None, f0)
    track_lidar = r[0]

    print("RGBD camera in track, poses along the road, noise on:")
    cam = RGBDCamera(track, rng=np.random.default_rng(2))
    f0 = first_call(lambda i: cam.render(road[i % 64], i / 30))
    rgbd = rate(lambda i: cam.render(road[i % 64], i / 30), int(600 * scale), batches)
    report("640x480 colour + depth", rgbd, "frame pairs/s", 2000.0, f0)

    print("CSI cameras in track:")
    csi = CSICameras(track, rng=np.random.default_rng(3))
    f0 = first_call(lambda i: csi.render(road[i % 64], i / 30))
    sets = rate(lambda i: csi.render(road[i % 64], i / 30), int(90 * scale), batches)
    report("4 x 820x410 views", sets, "sets/s", 30.0, f0)

    if track_lidar:
        cost = p.rgbd_rate / rgbd[0] + p.lidar_rate / track_lidar
        print("One simulated second in track with the LIDAR at 10 Hz and the RGBD camera at 30 Hz (sensors only):")
        print(f"  {cost * 1000:.1f} ms of sensor work: at most {1.0 / cost:.0f}x real time from the sensors alone")

    print("SimCar in track, 100 Hz steps (write, advance, read, read_lidar, read_rgbd), 3 simulated s:")
    n = 3 if args.quick else 5
    ok = True
    for realism in ("ideal", "lab"):
        runs, other = [], []
        for _ in range(n):
            runs.append(simcar_factor(realism=realism))
            if args.against:
                other.append(_simcar_elsewhere(args.against, realism))
        factor = statistics.median(r[0] for r in runs)
        f_rgbd = statistics.median(r[1] for r in runs)
        f_lidar = statistics.median(r[2] for r in runs)
        wall_factor = statistics.median(r[3] for r in runs)
        ok &= factor >= 60.0
        print(f"  {'real-time factor, ' + realism:<30} {factor:>9.1f} x per CPU s, {wall_factor:>9.1f} x per wall s  "
              f"target >= 60: {'met' if factor >= 60.0 else 'NOT met'}")
        print(f"    of the CPU time: RGBD frames {f_rgbd * 100:.0f} %, LIDAR scans {f_lidar * 100:.0f} %, "
              f"the rest (physics, the car's calls) {(1 - f_rgbd - f_lidar) * 100:.0f} %")
        if other:
            o = statistics.median(r[0] for r in other)
            print(f"    {args.against} in alternating runs: {o:.1f} x per CPU s; this code {factor / o:.2f}x its rate")
    print(f"load after: {load_note()}")
    return 0


def _simcar_elsewhere(root: str, realism: str) -> tuple[float, float, float, float]:
    """:func:`simcar_factor` run in a subprocess on the checkout at ``root`` (same core)."""
    import inspect
    import json
    import subprocess
    import textwrap

    code = "\n".join([
        "import json, sys",
        f"sys.path[:0] = [{str(Path(root).resolve())!r}, {str(Path(__file__).resolve().parent)!r}]",
        textwrap.dedent(inspect.getsource(simcar_factor)),
        "car = None",
        f"print(json.dumps(simcar_factor(realism={realism!r})))",
    ])
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root)
    return tuple(json.loads(out.stdout.strip().splitlines()[-1]))


if __name__ == "__main__":
    raise SystemExit(main())
