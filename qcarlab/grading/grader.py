"""Grading: a sheet's tasks for each student planned as jobs, run, and their outcomes graded.

    plan = make_plan(sheets, tasks, students, options, commands)   # what each task runs, or why not
    outcomes = run_jobs([p.job for p in plan if p.job], jobs=2)    # qcarlab.grading.schedule
    grades = [grade(p, outcome) for ...]                           # verdicts, points, reasons

The grader process reads the submissions (without running them: :mod:`.submission`), builds one
:class:`~qcarlab.grading.runner.Job` per task and grades what comes back; the student's code only
ever runs inside a job's own process. ``commands`` is the CLI's parser (``parse(argv)`` and
``accepts(argv, option)``), passed in so this package does not import the CLI.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from qcarlab.grading.checks import Verdict, check_case, check_metrics, fail_all
from qcarlab.grading.invocation import verify
from qcarlab.grading.limits import Limits
from qcarlab.grading.runner import Job
from qcarlab.grading.sheet import CaseCriterion, Sheet, Task
from qcarlab.grading.submission import Submission, read_submission


class Commands(Protocol):
    def parse(self, argv: list[str]) -> tuple[str, dict[str, Any], dict[str, str]]: ...

    def accepts(self, argv: list[str], option: str) -> bool: ...


@dataclass
class Options:
    limits: Limits = field(default_factory=Limits)
    car: str | None = None  # tcp://HOST:PORT: run the commands on this car
    figures: bool = False  # keep each run's figures (for --out / the class report)
    results: Path | None = None  # grade saved runs of the scenario tasks: DIR/TASK-ID/results.json
    sandbox: str = "auto"  # the student's process: "required", "auto" or "off" (qcarlab.sandbox)


@dataclass
class Planned:
    """One (student, task): the job to run, or the reason there is none."""

    student: str
    sheet: Sheet
    task: Task
    submission: Submission | None
    job: Job | None = None
    problem: str | None = None  # the task fails without running (a block missing or not filled in)
    skipped: str | None = None  # the task is not graded here (it needs a real car)
    command: str = ""  # the command as the job runs it, for the report

    @property
    def key(self) -> tuple[str, str, str]:
        return (self.student, self.sheet.name, self.task.id)


def _plan_one(student: str, sheet: Sheet, task: Task, sub: Submission | None, opts: Options,
              commands: Commands) -> Planned:
    from qcarlab import __version__

    p = Planned(student, sheet, task, sub)
    if task.needs_car and opts.car is None and opts.results is None:
        p.skipped = "needs a car: grade with --car tcp://HOST:PORT"
        return p
    if sub is not None:
        for name in task.student_blocks:
            why = sub.borrowed(name) or sub.block_problem(name)
            if why:
                p.problem = why
                return p
        for name in task.params:
            why = sub.param_problem(name)
            if why:
                p.problem = why
                return p
    if opts.results is not None and task.kind == "scenario":  # graded from the saved run
        return p
    limits = opts.limits.as_dict()
    if task.kind == "block":
        if sub is None:
            p.skipped = "a block task grades a student's block: give --submission DIR"
            return p
        p.job = Job(p.key, "block", limits, lab=sheet.lab, block=task.block, file=sub.defined()[task.block],
                    cases=[{"args": list(c.args), "calls": [list(a) for a in c.calls]} for c in task.criteria
                           if isinstance(c, CaseCriterion)],
                    files=dict(sub.files), qcarlab=__version__, sandbox=opts.sandbox)
        p.command = f"{task.block}(...) from {p.job.file}"
        return p
    argv = task.argv(opts.car)
    if opts.car is not None and not task.needs_car and commands.accepts(argv, "car") and "--car" not in argv:
        argv += ["--car", opts.car]
    shown = list(argv)
    params = None
    if sub is not None and sheet.lab is not None:
        if commands.accepts(argv, "block"):  # the student's blocks the task grades; the rest are qcarlab's
            defined = sub.defined()
            for name in task.uses:
                argv += ["--block", f"{name}=submission/{defined[name]}:{name}"]
                shown += ["--block", f"{name}={defined[name]}:{name}"]
        if "params.yaml" in sub.files and commands.accepts(argv, "params"):
            params = "params.yaml"
            shown += ["--params", "params.yaml"]
    json_words = ["--json"] if not commands.accepts(argv, "out") and commands.accepts(argv, "json_out") else []
    argv += json_words
    p.job = Job(p.key, "scenario", limits, argv=argv, params=params, files=dict(sub.files) if sub else {},
                figures=opts.figures and commands.accepts(argv, "out"), qcarlab=__version__, sandbox=opts.sandbox)
    p.command = "qcarlab " + " ".join(shown)
    return p


def _folder_names(sheet: Sheet) -> list[str | None]:
    names: list[str | None] = [sheet.name, sheet.extends]
    if sheet.lab is not None:
        from qcarlab.experiments.labs import find_lab

        lab = find_lab(sheet.lab)
        names += [lab.sheet, lab.command]
    return names


def make_plan(sheets: list[Sheet], tasks: list[Task], students: list[tuple[str, Path | None]], opts: Options,
              commands: Commands) -> list[Planned]:
    """Every (student, task) in order: students in the given order, then the sheets' tasks."""
    plan = []
    for name, root in students:
        subs = {s.name: (read_submission(root, _folder_names(s), name) if root is not None else None)
                for s in sheets}
        for sheet in sheets:
            for task in tasks:
                if task in sheet.tasks:
                    plan.append(_plan_one(name, sheet, task, subs[sheet.name], opts, commands))
    return plan


