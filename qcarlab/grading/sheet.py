"""Lab sheets: the tasks of a section, what each runs and the criteria it is graded on.

A sheet is a YAML file (the shipped ones are in ``qcarlab/labs/``, installed with the package)::

    title: Stop sign detection and stopping (RGBD camera)
    section: "5.1-5.2"
    lab: stop-sign              # the lab whose blocks a submission fills in (qcarlab blocks stop-sign)
    tasks:
      - id: stop-sign-block     # a block task: call the student's block on given inputs
        block: stop_sign
        tolerance: 1.0e-6
        cases:
          - {args: [0.30, 0.5], expect: 0.0}
          - {args: [0.02, 0.5], expect: 0.5, points: 2}
      - id: 5.2-task1-stopsign  # a scenario task: run a lab command, check its results
        command: qcarlab stop-sign
        uses: [stop_sign]       # the student's blocks this task grades (must be in the submission)
        points: 3               # split over the criteria that give none of their own
        criteria:
          stopped: {min: 1}
          stop_distance_m: {min: 0.05, max: 0.40}

Criteria of scenario tasks name a metric of the command's results (``best.completion`` reaches
into nested objects, ``rgbd.color_size.0`` into lists) with ``min`` and/or ``max``. A case of a
block task has ``args`` (a ``{scan: ...}`` argument expands into ``distances, headings``, see
:func:`qcarlab.grading.checks.make_scan`) or, for a stateful block, ``calls`` (one instance,
the last output checked), and ``expect`` (a number or a list, ``null`` = any) within
``tol``/``tolerance``, or ``min``/``max``. A task whose ``command`` contains ``{car}`` needs a
real car (``qcarlab grade --car tcp://...``) and is skipped without one.

An instructor keeps extra tasks (other start distances, speeds, seeds) in a sheet of their own
that ``extends`` a shipped one; the students never see it::

    extends: stop-sign
    tasks:
      - {id: hidden-start-1.4, command: "qcarlab stop-sign --start 0,-1.0,-1.5708", uses: [stop_sign], ...}

:func:`load_sheet` checks everything and names the file and the field on any error.
"""

from __future__ import annotations

import math
import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from qcarlab.errors import InputError
from qcarlab.yamlio import load_yaml

LABS_DIR = Path(__file__).resolve().parents[1] / "labs"  # the shipped sheets (package data)
CAR = "{car}"  # the placeholder of a task that needs a real car


# --------------------------------------------------------------------------------------------
# criteria
# --------------------------------------------------------------------------------------------
def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join("any" if v is None else _fmt(v) for v in value) + "]"
    return str(value)


@dataclass(frozen=True)
class MetricCriterion:
    """A bound on one metric of a scenario's results: ``min <= value <= max``."""

    metric: str
    min: float | None = None
    max: float | None = None
    points: float = 1.0

    @property
    def key(self) -> str:
        return self.metric

    def describe(self) -> str:
        if self.min is not None and self.max is not None:
            return f"{_fmt(self.min)} <= {self.metric} <= {_fmt(self.max)}"
        return f"{self.metric} >= {_fmt(self.min)}" if self.min is not None else f"{self.metric} <= {_fmt(self.max)}"


@dataclass(frozen=True)
class CaseCriterion:
    """One call (or sequence of calls) of a student's block and what it must return."""

    name: str
    args: tuple = ()  # the call's arguments as written in the sheet ({scan: ...} not expanded)
    calls: tuple = ()  # a stateful block: several argument lists on one instance
    expect: Any = None  # a number or a list (None entries: any value)
    tol: float = 1e-6
    min: Any = None
    max: Any = None
    points: float = 1.0

    @property
    def key(self) -> str:
        return self.name

    def describe(self) -> str:
        parts = []
        if self.expect is not None:
            parts.append(f"== {_fmt(self.expect)} +- {self.tol:g}")
        if self.min is not None:
            parts.append(f">= {_fmt(self.min)}")
        if self.max is not None:
            parts.append(f"<= {_fmt(self.max)}")
        return f"{self.name} " + " and ".join(parts)


Criterion = MetricCriterion | CaseCriterion


