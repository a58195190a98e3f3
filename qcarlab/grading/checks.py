"""Pure checks: a run's results or a block's outputs in, verdicts out. No I/O, no student code.

A :class:`Verdict` says what was expected, what came, whether it passed, why not, and the
points it earned::

    check_metrics({"rms_cross_track_m": 0.01}, [MetricCriterion("rms_cross_track_m", max=0.02)])
    check_case({"value": 0.5}, CaseCriterion("stop_sign(0.3, 0.5)", (0.3, 0.5), expect=0.0))
    # -> passed False, reason "got 0.5, expected 0 +- 1e-06"

:func:`make_scan` builds the LIDAR scan a block case describes (``{scan: {obstacles: [[r, bearing]]}}``)
the way the lab gives the simulated RPLidar's to a block: ``beams`` headings 2 pi k / beams (k =
0..beams-1, counter-clockwise from forward) wrapped to (-pi, pi] (ahead 0, left positive, right
negative), range 0 where nothing returns. Each obstacle is a flat face
``half_width`` m each side, perpendicular to its bearing at ``r`` m: a beam at heading a with
``|r tan(a - bearing)| <= half_width`` returns ``r / cos(a - bearing)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from qcarlab.errors import InputError
from qcarlab.grading.sheet import CaseCriterion, MetricCriterion


@dataclass
class Verdict:
    criterion: str  # what it checks, as text
    expected: str
    value: Any  # what came (JSON-able), None when nothing came
    passed: bool
    reason: str = ""  # why it failed (one line)
    points: float = 0.0  # what it is worth
    earned: float = 0.0
    missing: str | None = None  # the value in words when the run measured none ("never settled", "not measured")

    def as_dict(self) -> dict[str, Any]:
        out = {"criterion": self.criterion, "expected": self.expected, "value": self.value, "passed": self.passed,
               "reason": self.reason or None, "points": self.points, "earned": self.earned}
        if self.missing:
            out["missing"] = self.missing
        return out


def absent(metric: str) -> str:
    """What a metric's null value means, in words (a step that never settled has no settling time)."""
    name = metric.rsplit(".", 1)[-1]
    if "settl" in name:
        return "never settled"
    if name.startswith("rise_time"):
        return "never reached 90 % of the step"
    return "not measured"


def value_text(criterion: dict[str, Any], digits: int = 4) -> str:
    """A criterion's value for a table (from :meth:`Verdict.as_dict`): the number, or in words
    when there is none (``missing``); empty when the task produced nothing to check."""
    v = criterion.get("value")
    if v is None:
        return criterion.get("missing") or ""
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def lookup(results: Any, dotted: str) -> Any:
    """``results["best"]["completion"]`` for ``"best.completion"``, list items by index
    (``rgbd.color_size.0``); KeyError when absent."""
    value = results
    for part in dotted.split("."):
        if isinstance(value, dict) and part in value:
            value = value[part]
        elif isinstance(value, list) and part.lstrip("-").isdigit() and -len(value) <= int(part) < len(value):
            value = value[int(part)]
        else:
            raise KeyError(dotted)
    return value


