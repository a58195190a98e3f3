"""A lab sheet's self-check: every point depends on the student (``qcarlab labs check SHEET``).

Two rules, each checked twice (by reading the sheet, then by grading):

1. **An untouched template earns nothing.** Every scenario task uses at least one of the student's
   blocks (one the template leaves to fill) or choices (a ``params.yaml`` tunable the template
   leaves empty); every block task grades a block of the student's. A sheet without a lab (the
   sensors' sections) is graded only on a car: on the simulator its tasks would measure qcarlab's
   simulated sensor. Graded: the template as ``qcarlab template`` writes it scores 0 points.
2. **The reference earns everything.** :mod:`qcarlab.grading.reference` (qcarlab's blocks and
   choices, handed in as a submission) scores every point of the tasks that run here.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from qcarlab.grading.grader import Commands, Options, grade, make_plan, summary
from qcarlab.grading.sheet import Sheet


def static_problems(sheet: Sheet) -> list[str]:
    """Why an untouched template could earn points on ``sheet``, read from the sheet (empty: it cannot)."""
    if sheet.lab is None:
        return [f"{t.id}: runs only qcarlab's code (the sheet has no lab, so no block or choice of the student's): "
                "grade it on a car ({car} in its command) or give the sheet a lab"
                for t in sheet.tasks if not t.needs_car]
    from qcarlab.experiments.labs import find_lab

    lab = find_lab(sheet.lab)
    to_fill = {b.name for b in lab.to_fill}
    choices = {c.name for c in lab.choose}
    out = []
    for t in sheet.tasks:
        if t.kind == "block":
            continue  # the student's block on given inputs: the template's stub (or no block) fails it
        if not t.uses and not t.params:
            out.append(f"{t.id}: uses none of the student's blocks or choices: an untouched template earns its "
                       "points (add uses: [BLOCK or TUNABLE])")
            continue
        given = [p for p in t.params if p not in choices]
        if given and not [u for u in t.uses if u in to_fill]:
            out.append(f"{t.id}: uses {', '.join(given)}, which the template fills with qcarlab's value: add it "
                       f"to the lab's choices (qcarlab.experiments.labs, choose=) so the template leaves it empty")
    return out


@dataclass
class Outcome:
    """The self-check of one sheet."""

    sheet: str
    problems: list[str] = field(default_factory=list)  # read from the sheet
    template: dict[str, Any] = field(default_factory=dict)  # summary() of the template's grade
    reference: dict[str, Any] = field(default_factory=dict)  # summary() of the reference's grade
    template_points: list[str] = field(default_factory=list)  # "task: criterion" the template earned
    reference_missed: list[str] = field(default_factory=list)  # "task: why" the reference missed

    @property
    def ok(self) -> bool:
        return not (self.problems or self.template_points or self.reference_missed)


def _graded(sheet: Sheet, root: Path | None, commands: Commands, jobs: int, sandbox: str) -> list[dict[str, Any]]:
    from qcarlab.grading.schedule import run_local

    students = [("template" if root is not None else "reference", root)]
    plan = make_plan([sheet], sheet.tasks, students, Options(sandbox=sandbox), commands)
    to_run = [p.job for p in plan if p.job is not None]
    outcomes = dict(zip((j.key for j in to_run), run_local(to_run, jobs, lambda job, outcome: None)))
    return [grade(p, outcomes.get(p.key), commands) for p in plan]


def check_sheet(sheet: Sheet, commands: Commands, jobs: int = 1, sandbox: str = "auto",
                run: bool = True) -> Outcome:
    """Check ``sheet``: read it, then (``run``) grade the untouched template and the reference."""
    out = Outcome(sheet.name, static_problems(sheet))
    if not run or sheet.lab is None:
        return out
    from qcarlab.experiments.labs import find_lab, write_template
    from qcarlab.grading.reference import LAB_OF, REFERENCE, reference_submission

    lab = find_lab(sheet.lab)
    with tempfile.TemporaryDirectory(prefix="qcarlab-labs-check-") as tmp:
        template = Path(tmp) / "template" / lab.sheet
        write_template(lab, template)
        rows = _graded(sheet, template, commands, jobs, sandbox)
        out.template = summary(rows)
        out.template_points = [f"{r['id']}: {c['criterion']}" for r in rows for c in r["criteria"]
                               if c.get("earned")]
        base = next((name for name, command in LAB_OF.items() if command == lab.command), None)
        if base is None or base not in REFERENCE:
            out.problems.append(f"qcarlab.grading.reference has no reference submission for the lab {lab.command}")
            return out
        reference = reference_submission(Path(tmp) / "reference", (base,)) / base
        rows = _graded(sheet, reference, commands, jobs, sandbox)
        out.reference = summary(rows)
        out.reference_missed = [f"{r['id']}: {r['problem'] or '; '.join(c['criterion'] for c in r['criteria'] if not c['passed'])}"
                                for r in rows if r["status"] == "failed" or r["status"] == "error"]
    return out


__all__ = ["Outcome", "check_sheet", "static_problems"]