@dataclass
class Task:
    """One task of a sheet: a scenario (``command``) or a block test (``block``)."""

    id: str
    text: str = ""
    command: str | None = None  # "qcarlab stop-sign --speed 0.5"
    block: str | None = None  # "stop_sign"
    uses: tuple[str, ...] = ()  # the student's blocks the task grades
    params: tuple[str, ...] = ()  # the student's choices (params.yaml's lab: tunables) the task grades
    criteria: list[Criterion] = field(default_factory=list)
    sheet: str = ""  # the sheet's name, for reports

    @property
    def kind(self) -> str:
        return "block" if self.block is not None else "scenario"

    @property
    def needs_car(self) -> bool:
        return self.command is not None and CAR in self.command

    @property
    def points(self) -> float:
        return float(sum(c.points for c in self.criteria))

    @property
    def student_blocks(self) -> tuple[str, ...]:
        """Every block of the student's this task needs."""
        return (self.block,) if self.block else self.uses

    def argv(self, car: str | None = None) -> list[str]:
        """The command's words after ``qcarlab`` (``{car}`` replaced by ``car``); no --json / --out."""
        assert self.command is not None
        words = shlex.split(self.command)[1:]
        if car is not None:
            words = [w.replace(CAR, car) for w in words]
        drop = {"--json"}
        return [w for w in words if w not in drop]


@dataclass
class Sheet:
    """A lab sheet: its tasks in order; ``lab`` is the lab command whose blocks it grades."""

    name: str
    path: Path
    title: str
    section: str
    lab: str | None
    tasks: list[Task]
    extends: str | None = None
    text: str = ""

    @property
    def points(self) -> float:
        return float(sum(t.points for t in self.tasks))


# --------------------------------------------------------------------------------------------
# finding sheets
# --------------------------------------------------------------------------------------------
def shipped_sheets() -> list[Path]:
    """The sheets installed with qcarlab, by name."""
    return sorted(LABS_DIR.glob("*.yaml")) if LABS_DIR.is_dir() else []


def find_sheet(name: str | Path) -> Path:
    """A sheet by path (``my/sheet.yaml``), or by name in ./labs or the shipped ones (``path-following``)."""
    path = Path(name)
    if path.suffix in (".yaml", ".yml"):
        if not path.is_file():
            raise InputError(f"{path}: no such lab sheet")
        return path
    text = str(name)
    if not text or "/" in text or "\\" in text:
        raise InputError(f"unknown lab sheet {text!r} (give a sheet's name or the path of a sheet YAML)")
    for folder in (Path.cwd() / "labs", LABS_DIR):
        candidate = folder / f"{text}.yaml"
        if candidate.is_file():
            return candidate
    by_section = [p for p in shipped_sheets() if _section_of(p) == text]
    if len(by_section) == 1:
        return by_section[0]
    aliased = _by_command(text)
    if aliased is not None:
        return aliased
    known = [p.stem for p in shipped_sheets()]
    raise InputError(f"unknown lab sheet '{text}'" + (f" (sheets: {', '.join(known)}; qcarlab labs lists them)"
                                                      if known else " (give the path of a lab sheet YAML)"))


def _by_command(text: str) -> Path | None:
    """The shipped sheet a command or a lab's other name stands for (``avoid``, ``io-test``,
    ``5.1``: the lab's sheet; ``ping``, ``lidar-scan``: the one sheet whose tasks run it)."""
    from qcarlab.experiments.labs import find_lab

    try:
        lab = find_lab(text)
    except InputError:
        lab = None
    if lab is not None and (LABS_DIR / f"{lab.sheet}.yaml").is_file():
        return LABS_DIR / f"{lab.sheet}.yaml"
    running = []
    for path in shipped_sheets():
        try:
            data = load_yaml(path, "lab sheet")
        except InputError:
            continue
        tasks = data.get("tasks") if isinstance(data, dict) else None
        words = {str(t["command"]).split()[1] for t in tasks or () if isinstance(t, dict)
                 and len(str(t.get("command") or "").split()) > 1}
        if text in words:
            running.append(path)
    if len(running) > 1:
        raise InputError(f"lab sheet '{text}': several sheets run qcarlab {text} "
                         f"({', '.join(p.stem for p in running)}); name one")
    return running[0] if running else None


