"""Helpers for the car-side server's tests: the strict fake of Quanser's API, the car's Pythons
(3.6 and 3.8, found or skipped), and starting the server as a user would."""

from __future__ import annotations

import glob
import json
import os
import re
import select
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
FAKE = TESTS / "fake_quanser"
SERVER = REPO / "qcarlab" / "onboard" / "car_server.py"
SELFCHECK = TESTS / "onboard_selfcheck.py"


@pytest.fixture
def fake_quanser(monkeypatch):
    """Quanser's API replaced by the strict fake (a QCar 1 unless ``reset(car=2)``); yields its state module."""
    for name in list(sys.modules):
        if name == "quanser" or name.startswith("quanser."):
            monkeypatch.delitem(sys.modules, name)
    monkeypatch.syspath_prepend(str(FAKE))
    from quanser import _fake

    _fake.reset(car=1, watchdog=1, sensors=["lidar", "rgbd", "csi"], lidar_script=["block", "scan", "none", "scan"],
                journal="")
    yield _fake
    for name in list(sys.modules):
        if name == "quanser" or name.startswith("quanser."):
            del sys.modules[name]


# --- the car's Pythons -----------------------------------------------------------------------------
def _version_of(python: str) -> tuple[int, int] | None:
    try:
        out = subprocess.run([python, "-c", "import sys; print('%d.%d' % sys.version_info[:2])"],
                             capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired):
        return None
    m = re.fullmatch(r"(\d+)\.(\d+)\s*", out.stdout or "")
    return (int(m[1]), int(m[2])) if out.returncode == 0 and m else None


_FOUND: dict[tuple[str, bool], str | None] = {}


def car_python(version: str, numpy: bool = False) -> str | None:
    """A Python ``version`` ("3.6" or "3.8") interpreter, with NumPy if asked, or None.

    Looked for in QCARLAB_PY36 / QCARLAB_PY38, the repository's .venv-py36 / .venv-py38 (which
    .ci/run makes), pythonX.Y on PATH, and pyenv's versions."""
    key = (version, numpy)
    if key in _FOUND:
        return _FOUND[key]
    tag = version.replace(".", "")
    candidates = [os.environ.get(f"QCARLAB_PY{tag}", ""), str(REPO / f".venv-py{tag}" / "bin" / "python")]
    candidates.append(shutil.which(f"python{version}") or "")
    root = os.environ.get("PYENV_ROOT", os.path.expanduser("~/.pyenv"))
    candidates += sorted(glob.glob(os.path.join(root, "versions", f"{version}.*", "bin", "python")))
    want = tuple(int(x) for x in version.split("."))
    found = None
    for c in candidates:
        if not c or not os.path.exists(c) or _version_of(c) != want:
            continue
        if numpy and subprocess.run([c, "-c", "import numpy"], capture_output=True, timeout=30).returncode != 0:
            continue
        found = c
        break
    _FOUND[key] = found
    return found


def need_python(version: str, numpy: bool = False) -> str:
    python = car_python(version, numpy)
    if python is None:
        what = f"Python {version}" + (" with NumPy" if numpy else "")
        pytest.skip(f"{what} is not on this machine (.ci/run makes .venv-py{version.replace('.', '')})")
    return python


# --- running the server as a user would ------------------------------------------------------------
_HANGUP = "import os, signal, sys; signal.signal(signal.SIGHUP, signal.{}); os.execv(sys.argv[1], sys.argv[1:])"


class Served:
    """``python car_server.py ARGS`` in a subprocess; ``uri`` from its "serving ... on tcp://" line."""

    def __init__(self, python: str, *args: str, env: dict | None = None, script: Path | None = SERVER,
                 cwd: Path | None = None, hangup: str = "default"):
        full_env = dict(os.environ)
        full_env.pop("QCARLAB_TOKEN", None)
        full_env.update(env or {})
        argv = [python, str(script), *args] if script is not None else [python, *args]
        # the server's SIGHUP as a login shell leaves it ("default"), or as nohup does ("ignore"),
        # whatever the test run's own (under nohup every child would start with it ignored)
        argv = [python, "-c", _HANGUP.format("SIG_DFL" if hangup == "default" else "SIG_IGN"), *argv]
        self._err = tempfile.TemporaryFile(mode="w+")  # a file, not a pipe: a chatty server never blocks on it
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=self._err,
                                     text=True, env=full_env, cwd=str(cwd or REPO))
        self.line = ""
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:
            ready, _, _ = select.select([self.proc.stdout], [], [], 0.2)
            if ready:
                self.line = self.proc.stdout.readline()
                break
            if self.proc.poll() is not None:
                break
        m = re.search(r"tcp://([0-9.]+):([0-9]+)", self.line)
        if not m:
            err = self.stop()[1]
            raise AssertionError(f"the server did not start: {self.line!r} {err[-2000:]!r}")
        self.host, self.port = m[1], int(m[2])
        self.uri = f"tcp://{self.host}:{self.port}"

    @property
    def address(self) -> tuple[str, int]:
        return self.host, self.port

    def stop(self, sig: int | None = None, timeout: float = 10.0) -> tuple[int, str, str]:
        """Signal the server (SIGTERM by default), wait; returns (exit code, rest of stdout, stderr)."""
        import signal

        if self.proc.poll() is None:
            self.proc.send_signal(sig or signal.SIGTERM)
        try:
            out, _ = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        return self.proc.returncode, out, self.stderr

    @property
    def stderr(self) -> str:
        self._err.flush()
        self._err.seek(0)
        return self._err.read()

    def __enter__(self) -> Served:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc.poll() is None:
            self.stop()


def journal(path: Path) -> list[dict]:
    """The fake board's events, as the server's process wrote them."""
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def fake_env(car: int, journal_path: Path, **more: str) -> dict[str, str]:
    env = {"PYTHONPATH": str(FAKE), "QCARLAB_FAKE_CAR": str(car), "QCARLAB_FAKE_JOURNAL": str(journal_path)}
    env.update(more)
    return env
