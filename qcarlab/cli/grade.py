"""``qcarlab grade``: a student's submission (or a class) against lab sheets; ``qcarlab labs``: the sheets."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table
from rich.text import Text

from qcarlab.cli.app import app
from qcarlab.cli.common import DebugOpt, JsonOpt, stderr, stdout
from qcarlab.errors import InputError
from qcarlab.grading.grader import Options, grade, make_plan, summary
from qcarlab.grading.limits import Limits
from qcarlab.grading.sheet import Sheet, find_sheet, load_sheet, select_tasks, shipped_sheets
from qcarlab.grading.submission import class_folders
from qcarlab.record import dumps, inner_folder, write_bytes, write_json


class CliCommands:
    """The CLI's own parser, for the grader (which does not import the CLI). A command is parsed
    once (some 12 ms each: the sheet check and the plan both parse every scenario task's)."""

    def __init__(self) -> None:
        self.parsed: dict[tuple[str, ...], tuple[str, dict[str, Any], dict[str, str]]] = {}

    def parse(self, argv: list[str]) -> tuple[str, dict[str, Any], dict[str, str]]:
        import copy

        from qcarlab.cli.invocation import parse_command

        key = tuple(argv)
        if key not in self.parsed:
            self.parsed[key] = parse_command(argv)
        return copy.deepcopy(self.parsed[key])  # (a caller's changes reach no other)

    def accepts(self, argv: list[str], option: str) -> bool:
        from qcarlab.cli.invocation import command_accepts

        return command_accepts(argv, option)


def _shown(criterion: dict[str, Any]) -> str:
    """A criterion's value: the number, in words when the run measured none, "-" when nothing ran."""
    from qcarlab.grading.checks import value_text

    text = value_text(criterion) or "-"
    return text if len(text) <= 40 else text[:37] + "..."


def _check_sheet_commands(sheets: list[Sheet], commands: CliCommands) -> None:
    """Every scenario task's command must parse (a sheet's typo is the sheet's, exit 2)."""
    for s in sheets:
        for t in s.tasks:
            if t.command is not None:
                try:
                    commands.parse(t.argv("tcp://127.0.0.1:1"))
                except InputError as exc:
                    raise InputError(f"{s.path}: task {t.id}: {exc}") from None


def _write_artifacts(out: Path, parts: tuple[str, ...], row: dict[str, Any]) -> list[str]:
    """A task's results and figures in OUT/PARTS (no symbolic link followed on the way)."""
    written = []
    results = row.get("_results")
    figs = row.get("_figures") or {}
    if not figs and results is None:
        return written
    folder = inner_folder(out, *parts)
    if results is not None:
        write_json(folder / "results.json", results)
        written.append("results.json")
    for name, data in sorted(figs.items()):
        write_bytes(folder / Path(name).name, data)
        written.append(name)
    return written


def _progress(total: int, show: bool):
    """A progress bar on stderr (a terminal only): (advance(job, outcome), stop())."""
    if not show or total == 0:
        return (lambda job, outcome: None), (lambda: None)
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    bar = Progress(TextColumn("grading"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                   TextColumn("{task.description}"), console=stderr, transient=True)
    tid = bar.add_task("", total=total)
    bar.start()

    def advance(job, outcome) -> None:
        bar.update(tid, advance=1, description=f"{job.key[0]} {job.key[2]}")

    return advance, bar.stop


@app.command("grade")
def grade_cmd(
    sheets: Annotated[list[str], typer.Argument(help="Lab sheets: a name (path-following, stop-sign, ...; "
                                                "qcarlab labs lists them), a section (5.2) or a sheet YAML.",
                                                show_default=False)],
    submission: Annotated[Path | None, typer.Option(help="A student's folder as qcarlab template made it: their "
                                                    "block files, params.yaml, answers.md (one sub-folder per "
                                                    "sheet for several). Without it: qcarlab's own blocks.",
                                                    show_default=False)] = None,
    class_dir: Annotated[Path | None, typer.Option("--class", help="A class: one sub-folder per student "
                                                   "(each a submission). Writes gradebook.csv, report.html and "
                                                   "grade.json to --out.", show_default=False)] = None,
    results: Annotated[Path | None, typer.Option(help="Grade saved runs of the scenario tasks instead: "
                                                 "DIR/TASK-ID/results.json (each task's command run with --out "
                                                 "DIR/TASK-ID, e.g. on the real car).",
                                                 show_default=False)] = None,
    task: Annotated[list[str] | None, typer.Option("--task", help="Grade only this task (ID or SHEET/ID; "
                                                   "repeatable).", show_default=False)] = None,
    car: Annotated[str | None, typer.Option(help="Run the commands on this car (tcp://HOST:PORT); tasks that "
                                            "need a car are skipped without it.", show_default=False)] = None,
    timeout: Annotated[float, typer.Option(help="Wall-time limit of each task, s.")] = 300.0,
    memory: Annotated[float, typer.Option(help="Memory limit of each task's process, MB.")] = 2048.0,
    max_output: Annotated[float, typer.Option(help="Output limit of each task's process, MB.")] = 10.0,
    jobs: Annotated[int, typer.Option(help="Tasks run at a time on this machine (each in its own process).")] = 1,
    ray: Annotated[str | None, typer.Option("--ray", help="Run the tasks on a Ray cluster: its address (auto, "
                                            "ray://HOST:10001) or local; needs qcarlab\\[ray] installed.",
                                            show_default=False)] = None,
    ray_token_file: Annotated[Path | None, typer.Option(
        "--ray-token-file", help="With --ray: a file holding the cluster's token, for Ray's token authentication "
        "(ray start --head turns it on; the head's ~/.ray/auth_token, or what ray get-auth-token prints). "
        "RAY_AUTH_TOKEN or RAY_AUTH_TOKEN_PATH in the environment work too.", show_default=False)] = None,
    out: Annotated[Path | None, typer.Option("--out", help="Write grade.json (and each task's results and "
                                             "figures) here; with --class default: grades/.",
                                             show_default=False)] = None,
    junit: Annotated[Path | None, typer.Option(help="Write a JUnit XML report here (one testcase per "
                                               "criterion) for CI.", show_default=False)] = None,
    figures: Annotated[bool | None, typer.Option("--figures/--no-figures", help="Keep each run's figures "
                                                 "(default: with --out or --class).", show_default=False)] = None,
    sandbox: Annotated[str, typer.Option(help="The student's code runs in a process of its own; sandboxed "
                                         "(Linux namespaces, another user, a cgroup) when this machine can. "
                                         "required: refuse to grade without the sandbox (for CI); auto: "
                                         "grade anyway and mark those grades 'not sandboxed'; off: never.")]
    = "auto",
    json_out: JsonOpt = False,
    debug: DebugOpt = False,
) -> None:
    """Grade a submission against lab sheets: block tasks call the student's blocks on given inputs,
    scenario tasks run the lab with the student's blocks and params.yaml. Every task runs in its
    own process with a time, memory and output limit. Exit 0 when every task passes, 1 when one
    fails, 2 for bad input.

    Examples:
      qcarlab grade stop-sign --submission mylab
      qcarlab grade stop-sign --submission . --junit report.xml
      qcarlab grade path-following --class submissions/ --jobs 4 --out grades/
      qcarlab grade private/stop-sign-extra.yaml --class submissions/ --ray auto
    """
    limits = Limits(timeout, memory, max_output).check()
    if sandbox not in ("required", "auto", "off"):
        raise InputError(f"--sandbox must be required, auto or off, got {sandbox!r}")
    if jobs < 1 or jobs > 256:
        raise InputError(f"--jobs must be 1..256, got {jobs}")
    if submission is not None and class_dir is not None:
        raise InputError("give --submission DIR (one student) or --class DIR (a class), not both")
    if results is not None and class_dir is not None:
        raise InputError("--results grades one student's saved runs; it does not go with --class")
    if results is not None and not results.is_dir():
        raise InputError(f"--results {results}: not a folder")
    if submission is not None and not submission.is_dir():
        raise InputError(f"--submission {submission}: not a folder")
    for option, path in (("--out", out), ("--junit", junit)):
        if path is not None and path.exists() and (path.is_dir() if option == "--junit" else not path.is_dir()):
            raise InputError(f"{option} {path}: exists and is {'a folder' if option == '--junit' else 'not a folder'}")
    if ray_token_file is not None and ray is None:
        raise InputError("--ray-token-file is the token of a Ray cluster: it goes with --ray ADDRESS")
    if car is not None:
        from qcarlab.car import parse_car_uri

        if not car.startswith(("tcp://", "tcps://")):
            raise InputError(f"--car {car!r}: expected tcp://HOST:PORT (the simulator is the default)")
        parse_car_uri(car)  # a malformed address: one line now, not a failure in every task
    loaded = [load_sheet(find_sheet(s)) for s in sheets]
    names = [s.name for s in loaded]
    if len(set(names)) != len(names):
        raise InputError(f"sheet {next(n for n in names if names.count(n) > 1)!r} is given twice")
    chosen = select_tasks(loaded, task)
    commands = CliCommands()
    _check_sheet_commands(loaded, commands)
    if class_dir is not None:
        students: list[tuple[str, Path | None]] = list(class_folders(class_dir))
        out = out or Path("grades")
        if out.exists() and not out.is_dir():
            raise InputError(f"--out {out}: exists and is not a folder")
    elif submission is not None:
        students = [(submission.resolve().name, submission.resolve())]
    else:
        students = [("qcarlab", None)]
    keep = figures if figures is not None else (out is not None)
    sandboxed = _sandbox_state(sandbox, ray is not None, submission is not None or class_dir is not None,
                               json_out)
    opts = Options(limits, car, keep, results, sandbox)
    plan = make_plan(loaded, chosen, students, opts, commands)
    to_run = [p.job for p in plan if p.job is not None]
    advance, stop = _progress(len(to_run), not json_out and sys.stderr.isatty())
    try:
        if ray is not None:
            from qcarlab.grading.schedule import run_ray

            outcomes = run_ray(to_run, ray, advance, ray_token_file)
        else:
            from qcarlab.grading.schedule import run_local

            outcomes = run_local(to_run, jobs, advance)
    finally:
        stop()
    by_key = {job.key: o for job, o in zip(to_run, outcomes)}
    rows_by_student: dict[str, list[dict[str, Any]]] = {name: [] for name, _ in students}
    subs: dict[str, Any] = {}
    for p in plan:
        outcome = by_key.get(p.key)
        row = grade(p, outcome, commands, results)
        if outcome is not None and outcome.get("results") is not None and p.task.kind == "scenario":
            row["_results"] = outcome["results"]
        rows_by_student[p.student].append(row)
        if p.submission is not None:
            subs.setdefault(p.student, []).append(p.submission)
    report_students = []
    for name, root in students:
        rows = rows_by_student[name]
        entry: dict[str, Any] = {"student": name, "submission": str(root) if root is not None else None}
        problems = sorted({x for s in subs.get(name, []) for x in s.problems})
        if problems:
            entry["submission_problems"] = problems
        entry.update(summary(rows))
        entry["sandboxed"] = not any(r.get("sandbox") for r in rows)
        entry["tasks"] = rows
        report_students.append(entry)
    from qcarlab.grading.report import figure_href, report_dict, write_gradebook, write_html, write_junit

    single = class_dir is None
    report = report_dict(loaded, report_students, single)
    report["sandbox"] = sandboxed
    written = []
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        for st in report_students:
            for r in st["tasks"]:
                parts = (r["sheet"], r["id"]) if single else (st["student"], r["sheet"], r["id"])
                _write_artifacts(out, parts, r)
        written.append(write_json(out / "grade.json", report))
        if not single:
            written.append(write_gradebook(out / "gradebook.csv", report_students))
            answers: dict[str, list[tuple[str, str]]] = {}
            for st in report_students:
                seen = set()
                for s in subs.get(st["student"], []):
                    if s.answers and s.folder not in seen:
                        seen.add(s.folder)
                        answers.setdefault(st["student"], []).append((s.folder.name, s.answers))
            figs = {(st["student"], r["sheet"], r["id"]): r.get("_figures") or {}
                    for st in report_students for r in st["tasks"]}
            title = "qcarlab grade: " + ", ".join(f"{s.section} {s.title}" for s in loaded)
            names = [f"{s.section} {s.title} ({s.name})" for s in loaded]
            written.append(write_html(out / "report.html", title, report_students, figs, answers, sheets=names,
                                      href=figure_href))
    if junit is not None:
        written.append(write_junit(junit, report_students, single))
    if json_out:
        sys.stdout.write(dumps(report) + "\n")
    else:
        _print(loaded, report_students, single)
        if written:
            stdout.print("wrote " + ", ".join(str(w) for w in written), markup=False)
    errors = sum(st["errors"] for st in report_students)
    if errors:
        stderr.print(f"grade: {errors} task(s) not graded: the grader failed to run them (not the student's "
                     "fault; see each task's problem); run again", markup=False)
    if errors or any(st["passed"] != st["total"] for st in report_students):
        raise typer.Exit(1)


def _sandbox_state(mode: str, on_ray: bool, student_code: bool, quiet: bool) -> dict[str, Any]:
    """Whether the student's code will be sandboxed here (with --ray each worker decides and
    the report marks each task); ``--sandbox required`` without it is refused (exit 2)."""
    from qcarlab.sandbox.jail import unavailable

    why = None if on_ray and mode != "off" else unavailable(mode)
    if why is not None and mode == "required":
        raise InputError(f"--sandbox required: {why}")
    if why is not None and student_code and not quiet:
        stderr.print(f"grade: the students' code is not sandboxed: {why}; the report marks these grades "
                     "'not sandboxed'", markup=False)
    return {"mode": mode, "sandboxed": why is None, "why": why}


def _table(title: str, columns: tuple[str, ...], rows: list[tuple[str, ...]], keep: int = 0) -> Table:
    """A table that wraps its cells at the terminal's width instead of cutting them ("…"): words
    break at spaces, a word wider than its column folds onto the next line. The first ``keep``
    columns are as wide as their widest cell when that fits a quarter of the width (task ids, names).
    Cells are plain text: a criterion's ``[any, -0.5]`` is no markup."""
    table = Table(title=Text(title), title_justify="left")
    quarter = max(8, stdout.width // 4)
    for i, col in enumerate(columns):
        widest = max((len(line) for r in rows for line in str(r[i]).splitlines()), default=0)
        fit = max(len(col), widest)
        table.add_column(col, overflow="fold", width=min(fit, quarter) if i < keep else None)
    for r in rows:
        table.add_row(*(Text(str(cell)) for cell in r))
    return table


def _print(sheets: list[Sheet], students: list[dict[str, Any]], single: bool) -> None:
    title = ", ".join(s.title for s in sheets)
    if single:
        st = students[0]
        rows = []
        for r in st["tasks"]:
            label = r["id"] if len(sheets) == 1 else f"{r['sheet']}/{r['id']}"
            if r["status"] == "skipped":
                rows.append((label, "-", "-", f"skipped: {r['problem']}", "-"))
                continue
            if r["problem"]:
                rows.append((label, "-", "-", f"FAIL: {r['problem']}", f"0/{r['points']:g}"))
                if all(c["reason"] == r["problem"] for c in r["criteria"]):
                    continue
            for c in r["criteria"]:
                verdict = "pass" if c["passed"] else f"FAIL: {c['reason']}"
                rows.append((label, c["criterion"], _shown(c), verdict, f"{c['earned']:g}/{c['points']:g}"))
        stdout.print(_table(f"{title}: {st['passed']} of {st['total']} tasks passed, {st['points']:g} of "
                            f"{st['max_points']:g} points" + (f" ({st['skipped']} skipped)" if st["skipped"] else ""),
                            ("task", "criterion", "value", "result", "points"), rows, keep=1))
        for r in st["tasks"]:
            if r.get("run_failure"):
                stdout.print(f"{r['id']}: the run failed: {r['run_failure']}", markup=False, highlight=False)
        for r in st["tasks"]:
            if r.get("detail") and r["status"] == "failed":
                stdout.print(f"[b]{r['id']}[/b]:", r["detail"].strip()[-800:], markup=True, highlight=False)
        return
    rows = []
    for st in students:
        first = next((f"{r['id']}: {r['problem'] or next((c['reason'] for c in r['criteria'] if not c['passed']), '')}"
                      for r in st["tasks"] if r["status"] == "failed"), "")
        rows.append((st["student"], f"{st['passed']}/{st['total']}", f"{st['points']:g}/{st['max_points']:g}",
                     first if len(first) <= 80 else first[:77] + "..."))
    stdout.print(_table(f"{title}: {len(students)} students", ("student", "tasks passed", "points", "first failure"),
                        rows, keep=1))


@app.command("labs")
def labs_cmd(
    sheet: Annotated[list[str] | None, typer.Argument(
        help="Show this sheet's tasks (a name, a section or a YAML); or: check [SHEET ...] to self-check sheets "
             "(all the shipped ones by default).", show_default=False)] = None,
    jobs: Annotated[int, typer.Option(help="With check: tasks graded at a time.")] = 1,
    json_out: JsonOpt = False,
    debug: DebugOpt = False,
) -> None:
    """List the lab sheets qcarlab grade knows (installed with qcarlab), or one sheet's tasks; with
    check, self-check sheets: the untouched template (qcarlab template) must earn 0 points and
    qcarlab's reference blocks every point, so every point depends on the student. Exit 1 when a
    sheet fails its check.

    Examples:
      qcarlab labs
      qcarlab labs stop-sign
      qcarlab labs 6.1 --json
      qcarlab labs check stop-sign
      qcarlab labs check my-sheet.yaml --jobs 2
    """
    if sheet and sheet[0] == "check":
        _labs_check(sheet[1:], jobs, json_out)
        return
    if sheet and len(sheet) > 1:
        raise InputError(f"give one sheet to show (or: qcarlab labs check {' '.join(sheet)}), got {len(sheet)}")
    sheet = sheet[0] if sheet else None
    if sheet is None:
        rows = []
        for path in shipped_sheets():
            s = load_sheet(path)
            rows.append({"name": s.name, "section": s.section, "title": s.title, "lab": s.lab,
                         "tasks": len(s.tasks), "points": s.points, "path": str(path)})
        if json_out:
            sys.stdout.write(dumps({"sheets": rows}) + "\n")
            return
        stdout.print(_table("Lab sheets (qcarlab grade NAME; qcarlab labs NAME for the tasks)",
                            ("name", "section", "title", "blocks of", "tasks", "points"),
                            [(r["name"], r["section"], r["title"], r["lab"] or "-", str(r["tasks"]), f"{r['points']:g}")
                             for r in rows], keep=1))
        if rows:
            stdout.print(f"from {Path(rows[0]['path']).parent}", markup=False)
        return
    s = load_sheet(find_sheet(sheet))
    tasks = [{"id": t.id, "kind": t.kind, "command": t.command, "block": t.block, "uses": list(t.uses) + list(t.params),
              "needs_car": t.needs_car, "points": t.points, "text": t.text,
              "criteria": [{"criterion": c.describe(), "points": c.points} for c in t.criteria]} for t in s.tasks]
    if json_out:
        sys.stdout.write(dumps({"name": s.name, "section": s.section, "title": s.title, "lab": s.lab,
                                "path": str(s.path), "points": s.points, "tasks": tasks}) + "\n")
        return
    rows = []
    for t in tasks:
        runs = t["command"] if t["kind"] == "scenario" else f"your {t['block']} on {len(t['criteria'])} inputs"
        if t["uses"]:
            runs += f"  (with your {', '.join(t['uses'])})"
        rows.append((t["id"], runs, "\n".join(c["criterion"] for c in t["criteria"]), f"{t['points']:g}"))
    stdout.print(_table(f"{s.section} {s.title} ({s.path}): {len(tasks)} tasks, {s.points:g} points",
                        ("task", "runs", "criteria", "points"), rows, keep=1))


def _labs_check(names: list[str], jobs: int, json_out: bool) -> None:
    """``qcarlab labs check``: each sheet read, then graded as the untouched template and as the reference."""
    from qcarlab.grading.selfcheck import check_sheet

    if not 1 <= jobs <= 256:
        raise InputError(f"--jobs must be 1..256, got {jobs}")
    sheets = [load_sheet(find_sheet(n)) for n in names] if names else [load_sheet(p) for p in shipped_sheets()]
    commands = CliCommands()
    _check_sheet_commands(sheets, commands)
    outcomes = []
    for s in sheets:
        if not json_out:
            stderr.print(f"labs check: {s.name}: grading the untouched template and the reference ...", markup=False)
        outcomes.append(check_sheet(s, commands, jobs))
    if json_out:
        sys.stdout.write(dumps({"sheets": [{"sheet": o.sheet, "ok": o.ok, "problems": o.problems,
                                            "template": o.template, "template_points": o.template_points,
                                            "reference": o.reference, "reference_missed": o.reference_missed}
                                           for o in outcomes]}) + "\n")
    else:
        def pts(d: dict[str, Any]) -> str:
            return f"{d['points']:g} of {d['max_points']:g}" if d else "-"

        stdout.print(_table("Lab sheets' self-check: the untouched template earns 0, the reference every point",
                            ("sheet", "template", "reference", "check"),
                            [(o.sheet, pts(o.template), pts(o.reference), "ok" if o.ok else "FAIL") for o in outcomes],
                            keep=1))
        for o in outcomes:
            for line in o.problems:
                stdout.print(f"{o.sheet}: {line}", markup=False)
            for line in o.template_points:
                stdout.print(f"{o.sheet}: the untouched template earns {line}", markup=False)
            for line in o.reference_missed:
                stdout.print(f"{o.sheet}: the reference misses {line}", markup=False)
    if not all(o.ok for o in outcomes):
        raise typer.Exit(1)