def _section_of(path: Path) -> str | None:
    try:
        data = load_yaml(path, "lab sheet")
    except InputError:
        return None
    return str(data.get("section")) if isinstance(data, dict) and data.get("section") is not None else None


# --------------------------------------------------------------------------------------------
# reading a sheet
# --------------------------------------------------------------------------------------------
def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{where}: expected a number, got {value!r}")
    return float(value)


def _bound(value: Any, where: str) -> Any:
    """A number, or a list of numbers and nulls (one per element of a tuple output)."""
    if isinstance(value, list):
        if not value:
            raise InputError(f"{where}: expected a number or a list of numbers, got []")
        return tuple(None if v is None else _number(v, f"{where}[{i}]") for i, v in enumerate(value))
    return _number(value, where)


def _points(value: Any, where: str) -> float:
    p = _number(value, where)
    if p < 0:
        raise InputError(f"{where}: points must be >= 0, got {value!r}")
    return p


def _check_args(args: Any, where: str) -> tuple:
    if not isinstance(args, list):
        raise InputError(f"{where}: expected a list of the block's arguments")
    for i, a in enumerate(args):
        if isinstance(a, dict):
            if set(a) != {"scan"} or not isinstance(a["scan"], dict):
                raise InputError(f"{where}[{i}]: the only mapping argument is {{scan: {{obstacles: [[r, bearing]], "
                                 "...}}}")
            from qcarlab.grading.checks import make_scan

            make_scan(a["scan"], f"{where}[{i}].scan")  # checks it
    return tuple(args)


def _case(item: Any, where: str, block: str, tolerance: float, share: float | None) -> CaseCriterion:
    if not isinstance(item, dict):
        raise InputError(f"{where}: expected a mapping with args (or calls) and expect (or min/max)")
    unknown = set(item) - {"name", "args", "calls", "expect", "tol", "min", "max", "points"}
    if unknown:
        raise InputError(f"{where}: unknown field {sorted(unknown)[0]!r} (fields: name, args, calls, expect, tol, "
                         "min, max, points)")
    if ("args" in item) == ("calls" in item):
        raise InputError(f"{where}: give args (one call) or calls (a list of calls on one instance)")
    args, calls = (), ()
    if "args" in item:
        args = _check_args(item["args"], f"{where}.args")
    else:
        if not isinstance(item["calls"], list) or not item["calls"]:
            raise InputError(f"{where}.calls: expected a non-empty list of argument lists")
        calls = tuple(_check_args(c, f"{where}.calls[{i}]") for i, c in enumerate(item["calls"]))
    if not any(k in item for k in ("expect", "min", "max")):
        raise InputError(f"{where}: give expect (with tol) or min and/or max")
    expect = _bound(item["expect"], f"{where}.expect") if "expect" in item else None
    tol = _number(item.get("tol", tolerance), f"{where}.tol")
    if tol < 0:
        raise InputError(f"{where}.tol: must be >= 0")
    lo = _bound(item["min"], f"{where}.min") if "min" in item else None
    hi = _bound(item["max"], f"{where}.max") if "max" in item else None
    points = _points(item["points"], f"{where}.points") if "points" in item else (share if share is not None else 1.0)
    name = item.get("name")
    if name is None:
        shown = args if args else calls[-1]
        name = f"{block}({', '.join(_show_arg(a) for a in shown)})" + (f" after {len(calls)} calls" if calls else "")
    return CaseCriterion(str(name), args, calls, expect, tol, lo, hi, points)


def _show_arg(a: Any) -> str:
    if isinstance(a, dict) and "scan" in a:
        obs = a["scan"].get("obstacles") or []
        return "scan(" + (", ".join(f"{o[0]:g} m at {o[1]:g} rad" for o in obs) or "no returns") + ")"
    if isinstance(a, list):
        return "(" + ", ".join(_show_arg(v) for v in a) + ")"
    return _fmt(a)


def _metric(metric: str, bound: Any, where: str, share: float | None) -> MetricCriterion:
    if not isinstance(bound, dict) or not (set(bound) & {"min", "max"}) or set(bound) - {"min", "max", "points"}:
        raise InputError(f"{where}: expected {{min: NUMBER}} and/or {{max: NUMBER}} (and optional points)")
    lo = _number(bound["min"], f"{where}.min") if "min" in bound else None
    hi = _number(bound["max"], f"{where}.max") if "max" in bound else None
    if lo is not None and hi is not None and lo > hi:
        raise InputError(f"{where}: min {lo:g} is above max {hi:g}")
    points = _points(bound["points"], f"{where}.points") if "points" in bound else (share if share is not None else 1.0)
    return MetricCriterion(str(metric), lo, hi, points)


