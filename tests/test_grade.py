"""``qcarlab grade``: criteria checks and the command as a student or a CI script runs it."""

from __future__ import annotations

import json

import pytest

from qcarlab.errors import InputError
from qcarlab.grade import Criterion, check, load_sheet


def test_check_bounds_nested_metrics_and_missing_values():
    results = {"rms": 0.01, "best": {"completion": 0.995}, "flag": True, "bad": None}
    verdicts = check(results, [Criterion("rms", max=0.02), Criterion("best.completion", min=0.99),
                               Criterion("flag", min=1), Criterion("rms", min=0.05), Criterion("nope", max=1),
                               Criterion("bad", max=1)])
    assert [v.passed for v in verdicts] == [True, True, True, False, False, False]
    assert verdicts[4].reason == "not in the results" and verdicts[5].reason == "not a number"


def test_grade_saved_results_pass_and_fail(cli, tmp_path):
    code, _, err = cli("path-follow", "circle", "--out", tmp_path / "p2-circle")
    assert code == 0, err
    code, out, _ = cli("grade", "path-following", "--results", tmp_path, "--task", "p2-circle", "--json")
    report = json.loads(out)
    assert code == 0 and report["passed"] == report["total"] == 1
    # a run that misses the bound fails the grade with exit 1
    res = json.loads((tmp_path / "p2-circle" / "results.json").read_text())
    res["rms_cross_track_m"] = 0.5
    (tmp_path / "p2-circle" / "results.json").write_text(json.dumps(res))
    code, out, _ = cli("grade", "path-following", "--results", tmp_path, "--task", "p2-circle", "--json")
    assert code == 1 and json.loads(out)["passed"] == 0
    # a task never run fails too, and says so
    code, out, _ = cli("grade", "path-following", "--results", tmp_path, "--task", "p1-line", "--json")
    assert code == 1 and "not run" in json.loads(out)["tasks"][0]["problem"]


def test_grade_runs_the_commands(cli):
    code, out, err = cli("grade", "path-following", "--task", "p1-line", "--json")
    assert code == 0, err
    assert json.loads(out)["tasks"][0]["passed"] is True


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("grade", "nosuch"), "unknown lab sheet 'nosuch'"),
        (("grade", "path-following", "--task", "p9"), "--task 'p9' is not in"),
        (("grade", "path-following", "--results", "/nonexistent"), "not a folder"),
    ],
)
def test_bad_input(cli, args, message):
    code, out, err = cli(*args)
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_malformed_sheet_names_file_and_field(tmp_path):
    sheet = tmp_path / "lab.yaml"
    sheet.write_text("tasks:\n  - id: t1\n    command: qcarlab io-test --json\n    criteria:\n      x: {max: low}\n")
    with pytest.raises(InputError, match=r"lab.yaml: tasks\[0\].criteria.x.max: expected a number"):
        load_sheet(sheet)
