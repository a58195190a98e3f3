"""An interrupted run (Ctrl-C, SIGTERM) stops the car and still saves what it has (issue 16 item 6)."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from qcarlab.experiments.result import Result


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_mid_run_saves_the_run_so_far_and_exits_130(tmp_path, sig):
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    child = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
             "from qcarlab.cli import main; print('ready', flush=True); main()")
    proc = subprocess.Popen([sys.executable, "-c", child,
                             "io-test", "--realtime", "--on-floor", "--duration", "30", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stdout.readline().strip() == "ready"  # imported (a cold machine compiles first)
    time.sleep(2.0)  # the run is going
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    assert "interrupted; the car was stopped" in stderr and "saved to" in stderr
    m = json.loads((out / "results.json").read_text())
    assert m["interrupted"] is True and 0.5 < m["duration_s"] < 29.0
    with (out / "log.csv").open() as fh:
        rows = list(csv.reader(fh))
    assert len(rows) - 1 == m["loop"]["ticks"] > 10  # the log holds every tick the results describe


def test_results_json_is_written_last_and_atomically(tmp_path):
    order = []

    def figure(path: Path) -> None:
        order.append(("figure", (tmp_path / "results.json").exists()))
        path.write_text("png")

    (tmp_path / "results.json").write_text('{"old": true}')
    Result("x", {"a": 1}, logs={"log.csv": {"t": [0.0, 0.1]}}, figures={"f.png": figure}).save(tmp_path)
    assert order == [("figure", False)]  # an old results.json never describes new logs
    assert json.loads((tmp_path / "results.json").read_text()) == {"a": 1}
    assert not list(tmp_path.glob(".*.part"))  # no temporary files left behind
