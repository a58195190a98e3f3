"""An interrupted run (Ctrl-C, SIGTERM) stops the car and still saves what it has (issue 16 item 6)."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from qcarlab.experiments.result import Result


# The child says "running" once the run has simulated 1 s (a marker, not a sleep: at load 8 the start
# can take many seconds), then the test sends the signal.
_CHILD = """
import signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)
import qcarlab.cli.io_test as cmd
run = cmd.io_test

def marked(*args, **kwargs):
    said = []

    def tick(t, r, c, speed):
        if t >= 1.0 and not said:
            said.append(t)
            print("running", flush=True)

    return run(*args, **kwargs, on_tick=tick)

cmd.io_test = marked
from qcarlab.cli import main
main()
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_mid_run_saves_the_run_so_far_and_exits_130(tmp_path, sig):
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-c", _CHILD,
                             "io-test", "--realtime", "--on-floor", "--duration", "30", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout.readline().strip() == "running", proc.stderr.read() if proc.poll() is not None else ""
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, stderr
    assert f"interrupted; the car was stopped; the run so far was saved to {out}" in stderr
    m = json.loads((out / "results.json").read_text())
    assert m["interrupted"] is True and 1.0 <= m["duration_s"] < 29.0
    with (out / "log.csv").open() as fh:
        rows = list(csv.reader(fh))
    assert len(rows) - 1 == m["loop"]["ticks"] > 10  # the log holds every tick the results describe


@pytest.mark.parametrize("where", ["qcarlab.cli.io_test.parse_lamps", "qcarlab.cli.load_command"])
def test_a_ctrl_c_before_the_run_begins_says_so_and_exits_130(cli, monkeypatch, tmp_path, where):
    """A Ctrl-C while the command is loaded or set up (typer would return 130 without a word)."""
    import qcarlab.cli.io_test  # noqa: F401  (the module patched)

    def ctrl_c(*_args, **_kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(where, ctrl_c)
    code, out, err = cli("io-test", "--out", tmp_path / "run")
    assert code == 130
    assert err.strip().splitlines()[-1] == "qcarlab io-test: interrupted; the car was stopped"


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
