"""The lab sheets in labs/ are well formed and their commands meet their own criteria."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest
import yaml

LABS = Path(__file__).resolve().parents[1] / "labs"
SHEETS = sorted(LABS.glob("*.yaml"))


def lookup(results: dict, dotted: str):
    value = results
    for part in dotted.split("."):
        value = value[part]
    return value


def tasks():
    for sheet in SHEETS:
        for task in yaml.safe_load(sheet.read_text())["tasks"]:
            yield pytest.param(task, id=f"{sheet.stem}:{task['id']}")


@pytest.mark.parametrize("task", list(tasks()))
def test_task_command_meets_its_criteria(cli, task):
    argv = shlex.split(task["command"])
    assert argv[0] == "qcarlab" and "--json" in argv
    code, out, err = cli(*argv[1:])
    assert code == 0, err
    results = json.loads(out)
    for metric, bound in task["criteria"].items():
        value = lookup(results, metric)
        if "max" in bound:
            assert value <= bound["max"], (metric, value)
        if "min" in bound:
            assert value >= bound["min"], (metric, value)
