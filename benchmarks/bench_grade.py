"""How long grading takes: one student on the five lab sheets, and a class of 20 with --jobs 2 vs 1.

    python benchmarks/bench_grade.py                 # both measurements (about 15 minutes on 2 cores)
    python benchmarks/bench_grade.py --student       # one student, all five sheets, --jobs 1 and 2
    python benchmarks/bench_grade.py --class-size 20 --reps 2
    python benchmarks/bench_grade.py --student --cold    # also with every task a fresh interpreter
    python benchmarks/bench_grade.py --student --against /tmp/start   # ours and that checkout, alternated (issue 28)
    python benchmarks/bench_grade.py --sandbox --against /tmp/before   # the sandbox's cost (issue 26)

``--sandbox`` alternates ``--sandbox required`` (the student's code in its own confined process)
with ``--sandbox off`` (its own process, not confined) and, with ``--against DIR``, with the
grader of the checkout in DIR (the code before the split: the student's code in the task's
process), and prints the sandbox's cost per task (the wall-time difference over the tasks, at
``--jobs 1``) and the graded tasks per hour of each (``--jobs 2``). Target (issue 26): at most
0.2 s of extra wall time per task, and tasks per hour within 20 % of the code before.

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
import json
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


def grade(args: list[str], cold: bool = False, against: str | None = None) -> float:
    """Wall seconds of one ``qcarlab grade`` run (of the checkout ``against``, when given); its CPU
    seconds go to CPU."""
    env = dict(os.environ)
    env.pop("QCARLAB_GRADE_COLD", None)
    if cold:
        env["QCARLAB_GRADE_COLD"] = "1"
    if against:
        env["PYTHONPATH"] = against + os.pathsep + env.get("PYTHONPATH", "")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    # from a folder that holds no qcarlab: ``python -m`` puts the working folder first on the path, so
    # run from a checkout it would import that checkout's qcarlab whatever PYTHONPATH says
    done = subprocess.run([sys.executable, "-m", "qcarlab", "grade", *args], capture_output=True, text=True, env=env,
                          cwd=tempfile.gettempdir())
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    CPU.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    if done.returncode not in (0, 1):
        raise SystemExit(f"qcarlab grade {' '.join(args)} failed ({done.returncode}): {done.stderr[-500:]}")
    return wall


def load() -> str:
    return "load %.1f %.1f %.1f" % os.getloadavg()


def student(reps: int, tmp: Path, cold: bool, against: str | None = None) -> None:
    """One student's five sheets, ``--jobs 1`` and 2 (and cold with ``cold``); with ``against``, also
    the checkout in that folder at ``--jobs 1``, alternated with ours, and the two CPU medians side by
    side against issue 28's target (10 s of CPU)."""
    sub = correct_submission(tmp / "student")
    configs = [(jobs, c, None) for c in ((False, True) if cold else (False,)) for jobs in (1, 2)]
    if against:
        configs.append((1, False, against))
    times: dict[tuple, list[float]] = {c: [] for c in configs}
    cpu: dict[tuple, list[float]] = {c: [] for c in configs}
    if against:  # its first run compiles its numba kernels into its own checkout: not timed
        grade([*FIVE, "--submission", str(sub), "--jobs", "1", "--out", str(tmp / "warm-against")], against=against)
    for rep in range(reps):
        for jobs, c, where in configs if rep % 2 == 0 else configs[::-1]:
            before = load()
            out = tmp / f"s{jobs}{c}{bool(where)}"
            wall = grade([*FIVE, "--submission", str(sub), "--jobs", str(jobs), "--out", str(out)], c, where)
            times[(jobs, c, where)].append(wall)
            cpu[(jobs, c, where)].append(CPU[-1])
            who = f" ({where})" if where else ""
            print(f"  one student, five sheets, --jobs {jobs}{' (cold)' if c else ''}{who}: {wall:6.1f} s wall, "
                  f"{CPU[-1]:6.1f} s CPU   ({before} -> {load()})", flush=True)
    for (jobs, c, where), t in times.items():
        who = f" [{where}]" if where else ""
        print(f"one student, all five lab sheets (25 tasks), --jobs {jobs}{' cold' if c else ''}{who}: median "
              f"{statistics.median(t):.1f} s wall, {statistics.median(cpu[(jobs, c, where)]):.1f} s CPU "
              f"over {len(t)} run(s)")
    if against:
        ours, theirs = statistics.median(cpu[(1, False, None)]), statistics.median(cpu[(1, False, against)])
        print(f"target (issue 28): one student, five sheets <= 10 s of CPU: ours {ours:.1f} s, {against} {theirs:.1f} s "
              f"-> {'met' if ours <= 10.0 else 'MISSED'}")


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


