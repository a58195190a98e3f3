"""Options every lab subcommand shares (DESIGN.md section 2) and the output of results."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.table import Table

from qcarlab.car import Car, open_car
from qcarlab.experiments.result import Result
from qcarlab.record import dumps

CarOpt = Annotated[
    str, typer.Option("--car", help="Which car: [b]sim[/b] (built-in simulator) or [b]tcp://HOST:PORT[/b].")
]
WorldOpt = Annotated[
    str | None,
    typer.Option("--world", help="Simulator world: a shipped name (studio, track, ...), a world YAML or a ROS map YAML."),
]
SeedOpt = Annotated[int, typer.Option("--seed", min=0, help="Seed of the simulator's noise; same seed, same numbers.")]
def check_out(out: Path | None) -> Path | None:
    """Refuse an --out that cannot be a folder before the run starts, not after it."""
    if out is not None and out.exists() and not out.is_dir():
        raise typer.BadParameter(f"{out} exists and is not a folder")
    return out


OutOpt = Annotated[
    Path | None,
    typer.Option("--out", help="Folder for results.json, the CSV log and the figures.", callback=check_out),
]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the results as JSON on stdout, nothing else.")]
RealtimeOpt = Annotated[
    bool, typer.Option("--realtime", help="Pace the simulator in real time (default: as fast as possible).")
]
DebugOpt = Annotated[bool, typer.Option("--debug", help="Show tracebacks on errors.")]
ParamsOpt = Annotated[
    Path | None,
    typer.Option("--params", help="YAML file overriding the simulated car's parameters (see qcarlab/constants.py)."),
]
RateOpt = Annotated[float, typer.Option("--rate", help="Control loop rate in Hz (the lab's Python loops: 60-200).")]

stdout = Console(highlight=False)


def open_from_options(
    car: str,
    world: str | None = None,
    seed: int = 0,
    realtime: bool = False,
    params: Path | None = None,
    **extra: Any,
) -> Car:
    """Open the car the shared options describe."""
    return open_car(car, world=world, seed=seed, realtime=realtime, params=params, **extra)


def interactive(json_out: bool) -> bool:
    """Live views and progress bars only on a terminal, never with --json."""
    return not json_out and sys.stdout.isatty()


def emit(result: Result, json_out: bool, out: Path | None, summary) -> None:
    """Save to --out, then print JSON (with --json) or the human summary."""
    written = result.save(out) if out is not None else []
    if json_out:
        sys.stdout.write(dumps(result.metrics) + "\n")
        return
    summary(result)
    if written:
        stdout.print(f"wrote {len(written)} file(s) to {out}: " + ", ".join(p.name for p in written))


def summary_table(title: str) -> Table:
    """The two-column "what / value" table every command's human summary prints."""
    table = Table(title=title, title_justify="left", show_header=False)
    table.add_column("what")
    table.add_column("value", justify="right")
    return table