# --------------------------------------------------------------------------------------------
# grading an outcome
# --------------------------------------------------------------------------------------------
def _saved(task: Task, folder: Path) -> tuple[dict | None, str]:
    """DIR/TASK-ID/results.json (what --out DIR/TASK-ID writes) or DIR/TASK-ID.json."""
    from qcarlab.record import IN_PROGRESS

    if (folder / task.id / IN_PROGRESS).exists():
        return None, (f"{folder / task.id}: a run started there after these results and did not save its own "
                      f"({IN_PROGRESS}): run the task again")
    for path in (folder / task.id / "results.json", folder / f"{task.id}.json"):
        if path.exists():
            try:
                data = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
                return None, f"{path}: unreadable ({exc})"
            return (data, "") if isinstance(data, dict) else (None, f"{path}: not a results object")
    return None, f"not run: no {task.id}/results.json in {folder}"


def _used(task: Task, results: dict) -> str | None:
    """Why the run did not grade the student's blocks the task names (None when it did)."""
    mine = results.get("student_blocks")
    if mine is None and isinstance(results.get("best"), dict):  # a sweep: its best run's blocks
        mine = results["best"].get("student_blocks")
    if mine is None:  # an aggregate without the runs' block reports (trials): what the command line gave
        params = (results.get("invocation") or {}).get("params") or {}
        given = {str(b).split("=", 1)[0].strip() for b in params.get("block") or []}
        for name in task.uses:
            if name not in given and not params.get("use"):
                return f"the run did not use your {name}"
        return None
    for name in task.uses:
        timing = mine.get(name)
        if not isinstance(timing, dict):
            return f"the run did not use your {name}"
        if not timing.get("calls"):
            return f"your {name} was never called in the run"
    return None


def _run_failure(data: dict) -> str | None:
    """The run's own sentence for why it failed (a collision, "did not stop before the sign"); a
    sweep's is its best run's."""
    best = data.get("best")
    failure = data.get("failure") or (best.get("failure") if isinstance(best, dict) else None)
    return str(failure) if failure else None


def _grade_saved(p: Planned, commands: Commands, folder: Path,
                 row: dict[str, Any]) -> tuple[str | None, list[Verdict] | None]:
    data, why = _saved(p.task, folder)
    if data is None:
        return why, None
    name, want, labels = commands.parse(p.task.argv())
    problem = verify(data, name, want, p.submission.files if p.submission else None, labels)
    problem = problem or (_used(p.task, data) if p.submission is not None else None)
    if problem:
        return problem, None
    if _run_failure(data):
        row["run_failure"] = _run_failure(data)
    return None, check_metrics(data, p.task.criteria)  # type: ignore[arg-type]


def _grade_results(p: Planned, outcome: dict[str, Any], commands: Commands,
                   row: dict[str, Any]) -> tuple[str | None, list[Verdict] | None]:
    if outcome.get("reason"):
        return outcome["reason"], None
    data = outcome.get("results") or {}
    name, want, labels = commands.parse(p.task.argv())
    problem = verify(data, name, want, None, labels)  # results without their invocation record are refused
    problem = problem or (_used(p.task, data) if p.submission is not None else None)
    if problem:
        return problem, None
    if _run_failure(data):
        row["run_failure"] = _run_failure(data)
    return None, check_metrics(data, p.task.criteria)  # type: ignore[arg-type]


