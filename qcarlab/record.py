"""Writing what a run produced: ``results.json``, CSV logs, into the ``--out`` folder.

JSON is written with sorted-free, stable key order and plain Python numbers, so the same run
gives byte-identical files (grades are reproducible).
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from qcarlab.errors import InputError


def to_jsonable(value: Any) -> Any:
    """Convert numpy scalars/arrays, tuples and non-finite floats into plain JSON values."""
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return [to_jsonable(v) for v in value.tolist()]
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (float, np.floating)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, Path):
        return str(value)
    return value


def dumps(results: Mapping[str, Any]) -> str:
    return json.dumps(to_jsonable(results), indent=2)


def prepare_out_dir(out: str | Path) -> Path:
    """Create the output folder (and parents); refuse a path that is a file."""
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise InputError(f"--out {path}: exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out {path}: cannot create folder ({exc.strerror or exc})") from None
    return path


def write_json(path: Path, results: Mapping[str, Any]) -> Path:
    path.write_text(dumps(results) + "\n", encoding="utf-8")
    return path


def write_csv(path: Path, columns: Mapping[str, Any]) -> Path:
    """Write equal-length columns as CSV with a header row; floats with full precision."""
    names = list(columns)
    arrays = [np.asarray(columns[n]) for n in names]
    lengths = {len(a) for a in arrays}
    if len(lengths) > 1:
        raise ValueError(f"columns of unequal length: {dict(zip(names, map(len, arrays)))}")
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(names)
        for row in zip(*(a.tolist() for a in arrays)):
            writer.writerow([repr(v) if isinstance(v, float) else v for v in row])
    return path