def _share(item: dict, n: int, given: int, where: str) -> float | None:
    """The points of a criterion without its own: the task's points split evenly."""
    if "points" not in item:
        return None
    total = _points(item["points"], f"{where}.points")
    free = n - given
    return total / free if free else None


def _task(item: Any, where: str, sheet: str, lab_blocks: set[str] | None, lab_params: set[str] = frozenset()) -> Task:
    if not isinstance(item, dict) or not isinstance(item.get("id"), str) or not item["id"].strip():
        raise InputError(f"{where}: expected a mapping with an 'id'")
    unknown = set(item) - {"id", "text", "command", "block", "uses", "criteria", "cases", "points", "tolerance"}
    if unknown:
        raise InputError(f"{where}: unknown field {sorted(unknown)[0]!r}")
    tid = item["id"].strip()
    if any(ch in tid for ch in "/\\") or tid in (".", ".."):
        raise InputError(f"{where}.id: {tid!r} may not contain / or \\")
    text = str(item.get("text", "") or "").strip()
    if ("command" in item) == ("block" in item):
        raise InputError(f"{where}: give a command (a scenario task) or a block (a block task), not both")
    if "command" in item:
        command = item["command"]
        if not isinstance(command, str) or not command.startswith("qcarlab "):
            raise InputError(f"{where}.command: expected a 'qcarlab ...' command line")
        try:
            shlex.split(command)
        except ValueError as exc:
            raise InputError(f"{where}.command: {exc}") from None
        uses = item.get("uses", [])
        if not isinstance(uses, list) or not all(isinstance(u, str) for u in uses):
            raise InputError(f"{where}.uses: expected a list of block names")
        for u in uses:
            if lab_blocks is not None and u not in lab_blocks and u not in lab_params:
                raise InputError(f"{where}.uses: the sheet's lab has no block or tunable {u!r} (its blocks: "
                                 f"{', '.join(sorted(lab_blocks))}; its tunables: {', '.join(sorted(lab_params))})")
        if uses and lab_blocks is None:
            raise InputError(f"{where}.uses: the sheet names no lab (add lab: LAB at the top)")
        if "cases" in item:
            raise InputError(f"{where}.cases: only a block task has cases")
        crits = item.get("criteria")
        if not isinstance(crits, dict) or not crits:
            raise InputError(f"{where}.criteria: expected a mapping of metric: {{min: .., max: ..}}")
        given = sum(1 for b in crits.values() if isinstance(b, dict) and "points" in b)
        share = _share(item, len(crits), given, where)
        criteria: list[Criterion] = [_metric(m, b, f"{where}.criteria.{m}", share) for m, b in crits.items()]
        return Task(tid, text, command=command, uses=tuple(u for u in uses if u not in lab_params),
                    params=tuple(u for u in uses if u in lab_params), criteria=criteria, sheet=sheet)
    block = item["block"]
    if not isinstance(block, str) or not block.isidentifier():
        raise InputError(f"{where}.block: expected a block's name (qcarlab blocks LAB lists them)")
    if lab_blocks is None:
        raise InputError(f"{where}.block: the sheet names no lab (add lab: LAB at the top)")
    if block not in lab_blocks:
        raise InputError(f"{where}.block: the sheet's lab has no block {block!r} (its blocks: "
                         f"{', '.join(sorted(lab_blocks))})")
    if "criteria" in item or "uses" in item:
        raise InputError(f"{where}: a block task has cases, not criteria or uses")
    cases = item.get("cases")
    if not isinstance(cases, list) or not cases:
        raise InputError(f"{where}.cases: expected a list of calls and their expected results")
    tolerance = _number(item.get("tolerance", 1e-6), f"{where}.tolerance")
    given = sum(1 for c in cases if isinstance(c, dict) and "points" in c)
    share = _share(item, len(cases), given, where)
    criteria = [_case(c, f"{where}.cases[{i}]", block, tolerance, share) for i, c in enumerate(cases)]
    names = [c.name for c in criteria]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise InputError(f"{where}.cases: two cases are both {dup!r}; give one of them a name")
    return Task(tid, text, block=block, criteria=criteria, sheet=sheet)


