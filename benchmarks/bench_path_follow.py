"""Path following: quality on the sheet's paths and simulator speed (issue 3's targets).

Run: python benchmarks/bench_path_follow.py [--repeat 5]

Quality (simulator, defaults, 0.5 m/s): circle r = 1.5 m RMS <= 0.02 m; p3 (4 m butterfly)
RMS <= 0.04 m; p4 (2 m butterfly) best of the look-ahead sweep RMS <= 0.10 m; the line stops
within 0.10 m of (0, -3); completion >= 0.99 everywhere.
Speed: a 30 s run at 100 Hz without plots in < 0.3 s wall (>= 100x real time). Figures are
medians over --repeat runs.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import qcarlab
from qcarlab import paths
from qcarlab.experiments.path_follow import FollowConfig, follow_path


def run(path, **cfg):
    with qcarlab.open_car("sim", seed=0) as car:
        t0 = time.perf_counter()
        m = follow_path(car, path, FollowConfig(**cfg)).metrics
        return m, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    print(f"machine: {platform.machine()} {platform.processor() or ''}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}")
    ok = True
    print(f"{'case':<28}{'RMS cm':>8}{'max cm':>8}{'compl %':>9}{'goal cm':>9}{'sim s':>8}{'wall s':>8}{'x real':>8}")
    cases = [("circle r1.5", paths.circle(), {}, 0.02), ("p3 butterfly 4", paths.butterfly(4, 4), {}, 0.04),
             ("line 3 m", paths.line(3, 4), {}, None)]
    cases += [(f"p4 butterfly 2, l_d {la}", paths.butterfly(2, 2), {"lookahead": la}, None) for la in (0.2, 0.3, 0.5, 0.8)]
    p4_best = float("inf")
    for name, path, cfg, bound in cases:
        walls = []
        for _ in range(args.repeat):
            m, wall = run(path, **cfg)
            walls.append(wall)
        wall = statistics.median(walls)
        print(f"{name:<28}{m['rms_cross_track_m'] * 100:8.2f}{m['max_cross_track_m'] * 100:8.2f}"
              f"{m['completion'] * 100:9.1f}{m['final_distance_to_goal_m'] * 100:9.1f}{m['duration_s']:8.1f}"
              f"{wall:8.3f}{m['duration_s'] / wall:8.0f}")
        ok &= m["completion"] >= 0.99
        if bound is not None:
            ok &= m["rms_cross_track_m"] <= bound
        if name.startswith("line"):
            ok &= m["final_distance_to_goal_m"] <= 0.10
        if name.startswith("p4"):
            p4_best = min(p4_best, m["rms_cross_track_m"])
    ok &= p4_best <= 0.10
    # speed: a 30 s run at 100 Hz (the circle, repeated laps, capped at 30 s of simulated time)
    walls = []
    for _ in range(args.repeat):
        m, wall = run(paths.circle(), laps=3, max_time=30.0)
        walls.append(wall)
    wall = statistics.median(walls)
    print(f"30 s simulated at 100 Hz: median {wall:.3f} s wall = {30.0 / wall:.0f}x real time (target < 0.3 s)")
    ok &= wall < 0.3
    print("all targets met" if ok else "SOME TARGETS MISSED")


if __name__ == "__main__":
    main()
