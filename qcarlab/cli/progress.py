"""A progress bar on the terminal for any run longer than a few seconds (rich).

Every lab command's run goes through the one control loop (:func:`qcarlab.experiments.loop.run_loop`),
which tells a tracker the run's time after each tick when the CLI has set one
(:data:`~qcarlab.experiments.loop.PROGRESS`). The bar (on stderr, erased when the run ends) shows
the run's time against its length, the time taken and the time left. It appears only once a run
has taken :data:`AFTER_S` seconds (``QCARLAB_PROGRESS_AFTER`` overrides it), so short runs print
nothing new; and never under ``--json``, when stdout or stderr is not a terminal, in CI (``CI`` set,
as GitHub, GitLab and most CI systems set it) or on a dumb terminal; nor beside a command's own
live view (``keyboard-drive``, ``io-test``'s table, ``lidar-scan --watch``) or ``--trials``' lines.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from typing import Any

AFTER_S = 2.0  #: a run shows its bar once it has taken this long (wall clock)
REFRESH_S = 0.1  #: the bar is redrawn at most this often


def wanted(quiet: bool = False) -> bool:
    """Whether this process may show a progress bar: not ``quiet`` (--json), a terminal on both
    stdout and stderr, not in CI, not a dumb terminal."""
    if quiet or os.environ.get("CI", "").lower() not in ("", "0", "false", "no"):
        return False
    if os.environ.get("TERM", "") == "dumb":
        return False
    try:
        return sys.stdout.isatty() and sys.stderr.isatty()
    except (AttributeError, ValueError):  # closed or replaced streams
        return False


def _after() -> float:
    try:
        return max(0.0, float(os.environ.get("QCARLAB_PROGRESS_AFTER", AFTER_S)))
    except ValueError:
        return AFTER_S


class Tracker:
    """One run's bar: called with the run's time after each tick; cheap: a clock read every 8 ticks, and redrawn at most every :data:`REFRESH_S` s."""

    def __init__(self, label: str, total_s: float, after_s: float):
        self.label, self.total = label, total_s
        self.start = time.monotonic()
        self.show_at = self.start + after_s
        self.next = self.show_at
        self.k = 0
        self.bar: Any = None
        self.task: Any = None

    def __call__(self, t: float) -> None:
        self.k += 1
        if self.k & 7:
            return
        now = time.monotonic()
        if now < self.next:
            return
        self.next = now + REFRESH_S
        if self.bar is None:
            self._open()
        self.bar.update(self.task, completed=min(t, self.total))
        self.bar.refresh()

    def _open(self) -> None:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        from qcarlab.cli.common import stderr

        self.bar = Progress(TextColumn(self.label), BarColumn(), TextColumn("{task.completed:.1f} / {task.total:.1f} s"),
                            TimeElapsedColumn(), TextColumn("elapsed,"), TimeRemainingColumn(), TextColumn("left"),
                            console=stderr, transient=True, auto_refresh=False)
        self.bar.start()
        self.task = self.bar.add_task(self.label, total=self.total)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None


@contextlib.contextmanager
def progress_bars(label: str, quiet: bool = False):
    """Within the block, each run of the control loop longer than a few seconds shows a bar
    labelled ``label`` on a terminal, unless ``quiet`` (--json; see the module's doc for when else
    it stays quiet)."""
    from qcarlab.experiments.loop import PROGRESS

    if not wanted(quiet):
        yield
        return
    after = _after()
    token = PROGRESS.set(lambda total_s: Tracker(label, total_s, after))
    try:
        yield
    finally:
        PROGRESS.reset(token)


__all__ = ["AFTER_S", "Tracker", "progress_bars", "wanted"]
