"""``qcarlab grade`` without running student code: the checks, the sheets, bad options, saved runs."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from qcarlab.errors import InputError
from qcarlab.grading import CaseCriterion, MetricCriterion, check_case, check_metrics, load_sheet, make_scan
from qcarlab.grading.sheet import find_sheet, shipped_sheets

REPO = Path(__file__).resolve().parents[1]


def test_metric_checks_bounds_nested_lists_and_missing_values():
    results = {"rms": 0.01, "best": {"completion": 0.995}, "flag": True, "bad": None, "size": [640, 480]}
    verdicts = check_metrics(results, [MetricCriterion("rms", max=0.02), MetricCriterion("best.completion", min=0.99),
                                       MetricCriterion("flag", min=1), MetricCriterion("rms", min=0.05, points=2),
                                       MetricCriterion("nope", max=1), MetricCriterion("bad", max=1),
                                       MetricCriterion("size.1", min=480, max=480)])
    assert [v.passed for v in verdicts] == [True, True, True, False, False, False, True]
    assert verdicts[3].reason == "rms = 0.01, below the minimum 0.05" and verdicts[3].points == 2
    assert verdicts[3].earned == 0 and verdicts[0].earned == 1
    assert verdicts[4].reason == "nope is not in the results" and verdicts[5].reason == "bad: not measured"  # in words (issue 27)


def test_case_checks_say_what_was_expected_and_what_came():
    c = CaseCriterion("stop_sign(0.3, 0.5)", (0.3, 0.5), expect=0.0, tol=1e-6)
    assert check_case({"value": 0.0}, c).passed
    bad = check_case({"value": 0.5}, c)
    assert not bad.passed and bad.reason == "got 0.5, expected 0 +- 1e-06" and bad.expected == c.describe()
    assert check_case({"value": "fast"}, c).reason == "got 'fast', expected a number"
    assert check_case({"error": "block stop_sign raised ZeroDivisionError"}, c).reason.startswith("block stop_sign")
    pair = CaseCriterion("lidar_avoid(...)", (), max=(0.0, 0.5), min=(None, -0.5))
    assert check_case({"value": [0.0, 0.2]}, pair).passed
    assert check_case({"value": [0.1, 0.2]}, pair).reason == "[0] got 0.1, expected <= 0"
    assert check_case({"value": 0.1}, pair).reason == "got 0.1, expected 2 values"


def test_synthetic_scan_is_a_flat_face_at_its_range_and_bearing():
    d, h = make_scan({"obstacles": [[0.3, 0.0]]})
    assert d.size == h.size == 800 and h[0] == 0.0 and h[-1] < 2 * math.pi
    assert d[0] == pytest.approx(0.3)
    hit = d > 0
    assert np.all(np.abs(0.3 * np.tan(np.remainder(h[hit] + math.pi, 2 * math.pi) - math.pi)) <= 0.1 + 1e-12)
    assert not make_scan({"obstacles": []})[0].any()
    d, h = make_scan({"obstacles": [[2.0, math.pi]], "beams": 360})
    assert d.size == 360 and d[180] == pytest.approx(2.0) and d[0] == 0.0
    with pytest.raises(InputError, match=r"scan.obstacles\[0\]: expected \[range_m > 0"):
        make_scan({"obstacles": [[-1, 0]]})


def test_every_shipped_sheet_loads_and_its_commands_parse():
    from qcarlab.cli.grade import CliCommands

    names = {p.stem for p in shipped_sheets()}
    assert {"basic-io", "path-following", "stop-sign", "lane-following", "obstacle-avoidance", "connectivity",
            "lidar", "csi-cameras", "rgbd-camera"} <= names
    commands = CliCommands()
    for path in shipped_sheets():
        sheet = load_sheet(path)
        assert sheet.tasks and sheet.points > 0
        for t in sheet.tasks:
            if t.command:
                name, params, _ = commands.parse(t.argv("tcp://127.0.0.1:1"))
                assert name == t.argv()[0] and params
    assert find_sheet("5.3").stem == "lane-following" and find_sheet("6.1").stem == "obstacle-avoidance"


def test_points_split_over_criteria_and_extending_sheets(tmp_path):
    base = tmp_path / "base.yaml"
    base.write_text("lab: stop-sign\ntasks:\n  - id: t1\n    command: qcarlab stop-sign\n    uses: [stop_sign]\n"
                    "    points: 3\n    criteria:\n      stopped: {min: 1}\n      stop_distance_m: {max: 0.4}\n"
                    "      passed_sign: {min: 1, points: 1}\n")
    sheet = load_sheet(base)
    assert [c.points for c in sheet.tasks[0].criteria] == [1.5, 1.5, 1] and sheet.points == 4
    extra = tmp_path / "private.yaml"
    extra.write_text("extends: base.yaml\ntasks:\n  - id: hidden\n    block: stop_sign\n"
                     "    cases:\n      - {args: [0.2, 0.7], expect: 0.0, points: 2}\n")
    private = load_sheet(extra)
    assert [t.id for t in private.tasks] == ["t1", "hidden"] and private.lab == "stop-sign" and private.points == 6
    assert private.tasks[1].criteria[0].name == "stop_sign(0.2, 0.7)"
    # the shipped sheet by name, too
    shipped = tmp_path / "more.yaml"
    shipped.write_text("extends: stop-sign\ntasks:\n  - {id: x, command: qcarlab stop-sign --speed 0.4, "
                       "uses: [stop_sign], criteria: {stopped: {min: 1}}}\n")
    assert load_sheet(shipped).tasks[0].id == "5.2-task1-block"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("tasks:\n  - id: t1\n    command: qcarlab io-test\n    criteria:\n      x: {max: low}\n",
         r"tasks\[0\].criteria.x.max: expected a number"),
        ("tasks:\n  - id: t1\n    command: io-test\n    criteria: {x: {max: 1}}\n",
         r"tasks\[0\].command: expected a 'qcarlab \.\.\.' command line"),
        ("lab: stop-sign\ntasks:\n  - id: t1\n    block: nosuch\n    cases: [{args: [1], expect: 0}]\n",
         r"tasks\[0\].block: the sheet's lab has no block 'nosuch'"),
        ("lab: stop-sign\ntasks:\n  - id: t1\n    block: stop_sign\n    cases: [{args: [1]}]\n",
         r"tasks\[0\].cases\[0\]: give expect \(with tol\) or min and/or max"),
        ("tasks:\n  - id: t1\n    command: qcarlab io-test\n    uses: [stop_sign]\n    criteria: {x: {max: 1}}\n",
         r"tasks\[0\].uses: the sheet names no lab"),
        ("lab: nolab\ntasks: []\n", r"lab: unknown lab 'nolab'"),
        ("tasks:\n  - {id: a, command: qcarlab io-test, criteria: {x: {max: 1}}}\n"
         "  - {id: a, command: qcarlab io-test, criteria: {x: {max: 2}}}\n", r"tasks\[1\].id: 'a' is already a task"),
        ("tasks:\n  - {id: a, command: qcarlab io-test, criteria: {x: {min: 2, max: 1}}}\n", r"min 2 is above max 1"),
    ],
)
def test_malformed_sheet_names_file_and_field(tmp_path, text, message):
    sheet = tmp_path / "lab.yaml"
    sheet.write_text(text)
    with pytest.raises(InputError, match=r"lab.yaml: .*" + message):
        load_sheet(sheet)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("grade", "nosuch"), "unknown lab sheet 'nosuch'"),
        (("grade", "path-following", "--task", "p9"), "--task 'p9' is not in"),
        (("grade", "path-following", "--results", "/nonexistent"), "not a folder"),
        (("grade", "path-following", "--timeout", "nan"), "--timeout must be a positive number of seconds, got nan"),
        (("grade", "path-following", "--timeout", "-1"), "--timeout must be a positive number of seconds, got -1"),
        (("grade", "path-following", "--timeout", "inf"), "--timeout must be a positive number"),
        (("grade", "path-following", "--memory", "0"), "--memory must be a positive number of MB above 256"),
        (("grade", "path-following", "--max-output", "nan"), "--max-output must be a positive number"),
        (("grade", "path-following", "--jobs", "0"), "--jobs must be 1..256"),
        (("grade", "path-following", "--submission", "/nonexistent"), "--submission /nonexistent: not a folder"),
        (("grade", "path-following", "--class", "/nonexistent"), "--class /nonexistent: not a folder"),
        (("grade", "path-following", "--submission", ".", "--class", "."), "not both"),
        (("grade", "path-following", "--car", "sim"), "--car 'sim': expected tcp://HOST:PORT"),
        (("grade", "stop-sign", "stop-sign"), "sheet 'stop-sign' is given twice"),
        (("labs", "nosuch"), "unknown lab sheet 'nosuch'"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(cli, args, message):
    code, out, err = cli(*args)
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err


def test_labs_lists_the_installed_sheets(cli):
    code, out, _ = cli("labs", "--json")
    rows = {r["name"]: r for r in json.loads(out)["sheets"]}
    assert code == 0 and rows["stop-sign"]["lab"] == "stop-sign" and rows["lidar"]["section"] == "3.5"
    code, out, _ = cli("labs", "stop-sign", "--json")
    tasks = {t["id"]: t for t in json.loads(out)["tasks"]}
    assert tasks["5.2-task1-block"]["kind"] == "block" and tasks["5.2-task1-stopsign"]["uses"] == ["stop_sign"]
    code, out, _ = cli("labs")
    assert code == 0 and "obstacle-avoidance" in out


def test_the_sheets_are_found_from_any_folder(tmp_path):
    done = subprocess.run([sys.executable, "-m", "qcarlab", "labs", "--json"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert len(json.loads(done.stdout)["sheets"]) >= 9


QUICK = """\
title: quick
tasks:
  - id: short
    command: qcarlab io-test --on-floor --throttle 0.1 --duration 0.5
    criteria:
      mean_speed_mps: {min: 0.05}
  - id: long
    command: qcarlab io-test --on-floor --throttle 0.1 --duration 1
    criteria:
      mean_speed_mps: {min: 0.05}
