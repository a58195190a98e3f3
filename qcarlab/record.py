"""Writing what a run produced: ``results.json``, CSV logs, into the ``--out`` folder.

JSON is written with sorted-free, stable key order and plain Python numbers, so the same run
gives byte-identical files (grades are reproducible). Every file is written atomically (a
temporary file in the same folder, then a rename), so a run killed while saving leaves either
the old file or the complete new one, never half a file; ``Result.save`` writes ``results.json``
last, so a ``results.json`` always describes logs that are complete.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import tempfile
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


def _umask() -> int:
    """This process's umask, read without changing it (Linux: /proc/self/status), else 022."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return 0o022


@contextlib.contextmanager
def atomic_file(path: Path, mode: str = "w", **kw: Any):
    """Open a temporary file beside ``path``; on success it replaces ``path`` in one rename."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # as open() would make it (mkstemp's is 0600)
        with os.fdopen(fd, mode, **kw) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


IN_PROGRESS = "run-in-progress.txt"  #: in a run's --out folder from its start until its results are saved


def mark_in_progress(out: str | Path, command: str) -> None:
    """Create ``out`` and put :data:`IN_PROGRESS` in it (what runs, since when, which process)."""
    import datetime

    folder = prepare_out_dir(out)
    text = (f"{command}\nstarted {datetime.datetime.now().isoformat(timespec='seconds')}, process {os.getpid()}\n"
            "While this file is here, the run has not saved its results: the files beside it are an earlier "
            "run's (or this run's, cut short).\n")
    try:
        with atomic_file(folder / IN_PROGRESS, "w", encoding="utf-8") as fh:
            fh.write(text)
    except OSError as exc:
        raise InputError(f"--out {folder}: cannot write there ({exc.strerror or exc})") from None


def inner_folder(base: Path, *parts: str) -> Path:
    """``base/parts...`` made as real folders: a symbolic link planted on the way is removed, never
    followed (``base`` itself is the user's choice and taken as it is)."""
    path = Path(base)
    path.mkdir(parents=True, exist_ok=True)
    for part in parts:
        path = path / part
        if path.is_symlink() or (path.exists() and not path.is_dir()):
            path.unlink()
        path.mkdir(exist_ok=True)
    return path


def write_bytes(path: Path, data: bytes) -> Path:
    """``data`` to ``path`` through :func:`atomic_file` (a symbolic link at ``path`` is replaced, not followed)."""
    with atomic_file(path, "wb") as fh:
        fh.write(data)
    return path


def write_json(path: Path, results: Mapping[str, Any]) -> Path:
    with atomic_file(path, "w", encoding="utf-8") as fh:
        fh.write(dumps(results) + "\n")
    return path


def write_csv(path: Path, columns: Mapping[str, Any]) -> Path:
    """Write equal-length columns as CSV with a header row; floats with full precision."""
    names = list(columns)
    arrays = [np.asarray(columns[n]) for n in names]
    lengths = {len(a) for a in arrays}
    if len(lengths) > 1:
        raise ValueError(f"columns of unequal length: {dict(zip(names, map(len, arrays)))}")
    with atomic_file(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(names)
        writer.writerows(zip(*(a.tolist() for a in arrays)))  # (csv writes a float as str(), its shortest repr)
    return path
