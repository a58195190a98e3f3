"""What every experiment returns: metrics for ``results.json`` and ``--json``, logs, figures."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from qcarlab.record import IN_PROGRESS, prepare_out_dir, write_csv, write_json

#: Whether :meth:`Result.save` writes the CSV logs. A graded task's process turns it off
#: (:mod:`qcarlab.grading.child`): the grader keeps a run's figures, reads its results from
#: ``$QCARLAB_RESULTS`` and deletes the rest (p4-lookahead's logs were a quarter of its saving).
WRITE_LOGS = True


@dataclass
class Result:
    """A run's outcome. ``metrics`` is the JSON object; ``logs`` map a CSV file name to columns;
    ``figures`` map a file name to a function that draws it to that path (run only with --out)."""

    name: str
    metrics: dict[str, Any]
    logs: dict[str, dict[str, Any]] = field(default_factory=dict)
    figures: dict[str, Callable[[Path], None]] = field(default_factory=dict)
    data: dict[str, Any] = field(default_factory=dict)  # in-memory artefacts (frames, scans), not saved

    def save(self, out: str | Path) -> list[Path]:
        """Write the CSV logs (unless :data:`WRITE_LOGS` is off), the figures and, last, results.json
        into ``out``; return the paths.

        Each file is written atomically; results.json comes last, so when it is there the logs it
        describes are complete (a run killed while saving leaves no results.json claiming them).
        """
        folder = prepare_out_dir(out)
        stale = folder / "results.json"
        if stale.exists():
            stale.unlink()  # a results.json of an earlier run must not describe this run's logs
        written = []
        for filename, columns in self.logs.items() if WRITE_LOGS else ():
            written.append(write_csv(folder / filename, columns))
        for filename, draw in self.figures.items():
            draw(folder / filename)
            written.append(folder / filename)
        written.append(write_json(folder / "results.json", self.metrics))
        (folder / IN_PROGRESS).unlink(missing_ok=True)  # saved: the folder is this run's
        return written


def save_figure(file: Any, fig: Any) -> None:
    """Write a matplotlib Figure of :mod:`qcarlab.plots` to ``file`` (a figure's draw function for
    ``Result.figures``); a file that cannot be written is one line (InputError)."""
    from qcarlab import plots
    from qcarlab.errors import InputError

    try:
        plots.save_figure(fig, file)
    except OSError as exc:
        raise InputError(f"cannot write {file} ({exc.strerror or exc})") from None
