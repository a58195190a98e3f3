"""Recording: file size and what --record costs in the simulator's real-time factor.

    python benchmarks/bench_record.py              # 60 s lane-follow size + overhead, alternating batches
    python benchmarks/bench_record.py --quick      # shorter runs (a smoke test of the script)
    python benchmarks/bench_record.py --labs lane-follow --no-size --batches 7

Targets (issue 13): a 60 s lane-follow recording with the RGBD camera at 30 Hz stays under 100 MB
(compact profile: JPEG colour every frame, 16-bit mm depth every 15th frame), and recording costs
at most 20 % of the real-time factor. Each figure is the median of alternating batches (plain,
recorded, plain, recorded, ...) so a load change on a shared machine hits both alike; the load
average is printed with them. Beside the wall-clock figure, the same from the process's CPU time
(all its threads): on a machine whose cores other jobs keep busy the wall clock swings by 2-3x
between two runs of the same thing, the CPU time far less; it is what the real-time factor would
be with a core to itself.

The recorder runs in a child process of its own (qcarlab.recording.process: the MCAP writing and
the JPEG and depth encoding there, the images handed over through shared memory): on two cores,
the wall-clock figure is what recording costs with the second core free to take that work; the
wall clock counts the child's start and the file's finishing (both inside the timed run). The CPU
figure adds the child's CPU time to the lab's, so it is the cost in work done, whichever core does
it. A third pass (``--one-core``, on by default for lane-follow) pins the process to one core,
where the recorder stays in the lab's process (no child) and encodes in the calling thread: its
wall clock is the one-core figure.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from qcarlab.car import open_car  # noqa: E402
from qcarlab.cli.common import opencv_single_threaded  # noqa: E402
from qcarlab.experiments.avoid import AvoidConfig, avoid  # noqa: E402
from qcarlab.experiments.lane_follow import LaneFollowConfig, run_lane_follow  # noqa: E402
from qcarlab.recording.car import RecordingCar  # noqa: E402
from qcarlab.recording.process import open_recorder, prestart  # noqa: E402
from qcarlab.sim.world import load_world  # noqa: E402


def lane(car, seconds):
    return run_lane_follow(car, LaneFollowConfig(duration=seconds), None)


def lidar(car, seconds):
    return avoid(car, AvoidConfig(duration=seconds))


LABS = {"lane-follow": ("track", lane), "avoid": ("obstacles", lidar)}


def run_once(lab: str, seconds: float, record: Path | None, profile: str = "compact",
             cpu: list[float] | None = None) -> tuple[float, int]:
    """Wall time of one run (s) and the recording's size (bytes, 0 without); ``cpu`` gets the run's
    CPU time appended (this process's and the recorder child's)."""
    world, fn = LABS[lab]
    if record is not None:
        prestart()  # as a command with --record does first thing: the child starts while the car opens
    car = open_car("sim", world=load_world(world), seed=0)
    t, c, k = time.perf_counter(), time.process_time(), _children_cpu()
    if record is not None:  # (timed: the recorder's start, a child process where it can, is part of the cost)
        car = RecordingCar(car, open_recorder(record, profile=profile))
    with car:
        fn(car, seconds)
    wall = time.perf_counter() - t  # includes finishing the file (closing is inside the with)
    if cpu is not None:
        cpu.append(time.process_time() - c + _children_cpu() - k)
    return wall, (record.stat().st_size if record is not None else 0)


def _children_cpu() -> float:
    """CPU time (s) of this process's ended children: the recorder's child, once closed."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def pin(cores: set[int]) -> None:
    """Every thread of this process (the recorder's encoder, OpenCV's and numba's pools, started
    before) and the ones started after, on ``cores``: os.sched_setaffinity(0) alone moves only the
    calling thread."""
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), cores)
        except OSError:  # a thread that ended meanwhile
            pass


