"""Shared test helpers: run the CLI in-process, find ../shared/data."""

from __future__ import annotations

import json
import logging
import os
import signal
from pathlib import Path

import pytest

from qcarlab.cli import main

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

# Every ``qcarlab`` process a test starts runs cold: no test starts (or uses) a warm server
# (qcarlab.warm) unless it asks for one itself (tests/test_warm.py).
os.environ["QCARLAB_WARM"] = "0"

# A line a server thread logs after its test ended (a client's disconnect) goes nowhere instead of
# into the progress dots: the root logger's handler keeps logging's last resort from printing it.
logging.getLogger().addHandler(logging.NullHandler())


def pytest_configure(config):
    """In a fresh clone numba's cache is empty: the simulator's kernels are compiled once, here,
    before the test processes start (each would otherwise compile the ones its tests use, the
    same kernels on every worker at once, and a warm server's start compiles them all)."""
    if hasattr(config, "workerinput") or config.option.collectonly:
        return  # (an xdist worker: the controller did it)
    import subprocess
    import sys

    import qcarlab

    here = str(Path(qcarlab.__file__).resolve().parents[1])  # the qcarlab these tests import: its kernels
    try:
        subprocess.run([sys.executable, "-m", "qcarlab.precompile", "--if-needed"], stdin=subprocess.DEVNULL,
                       capture_output=True, timeout=900, check=False,
                       env={**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH")) if p)})
    except subprocess.TimeoutExpired:  # the tests compile what they use themselves, as before
        pass


@pytest.fixture(autouse=True)
def _cli_logging_ends_with_the_test():
    """``main`` gives the ``qcarlab`` logger a handler that prints to the terminal's stderr; after
    the test it is taken off again, so a thread still running (a server saying a client left)
    does not print between later tests' dots. Records propagate to pytest's capture again."""
    yield
    logger = logging.getLogger("qcarlab")
    for handler in [h for h in logger.handlers if type(h).__name__ == "_OneLineHandler"]:
        logger.removeHandler(handler)
    logger.propagate = True
    logger.setLevel(logging.NOTSET)


@pytest.fixture
def cli(capsys):
    """Run ``qcarlab ARGS`` in-process; returns (exit code, stdout, stderr)."""

    def run(*args: str) -> tuple[int, str, str]:
        with pytest.raises(SystemExit) as exc:
            main([str(a) for a in args])
        out, err = capsys.readouterr()
        return exc.value.code, out, err

    return run


@pytest.fixture
def cli_json(cli):
    """Run ``qcarlab ARGS --json`` and parse stdout; fails the test on a non-zero exit."""

    def run(*args: str) -> dict:
        code, out, err = cli(*args, "--json")
        assert code == 0, err
        return json.loads(out)

    return run


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not beside this checkout")
    return SHARED_DATA


@pytest.fixture
def netlog():
    """The lines the network server logs during a test (logger ``qcarlab.net``, INFO and up)."""
    lines: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record):
            lines.append(record.getMessage())

    handler, logger = Collect(), logging.getLogger("qcarlab.net")
    old = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    yield lines
    logger.removeHandler(handler)
    logger.setLevel(old)


def _children(pid: int) -> set[int]:
    """The processes ``pid`` started, and theirs (Linux: /proc/PID/task/TID/children), alive or
    zombie; empty where /proc does not say."""
    found: set[int] = set()
    todo = [pid]
    while todo:
        parent = todo.pop()
        try:
            tasks = os.listdir(f"/proc/{parent}/task")
        except OSError:
            continue
        for tid in tasks:
            try:
                kids = Path(f"/proc/{parent}/task/{tid}/children").read_text().split()
            except OSError:
                continue
            for kid in map(int, kids):
                if kid not in found:
                    found.add(kid)
                    todo.append(kid)
    return found


def _helper(pid: int) -> bool:
    """multiprocessing's process-wide helpers (resource tracker, fork server): they outlive a test
    by design and are restarted when gone, so they are left alone."""
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return True
    return b"multiprocessing.resource_tracker" in cmdline or b"multiprocessing.forkserver" in cmdline


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    """Every process a test body started and left running (a failed assert before its own stop, a
    forgotten server) is killed when the test ends, pass or fail, so no ``serve`` outlives it.
    Fixtures' processes (started before the body) are their teardown's business."""
    before = _children(os.getpid())
    yield
    left = [pid for pid in _children(os.getpid()) - before if not _helper(pid)]
    for pid in left:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    for pid in left:  # reap the direct children now (a Popen object reaps its own on its next poll)
        try:
            os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:
            pass
