"""``qcarlab grade`` running students' code: each task in its own process, surviving what students write."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from tests.grading_submissions import correct_submission, write_block

STOP_SIGN_BAD = {
    "wrong_window": "def stop_sign(distance_to_sign, desired_speed):\n"
                    "    return 0.0 if 0.5 < distance_to_sign < 1.0 else desired_speed\n",
    "raises": "def stop_sign(distance_to_sign, desired_speed):\n    return desired_speed / (distance_to_sign * 0)\n",
    "hangs": "def stop_sign(distance_to_sign, desired_speed):\n    while True:\n        pass\n",
    "hogs_memory": "import numpy as np\n\ndef stop_sign(distance_to_sign, desired_speed):\n    keep = []\n"
                   "    while True:\n        keep.append(np.empty(10**8))\n",
    "calls_sys_exit": "import sys\n\ndef stop_sign(distance_to_sign, desired_speed):\n    sys.exit(0)\n",
    "calls_os_exit": "import os\n\ndef stop_sign(distance_to_sign, desired_speed):\n    os._exit(3)\n",
    "prints_megabytes": "def stop_sign(distance_to_sign, desired_speed):\n    while True:\n"
                        "        print('x' * 10000)\n",
    "returns_garbage": "def stop_sign(distance_to_sign, desired_speed):\n    return 'fast'\n",
    "syntax_error": "def stop_sign(distance_to_sign, desired_speed)\n    return 0\n",
}
EXPECT = {  # student -> what the reason of their first failed case must say
    "wrong_window": "got 0.5, expected 0 +- 1e-06",
    "raises": "block stop_sign (stop_sign.py:stop_sign) raised ZeroDivisionError",
    "hangs": "did not finish within 4 s (stopped)",
    "hogs_memory": "ran out of memory",
    "calls_sys_exit": "called sys.exit(0); a block returns its value instead",
    "calls_os_exit": "exited with code 3",
    "prints_megabytes": "printed more than 1 MB (output is capped)",
    "returns_garbage": "block stop_sign returned 'fast' (str); expected a number in m/s",
    "syntax_error": "stop_sign.py line 1: syntax error",
    "unfilled": "stop_sign.py: stop_sign is not filled in yet",
}


def stop_sign_class(root: Path, bad: dict[str, str]) -> Path:
    """A class folder: 'good' (the reference), one student per misbehaving stop_sign, one unfilled template."""
    correct_submission(root / "good", ("stop-sign",))
    for name, source in bad.items():
        correct_submission(root / name, ("stop-sign",))
        write_block(root / name / "stop-sign", "stop_sign.py", source)
    if "unfilled" in EXPECT:
        correct_submission(root / "unfilled", ("stop-sign",))
        from qcarlab.experiments.labs import find_lab, write_template

        write_template(find_lab("stop-sign"), root / "unfilled" / "stop-sign", force=True)
    (root / "good" / "stop-sign" / "answers.md").write_text("Stops at 0.31 m. <script>alert(1)</script>\n")
    return root


def test_a_class_survives_every_kind_of_broken_block(cli, tmp_path):
    klass = stop_sign_class(tmp_path / "class", STOP_SIGN_BAD)
    out = tmp_path / "grades"
    t0 = time.monotonic()
    code, stdout_text, err = cli("grade", "stop-sign", "--class", klass, "--task", "5.2-task1-block", "--jobs", "2",
                                 "--timeout", "4", "--max-output", "1", "--out", out, "--junit", tmp_path / "r.xml",
                                 "--json")
    assert code == 1, err
    assert time.monotonic() - t0 < 120  # the hanging student did not hold the class up
    report = json.loads(stdout_text)
    by = {s["student"]: s for s in report["students"]}
    assert set(by) == {"good", "unfilled", *STOP_SIGN_BAD}
    assert by["good"]["points"] == by["good"]["max_points"] == 6 and by["good"]["passed"] == 1
    assert by["wrong_window"]["points"] == 4  # 0.30 and 0.10 m are in the sheet's window, not in 0.5-1.0
    for name, text in EXPECT.items():
        task = by[name]["tasks"][0]
        reasons = [c["reason"] for c in task["criteria"] if not c["passed"]]
        assert reasons and text in reasons[0], (name, reasons[0])
        assert all(len(r.splitlines()) == 1 for r in reasons)
        assert "qcarlab-grade-" not in json.dumps(task)  # no temporary paths in what students read
    # the gradebook: a row per student, the task's points and the total
    rows = list(csv.DictReader(open(out / "gradebook.csv", encoding="utf-8")))
    book = {r["student"]: r for r in rows}
    assert book["good"]["stop-sign/5.2-task1-block"] == "6" and book["good"]["total"] == "6"
    assert book["hangs"]["total"] == "0" and book["wrong_window"]["max_points"] == "6"
    # the HTML report: self-contained, every student, the answers as text
    page = (out / "report.html").read_text(encoding="utf-8")
    assert "<script>alert" not in page and "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    assert all(f"id='s-{name}'" in page for name in by) and "src='http" not in page and "<link" not in page
    # JUnit: one testcase per criterion and student, failures for the broken ones
    suites = ET.parse(tmp_path / "r.xml").getroot()
    cases = suites.findall("./testsuite/testcase")
    assert len(cases) == 6 * len(by)
    assert all(c.get("name") and c.get("classname") for c in cases)
    good = [c for c in cases if c.get("classname").startswith("good.")]
    assert good and all(not list(c) or c[0].tag == "system-out" for c in good)
    hung = [c for c in cases if c.get("classname").startswith("hangs.")]
    assert all(c.find("error") is not None or c.find("failure") is not None for c in hung)
    stats = {s.get("name"): s for s in suites.findall("./testsuite")}
    assert stats["good: stop-sign"].get("tests") == "6" and stats["good: stop-sign"].get("failures") == "0"
    assert int(stats["raises: stop-sign"].get("failures")) + int(stats["raises: stop-sign"].get("errors")) == 6
    from junitparser import JUnitXml

    assert sum(1 for suite in JUnitXml.fromfile(str(tmp_path / "r.xml")) for _ in suite) == len(cases)


def avoid_sheet(path: Path) -> Path:
    path.write_text("""\