def report(lab: str, speed_s: float, batches: int, note: str, plain: list[float], rec: list[float],
           cpu_p: list[float], cpu_r: list[float]) -> None:
    p, r = statistics.median(plain), statistics.median(rec)
    rtf_p, rtf_r = speed_s / p, speed_s / r
    wall_pairs = statistics.median(1 - a / b for a, b in zip(plain, rec))  # (each pair ran back to back)
    print(f"speed: {lab} {speed_s:g} s x {batches} ({note}, load {os.getloadavg()[0]:.2f}): real-time factor "
          f"{rtf_p:.2f} plain, {rtf_r:.2f} recorded: recording costs {100 * (1 - rtf_r / rtf_p):.1f} % (target <= 20 %; "
          f"median of the pairs {100 * wall_pairs:.1f} %); "
          f"walls plain {[round(x, 2) for x in plain]}, recorded {[round(x, 2) for x in rec]}")
    cp, cr = statistics.median(cpu_p), statistics.median(cpu_r)
    pairs = statistics.median(1 - a / b for a, b in zip(cpu_p, cpu_r))
    print(f"       in CPU time: {speed_s / cp:.2f} plain, {speed_s / cr:.2f} recorded (real time per CPU "
          f"second): recording costs {100 * (1 - cp / cr):.1f} % (median of the pairs {100 * pairs:.1f} %); "
          f"CPU s plain {[round(x, 2) for x in cpu_p]}, recorded {[round(x, 2) for x in cpu_r]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="short runs")
    ap.add_argument("--batches", type=int, default=3)
    ap.add_argument("--labs", default=",".join(LABS), help="comma-separated: " + ", ".join(LABS))
    ap.add_argument("--no-size", action="store_true", help="skip the file-size runs")
    ap.add_argument("--one-core", default="lane-follow",
                    help="labs also measured pinned to one core (comma-separated; 'none' for none)")
    args = ap.parse_args()
    opencv_single_threaded()  # as the CLI does for a run on the simulator
    labs = [x for x in args.labs.split(",") if x]
    pinned = [x for x in args.one_core.split(",") if x in LABS]
    bad = [x for x in labs if x not in LABS]
    if bad:
        ap.error(f"unknown lab {bad[0]!r}; choose from {', '.join(LABS)}")
    size_s = 10.0 if args.quick else 60.0
    speed_s = 5.0 if args.quick else 15.0
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at start")
    cores = os.sched_getaffinity(0)
    with tempfile.TemporaryDirectory() as tmp:
        for lab in LABS:  # warm-up: numba kernels, rasters
            run_once(lab, 1.0, None)
        if not args.no_size:
            f = Path(tmp) / "size.mcap"
            wall, size = run_once("lane-follow", size_s, f)
            per_min = size / size_s * 60.0
            print(f"size: lane-follow {size_s:g} s, RGBD 30 Hz, compact: {size / 1e6:.1f} MB "
                  f"({per_min / 1e6:.1f} MB per minute; target < 100 MB)")
            wall_x, size_x = run_once("lane-follow", 3.0, Path(tmp) / "exact.mcap", "exact")
            print(f"size: lane-follow 3 s, exact profile: {size_x / 1e6:.1f} MB ({size_x / 3.0 * 60 / 1e6:.0f} MB per "
                  "minute; for exact replays of camera labs)")
        passes = [(lab, False) for lab in labs] + [(lab, True) for lab in labs if lab in pinned]
        for lab, one in passes:
            if one:
                pin({max(cores)})
            note = f"every thread pinned to core {max(cores)}" if one else "both cores"
            try:
                plain, rec, cpu_p, cpu_r = [], [], [], []
                for b in range(args.batches):
                    plain.append(run_once(lab, speed_s, None, cpu=cpu_p)[0])
                    rec.append(run_once(lab, speed_s, Path(tmp) / f"{lab}{b}.mcap", cpu=cpu_r)[0])
            finally:
                if one:
                    pin(cores)
            report(lab, speed_s, args.batches, note, plain, rec, cpu_p, cpu_r)
    print(f"load average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
