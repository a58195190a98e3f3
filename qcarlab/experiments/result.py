"""What every experiment returns: metrics for ``results.json`` and ``--json``, logs, figures."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from qcarlab.record import prepare_out_dir, write_csv, write_json


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
        """Write results.json, the CSV logs and the figures into ``out``; return the paths."""
        folder = prepare_out_dir(out)
        written = [write_json(folder / "results.json", self.metrics)]
        for filename, columns in self.logs.items():
            written.append(write_csv(folder / filename, columns))
        for filename, draw in self.figures.items():
            draw(folder / filename)
            written.append(folder / filename)
        return written
