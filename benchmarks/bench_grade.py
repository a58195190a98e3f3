"""Graded tasks per hour on this machine, and what a class needs (issue 12, "Scale beyond one machine").

    python benchmarks/bench_grade.py              # every shipped lab sheet, 1 then N workers
    python benchmarks/bench_grade.py --workers 2  # N (default: the cores this process may use)

Runs ``qcarlab grade SHEET --json`` for every sheet in labs/ (each task of a sheet is a lab
command run on the simulator, as a grader runs it), first one sheet at a time, then the sheets
spread over N worker processes at once; prints the tasks, the wall time and graded tasks per
hour for each, how much of a task is the Python process starting up (``qcarlab --help``: the
imports), and what a class of 200 students x 5 sheets (every student's sheets graded once)
takes at that rate on one such machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import load_note, machine  # noqa: E402

STUDENTS, SHEETS_EACH = 200, 5


def grade(sheet: Path) -> tuple[int, int, float]:
    """(tasks, passed, wall s) of grading one sheet in a fresh process."""
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "qcarlab", "grade", str(sheet), "--json"],
                         capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t
    try:
        d = json.loads(out.stdout)
        return int(d["total"]), int(d["passed"]), wall
    except (ValueError, KeyError):
        print(f"  {sheet.name}: no JSON result (exit {out.returncode}): {out.stderr.strip()[-200:]}")
        return 0, 0, wall


def batch(sheets: list[Path], workers: int) -> tuple[int, int, float]:
    t = time.perf_counter()
    with ThreadPoolExecutor(workers) as pool:  # each job is its own process
        res = list(pool.map(grade, sheets))
    return sum(r[0] for r in res), sum(r[1] for r in res), time.perf_counter() - t


def main() -> int:
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover
        cores = os.cpu_count() or 1
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workers", type=int, default=cores, help="parallel graders (default: the usable cores)")
    args = ap.parse_args()
    print(f"machine: {machine()}")
    print(f"load: {load_note()}")
    sheets = sorted((ROOT / "labs").glob("*.yaml"))
    starts = []
    for _ in range(3):
        t = time.perf_counter()
        subprocess.run([sys.executable, "-m", "qcarlab", "--help"], capture_output=True, cwd=ROOT)
        starts.append(time.perf_counter() - t)
    start = statistics.median(starts)
    print(f"a qcarlab process starting (imports, `qcarlab --help`): {start:.2f} s")
    rates = {}
    for workers in sorted({1, max(1, args.workers)}):
        tasks, passed, wall = batch(sheets, workers)
        rate = tasks / wall * 3600.0 if wall > 0 else 0.0
        rates[workers] = (rate, tasks, wall)
        print(f"{len(sheets)} sheets, {tasks} tasks ({passed} passed), {workers} worker(s): {wall:.1f} s wall = "
              f"{wall / max(tasks, 1):.2f} s a task, {rate:,.0f} graded tasks per hour")
    best = max(rates, key=lambda w: rates[w][0])
    rate, tasks, _ = rates[best]
    per_sheet = tasks / max(len(sheets), 1)
    need = STUDENTS * SHEETS_EACH * per_sheet
    print(f"a class: {STUDENTS} students x {SHEETS_EACH} sheets x {per_sheet:.1f} tasks a sheet = {need:,.0f} tasks: "
          f"{need / rate:.1f} h on this machine with {best} worker(s) ({need / rate * 60 / 10:.0f} min on 10 such machines)")
    print(f"load after: {load_note()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