def sandbox_cost(reps: int, tmp: Path, against: str | None) -> None:
    """One student's five sheets (``--jobs 1``: the cost per task) and a class of 10 on the
    stop-sign sheet (``--jobs 2``: tasks per hour), sandboxed, not, and the code before."""
    sub = correct_submission(tmp / "student")
    root = tmp / "class10"
    for i in range(10):
        correct_submission(root / f"student{i:02d}", ("stop-sign",))
    configs = [("sandboxed", ["--sandbox", "required"], None), ("not sandboxed", ["--sandbox", "off"], None)]
    if against:
        configs.append(("code before", [], against))
    runs = {"one": ([*FIVE, "--submission", str(sub), "--jobs", "1"], 25),
            "class": (["stop-sign", "--class", str(root), "--jobs", "2"], 50)}
    wall: dict[tuple[str, str], list[float]] = {(r, c[0]): [] for r in runs for c in configs}
    per_task: dict[tuple[str, str], list[float]] = {}  # (config, task) -> its seconds in grade.json
    for rep in range(reps):
        for label, extra, where in configs if rep % 2 == 0 else configs[::-1]:
            for run, (args, _) in runs.items():
                before = load()
                out = tmp / f"{run}-{len(wall[(run, label)])}-{label[:3]}"
                t = grade([*args, *extra, "--out", str(out)], against=where)
                if run == "one":
                    for task in json.loads((out / "grade.json").read_text())["tasks"]:
                        per_task.setdefault((label, f"{task['sheet']}/{task['id']}"), []).append(task["seconds"] or 0.0)
                wall[(run, label)].append(t)
                print(f"  {run:5s} {label:13s}: {t:6.1f} s wall, {CPU[-1]:6.1f} s CPU   ({before} -> {load()})",
                      flush=True)
    base = "code before" if against else "not sandboxed"
    print(f"\nsandbox cost (medians of {reps}; {load()}):")
    for label, _, _ in configs:
        one = statistics.median(wall[("one", label)])
        klass_s = statistics.median(wall[("class", label)])
        extra = (one - statistics.median(wall[("one", base)])) / runs["one"][1]
        per_hour = runs["class"][1] / klass_s * 3600
        ratio = per_hour / (runs["class"][1] / statistics.median(wall[("class", base)]) * 3600)
        print(f"  {label:13s}: one student, 25 tasks, --jobs 1: {one:6.1f} s ({extra:+.3f} s a task against {base}); "
              f"class of 10, 50 tasks, --jobs 2: {klass_s:6.1f} s = {per_hour:,.0f} tasks an hour ({ratio:.2f}x)")
    tasks = sorted({task for _, task in per_task})
    extra_by_task = sorted(((statistics.median(per_task[("sandboxed", k)]) - statistics.median(per_task[(base, k)]), k)
                            for k in tasks if ("sandboxed", k) in per_task and (base, k) in per_task), reverse=True)
    print("  the tasks the sandbox costs most (median seconds in grade.json, sandboxed - " + base + "):")
    for d, k in extra_by_task[:4]:
        print(f"    {k}: {d:+.3f} s ({statistics.median(per_task[(base, k)]):.3f} -> "
              f"{statistics.median(per_task[('sandboxed', k)]):.3f} s)")
    if against:
        one_extra = (statistics.median(wall[("one", "sandboxed")]) - statistics.median(wall[("one", base)])) / 25
        ratio = statistics.median(wall[("class", base)]) / statistics.median(wall[("class", "sandboxed")])
        ok = one_extra <= 0.2 and ratio >= 0.8
        print(f"target: <= 0.2 s a task and >= 0.8x the tasks an hour of the code before: "
              f"{one_extra:+.3f} s, {ratio:.2f}x -> {'met' if ok else 'MISSED'}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--student", action="store_true", help="only the one-student measurement")
    ap.add_argument("--class-only", action="store_true", help="only the class measurement")
    ap.add_argument("--class-size", type=int, default=20)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--cold", action="store_true", help="also measure with every task a fresh interpreter")
    ap.add_argument("--sandbox", action="store_true", help="only the sandbox's cost: sandboxed, not, and --against")
    ap.add_argument("--against", metavar="DIR", help="with --sandbox or --student: also the grader of the checkout in DIR")
    a = ap.parse_args()
    print(f"{os.cpu_count()} cores; {load()}")
    with tempfile.TemporaryDirectory(prefix="bench-grade-") as tmp:
        if a.sandbox:
            sandbox_cost(a.reps, Path(tmp), a.against)
            return
        if not a.class_only:
            student(a.reps, Path(tmp), a.cold, a.against)
        if not a.student:
            klass(a.class_size, a.reps, Path(tmp))


if __name__ == "__main__":
    main()
