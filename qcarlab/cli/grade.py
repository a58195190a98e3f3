"""``qcarlab grade``: check runs against a lab sheet's criteria, for a student or a CI script."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from qcarlab.cli.app import app
from qcarlab.cli.common import DebugOpt, JsonOpt, check_out, stdout
from qcarlab.errors import InputError
from qcarlab.grade import Task, check, find_sheet, load_sheet
from qcarlab.record import dumps, prepare_out_dir, write_json


def _run_task(task: Task, car: str | None, timeout: float) -> tuple[dict | None, str]:
    """Run the task's command with --json in a fresh process; (results, problem)."""
    argv = shlex.split(task.command)[1:]
    if "--json" not in argv:
        argv.append("--json")
    if car is not None and "--car" not in argv:
        argv += ["--car", car]
    try:
        done = subprocess.run([sys.executable, "-m", "qcarlab", *argv], capture_output=True, text=True,
                              timeout=timeout)
    except subprocess.TimeoutExpired:
        return None, f"did not finish within {timeout:g} s"
    if done.returncode != 0:
        lines = done.stderr.strip().splitlines()
        return None, lines[-1] if lines else f"exit code {done.returncode}"
    try:
        return json.loads(done.stdout), ""
    except json.JSONDecodeError:
        return None, "the command printed no JSON"


def _read_results(task: Task, folder: Path) -> tuple[dict | None, str]:
    """DIR/TASK-ID/results.json (what --out writes) or DIR/TASK-ID.json."""
    for path in (folder / task.id / "results.json", folder / f"{task.id}.json"):
        if path.exists():
            try:
                return json.loads(path.read_text(encoding="utf-8")), ""
            except (OSError, json.JSONDecodeError) as exc:
                return None, f"{path}: unreadable ({exc})"
    return None, f"not run: no {task.id}/results.json in {folder}"


@app.command("grade")
def grade_cmd(
    sheet: Annotated[str, typer.Argument(help="A lab sheet: its name in labs/ (path-following, stop-sign, ...) "
                                         "or the path of a sheet YAML.")],
    results: Annotated[Path | None, typer.Option(help="Grade saved runs: DIR/TASK-ID/results.json (run each "
                                                 "task's command with --out DIR/TASK-ID). Without it, grade runs "
                                                 "each task's command now.", show_default=False)] = None,
    task: Annotated[list[str] | None, typer.Option("--task", help="Grade only this task (repeatable).",
                                                   show_default=False)] = None,
    car: Annotated[str | None, typer.Option(help="Run the commands on this car (tcp://HOST:PORT).",
                                            show_default=False)] = None,
    timeout: Annotated[float, typer.Option(help="Seconds a task's command may take.")] = 300.0,
    out: Annotated[Path | None, typer.Option("--out", help="Write grade.json here.", callback=check_out,
                                             show_default=False)] = None,
    json_out: JsonOpt = False,
    debug: DebugOpt = False,
) -> None:
    """Grade runs against a lab sheet's criteria. Exit 0 when every task passes, 1 otherwise.

    Examples: qcarlab grade path-following | qcarlab grade stop-sign --results runs/ --json |
    qcarlab grade labs/path-following.yaml --task p2-circle
    """
    path = find_sheet(sheet)
    title, tasks = load_sheet(path)
    if task:
        unknown = [t for t in task if t not in {x.id for x in tasks}]
        if unknown:
            raise InputError(f"--task {unknown[0]!r} is not in {path} (tasks: {', '.join(t.id for t in tasks)})")
        tasks = [t for t in tasks if t.id in task]
    if results is not None and not results.is_dir():
        raise InputError(f"--results {results}: not a folder")
    report = {"sheet": str(path), "title": title, "tasks": []}
    for t in tasks:
        data, problem = _read_results(t, results) if results is not None else _run_task(t, car, timeout)
        verdicts = check(data, t.criteria) if data is not None else []
        passed = data is not None and all(v.passed for v in verdicts)
        report["tasks"].append({
            "id": t.id, "command": t.command, "passed": passed, "problem": problem or None,
            "criteria": [{"criterion": v.criterion.describe(), "value": v.value, "passed": v.passed,
                          "reason": v.reason or None} for v in verdicts],
        })
    report["passed"] = sum(r["passed"] for r in report["tasks"])
    report["total"] = len(report["tasks"])
    if out is not None:
        write_json(prepare_out_dir(out) / "grade.json", report)
    if json_out:
        sys.stdout.write(dumps(report) + "\n")
    else:
        table = Table(title=f"{title}: {report['passed']} of {report['total']} tasks passed", title_justify="left")
        for col in ("task", "criterion", "value", "result"):
            table.add_column(col)
        for r in report["tasks"]:
            if r["problem"]:
                table.add_row(r["id"], "-", "-", f"FAIL: {r['problem']}")
            for c in r["criteria"]:
                value = c["value"]
                shown = f"{value:.4g}" if isinstance(value, (int, float)) and not isinstance(value, bool) else str(value)
                table.add_row(r["id"], c["criterion"], shown, "pass" if c["passed"] else f"FAIL{': ' + c['reason'] if c['reason'] else ''}")
        stdout.print(table)
    if report["passed"] != report["total"]:
        raise typer.Exit(1)
