"""``qcarlab replay info FILE``: what a recording (MCAP or rosbag2) holds.

Replaying itself is ``--car replay:FILE`` on any lab command (see ``qcarlab.car.replay``).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from qcarlab.cli.app import app
from qcarlab.cli.common import DebugOpt, JsonOpt, stdout
from qcarlab.cli.helpfmt import Typer
from qcarlab.record import dumps

replay_app = Typer(help="Recordings: what they hold (replay one with --car replay:FILE on a lab command).",
                         no_args_is_help=True)
app.add_typer(replay_app, name="replay")


@replay_app.command("info")
def info_cmd(
    file: Annotated[Path, typer.Argument(help="A recording: FILE.mcap (from --record) or a rosbag2 folder / .db3.")],
    topics: Annotated[bool, typer.Option("--topics", help="Only the topics, one a line in full: name, schema and "
                                         "message count, tab-separated (for scripts: cut -f1).")] = False,
    json_out: JsonOpt = False,
    debug: DebugOpt = False,
) -> None:
    """Topics, schemas, message counts, duration and rates of a recording.

    Examples:
      qcarlab replay info run.mcap
      qcarlab replay info run.mcap --topics
      qcarlab replay info rosbag2_2024_05_01/ --json
    """
    from qcarlab.recording.reader import open_recording

    info = open_recording(file).info()
    if json_out:
        sys.stdout.write(dumps(info) + "\n")
        return
    if topics:
        for topic, t in info["topics"].items():
            sys.stdout.write(f"{topic}\t{t['schema'] or t['encoding'] or '-'}\t{t['count']}\n")
        return
    head = f"{info['file']}: {info['format']}, {info['duration_s']:.2f} s, {info['messages']} messages"
    if info.get("bytes") is not None:
        head += f", {info['bytes'] / 1e6:.1f} MB"
    stdout.print(head, markup=False, highlight=False)
    if not info["complete"]:
        stdout.print("the recording was cut off (no summary at its end): everything up to the cut is listed",
                     markup=False)
    details = [f"{k} {info[k]}" for k in ("profile", "world", "car") if info.get(k)]
    if info.get("command"):
        details.append("recorded by: qcarlab " + " ".join(info["command"]))
    for line in details:
        stdout.print(line, markup=False, highlight=False)
    stdout.print(topics_table(info["topics"]))


def topics_table(topics: dict) -> Table:
    """The topics as a table that keeps every topic name whole (qcarlab's fit in 80 columns): no
    vertical rules, the name never wrapped or cut; a schema too long for the width folds onto a
    second line instead (``--topics`` lists them one a line whatever the width)."""
    from rich import box

    table = Table(title="topics", title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)
    longest = max((len(name) for name in topics), default=5)
    table.add_column("topic", no_wrap=True, min_width=longest)
    table.add_column("schema", overflow="fold", ratio=1)
    for name in ("count", "Hz", "t (s)"):
        table.add_column(name, justify="right", overflow="fold")
    for topic, t in topics.items():
        rate = f"{t['rate_hz']:.1f}" if t["rate_hz"] is not None else "-"
        table.add_row(topic, t["schema"] or t["encoding"] or "-", str(t["count"]), rate,
                      f"{t['first_s']:.2f}-{t['last_s']:.2f}")
    return table


__all__ = ["info_cmd", "replay_app", "topics_table"]
