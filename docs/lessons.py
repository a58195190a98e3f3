"""Write docs/lessons.md: each lesson of the lab sheet as the commands print it on the defaults.

    python docs/lessons.py            # rewrite docs/lessons.md from the commands' own output
    python docs/lessons.py --check    # exit 1 when docs/lessons.md is not what the commands print

Every number on the page comes from a ``qcarlab ... --json`` run typed as a student would type it
(the simulator, seed 0, the default ``--realism lab``); ``tests/test_lessons_page.py`` runs this
and fails when the page has gone stale, so the page cannot rot.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

PAGE = Path(__file__).resolve().parent / "lessons.md"

Runner = Callable[[list[str]], tuple[int, dict]]


def run_cli(argv: list[str]) -> tuple[int, dict]:
    """``qcarlab ARGV --json`` in a process of its own: (exit code, results)."""
    done = subprocess.run([sys.executable, "-m", "qcarlab", *argv, "--json"], capture_output=True, text=True)
    return done.returncode, json.loads(done.stdout)


def _cm(value: float | None) -> str:
    return "-" if value is None else f"{value * 100:.1f}"


def _s(value: float | None, missing: str = "never") -> str:
    return missing if value is None else f"{value:.2f}"


def lookahead(run: Runner) -> list[str]:
    argv = ["path-follow", "butterfly", "--size", "2", "--lookahead", "0.05,0.1,0.2,0.3,0.5,0.8,1.2"]
    _, m = run(argv)
    rows = sorted(m["runs"], key=lambda r: r["lookahead"])
    out = ["## 4.2.2 Tasks 3-4: the look-ahead distance", "",
           f"`qcarlab {' '.join(argv)}` (the 2 m butterfly, p4): the error pure pursuit sees (its pose "
           "estimate against the path) is smallest in the middle; short look-aheads weave, long ones cut "
           "the corners. The true error adds the dead reckoning's drift, which no look-ahead sees.", "",
           "| look-ahead m | tracking RMS cm | true RMS cm | drift cm | goal |", "|---|---|---|---|---|"]
    for r in rows:
        goal = "reached" if r.get("goal_reached", True) else f"missed: {r.get('failure')}"
        out.append(f"| {r['lookahead']:g} | {_cm(r.get('rms_cross_track_estimate_m'))} | "
                   f"{_cm(r['rms_cross_track_m'])} | {_cm(r.get('pose_drift_m'))} | {goal} |")
    out += ["", f"Best: {m['best']['lookahead']:g} m.", ""]
    return out


def pi_tuning(run: Runner) -> list[str]:
    gains = [("0.05", "0.2", "lab"), ("0.3", "1", "lab"), ("1", "5", "lab"), ("5", "20", "lab"),
             ("20", "200", "lab"), ("20", "200", "ideal")]
    out = ["## 4.2.3: the PI gains", "",
           "`qcarlab path-follow line --step-response --speed 0.5 --kp KP --ki KI` (add `--realism ideal` for "
           "the last row): the lab car's ESC acts 30 ms late and ignores 2 % of throttle about neutral, so "
           "gains too high ring and chatter, gains too low never settle. The ideal drive train has no such "
           "penalty.", "",
           "| Kp | Ki | realism | rise s | overshoot % | settling s | steady error m/s | throttle chatter | "
           "at the limit s |", "|---|---|---|---|---|---|---|---|---|"]
    for kp, ki, realism in gains:
        _, m = run(["path-follow", "line", "--step-response", "--speed", "0.5", "--kp", kp, "--ki", ki,
                    "--realism", realism])
        out.append(f"| {kp} | {ki} | {realism} | {_s(m['rise_time_s'])} | {m['overshoot_pct']:.1f} | "
                   f"{_s(m['settling_time_s'])} | {m['steady_state_error_mps']:.3f} | "
                   f"{m['throttle_chatter']:.3f} | {m['throttle_saturated_s']:.2f} |")
    return out + [""]


def hsv(run: Runner) -> list[str]:
    ranges = [("17,85,70", "38,255,255", "qcarlab's yellow"), ("22,120,120", "32,255,255", "a narrow yellow"),
              ("100,100,100", "130,255,255", "blue"), ("0,0,0", "179,255,255", "everything")]
    out = ["## 5.3.2: the HSV range", "",
           "`qcarlab lane-follow --duration 20 --hsv-min H,S,V --hsv-max H,S,V`: the yellow line found with "
           "your range is what the car follows; the white edge line only bridges the curves where the "
           "yellow one is out of the camera's view.", "",
           "| range | HSV min .. max | frames with the yellow line | white backup | RMS from the lane centre cm | "
           "result |", "|---|---|---|---|---|---|"]
    for lo, hi, name in ranges:
        code, m = run(["lane-follow", "--duration", "20", "--hsv-min", lo, "--hsv-max", hi])
        result = "in lane (exit 0)" if code == 0 else f"exit {code}: {m.get('failure')}"
        out.append(f"| {name} | {lo} .. {hi} | {m['frames_yellow']} of {m['frames']} | "
                   f"{m['frames_white_backup']} | {_cm(m['rms_lateral_deviation_m'])} | {result} |")
    return out + [""]


def stop_sign(run: Runner) -> list[str]:
    out = ["## 5.2 Tasks 3-4: the stopSign block at other speeds", "",
           "`qcarlab stop-sign --speed V` (the sheet's block) and `qcarlab stop-sign --behaviour hold --speed V` "
           "(the improved one, `stop_sign_hold`): the sheet's block brakes only inside 0.40 m, so at speed it "
           "stops later, and once the sign leaves the camera's view it drives on.", "",
           "| speed m/s | sheet's block: stop before the sign m | hold: stop m, held s |", "|---|---|---|"]
    for v in ("0.3", "0.5", "0.8", "1.0"):
        _, sheet = run(["stop-sign", "--speed", v])
        _, hold = run(["stop-sign", "--behaviour", "hold", "--speed", v])
        first = f"{sheet['stop_distance_m']:.3f}" if sheet["goal_reached"] else f"missed: {sheet['failure']}"
        second = (f"{hold['stop_distance_m']:.3f}, {hold['hold_s']:.2f}" if hold["goal_reached"]
                  else f"missed: {hold['failure']}")
        out.append(f"| {v} | {first} | {second} |")
    return out + [""]


def page(run: Runner = run_cli) -> str:
    lines = ["# The lessons of the lab sheet, on the defaults", "",
             "Made by `python docs/lessons.py` from the commands' own output (the simulator, seed 0, "
             "`--realism lab`); `tests/test_lessons_page.py` fails when the page and the commands disagree. "
             "Run any row yourself: the same command gives the same numbers.", ""]
    for part in (lookahead, pi_tuning, hsv, stop_sign):
        lines += part(run)
    return "\n".join(lines).rstrip() + "\n"


def main(argv: list[str]) -> int:
    text = page()
    if "--check" in argv:
        same = PAGE.exists() and PAGE.read_text(encoding="utf-8") == text
        print("docs/lessons.md is up to date" if same else "docs/lessons.md is stale: run python docs/lessons.py")
        return 0 if same else 1
    PAGE.write_text(text, encoding="utf-8")
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
