"""The lab sheets in labs/ are well formed and their commands meet their own criteria."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest

from qcarlab.grade import check, load_sheet

LABS = Path(__file__).resolve().parents[1] / "labs"
SHEETS = sorted(LABS.glob("*.yaml"))


def tasks():
    for sheet in SHEETS:
        for task in load_sheet(sheet)[1]:
            yield pytest.param(task, id=f"{sheet.stem}:{task.id}")


@pytest.mark.parametrize("task", list(tasks()))
def test_task_command_meets_its_criteria(cli, task):
    argv = shlex.split(task.command)
    assert argv[0] == "qcarlab" and "--json" in argv
    code, out, err = cli(*argv[1:])
    assert code == 0, err
    verdicts = check(json.loads(out), task.criteria)
    assert all(v.passed for v in verdicts), [(v.criterion.describe(), v.value, v.reason) for v in verdicts]