def _short(value: Any, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def check_metric(results: dict, c: MetricCriterion) -> Verdict:
    """One bound on one metric; a missing or non-numeric metric fails with a reason."""
    expected = c.describe()
    try:
        value = lookup(results, c.metric)
    except KeyError:
        return Verdict(expected, expected, None, False, f"{c.metric} is not in the results", c.points,
                       missing="not measured")
    if value is None:
        words = absent(c.metric)
        return Verdict(expected, expected, None, False, f"{c.metric}: {words}", c.points, missing=words)
    if isinstance(value, bool):
        value = int(value)
    if not isinstance(value, (int, float)) or not math.isfinite(value):
        return Verdict(expected, expected, value, False, f"{c.metric} is {_short(value)}, not a number", c.points)
    low = c.min is not None and value < c.min
    high = c.max is not None and value > c.max
    if low or high:
        bound = f"below the minimum {c.min:g}" if low else f"above the maximum {c.max:g}"
        return Verdict(expected, expected, value, False, f"{c.metric} = {value:.4g}, {bound}", c.points)
    return Verdict(expected, expected, value, True, "", c.points, c.points)


def check_metrics(results: dict, criteria: list[MetricCriterion]) -> list[Verdict]:
    return [check_metric(results, c) for c in criteria]


def fail_all(criteria: list, reason: str) -> list[Verdict]:
    """Every criterion of a task that produced nothing to check, with the task's reason."""
    return [Verdict(c.describe(), c.describe(), None, False, reason, c.points) for c in criteria]


# --------------------------------------------------------------------------------------------
# block cases
# --------------------------------------------------------------------------------------------
def make_scan(spec: Any, where: str = "scan") -> tuple[np.ndarray, np.ndarray]:
    """(distances, headings) of a synthetic LIDAR turn; see the module docstring."""
    if not isinstance(spec, dict):
        raise InputError(f"{where}: expected {{obstacles: [[r, bearing], ...], beams: 800, half_width: 0.1}}")
    unknown = set(spec) - {"obstacles", "beams", "half_width"}
    if unknown:
        raise InputError(f"{where}: unknown field {sorted(unknown)[0]!r} (fields: obstacles, beams, half_width)")
    beams = spec.get("beams", 800)
    if isinstance(beams, bool) or not isinstance(beams, int) or not 8 <= beams <= 8000:
        raise InputError(f"{where}.beams: expected a whole number 8..8000, got {beams!r}")
    hw = spec.get("half_width", 0.1)
    if isinstance(hw, bool) or not isinstance(hw, (int, float)) or not (math.isfinite(hw) and hw > 0):
        raise InputError(f"{where}.half_width: expected a positive number of metres, got {hw!r}")
    obstacles = spec.get("obstacles", [])
    if not isinstance(obstacles, list):
        raise InputError(f"{where}.obstacles: expected a list of [range_m, bearing_rad]")
    headings = 2.0 * np.pi * np.arange(beams) / beams
    distances = np.zeros(beams)
    for i, ob in enumerate(obstacles):
        if not (isinstance(ob, list) and len(ob) == 2 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                                and math.isfinite(v) for v in ob)) or ob[0] <= 0:
            raise InputError(f"{where}.obstacles[{i}]: expected [range_m > 0, bearing_rad], got {ob!r}")
        r, bearing = float(ob[0]), float(ob[1])
        off = np.remainder(headings - bearing + np.pi, 2.0 * np.pi) - np.pi
        hit = (np.abs(off) < np.pi / 2) & (np.abs(r * np.tan(off)) <= hw)
        d = r / np.cos(off)
        closer = hit & ((distances == 0.0) | (d < distances))
        distances[closer] = d[closer]
    return distances, np.where(headings > np.pi, headings - 2.0 * np.pi, headings)  # as the lab gives them


def expand_args(args: tuple | list) -> list[Any]:
    """The call's arguments: a ``{scan: ...}`` becomes two (distances, headings); lists of numbers
    become float arrays (a pose, a target, readings); numbers stay numbers."""
    out: list[Any] = []
    for a in args:
        if isinstance(a, dict) and "scan" in a:
            out.extend(make_scan(a["scan"]))
        elif isinstance(a, list):
            out.append(np.asarray(a, dtype=float))
        else:
            out.append(a)
    return out


def _elements(value: Any) -> list[Any] | None:
    if isinstance(value, (list, tuple)):
        return list(value)
    return None


def check_case(output: dict, c: CaseCriterion) -> Verdict:
    """A case's outcome (``{"value": ...}`` or ``{"error": "..."}``) against its expectation."""
    expected = c.describe()
    if output is None:
        return Verdict(expected, expected, None, False, "not run", c.points)
    if output.get("error"):
        return Verdict(expected, expected, None, False, output["error"], c.points)
    value = output.get("value")

    def problem(v: Any, want: Any, lo: Any, hi: Any, label: str) -> str | None:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return f"{label}got {_short(v)}, expected a number"
        if want is not None and abs(v - want) > c.tol:
            return f"{label}got {v:.6g}, expected {want:g} +- {c.tol:g}"
        if lo is not None and v < lo:
            return f"{label}got {v:.6g}, expected >= {lo:g}"
        if hi is not None and v > hi:
            return f"{label}got {v:.6g}, expected <= {hi:g}"
        return None

    bounds = [b for b in (c.expect, c.min, c.max) if b is not None]
    if any(isinstance(b, tuple) for b in bounds):
        n = max(len(b) for b in bounds if isinstance(b, tuple))
        items = _elements(value)
        if items is None or len(items) != n:
            return Verdict(expected, expected, value, False, f"got {_short(value)}, expected {n} values", c.points)

        def at(b: Any, i: int) -> Any:
            return b[i] if isinstance(b, tuple) else b

        for i, v in enumerate(items):
            why = problem(v, at(c.expect, i), at(c.min, i), at(c.max, i), f"[{i}] ") \
                if any(at(b, i) is not None for b in bounds) else None
            if why:
                return Verdict(expected, expected, value, False, why, c.points)
        return Verdict(expected, expected, value, True, "", c.points, c.points)
    why = problem(value, c.expect, c.min, c.max, "")
    if why:
        return Verdict(expected, expected, value, False, why, c.points)
    return Verdict(expected, expected, value, True, "", c.points, c.points)


__all__ = ["Verdict", "check_case", "check_metric", "check_metrics", "expand_args", "fail_all", "lookup",
           "make_scan"]
