"""The shipped lab sheets are right about qcarlab's own blocks: every scenario task's command meets
its criteria, and the reference blocks pass every block task's cases."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from qcarlab.experiments.labs import find_lab
from qcarlab.grading import check_case, check_metrics, load_sheet
from qcarlab.grading.child import run_block
from qcarlab.grading.sheet import shipped_sheets
from tests.grading_submissions import REFERENCE, correct_submission

SHEETS = shipped_sheets()
EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "grading" / "private-stop-sign.yaml"  # an instructor's


def tasks(kind: str):
    seen = set()
    for sheet in [*SHEETS, EXAMPLE]:
        loaded = load_sheet(sheet)
        for task in loaded.tasks:
            if task.kind == kind and not task.needs_car and (task.command, task.block, task.id) not in seen:
                seen.add((task.command, task.block, task.id))
                yield pytest.param(loaded.extends or sheet.stem, task, id=f"{sheet.stem}:{task.id}")


def reference_choices(sheet: str, task) -> list[str]:
    """The options that give the task's graded choices (params.yaml's) the reference's values."""
    lab = load_sheet(next(p for p in SHEETS if p.stem == sheet)).lab
    choices = {c.name: c.reference for c in find_lab(lab).choose} if lab else {}
    words = []
    for name in task.params:
        if choices.get(name) is not None:
            words += [f"--{name.replace('_', '-')}", str(choices[name])]
    return words


@pytest.mark.parametrize(("sheet", "task"), list(tasks("scenario")))
def test_task_command_meets_its_criteria(cli, sheet, task, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # camera writes its images to the current folder by default
    code, out, err = cli(*task.argv(), *reference_choices(sheet, task), "--json")
    assert code == 0, err
    verdicts = check_metrics(json.loads(out), task.criteria)
    assert all(v.passed for v in verdicts), [(v.criterion, v.value, v.reason) for v in verdicts]


@pytest.mark.parametrize(("sheet", "task"), list(tasks("block")))
def test_reference_blocks_pass_the_block_tasks(tmp_path, sheet, task):
    assert sheet in REFERENCE, f"tests/grading_submissions.py has no reference blocks for {sheet}"
    folder = correct_submission(tmp_path, (sheet,)) / sheet
    lab = load_sheet(next(p for p in SHEETS if p.stem == sheet)).lab  # (an extending sheet's lab is its base's)
    file = next(f for f in REFERENCE[sheet] if f == f"{task.block}.py")
    results = tmp_path / "cases.jsonl"
    run_block({"lab": lab, "block": task.block, "file": str(folder / file), "results": str(results),
               "cases": [{"args": list(c.args), "calls": [list(a) for a in c.calls]} for c in task.criteria]})
    outputs = [json.loads(line) for line in results.read_text().splitlines()]
    verdicts = [check_case(o, c) for o, c in zip(outputs, task.criteria)]
    assert len(verdicts) == len(task.criteria)
    assert all(v.passed for v in verdicts), [(v.criterion, v.value, v.reason) for v in verdicts if not v.passed]
