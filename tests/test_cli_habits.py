"""CLI habits (issue 29, item 4): shell completion, `replay info` at 80 columns, JUnit classnames
CI systems file correctly, a progress bar on a terminal for long runs (quiet otherwise)."""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _qcarlab(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    full = {k: v for k, v in os.environ.items() if not k.startswith("_QCARLAB_COMPLETE") and k != "CI"}
    full.update(env or {})
    return subprocess.run([sys.executable, "-m", "qcarlab", *args], capture_output=True, text=True, env=full,
                          cwd=REPO, timeout=120)


# --- shell completion ---------------------------------------------------------------------------
def test_shell_completion_completes_commands_and_options():
    words = _qcarlab(env={"_QCARLAB_COMPLETE": "complete_bash", "COMP_WORDS": "qcarlab pa", "COMP_CWORD": "1"})
    assert words.returncode == 0, words.stderr
    assert words.stdout.split() == ["path-gen", "path-follow"]
    opts = _qcarlab(env={"_QCARLAB_COMPLETE": "complete_bash", "COMP_WORDS": "qcarlab avoid --wor",
                         "COMP_CWORD": "2"})
    assert opts.stdout.split() == ["--world"]


def test_show_completion_prints_the_script():
    run = _qcarlab("--show-completion", "bash")
    assert run.returncode == 0 and "_qcarlab_completion" in run.stdout and "complete " in run.stdout
    assert "--install-completion" in _qcarlab("--help").stdout


# --- replay info --------------------------------------------------------------------------------
def test_replay_info_keeps_topic_names_whole_at_80_columns(cli, tmp_path, monkeypatch):
    pytest.importorskip("mcap")
    pytest.importorskip("foxglove")
    from rich.console import Console

    f = tmp_path / "lf.mcap"
    assert cli("lane-follow", "--duration", "1", "--record", f, "--json")[0] == 0
    code, out, _ = cli("replay", "info", f, "--json")
    import json

    topics = json.loads(out)["topics"]
    assert "/qcar/rgbd/calibration" in topics  # the longest of qcarlab's names (22 characters)
    monkeypatch.setattr("qcarlab.cli.replay.stdout", Console(width=80, highlight=False, force_terminal=False))
    code, out, err = cli("replay", "info", f)
    assert code == 0, err
    lines = out.splitlines()
    assert max(len(line) for line in lines) <= 80
    assert "…" not in out
    for topic, t in topics.items():  # every topic on a line of its own, whole, with its schema
        row = [line for line in lines if line.split() and line.split()[0] == topic]
        assert len(row) == 1, topic
        assert t["schema"] in row[0] and str(t["count"]) in row[0].split()
    # --topics: one a line, in full, tab-separated
    code, out, _ = cli("replay", "info", f, "--topics")
    assert code == 0
    rows = [line.split("\t") for line in out.splitlines()]
    assert [r[0] for r in rows] == list(topics)
    assert all(r[1] == topics[r[0]]["schema"] and int(r[2]) == topics[r[0]]["count"] for r in rows)


# --- JUnit --------------------------------------------------------------------------------------
def _task(sheet: str, task_id: str, passed: bool) -> dict:
    crit = {"criterion": "stopped_before_sign", "expected": "<= 0.4", "value": 0.3 if passed else 0.9,
            "earned": 1.0 if passed else 0.0, "points": 1.0, "passed": passed, "reason": None if passed else "too far"}
    return {"sheet": sheet, "id": task_id, "criteria": [crit], "status": "graded", "problem": None,
            "seconds": 1.5, "earned": crit["earned"], "points": 1.0}


def _classes(path: Path) -> list[str]:
    return [c.get("classname") for c in ET.parse(path).getroot().iter("testcase")]


def test_junit_classnames_have_one_dot_per_level(tmp_path):
    """Jenkins (and its xunit plugin) splits a classname at every dot into packages and a class:
    a task id's own dots (5.2-task1-block) must not make packages of the sheet's numbering."""
    from junitparser import JUnitXml

    from qcarlab.grading.report import junit_classname, write_junit

    tasks = [_task("stop-sign", "5.2-task1-block", True), _task("stop-sign", "5.1-detect", False),
             _task("path-following", "4.1.4-pure-pursuit-block", True)]
    one = write_junit(tmp_path / "one.xml", [{"student": "me", "tasks": tasks}], single=True)
    assert _classes(one) == ["stop-sign.5_2-task1-block", "stop-sign.5_1-detect",
                             "path-following.4_1_4-pure-pursuit-block"]
    klass = write_junit(tmp_path / "class.xml", [{"student": "j.smith", "tasks": tasks}], single=False)
    names = _classes(klass)
    assert names[0] == "j_smith.stop-sign.5_2-task1-block" and all(n.count(".") == 2 for n in names)
    # still a JUnit file junitparser reads, the failure where it was
    cases = [c for suite in JUnitXml.fromfile(str(klass)) for c in suite]
    assert [bool(c.result) for c in cases] == [False, True, False]
    assert junit_classname("a.b", "c") == "a_b.c"


# --- progress -----------------------------------------------------------------------------------
def _pty(monkeypatch, *args: str, after: str | None = "0", ci: str | None = None):
    sys.path.insert(0, str(Path(__file__).parent))
    from ptyrun import PtyRun

    monkeypatch.delenv("CI", raising=False)
    if ci is not None:
        monkeypatch.setenv("CI", ci)
    if after is None:
        monkeypatch.delenv("QCARLAB_PROGRESS_AFTER", raising=False)
    else:
        monkeypatch.setenv("QCARLAB_PROGRESS_AFTER", after)
    run = PtyRun(*args)
    rc = run.finish(120)
    return rc, run.text


BAR = "elapsed,"  # the bar's own text (rich's columns: time, "elapsed,", time left, "left")


def test_a_long_run_shows_a_progress_bar_on_a_terminal(monkeypatch):
    rc, text = _pty(monkeypatch, "avoid", "--world", "hallway", "--duration", "20")
    assert rc == 0, text[-1500:]
    assert BAR in text and "/ 20.0 s" in text and "avoid" in text
    assert "distance driven" in text  # the summary after it


def test_no_progress_bar_under_json_in_ci_or_for_a_short_run(monkeypatch):
    rc, text = _pty(monkeypatch, "avoid", "--world", "hallway", "--duration", "20", "--json")
    assert rc == 0 and BAR not in text and text.lstrip().startswith("{")
    rc, text = _pty(monkeypatch, "avoid", "--world", "hallway", "--duration", "20", ci="true")
    assert rc == 0 and BAR not in text and "distance driven" in text
    rc, text = _pty(monkeypatch, "avoid", "--world", "hallway", "--duration", "3", after=None)
    assert rc == 0 and BAR not in text  # a tenth of a second: well under the 2 s a bar waits for


def test_no_progress_bar_when_stdout_is_not_a_terminal():
    run = _qcarlab("avoid", "--world", "hallway", "--duration", "20", env={"QCARLAB_PROGRESS_AFTER": "0"})
    assert run.returncode == 0 and BAR not in run.stdout + run.stderr


def test_the_python_api_loop_has_no_progress_hook():
    from qcarlab.experiments.loop import PROGRESS

    assert PROGRESS.get() is None
