"""``qcarlab blocks LAB`` and ``qcarlab template LAB --out DIR``: the student's side of a lab."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from qcarlab.cli.app import app
from qcarlab.cli.common import JsonOpt, DebugOpt, stdout
from qcarlab.experiments.labs import LABS, block_rows, find_lab, write_template
from qcarlab.record import dumps

_LABS = ", ".join(f"{lab.command} ({lab.section})" for lab in LABS)


@app.command("blocks")
def blocks_cmd(
    lab: Annotated[str, typer.Argument(help=f"The lab: {_LABS}.")],
    json_out: JsonOpt = False,
    debug: DebugOpt = False,
) -> None:
    """List a lab's blocks (the sheet's Simulink blocks by name): signature, units, sheet section.

    Any of them can be replaced by your own function: qcarlab LAB --use FILE.py (every function or
    class in the file named like a block) or --block NAME=FILE.py:FUNCTION.

    Examples:
      qcarlab blocks stop-sign
      qcarlab blocks avoid --json
    """
    info = find_lab(lab)
    rows = block_rows(info)
    if json_out:
        sys.stdout.write(dumps({"lab": info.command, "section": info.section, "blocks": rows}) + "\n")
        return
    stdout.print(f"[b]{info.command}[/b]: sheet {info.section}, {info.title}; its blocks in the diagram's order:")
    for r in rows:
        marks = (" [yellow]*[/yellow]" if r["in_template"] else "") + (" (class)" if r["stateful"] else "")
        stdout.print(f"\n[b]{r['name']}[/b]{marks}   sheet {r['section']}")
        stdout.print(f"  {r['signature']}", markup=False)
        stdout.print(f"  units: {r['units']}", markup=False)
        stdout.print(f"  {r['what']}", markup=False)
    stdout.print()
    stdout.print("* a block the sheet asks you to fill (qcarlab template writes a file for it). "
                 "(class): stateful, may be a class with __call__ and reset().")
    stdout.print(f"Use yours: qcarlab {info.command} --use FILE.py  or  --block NAME=FILE.py:FUNCTION")


@app.command("template")
def template_cmd(
    lab: Annotated[str, typer.Argument(help=f"The lab: {_LABS}.")],
    out: Annotated[Path, typer.Option("--out", help="Folder for the workspace (created).")],
    force: Annotated[bool, typer.Option("--force", help="Replace files that already exist.")] = False,
    debug: DebugOpt = False,
) -> None:
    """Write a student workspace for a lab: one file per block to fill, params.yaml, answers.md.

    Each block file has the sheet's signature, the task text, units and section, and a body that
    raises NotImplementedError until you write it (a run with it unfilled says so and exits 2).

    Examples:
      qcarlab template stop-sign --out mylab
      qcarlab template avoid --out lidar-lab
    """
    info = find_lab(lab)
    written = write_template(info, out, force)
    top = [p.relative_to(out).as_posix() for p in written if len(p.relative_to(out).parts) == 1]
    others = len(written) - len(top)
    stdout.print(f"wrote the sheet {info.section} workspace to {out}: " + ", ".join(top)
                 + (f", and other-blocks/ (the lab's {others} other blocks, to replace them too)" if others else ""))
    fill = [f"{b.name}.py" for b in info.to_fill] + [f"{c.name} in params.yaml" for c in info.choose]
    if fill:
        stdout.print("fill in: " + ", ".join(fill))
    stdout.print(f"then, from {out}: {info.run}")


__all__ = ["blocks_cmd", "template_cmd"]