title: quick LIDAR
lab: avoid
tasks:
  - id: stop-block
    block: lidar_stop
    cases:
      - {args: [{scan: {obstacles: [[0.30, 0.0]]}}, 0.3], expect: 0.0}
      - {args: [{scan: {obstacles: [[2.0, 0.0]]}}, 0.3], expect: 0.3}
  - id: steer-block
    block: lidar_steer
    cases:
      - {args: [{scan: {obstacles: [[0.5, 0.3]]}}, 0.3], min: -0.5, max: -0.05}
      - {args: [{scan: {obstacles: [[0.5, -0.3]]}}, 0.3], min: 0.05, max: 0.5}
  - id: stop-run
    command: qcarlab avoid --strategy stop --duration 3
    uses: [lidar_stop]
    criteria:
      collisions: {max: 0}
      stopped_before_obstacle: {min: 0.27, max: 0.40}
  - id: steer-run
    command: qcarlab avoid --strategy steer --duration 4
    uses: [lidar_steer]
    criteria:
      collisions: {max: 0}
      distance_m: {min: 1.0}
""")
    return path


def test_one_wrong_block_fails_exactly_the_tasks_that_use_it(cli, tmp_path):
    sheet = avoid_sheet(tmp_path / "quick.yaml")
    klass = tmp_path / "class"
    correct_submission(klass / "right", ("obstacle-avoidance",))
    correct_submission(klass / "mirrored_steer", ("obstacle-avoidance",))
    write_block(klass / "mirrored_steer" / "obstacle-avoidance", "lidar_steer.py", """
        _reference = __import__("importlib").import_module("qcarlab.control.lidar_avoid").lidar_steer

        def lidar_steer(distances, headings, desired_speed):
            return -_reference(distances, headings, desired_speed)   # towards the obstacle
    """)
    correct_submission(klass / "no_stop", ("obstacle-avoidance",))
    (klass / "no_stop" / "obstacle-avoidance" / "lidar_stop.py").unlink()
    code, out, err = cli("grade", sheet, "--class", klass, "--jobs", "2", "--out", tmp_path / "g", "--json")
    assert code == 1, err
    by = {s["student"]: {t["id"]: t for t in s["tasks"]} for s in json.loads(out)["students"]}
    assert all(t["passed"] for t in by["right"].values()), by["right"]
    mirrored = by["mirrored_steer"]
    assert [tid for tid, t in mirrored.items() if not t["passed"]] == ["steer-block", "steer-run"]
    assert mirrored["steer-block"]["criteria"][0]["reason"].startswith("got 0.41")
    assert "collisions = 1, above the maximum 0" in [c["reason"] for c in mirrored["steer-run"]["criteria"]]
    assert mirrored["steer-run"]["run_failure"].startswith("collision at")
    no_stop = by["no_stop"]
    assert [tid for tid, t in no_stop.items() if not t["passed"]] == ["stop-block", "stop-run"]
    assert no_stop["stop-run"]["problem"].startswith("your submission has no lidar_stop")
    # the figures of each run are kept beside its results
    assert (tmp_path / "g" / "right" / "quick" / "stop-run" / "results.json").exists()
    assert list((tmp_path / "g" / "right" / "quick" / "stop-run").glob("*.png"))
    page = (tmp_path / "g" / "report.html").read_text()
    assert page.count("src='data:image/jpeg;base64,") >= 2 and "My answers for obstacle-avoidance." in page
    # each thumbnail links to its full-size figure, which is there beside the report (issue 29)
    import re

    from qcarlab import __version__

    links = re.findall(r"<a href='([^'#]+\.png)'", page)
    assert len(links) == page.count("src='data:image/jpeg;base64,")
    assert "right/quick/stop-run/" + next((tmp_path / "g" / "right" / "quick" / "stop-run").glob("*.png")).name in links
    assert all((tmp_path / "g" / link).is_file() for link in links)
    assert f"<dt>qcarlab</dt><dd>{__version__}</dd>" in page and "<dt>date</dt>" in page
    assert "<dt>sheets</dt><dd>" in page and "(quick)" in page


def grade_json(path: Path) -> dict:
    """grade.json without the wall times (the only thing that may differ between runs)."""
    data = json.loads(path.read_text())
    for st in data.get("students", [data]):
        for t in st["tasks"]:
            t.pop("seconds", None)
    return data


def small_class(root: Path) -> Path:
    correct_submission(root / "ada", ("stop-sign", "obstacle-avoidance"))
    correct_submission(root / "bob", ("stop-sign", "obstacle-avoidance"))
    write_block(root / "bob" / "stop-sign", "stop_sign.py", STOP_SIGN_BAD["wrong_window"])
    correct_submission(root / "cy", ("stop-sign", "obstacle-avoidance"))
    write_block(root / "cy" / "obstacle-avoidance", "lidar_stop.py",
                "def lidar_stop(distances, headings, desired_speed):\n    raise ValueError('todo')\n")
    return root


SMALL_TASKS = ("--task", "5.2-task1-block", "--task", "lidar-stop-block")


def test_jobs_give_the_gradebook_of_a_serial_run(cli, tmp_path):
    klass = small_class(tmp_path / "class")
    for jobs in ("1", "2"):
        code, _, err = cli("grade", "stop-sign", "obstacle-avoidance", "--class", klass, *SMALL_TASKS,
                           "--jobs", jobs, "--out", tmp_path / f"j{jobs}")
        assert code == 1, err
    assert (tmp_path / "j1" / "gradebook.csv").read_text() == (tmp_path / "j2" / "gradebook.csv").read_text()
    assert grade_json(tmp_path / "j1" / "grade.json") == grade_json(tmp_path / "j2" / "grade.json")
    book = {r["student"]: r for r in csv.DictReader(open(tmp_path / "j1" / "gradebook.csv"))}
    assert (book["ada"]["total"], book["bob"]["total"], book["cy"]["total"]) == ("11", "9", "6")


def test_a_task_that_needs_a_car_is_skipped_without_one_and_graded_with_one(cli, tmp_path):
    code, out, err = cli("grade", "connectivity", "--json")
    report = json.loads(out)
    assert code == 0 and report["skipped"] == 1 and report["tasks"][0]["status"] == "skipped", err
    port = 18000 + (int(time.time() * 1000) % 1000)
    server = subprocess.Popen([sys.executable, "-m", "qcarlab", "serve", "--backend", "sim", "--lockstep",
                               "--port", str(port)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while True:
            code, out, err = cli("grade", "connectivity", "--car", f"tcp://127.0.0.1:{port}", "--json",
                                 "--junit", tmp_path / "ping.xml")
            report = json.loads(out)
            if code == 0 or time.monotonic() > deadline:
                break
            time.sleep(1.0)  # the server is still starting
        assert code == 0 and report["passed"] == 1, report["tasks"][0]
        assert report["tasks"][0]["command"] == f"qcarlab ping tcp://127.0.0.1:{port} --count 20 --interval 0.05"
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_a_correct_submission_passes_a_sheet_with_reasons_in_the_table(cli, tmp_path):
    sub = correct_submission(tmp_path / "me", ("stop-sign",))
    code, out, err = cli("grade", "stop-sign", "--submission", sub, "--task", "5.2-task1-block",
                         "--junit", tmp_path / "r.xml")
    assert code == 0, err
    assert "1 of 1 tasks passed, 6 of 6 points" in " ".join(out.split())
    write_block(sub / "stop-sign", "stop_sign.py", STOP_SIGN_BAD["wrong_window"])
    code, out, err = cli("grade", "stop-sign", "--submission", sub, "--task", "5.2-task1-block")
    assert code == 1 and "4 of 6 points" in " ".join(out.split()) and out.count("FAIL: got 0.") == 2


@pytest.mark.slow
def test_a_correct_submission_passes_all_five_lab_sheets_and_a_wrong_block_fails_its_tasks(cli, tmp_path):
    klass = tmp_path / "class"
    correct_submission(klass / "right")
    correct_submission(klass / "wrong_stop")
    write_block(klass / "wrong_stop" / "stop-sign", "stop_sign.py", STOP_SIGN_BAD["wrong_window"])
    code, out, err = cli("grade", "basic-io", "path-following", "stop-sign", "lane-following",
                         "obstacle-avoidance", "--class", klass, "--jobs", "2", "--out", tmp_path / "g", "--json")
    by = {s["student"]: s for s in json.loads(out)["students"]}
    right = by["right"]
    assert right["passed"] == right["total"] and right["points"] == right["max_points"], \
        [(t["id"], t["problem"]) for t in right["tasks"] if not t["passed"]]
    failed = [t["id"] for t in by["wrong_stop"]["tasks"] if not t["passed"]]
    assert failed == ["5.2-task1-block", "5.2-task1-stopsign", "5.2-task3-faster"]


HARD_CODED = """\
PUBLIC = {(0.30, 0.5): 0.0, (0.02, 0.5): 0.5, (0.45, 0.5): 0.5, (0.0, 0.3): 0.3, (0.10, 0.3): 0.0, (1.5, 1.0): 1.0}

