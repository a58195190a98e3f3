"""What the realism profiles do (issue 11 item 1): dead-reckoning drift, tracking, look-ahead chatter.

Run: python benchmarks/bench_realism.py [--seeds 3]

For the sheet's paths (p1 line, p2 circle, p3 4 m butterfly, p4 2 m butterfly) at the lab's
defaults (0.5 m/s, look-ahead 0.3 m), under ``--realism ideal`` and ``lab``, with the sheet's
bicycle dead reckoning and with the gyro's heading: the estimate's drift from the truth at the
end per metre driven, the true RMS cross-track error, the RMS as the car's own estimate sees it,
and whether the car truly reached the end. Then the steering's standard deviation on p1 (after
the first quarter) with the true pose at look-aheads 0.02-0.3 m: chatter at look-aheads far below
the 0.47 m minimum turning radius. Medians over --seeds seeds (the bicycle runs do not depend on
the seed: no noise enters them). Quality figures, not timings: the machine does not matter.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import qcarlab  # noqa: E402
from qcarlab import paths  # noqa: E402
from qcarlab.experiments.path_follow import FollowConfig, follow_path  # noqa: E402


def run(path, realism, seed, **cfg):
    with qcarlab.open_car("sim", seed=seed, realism=realism) as car:
        return follow_path(car, path, FollowConfig(**cfg))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    cases = [("p1 line 3 m", paths.line(3, 4)), ("p2 circle r 1.5 m", paths.circle()),
             ("p3 butterfly 4 m", paths.butterfly(4, 4)), ("p4 butterfly 2 m", paths.butterfly(2, 2))]
    print(f"{'path':<20}{'realism':<8}{'pose':<9}{'drift cm/m':>11}{'RMS cm':>8}{'RMS est cm':>11}{'true end cm':>12}"
          f"{'goal':>6}")
    for name, path in cases:
        for realism in ("ideal", "lab"):
            for pose in ("bicycle", "gyro"):
                ms = [run(path, realism, s, pose=pose).metrics for s in range(args.seeds)]

                def med(key, ms=ms):
                    return statistics.median(m[key] for m in ms)

                print(f"{name:<20}{realism:<8}{pose:<9}{100 * med('pose_drift_per_m'):>11.2f}"
                      f"{100 * med('rms_cross_track_m'):>8.1f}{100 * med('rms_cross_track_estimate_m'):>11.1f}"
                      f"{100 * med('final_distance_to_goal_m'):>12.1f}{sum(m['goal_reached'] for m in ms):>4}/{len(ms)}")
    looks = (0.02, 0.05, 0.1, 0.2, 0.3)
    print()
    print("p1, true pose: the weave after the first third, by look-ahead: max |cross-track| cm / steering sd rad")
    print(f"{'realism':<8}" + "".join(f"{la:>14.2f} m" for la in looks))
    for realism in ("ideal", "lab"):
        row = []
        for la in looks:
            amps, sds = [], []
            for s in range(args.seeds):
                log = run(paths.line(3, 4), realism, s, lookahead=la, pose="truth").logs["log.csv"]
                x, st = np.asarray(log["true_x"]), np.asarray(log["steering"])
                amps.append(float(np.abs(x[len(x) // 3:]).max()))
                sds.append(float(st[len(st) // 3:].std()))
            row.append(f"{100 * statistics.median(amps):>9.1f} / {statistics.median(sds):.2f}")
        print(f"{realism:<8}" + "".join(f"{v:>16}" for v in row))
    print()
    print("p4 butterfly 2 m, lab, the sheet's bicycle estimate: RMS cross-track as the car sees it / true, cm")
    sweep = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7)
    print("".join(f"{la:>14.2f} m" for la in sweep))
    row = []
    for la in sweep:
        ms = [run(paths.butterfly(2, 2), "lab", s, lookahead=la).metrics for s in range(args.seeds)]
        est = statistics.median(m["rms_cross_track_estimate_m"] for m in ms)
        true = statistics.median(m["rms_cross_track_m"] for m in ms)
        goal = sum(m["goal_reached"] for m in ms)
        row.append(f"{100 * est:.1f} / {100 * true:.1f}{'' if goal == len(ms) else ' !'}")
    print("".join(f"{v:>16}" for v in row))
    print("(! = not every run reached the goal)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
