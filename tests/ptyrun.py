"""Run ``python -m qcarlab ARGS`` on a pseudo-terminal, as a user at a terminal would."""

from __future__ import annotations

import fcntl
import os
import re
import select
import struct
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

ANSI = re.compile(r"\x1b(\[[0-9;?]*[ -/]*[@-~]|\][^\x07\x1b]*(\x07|\x1b\\)|[()][A-Z0-9]|[=>78])")


class PtyRun:
    """``python -m qcarlab ARGS`` on a fresh pseudo-terminal (110 x 30), read continuously."""

    def __init__(self, *args: str):
        self.master, self.slave = os.openpty()
        fcntl.ioctl(self.slave, termios.TIOCSWINSZ, struct.pack("HHHH", 30, 110, 0, 0))
        self.before = termios.tcgetattr(self.slave)
        env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES", "QCARLAB_DEBUG")}
        env["TERM"] = "xterm-256color"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "qcarlab", *args],
            stdin=self.slave, stdout=self.slave, stderr=self.slave, env=env, cwd=REPO, start_new_session=True,
        )
        self.out = bytearray()
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.05)
            if ready:
                try:
                    data = os.read(self.master, 65536)
                except OSError:
                    return
                if not data:
                    return
                self.out.extend(data)

    @property
    def text(self) -> str:
        return ANSI.sub("", bytes(self.out).decode("utf-8", "replace")).replace("\r", "")

    # generous: a CLI's start (numpy, OpenCV, the simulator's first calls) takes over 8 s on a CI
    # machine whose both cores are busy; these bounds catch a hang, they do not time the start
    def wait_for(self, pattern: str, timeout: float = 30.0) -> None:
        end = time.monotonic() + timeout
        while pattern not in self.text:
            if self.proc.poll() is not None or time.monotonic() > end:
                self.close()
                pytest.fail(f"never saw {pattern!r} (exit {self.proc.returncode}); output:\n{self.text[-2000:]}")
            time.sleep(0.02)

    def send(self, keys: bytes, then: float = 0.0) -> None:
        os.write(self.master, keys)
        time.sleep(then)

    def finish(self, timeout: float = 30.0) -> int:
        try:
            rc = self.proc.wait(timeout)
        finally:
            self.close()
        return rc

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)
        time.sleep(0.05)  # the last output
        self._stop.set()
        self._reader.join(1.0)
        self.after = termios.tcgetattr(self.slave)
        os.close(self.master)
        os.close(self.slave)


