"""What every benchmark prints with its figures: the machine and how busy it was."""

from __future__ import annotations

import os
import time
import platform
from pathlib import Path

import numpy as np


def machine() -> str:
    """CPU, cores, Python, numpy, OpenCV and numba versions, on one line."""
    cpu = platform.processor() or ""
    if not cpu:
        try:
            for line in Path("/proc/cpuinfo").read_text().splitlines():
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
        except OSError:
            pass
    try:
        import numba

        nb = f"numba {numba.__version__}"
    except ImportError:
        nb = "numba not installed (pure Python kernels)"
    import cv2

    return (
        f"{cpu or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"numpy {np.__version__}, OpenCV {cv2.__version__}, {nb}"
    )


def load_note() -> str:
    """The load average (1, 5, 15 min) against the core count: above the core count, other
    processes were competing for the CPU and the figures are low."""
    try:
        a, b, c = os.getloadavg()
    except OSError:
        return "load average unknown"
    return f"load average {a:.2f} / {b:.2f} / {c:.2f} (1 / 5 / 15 min) on {os.cpu_count()} cores"


def one_core() -> str:
    """Pin this process to one core (the targets are per core); returns which, or why not."""
    try:
        cores = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cores[-1]})
        return f"pinned to core {cores[-1]}"
    except (AttributeError, OSError):
        return "not pinned (no sched_setaffinity here)"


class Timer:
    """Wall time and this process's CPU time (all threads) of a stretch of work.

    On a machine shared with other jobs the wall time counts the time others held the core;
    the CPU time counts only what this process used (cache sharing still slows it a little).
    The benchmarks print both and judge the targets on the CPU time, "per core-second".
    """

    __slots__ = ("wall", "cpu", "_w", "_c")

    def __init__(self) -> None:
        self.wall = 0.0
        self.cpu = 0.0

    def __enter__(self) -> "Timer":
        self._w = time.perf_counter()
        self._c = time.process_time()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall += time.perf_counter() - self._w
        self.cpu += time.process_time() - self._c