def stop_sign(distance_to_sign, desired_speed):
    return PUBLIC.get((distance_to_sign, desired_speed), desired_speed)
"""


def test_an_instructors_hidden_tasks_catch_a_hard_coded_block(cli, tmp_path):
    private = Path(__file__).resolve().parents[1] / "docs" / "grading" / "private-stop-sign.yaml"
    klass = tmp_path / "class"
    correct_submission(klass / "honest", ("stop-sign",))
    correct_submission(klass / "hard_coded", ("stop-sign",))
    write_block(klass / "hard_coded" / "stop-sign", "stop_sign.py", HARD_CODED)
    code, out, err = cli("grade", private, "--class", klass, "--task", "5.2-task1-block", "--task", "hidden-block",
                         "--jobs", "2", "--out", tmp_path / "g", "--json")
    assert code == 1, err
    by = {s["student"]: {t["id"]: t for t in s["tasks"]} for s in json.loads(out)["students"]}
    assert by["honest"]["5.2-task1-block"]["passed"] and by["honest"]["hidden-block"]["passed"]
    assert by["hard_coded"]["5.2-task1-block"]["passed"] and not by["hard_coded"]["hidden-block"]["passed"]
    assert by["hard_coded"]["hidden-block"]["earned"] == 3  # the cases where the desired speed is right
