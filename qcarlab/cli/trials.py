"""``--trials N`` on the lab commands (avoid, stop-sign, lane-follow): the option, a progress line
per trial on a terminal, and the summary tables. The trials themselves are
:mod:`qcarlab.experiments.trials`."""

from __future__ import annotations

import math
from typing import Annotated, Any

import typer

from qcarlab.car import parse_car_uri
from qcarlab.cli.common import Table, interactive, stderr, stdout, summary_table
from qcarlab.errors import InputError
from qcarlab.experiments.result import Result

TrialsOpt = Annotated[
    int | None,
    typer.Option("--trials", min=1, max=1000, show_default=False,
                 help="Run N seeded trials (seeds SEED..SEED+N-1) with a randomised start pose, obstacle "
                 "placements and ball start times; report the success rate, the collisions and where they "
                 "happened (trials.png and trials.csv with --out). Simulator only."),
]

MinSuccessOpt = Annotated[
    float,
    typer.Option("--min-success", min=0.0, max=1.0,
                 help="With --trials: the success rate (a fraction) the run needs to exit 0; 1 = every trial."),
]


def check_trials(trials: int | None, car: str, realtime: bool = False) -> None:
    """Trials move the simulated world's objects and run it as fast as it goes: refuse them for a
    remote car or a real-time simulator."""
    if trials is None:
        return
    if parse_car_uri(car)[0] != "sim":
        raise InputError("--trials randomises the simulated world (start pose, obstacles, ball): simulator only")
    if realtime:
        raise InputError("--trials runs the simulator as fast as it goes (seeded, repeatable): drop --realtime")


def progress(json_out: bool, n: int):
    """A one-line report per trial on stderr on a terminal (nothing in CI or with --json)."""
    if not interactive(json_out):
        return None

    def show(i: int, row: dict[str, Any]) -> None:
        what = "ok" if row["success"] else f"FAILED: {row['failure']}"
        stderr.print(f"trial {i + 1}/{n} (seed {row['seed']}): {what}", markup=False)

    return show


def given(ctx: typer.Context, name: str) -> bool:
    """True when the option ``name`` was typed on the command line (not its default)."""
    try:
        source = ctx.get_parameter_source(name)
    except Exception:  # noqa: BLE001
        return False
    return getattr(source, "name", None) == "COMMANDLINE"


def _start(row: dict[str, Any]) -> str:
    x, y, yaw = row["start"]
    return f"{x:+.2f},{y:+.2f},{math.degrees(yaw):+.0f}°"


def _cm(v: float | None) -> str:
    return "-" if v is None else f"{v * 100:.1f} cm"


def _what(r: dict[str, Any]) -> str:
    hit = r["collision"]
    if r["success"]:
        return "ok"
    if hit:
        return f"hit {hit['with']} {hit['x']:+.2f},{hit['y']:+.2f}"
    return r["failure"]


def _ball(r: dict[str, Any]) -> str:
    b = r["balls"][0] if r["balls"] else {}
    if b.get("ball_start_s") is None:
        return "not rolled"
    return f"{b['ball_start_s']:.1f} s"


def trials_summary(result: Result) -> None:
    """The per-trial table, then the totals (success rate, collisions and their places)."""
    m = result.metrics
    rows = m["runs"]
    table = Table(title=f"{m['experiment']} trials (seed {m['seed']}..{m['seed'] + m['trials'] - 1})",
                  title_justify="left")
    key = m.get("key_metric") or {}
    columns = [("trial", "right", lambda r: str(r["trial"])), ("start x, y, yaw", "right", _start),
               ("result", "left", _what)]
    table.caption = "hit: a collision, with what and where (m); ball: when it was rolled at the car"
    if key.get("trials_with_value"):
        columns.append((key["label"], "right", lambda r: _cm(r["metrics"].get(key["name"]))))
    if any(r["distance_m"] is not None for r in rows):
        columns.append(("distance", "right", lambda r: "-" if r["distance_m"] is None else f"{r['distance_m']:.2f} m"))
    if any(r["balls"] for r in rows):
        columns.append(("ball", "right", _ball))
    for name, justify, _ in columns:
        table.add_column(name, justify=justify)
    for r in rows:
        table.add_row(*(fn(r) for _, _, fn in columns))
    stdout.print(table)
    totals = summary_table(f"{m['experiment']}: {m['trials']} trials")
    totals.add_row("success rate", f"{m['successes']} of {m['trials']} ({100.0 * m['success_rate']:.0f} %)")
    if m.get("interrupted"):
        totals.add_row("interrupted", f"after {m['trials']} of {m['trials_asked']} trials")
    if key.get("trials_with_value"):
        totals.add_row(f"{key['label']}: mean (min..max)",
                       f"{_cm(key['mean'])} ({_cm(key['min'])} .. {_cm(key['max'])})")
    totals.add_row("collisions", str(m["collisions"]))
    for hit in m["collision_places"]:
        totals.add_row(f"  trial {hit['trial']}", f"{hit['with']} at ({hit['x']:+.2f}, {hit['y']:+.2f}) m, "
                       f"t = {hit['t']:.1f} s")
    other = [(t, why) for t, why in m["failures"].items() if not rows[int(t)]["collision"]]
    for t, why in other:
        totals.add_row(f"  trial {t}", why)
    stdout.print(totals)
