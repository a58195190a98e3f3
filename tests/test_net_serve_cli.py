"""``qcarlab serve`` as a user runs it: another process, then io-test and ping against it."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def start_serve(*args: str) -> tuple[subprocess.Popen, str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("QCARLAB_TOKEN", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "qcarlab", "serve", "--port", "0", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT,
    )
    line: list[str] = []
    reader = threading.Thread(target=lambda: line.append(proc.stdout.readline()))
    reader.start()
    reader.join(30)
    if not line or "serving" not in line[0]:
        proc.kill()
        pytest.fail(f"serve did not start: {line} {proc.stderr.read() if proc.poll() is not None else ''}")
    uri = re.search(r"tcp://[\d.]+:\d+", line[0]).group(0)
    return proc, uri


def stop_serve(proc: subprocess.Popen) -> tuple[int, str, str]:
    proc.send_signal(signal.SIGTERM)
    try:
        out, err = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail("serve did not stop on SIGTERM")
    return proc.returncode, out, err


def test_serve_lockstep_then_io_test_and_ping(cli):
    proc, uri = start_serve("--lockstep", "--seed", "3", "--on-floor")
    try:
        args = ("io-test", "--on-floor", "--throttle", "0.1", "--duration", "0.5", "--seed", "3", "--json")
        code, out, err = cli(*args, "--car", uri)
        assert code == 0, err
        code_p, out_p, err_p = cli("ping", uri, "-c", "2", "-i", "0", "--json")
        assert code_p == 0, err_p
    finally:
        code_s, out_s, err_s = stop_serve(proc)
    assert code_s == 0 and "stopped serving (SIGTERM); the car is stopped" in out_s, err_s
    assert "Traceback" not in err_s and "connected as control" in err_s and "car stopped" in err_s
    tcp = json.loads(out)
    tcp.pop("car")
    tcp.pop("invocation")  # the command that made it: --car differs
    local = json.loads(cli(*args)[1])
    local.pop("car")
    local.pop("invocation")
    assert local.pop("realism") == "lab"  # the served car is lab too (serve's default); a tcp result cannot know it
    assert tcp == local  # same seed, same numbers, across processes
    ping = json.loads(out_p)
    assert ping["backend"] == "sim" and ping["lockstep"] is True and ping["battery_v"] > 10


def test_every_stop_signal_stops_the_car_and_says_so():
    """SIGHUP is what serve gets when the ssh session that started it on the car closes; SIGQUIT is
    Ctrl-backslash. Each one stops the car (a controller is driving), says so, and exits 0."""
    from qcarlab.car.tcp import TcpCar

    names = ("SIGHUP", "SIGQUIT", "SIGTERM", "SIGINT")
    started = [start_serve("--watchdog", "5") for _ in names]  # a long watchdog: only the signal stops the car
    results = {}
    try:
        for (proc, uri), name in zip(started, names):
            host, port = uri[len("tcp://"):].rsplit(":", 1)
            ctl = TcpCar(host, int(port), timeout=5.0)
            assert ctl.write(0.2, 0.0).throttle == pytest.approx(0.2)
            proc.send_signal(getattr(signal, name))
            try:
                out, err = proc.communicate(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                out, err = proc.communicate()
                pytest.fail(f"serve did not stop on {name}")
            results[name] = (proc.returncode, out, err)
            ctl._sock = None  # the server is gone; nothing to say bye to
            ctl.closed = True
    finally:
        for proc, _ in started:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    for name, (code, out, err) in results.items():
        assert code == 0, (name, err)
        assert f"stopped serving ({name}); the car is stopped" in out, (name, out, err)
        assert "(control) disconnected: server stopping; car stopped" in err, (name, err)
        assert "Traceback" not in err, (name, err)