"""


def test_saved_runs_are_accepted_only_for_their_own_command(cli, tmp_path):
    sheet = tmp_path / "quick.yaml"
    sheet.write_text(QUICK)
    runs = tmp_path / "runs"
    for tid, duration in (("short", "0.5"), ("long", "1")):
        code, _, err = cli("io-test", "--throttle", "0.1", "--on-floor", "--duration", duration, "--out", runs / tid)
        assert code == 0, err
    code, out, _ = cli("grade", sheet, "--results", runs, "--json")
    report = json.loads(out)
    assert code == 0 and report["passed"] == report["total"] == 2 and report["points"] == 2
    # a copied run (the short one's results as the long task's) is refused, naming the option
    shutil.copy(runs / "short" / "results.json", runs / "long" / "results.json")
    code, out, _ = cli("grade", sheet, "--results", runs, "--json")
    long = json.loads(out)["tasks"][1]
    assert code == 1 and long["problem"] == "the results were made with --duration 0.5, the task's command has 1.0"
    # results that do not record their command are refused too
    res = json.loads((runs / "short" / "results.json").read_text())
    del res["invocation"]
    (runs / "short" / "results.json").write_text(json.dumps(res))
    code, out, _ = cli("grade", sheet, "--results", runs, "--task", "short", "--json")
    assert code == 1 and "do not record the command" in json.loads(out)["tasks"][0]["problem"]
    # a task never run fails too, and says so
    shutil.rmtree(runs / "long")
    code, out, _ = cli("grade", sheet, "--results", runs, "--task", "long", "--json")
    assert code == 1 and "not run: no long/results.json" in json.loads(out)["tasks"][0]["problem"]


def test_a_results_file_records_its_command_and_files(cli, tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text("lab: {}\n")
    code, out, err = cli("io-test", "--duration", "0.2", "--params", params, "--json")
    assert code == 0, err
    inv = json.loads(out)["invocation"]
    assert inv["command"] == "io-test" and inv["params"]["duration"] == 0.2
    assert inv["files"]["params"]["path"] == str(params) and len(inv["files"]["params"]["sha256"]) == 64


def test_a_run_of_another_path_is_refused_naming_the_path(cli, tmp_path):
    from qcarlab.cli.grade import CliCommands
    from qcarlab.grading.invocation import verify

    code, out, err = cli("path-follow", "line", "--length", "3", "--points", "4", "--max-time", "0.5", "--json")
    p1 = json.loads(out)
    name, want, labels = CliCommands().parse(["path-follow", "butterfly", "--size", "4"])
    assert verify(p1, name, want, None, labels) == "the results were made with PATH line, the task's command has butterfly"
    name, want, labels = CliCommands().parse(["path-follow", "line", "--points", "4", "--length", "3",
                                              "--max-time", "0.5", "--out", "x"])
    assert verify(p1, name, want, None, labels) is None  # order and --out do not matter


def test_saved_runs_must_be_made_with_the_submissions_own_files(cli, tmp_path):
    from tests.grading_submissions import correct_submission

    sub = correct_submission(tmp_path / "me", ("basic-io",)) / "basic-io"
    runs = tmp_path / "runs"
    run = ("io-test", "--on-floor", "--throttle", "0.1", "--duration", "2", "--out", runs / "task2-outputs")
    code, _, err = cli(*run, "--use", sub, "--params", sub / "params.yaml")
    assert code == 0, err
    grade = ("grade", "basic-io", "--task", "task2-outputs", "--results", runs, "--submission", sub, "--json")
    code, out, _ = cli(*grade)
    assert code == 0 and json.loads(out)["tasks"][0]["passed"], out
    with open(sub / "basic_speed_estimation.py", "a") as f:
        f.write("# changed after the run\n")
    code, out, _ = cli(*grade)
    assert code == 1
    assert json.loads(out)["tasks"][0]["problem"] == \
        "the results were made with another basic_speed_estimation.py than the submission's"
    code, _, err = cli(*run, "--params", sub / "params.yaml")  # qcarlab's own block, not the student's
    code, out, _ = cli(*grade)
    assert code == 1 and json.loads(out)["tasks"][0]["problem"] == "the run did not use your basic_speed_estimation"
