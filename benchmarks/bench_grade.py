"""How long grading takes: one student on the five lab sheets, and a class of 20 with --jobs 2 vs 1.

    python benchmarks/bench_grade.py                 # both measurements (about 15 minutes on 2 cores)
    python benchmarks/bench_grade.py --student       # one student, all five sheets, --jobs 1 and 2
    python benchmarks/bench_grade.py --class-size 20 --reps 2
    python benchmarks/bench_grade.py --student --cold    # also with every task a fresh interpreter

Tasks are forked from a warm zygote (qcarlab/grading/warm.py) unless ``QCARLAB_GRADE_COLD=1``;
``--cold`` measures both, alternated, so the warm start's saving is measured under the same load.

Every figure is the wall time of ``qcarlab grade`` as a user types it (a fresh process), the
median over ``--reps`` runs, the configurations alternated so that a change of the machine's
load hits both. The load average is printed with each batch: on a shared machine the wall figures
move with it; the CPU seconds (the grader and all its task processes) hardly do, and CPU / cores
is what the wall time would be on an idle machine with --jobs = cores. The submissions are synthetic (tests/grading_submissions.py): the reference
blocks, and for the class every third student with a wrong stop window, every fifth with a
stop_sign that raises.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.grading_submissions import correct_submission, write_block  # noqa: E402

FIVE = ("basic-io", "path-following", "stop-sign", "lane-following", "obstacle-avoidance")
CLASS_TASKS = ("--task", "5.2-task1-block", "--task", "5.2-task1-stopsign")
WRONG = "def stop_sign(distance_to_sign, desired_speed):\n    return 0.0 if 0.5 < distance_to_sign < 1.0 else desired_speed\n"
RAISES = "def stop_sign(distance_to_sign, desired_speed):\n    return desired_speed / (distance_to_sign * 0)\n"


CPU: list[float] = []  # CPU seconds (user + system) of each grade run and all its task processes


def grade(args: list[str], cold: bool = False) -> float:
    """Wall seconds of one ``qcarlab grade`` run; its CPU seconds go to CPU."""
    env = dict(os.environ)
    env.pop("QCARLAB_GRADE_COLD", None)
    if cold:
        env["QCARLAB_GRADE_COLD"] = "1"
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "qcarlab", "grade", *args], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    CPU.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    if done.returncode not in (0, 1):
        raise SystemExit(f"qcarlab grade {' '.join(args)} failed ({done.returncode}): {done.stderr[-500:]}")
    return wall


def load() -> str:
    return "load %.1f %.1f %.1f" % os.getloadavg()


def student(reps: int, tmp: Path, cold: bool) -> None:
    sub = correct_submission(tmp / "student")
    configs = [(jobs, c) for c in ((False, True) if cold else (False,)) for jobs in (1, 2)]
    times: dict[tuple[int, bool], list[float]] = {c: [] for c in configs}
    cpu: dict[tuple[int, bool], list[float]] = {c: [] for c in configs}
    for rep in range(reps):
        for jobs, c in configs if rep % 2 == 0 else configs[::-1]:
            before = load()
            wall = grade([*FIVE, "--submission", str(sub), "--jobs", str(jobs), "--out", str(tmp / f"s{jobs}{c}")], c)
            times[(jobs, c)].append(wall)
            cpu[(jobs, c)].append(CPU[-1])
            print(f"  one student, five sheets, --jobs {jobs}{' (cold)' if c else ''}: {wall:6.1f} s wall, "
                  f"{CPU[-1]:6.1f} s CPU   ({before} -> {load()})", flush=True)
    for (jobs, c), t in times.items():
        print(f"one student, all five lab sheets (25 tasks), --jobs {jobs}{' cold' if c else ''}: median "
              f"{statistics.median(t):.1f} s wall, {statistics.median(cpu[(jobs, c)]):.1f} s CPU over {len(t)} run(s)")


def klass(size: int, reps: int, tmp: Path) -> None:
    root = tmp / "class"
    for i in range(size):
        folder = correct_submission(root / f"student{i:02d}", ("stop-sign",)) / "stop-sign"
        if i % 3 == 1:
            write_block(folder, "stop_sign.py", WRONG)
        elif i % 5 == 4:
            write_block(folder, "stop_sign.py", RAISES)
    times: dict[int, list[float]] = {1: [], 2: []}
    books: dict[int, str] = {}
    for rep in range(reps):
        for jobs in (1, 2) if rep % 2 == 0 else (2, 1):
            before = load()
            out = tmp / f"c{jobs}"
            wall = grade(["stop-sign", "--class", str(root), *CLASS_TASKS, "--jobs", str(jobs), "--out", str(out)])
            times[jobs].append(wall)
            books[jobs] = (out / "gradebook.csv").read_text()
            print(f"  class of {size}, 2 tasks each, --jobs {jobs}: {wall:6.1f} s wall, {CPU[-1]:6.1f} s CPU   "
                  f"({before} -> {load()})", flush=True)
    serial, parallel = statistics.median(times[1]), statistics.median(times[2])
    print(f"class of {size} (stop-sign block task + a stop-sign run each): --jobs 1 median {serial:.1f} s, "
          f"--jobs 2 median {parallel:.1f} s, speed-up {serial / parallel:.2f}x; "
          f"gradebooks identical: {books[1] == books[2]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--student", action="store_true", help="only the one-student measurement")
    ap.add_argument("--class-only", action="store_true", help="only the class measurement")
    ap.add_argument("--class-size", type=int, default=20)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--cold", action="store_true", help="also measure with every task a fresh interpreter")
    a = ap.parse_args()
    print(f"{os.cpu_count()} cores; {load()}")
    with tempfile.TemporaryDirectory(prefix="bench-grade-") as tmp:
        if not a.class_only:
            student(a.reps, Path(tmp), a.cold)
        if not a.student:
            klass(a.class_size, a.reps, Path(tmp))


if __name__ == "__main__":
    main()