def _grade_cases(task: Task, outcome: dict[str, Any], row: dict[str, Any]) -> tuple[str | None, list[Verdict]]:
    """Each case's verdict; the cases a dead or stopped process never reached fail with its reason."""
    cases = outcome.get("cases") or []
    problem = outcome.get("reason")
    if cases and "load_error" in cases[0]:
        row["detail"] = cases[0].get("detail")
        return cases[0]["load_error"], fail_all(task.criteria, cases[0]["load_error"])
    verdicts = [check_case(cases[i] if i < len(cases) else {"error": problem or "not run"}, c)
                for i, c in enumerate(task.criteria)]  # type: ignore[arg-type]
    details = [c["detail"] for c in cases if c.get("detail")]
    if details:
        row["detail"] = details[0]
    return problem, verdicts


def grade(p: Planned, outcome: dict[str, Any] | None, commands: Commands,
          results_dir: Path | None = None) -> dict[str, Any]:
    """The graded task: status, verdicts, points; ``outcome`` is what :func:`runner.execute` returned
    (None when there was no job); with ``results_dir`` the saved runs there are graded instead."""
    task = p.task
    row: dict[str, Any] = {"sheet": p.sheet.name, "id": task.id, "kind": task.kind,
                           "command": p.command or task.command or None,
                           "uses": list(task.student_blocks) + list(task.params),
                           "status": "failed", "passed": False, "problem": None, "criteria": [],
                           "points": task.points, "earned": 0.0, "seconds": None, "_figures": {}}
    if p.skipped:
        row.update(status="skipped", problem=p.skipped,
                   criteria=[v.as_dict() for v in fail_all(task.criteria, p.skipped)])
        return row
    problem, verdicts = p.problem, None
    if problem is None:
        if results_dir is not None and task.kind == "scenario":
            problem, verdicts = _grade_saved(p, commands, results_dir, row)
        elif outcome is None:
            problem = "not run"
        elif outcome.get("status") == "infrastructure":  # the grader's failure: not graded, never 0 points
            row.update(status="error", problem=outcome.get("reason"), seconds=outcome.get("seconds"),
                       criteria=[v.as_dict() for v in fail_all(task.criteria, str(outcome.get("reason")))])
            return row
        else:
            row["seconds"] = outcome.get("seconds")
            row["_figures"] = outcome.get("figures") or {}
            if "sandboxed" in outcome and not outcome["sandboxed"] and p.task.student_blocks:
                row["sandbox"] = outcome.get("sandbox") or "not sandboxed"
            printed = "".join(f"{outcome.get(k) or ''}" for k in ("student_stdout", "student_stderr")).strip()
            if printed:
                row["student_output"] = printed[-2000:]
            if task.kind == "block":
                problem, verdicts = _grade_cases(task, outcome, row)
            else:
                problem, verdicts = _grade_results(p, outcome, commands, row)
            if problem and outcome.get("stderr") and not row.get("detail"):
                row["detail"] = outcome["stderr"][-2000:]
    if verdicts is None:
        verdicts = fail_all(task.criteria, problem or "not run")
    row["criteria"] = [v.as_dict() for v in verdicts]
    row["problem"] = problem
    row["earned"] = float(sum(v.earned for v in verdicts))
    row["passed"] = problem is None and all(v.passed for v in verdicts)
    row["status"] = "passed" if row["passed"] else "failed"
    return row


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Passed and total over the graded tasks: not the skipped ones, nor those the grader failed
    to run (``errors``: the grader's failure, to run again; they count neither for nor against)."""
    graded = [r for r in rows if r["status"] not in ("skipped", "error")]
    return {"passed": sum(r["passed"] for r in graded), "total": len(graded),
            "skipped": sum(r["status"] == "skipped" for r in rows),
            "errors": sum(r["status"] == "error" for r in rows),
            "points": round(sum(r["earned"] for r in graded), 6),
            "max_points": round(sum(r["points"] for r in graded), 6)}


__all__ = ["Commands", "Options", "Planned", "grade", "make_plan", "summary"]

