"""Tasks forked from a warm zygote (qcarlab.grading.warm) grade exactly as fresh processes do,
misbehaving students included, and are still killed, limited and isolated one by one."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest

from tests.grading_submissions import correct_submission, write_block

pytestmark = pytest.mark.skipif(not hasattr(os, "pidfd_open"), reason="the warm start is Linux only")

SHEET = """\
title: warm
lab: io-test
tasks:
  - id: drive
    command: qcarlab io-test --on-floor --throttle 0.1 --duration 0.5
    uses: [basic_speed_estimation]
    criteria:
      mean_speed_mps: {min: 0.05, max: 0.5}
"""
HEADER = "_ref = __import__('importlib').import_module('qcarlab.control.speed').basic_speed_estimation\n\n"
BAD = {
    "raises": "def basic_speed_estimation(counts_per_s):\n    return 1 / (counts_per_s * 0)\n",
    "hangs": "def basic_speed_estimation(counts_per_s):\n    while True:\n        pass\n",
    "calls_os_exit": "import os\n\ndef basic_speed_estimation(counts_per_s):\n    os._exit(3)\n",
    "prints_megabytes": "def basic_speed_estimation(counts_per_s):\n    while True:\n        print('x' * 10000)\n",
    "kills_itself": "import os, signal\n\ndef basic_speed_estimation(counts_per_s):\n"
                    "    os.kill(os.getpid(), signal.SIGSEGV)\n",
    "leaves_a_child": "import subprocess, sys\n\nLEFT = []\n\ndef basic_speed_estimation(counts_per_s):\n"
                      "    if not LEFT:  # a process the task never waits for: killed with the task's group\n"
                      "        LEFT.append(subprocess.Popen(['sleep', '600']))\n"
                      "    return _ref(counts_per_s)\n",
}


# filling 1 GB takes seconds when the machine is loaded: it is graded apart, with the block
# watchdog and the task's limit far off, so that it meets the memory limit first at any load
HOG = {"hogs_memory": "import numpy as np\n\ndef basic_speed_estimation(counts_per_s):\n    keep = []\n"
                      "    while True:\n        keep.append(np.ones(10**8))\n"}


def klass(root: Path, bad: dict[str, str] = BAD) -> Path:
    correct_submission(root / "good", ("basic-io",))
    for name, body in bad.items():
        correct_submission(root / name, ("basic-io",))
        write_block(root / name / "basic-io", "basic_speed_estimation.py", HEADER + body)
    return root


def graded(cli, sheet: Path, root: Path, out: Path, timeout: str = "8") -> dict:
    code, stdout, err = cli("grade", sheet, "--class", root, "--jobs", "2", "--timeout", timeout, "--memory", "1024",
                            "--max-output", "1", "--out", out, "--json")
    assert code == 1, err
    by = {}
    for st in json.loads(stdout)["students"]:
        task = st["tasks"][0]
        by[st["student"]] = (task["passed"], task["problem"], [c["reason"] for c in task["criteria"]])
    return by


def test_warm_tasks_fail_like_cold_ones(cli, tmp_path, monkeypatch):
    sheet = tmp_path / "warm.yaml"
    sheet.write_text(SHEET)
    root = klass(tmp_path / "class")
    # the task's limit far enough past the block watchdog's 5 s that a cold task's start (a fresh
    # interpreter, 3 s and more on a loaded machine) never lets the limit come first
    t0 = time.monotonic()
    warm = graded(cli, sheet, root, tmp_path / "warm", timeout="20")
    warm_s = time.monotonic() - t0
    monkeypatch.setenv("QCARLAB_GRADE_COLD", "1")
    cold = graded(cli, sheet, root, tmp_path / "cold", timeout="20")
    for name in warm:
        assert warm[name] == cold[name], (name, warm[name], cold[name])
    assert warm["good"][0] and warm["leaves_a_child"][0], warm
    assert not any(warm[name][0] for name in BAD if name != "leaves_a_child")
    assert "raised ZeroDivisionError" in warm["raises"][1]
    assert warm["hangs"][1] == ("block basic_speed_estimation (basic_speed_estimation.py:basic_speed_estimation) "
                                "has not returned after 5 s: an endless loop?")  # the block watchdog, before the task's limit
    block = "block basic_speed_estimation (basic_speed_estimation.py:basic_speed_estimation): "
    assert warm["calls_os_exit"][1] == block + "the process running your blocks exited with code 3 (os._exit in " \
        "your code?)"
    assert warm["prints_megabytes"][1] == block + "printed more than 1 MB (output is capped)"
    assert warm["kills_itself"][1] == block + "the process running your blocks was killed (SIGSEGV)"
    assert warm_s < 60  # the hanging task was killed at its limit, the others went on
    assert (tmp_path / "warm" / "gradebook.csv").read_text() == (tmp_path / "cold" / "gradebook.csv").read_text()


def test_a_memory_hog_fails_alike_warm_and_cold(cli, tmp_path, monkeypatch):
    sheet = tmp_path / "warm.yaml"
    sheet.write_text(SHEET)
    root = klass(tmp_path / "class", HOG)
    monkeypatch.setenv("QCARLAB_BLOCK_TIMEOUT_S", "60")
    warm = graded(cli, sheet, root, tmp_path / "warm", timeout="90")
    monkeypatch.setenv("QCARLAB_GRADE_COLD", "1")
    cold = graded(cli, sheet, root, tmp_path / "cold", timeout="90")
    assert warm == cold
    assert warm["good"][0] and not warm["hogs_memory"][0]
    assert "ran out of memory" in warm["hogs_memory"][1] and "the limit is 1024 MB" in warm["hogs_memory"][1], \
        warm["hogs_memory"]  # (the cgroup killed it, or, without one, MemoryError under its address-space limit)


def test_one_task_cannot_change_the_next_ones_start(tmp_path):
    """The zygote's state is every task's start: a task that rewrites qcarlab leaves the next alone."""
    from qcarlab.grading.runner import task_env
    from qcarlab.grading.warm import WarmStart

    warm = WarmStart.start(task_env())
    assert warm is not None
    try:
        seen = []
        for k in range(2):
            work = tmp_path / f"t{k}"
            work.mkdir()
            script = work / "spec.json"
            # a block task whose 'student file' rewrites a qcarlab function and reports what it found
            student = work / "basic_speed_estimation.py"
            student.write_text("import os, qcarlab.control.speed as s\n"
                               "FOUND = getattr(s, 'MARK', None)\ns.MARK = os.getpid()\n\n"
                               "def basic_speed_estimation(counts_per_s):\n    return 0.0 if FOUND is None else 1.0\n")
            script.write_text(json.dumps({"kind": "block", "limits": {"timeout": 30, "memory_mb": 2048,
                                                                        "output_mb": 10},
                                          "results": str(work / "cases.jsonl"), "lab": "io-test",
                                          "block": "basic_speed_estimation", "file": str(student),
                                          "cases": [{"args": [1.0], "calls": []}]}))
            rc, timed_out = warm.run(script, work, work / "out.txt", work / "err.txt", {}, 30.0)
            assert (rc, timed_out) == (0, False), (work / "err.txt").read_text()
            seen.append(json.loads((work / "cases.jsonl").read_text().splitlines()[0])["value"])
        assert seen == [0.0, 0.0]
    finally:
        warm.close()
    assert warm.proc.returncode == 0 and not warm.folder.exists()
