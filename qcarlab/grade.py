"""Grading runs against a lab sheet's criteria (the YAML sheets in ``labs/``).

A sheet lists tasks; each task has a ``command`` and ``criteria`` on the metrics of that
command's results (``--json`` / ``results.json``)::

    criteria:
      rms_cross_track_m: {max: 0.02}      # passes when the metric is <= 0.02
      best.completion: {min: 0.99}        # dotted names reach into nested results

:func:`check` is pure: results in, verdicts out. :func:`load_sheet` reads and validates a sheet,
naming the file and the field on any error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from qcarlab.errors import InputError
from qcarlab.yamlio import load_yaml

LABS_DIR = Path(__file__).resolve().parents[1] / "labs"  # the checkout's lab sheets


@dataclass
class Criterion:
    metric: str
    min: float | None = None
    max: float | None = None

    def describe(self) -> str:
        if self.min is not None and self.max is not None:
            return f"{self.min:g} <= {self.metric} <= {self.max:g}"
        return f"{self.metric} >= {self.min:g}" if self.min is not None else f"{self.metric} <= {self.max:g}"


@dataclass
class Task:
    id: str
    command: str
    text: str = ""
    criteria: list[Criterion] = field(default_factory=list)


@dataclass
class Verdict:
    criterion: Criterion
    value: Any
    passed: bool
    reason: str = ""


def find_sheet(name: str | Path) -> Path:
    """A sheet by file path, or by name in ./labs or the checkout's labs/ (``path-following``)."""
    path = Path(name)
    if path.suffix in (".yaml", ".yml"):
        if not path.exists():
            raise InputError(f"{path}: no such lab sheet")
        return path
    for folder in (Path.cwd() / "labs", LABS_DIR):
        candidate = folder / f"{name}.yaml"
        if candidate.exists():
            return candidate
    known = sorted(p.stem for p in LABS_DIR.glob("*.yaml")) if LABS_DIR.is_dir() else []
    raise InputError(f"unknown lab sheet '{name}'" + (f" (sheets: {', '.join(known)})" if known else
                                                       " (give the path of a lab sheet YAML)"))


def load_sheet(path: Path) -> tuple[str, list[Task]]:
    """The sheet's title and tasks; malformed sheets name the file and the field."""
    data = load_yaml(path, "lab sheet")
    if not isinstance(data, dict) or not isinstance(data.get("tasks"), list) or not data["tasks"]:
        raise InputError(f"{path}: expected a mapping with a non-empty 'tasks' list")
    tasks = []
    for i, item in enumerate(data["tasks"]):
        where = f"{path}: tasks[{i}]"
        if not isinstance(item, dict) or not isinstance(item.get("id"), str):
            raise InputError(f"{where}: expected a mapping with an 'id'")
        if not isinstance(item.get("command"), str) or not item["command"].startswith("qcarlab "):
            raise InputError(f"{where}.command: expected a 'qcarlab ...' command line")
        crits = item.get("criteria")
        if not isinstance(crits, dict) or not crits:
            raise InputError(f"{where}.criteria: expected a mapping of metric: {{min: .., max: ..}}")
        criteria = []
        for metric, bound in crits.items():
            if not isinstance(bound, dict) or not bound or set(bound) - {"min", "max"}:
                raise InputError(f"{where}.criteria.{metric}: expected {{min: NUMBER}} and/or {{max: NUMBER}}")
            for key, value in bound.items():
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise InputError(f"{where}.criteria.{metric}.{key}: expected a number, got {value!r}")
            criteria.append(Criterion(str(metric), bound.get("min"), bound.get("max")))
        tasks.append(Task(item["id"], item["command"], str(item.get("text", "")).strip(), criteria))
    return str(data.get("title", path.stem)), tasks


def lookup(results: Any, dotted: str) -> Any:
    """``results["best"]["completion"]`` for ``"best.completion"``; KeyError when absent."""
    value = results
    for part in dotted.split("."):
        if not isinstance(value, dict) or part not in value:
            raise KeyError(dotted)
        value = value[part]
    return value


def check(results: dict, criteria: list[Criterion]) -> list[Verdict]:
    """Each criterion against the results: missing or non-numeric metrics fail with a reason."""
    verdicts = []
    for c in criteria:
        try:
            value = lookup(results, c.metric)
        except KeyError:
            verdicts.append(Verdict(c, None, False, "not in the results"))
            continue
        if isinstance(value, bool):
            value = int(value)
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            verdicts.append(Verdict(c, value, False, "not a number"))
            continue
        ok = (c.min is None or value >= c.min) and (c.max is None or value <= c.max)
        verdicts.append(Verdict(c, value, ok))
    return verdicts
