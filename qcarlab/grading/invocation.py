"""What a run records about how it was made, and the check that a results file is the task's own.

Every lab command's results carry an ``invocation`` (added by the CLI's ``emit`` through
:func:`qcarlab.cli.invocation.record_invocation`)::

    "invocation": {"command": "path-follow", "params": {"path": "circle", "speed": 0.5, ...},
                   "files": {"params": {"path": "params.yaml", "sha256": "..."},
                             "use": [{"path": "mylab/pure_pursuit.py", "sha256": "..."}], ...},
                   "qcarlab": "0.1.0"}

``params`` are the command's parsed options and arguments (defaults included), so option order
and spelling do not matter. :func:`verify` accepts a results file for a task only when its
command and every option that shapes the run equal the task's (``--out``, ``--json``, ``--car``,
``--realtime``, ``--token``, ``--debug``, the recording options, the car a sheet's ``{car}`` stands
for and the student's ``--use``/``--block``/``--params`` may differ; the files are checked by hash
against the submission when one is given). A token is recorded as ``(given)``, never itself. So a ``p1-line`` results
file copied into ``p3-butterfly/`` is refused, naming the first option that differs.

This guards against mistakes and copied runs, not against a student who edits the JSON by hand:
the grader runs the tasks itself for that (``qcarlab grade SHEET --submission DIR``).
"""

from __future__ import annotations

import enum
import hashlib
import math
from pathlib import Path
from typing import Any

# options that do not change what a run measures (or are checked through the files' hashes)
FREE = frozenset({"out", "json_out", "debug", "car", "token", "realtime", "use", "block", "params", "frames",
                  "record", "record_exact", "live", "live_port", "topics"})  # (recording: issue 13)
CAR = "{car}"  # a sheet's placeholder for the car (qcarlab.grading.sheet.CAR): any car's run is the task's


def jsonable(value: Any) -> Any:
    if isinstance(value, enum.Enum):
        return jsonable(value.value)
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


def sha256_file(path: str | Path, limit: int = 16 * 2**20) -> str | None:
    """The SHA-256 of a file (of its first ``limit`` bytes); None when it cannot be read."""
    try:
        with open(path, "rb") as f:
            return hashlib.sha256(f.read(limit)).hexdigest()
    except OSError:
        return None


def files_of(params: dict[str, Any]) -> dict[str, Any]:
    """The files a run read (``--params``, ``--use`` files or folders, ``--block`` files) with their hashes."""
    out: dict[str, Any] = {}
    if params.get("params"):
        p = Path(params["params"])
        out["params"] = {"path": str(p), "sha256": sha256_file(p)}
    used = []
    for item in params.get("use") or []:
        p = Path(item)
        files = sorted(p.glob("*.py")) if p.is_dir() else [p]
        used += [{"path": str(f), "sha256": sha256_file(f)} for f in files]
    for text in params.get("block") or []:
        from qcarlab.blocks import parse_block_option

        try:
            _, f, _ = parse_block_option(text)
        except ValueError:
            continue
        used.append({"path": str(f), "sha256": sha256_file(f)})
    if used:
        out["use"] = used
    return out


def verify(results: dict[str, Any], name: str, want: dict[str, Any],
           submission_files: dict[str, bytes] | None = None, labels: dict[str, str] | None = None) -> str | None:
    """None when ``results`` were made by the task's command, else the one-line reason. ``name``
    and ``want`` are the task's command and its parsed parameters (``qcarlab.cli.invocation``).

    With the submission's files (name -> bytes), the run's ``--params`` file and the files of its
    ``--use``/``--block`` must be the submission's (same content, matched by file name)."""
    inv = results.get("invocation") if isinstance(results, dict) else None
    if not isinstance(inv, dict) or not isinstance(inv.get("params"), dict):
        return "the results do not record the command that made them (run the task's command with this qcarlab)"
    if inv.get("command") != name:
        return f"the results are of 'qcarlab {inv.get('command')}', not of the task's 'qcarlab {name}'"
    got = inv["params"]
    for key in [*want, *sorted(set(got) - set(want))]:  # the command's own order: its arguments first
        if key in FREE or want.get(key) == CAR:  # e.g. ping {car}: the run names the car it pinged
            continue
        if jsonable(want.get(key)) != got.get(key):
            option = (labels or {}).get(key) or "--" + key.replace("_", "-")
            return (f"the results were made with {option} {_show(got.get(key))}, the task's command has "
                    f"{_show(want.get(key))}")
    if submission_files is not None:
        files = inv.get("files") or {}
        mine = {Path(n).name: hashlib.sha256(b).hexdigest() for n, b in submission_files.items()}
        rec = files.get("params")
        if "params.yaml" in mine and (rec is None or rec.get("sha256") != mine["params.yaml"]):
            return ("the results were not made with the submission's params.yaml"
                    + (f" (made with {rec.get('path')})" if rec else " (no --params)"))
        for used in files.get("use") or []:
            base = Path(str(used.get("path"))).name
            if base in mine and used.get("sha256") != mine[base]:
                return f"the results were made with another {base} than the submission's"
    return None


def _show(value: Any) -> str:
    if value is None:
        return "(not given)"
    if isinstance(value, list):
        return ",".join(str(v) for v in value) or "(none)"
    return str(value)


__all__ = ["FREE", "files_of", "jsonable", "sha256_file", "verify"]