def _lab_names(lab: str, where: str) -> tuple[set[str], set[str]]:
    """The lab's blocks and its tunables (what a task's ``uses`` may name)."""
    from qcarlab.experiments.labs import find_lab

    try:
        found = find_lab(lab)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None
    return {b.name for b in found.blocks}, set(found.tunables)


def load_sheet(path: str | Path, _seen: tuple[Path, ...] = ()) -> Sheet:
    """The sheet at ``path`` (with the tasks of the sheet it ``extends`` first)."""
    path = Path(path)
    if path.resolve() in _seen:
        raise InputError(f"{path}: extends itself (through {', '.join(p.name for p in _seen)})")
    data = load_yaml(path, "lab sheet")
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping with a 'tasks' list")
    unknown = set(data) - {"title", "section", "lab", "tasks", "extends", "parameters", "text"}
    if unknown:
        raise InputError(f"{path}: unknown field {sorted(unknown)[0]!r}")
    base = None
    if data.get("extends") is not None:
        if not isinstance(data["extends"], str):
            raise InputError(f"{path}: extends: expected a sheet's name or path")
        ref = data["extends"]
        try:
            base_path = find_sheet(path.parent / ref if ref.endswith((".yaml", ".yml")) else ref)
        except InputError as exc:
            raise InputError(f"{path}: extends: {exc}") from None
        base = load_sheet(base_path, _seen + (path.resolve(),))
    lab = data.get("lab", base.lab if base else None)
    if lab is not None and not isinstance(lab, str):
        raise InputError(f"{path}: lab: expected a lab's name (io-test, path-follow, stop-sign, lane-follow, avoid)")
    if base is not None and base.lab is not None and lab != base.lab:
        raise InputError(f"{path}: lab: {lab!r} differs from the lab of the sheet it extends ({base.lab!r})")
    lab_blocks, lab_params = _lab_names(lab, f"{path}: lab") if lab is not None else (None, set())
    if lab is not None:
        from qcarlab.experiments.labs import find_lab

        lab = find_lab(lab).command
    items = data.get("tasks")
    if not isinstance(items, list) or (not items and base is None):
        raise InputError(f"{path}: expected a non-empty 'tasks' list")
    name = path.stem
    tasks = list(base.tasks) if base else []
    for i, item in enumerate(items):
        task = _task(item, f"{path}: tasks[{i}]", name, lab_blocks, lab_params)
        if any(t.id == task.id for t in tasks):
            raise InputError(f"{path}: tasks[{i}].id: {task.id!r} is already a task of this sheet"
                             + (f" (or of {base.name})" if base else ""))
        tasks.append(task)
    for t in tasks:  # an extending sheet is graded as one sheet: the base's tasks, then its own
        t.sheet = name
    title = str(data.get("title", base.title if base else path.stem))
    section = str(data.get("section", base.section if base else ""))
    return Sheet(name, path, title, section, lab, tasks, base.name if base else None,
                 str(data.get("text", "") or "").strip())


def select_tasks(sheets: list[Sheet], wanted: list[str] | None) -> list[Task]:
    """The sheets' tasks named by ``--task`` (``ID`` or ``SHEET/ID``; all when none is given);
    a name that is no task of the sheets is refused, listing the tasks."""
    tasks = [t for s in sheets for t in s.tasks]
    if not wanted:
        return tasks
    for w in wanted:
        if not any(w in (t.id, f"{t.sheet}/{t.id}") for t in tasks):
            names = ", ".join(t.id for t in tasks)
            raise InputError(f"--task {w!r} is not in {', '.join(str(s.path) for s in sheets)} (tasks: {names})")
    return [t for t in tasks if t.id in wanted or f"{t.sheet}/{t.id}" in wanted]


__all__ = ["CAR", "CaseCriterion", "Criterion", "LABS_DIR", "MetricCriterion", "Sheet", "Task", "find_sheet",
           "load_sheet", "select_tasks", "shipped_sheets"]
