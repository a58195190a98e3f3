"""The lab process's heap settings (qcarlab.heap): set once, where glibc is, and harmless elsewhere."""

from __future__ import annotations

import subprocess
import sys

import pytest

from qcarlab import heap


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux")
def test_a_lab_keeps_its_frames_in_the_heap_once_it_runs():
    """After a lab's loop has run, a block of a frame's size is served from the heap (glibc's
    mmap threshold is fixed at 32 MB): no mapping of its own appears in /proc/self/maps."""
    code = (
        "import re, numpy as np\n"
        "from qcarlab.experiments.loop import run_loop\n"
        "from qcarlab.car.sim import SimCar\n"
        "from qcarlab.car.base import Command\n"
        "def maps():\n"
        "    return {l.split()[0] for l in open('/proc/self/maps') if len(l.split()) == 5}\n"
        "def grows():\n"
        "    before = maps(); a = np.ones(3_000_000, np.uint8); after = maps(); del a\n"
        "    return len(after - before) > 0\n"
        "first = grows()\n"
        "run_loop(SimCar(seed=0), lambda t, r: Command(0.0, 0.0), duration=0.02)\n"
        "from qcarlab import heap\n"
        "print(first, grows(), heap.keep_heap())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-800:]
    first, then, kept = out.stdout.split()
    if kept != "True":
        pytest.skip("not glibc: mallopt is not there")
    assert (first, then) == ("True", "False")


def test_keep_heap_is_set_once_and_says_so(monkeypatch):
    monkeypatch.setattr(heap, "_done", None)
    monkeypatch.setattr(heap.sys, "platform", "win32")
    assert heap.keep_heap() is False
    assert heap.keep_heap() is False  # once: not tried again
