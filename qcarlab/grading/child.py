"""The process a graded task runs in: ``python -m qcarlab.grading.child SPEC.json``.

The grader (:mod:`qcarlab.grading.runner`) starts one of these per task, in a fresh folder, with
no shell. It sets the task's limits (:mod:`qcarlab.grading.limits`) on itself first, then runs,
depending on ``SPEC["kind"]``:

- ``scenario``: the lab command ``SPEC["argv"]`` exactly as ``qcarlab ...`` would, in this process
  (the student's blocks come in through ``--block``). The student's ``params.yaml`` is cut to its
  ``lab:`` section first (the tunables), so a submission cannot change the car's physics. The
  command writes its results to ``$QCARLAB_RESULTS``.
- ``block``: the student's block ``SPEC["block"]`` from ``SPEC["file"]``, called on each case's
  inputs through :class:`qcarlab.blocks.StudentBlock` (so a wrong type, NaN, an exception or a
  ``sys.exit`` is one line naming the block); one JSON line per case is appended to
  ``SPEC["results"]`` as soon as it is known, so a case that hangs leaves the earlier ones graded.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any


def _jsonable(value: Any) -> Any:
    import numpy as np

    if isinstance(value, np.ndarray):
        return [_jsonable(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    text = repr(value)
    return text if len(text) <= 200 else text[:197] + "..."


def lab_only_params(source: Path, target: Path, argv: list[str] = ()) -> None:
    """Write ``target`` with only the ``lab:`` section of the student's parameter file, less the
    tunables the task's command sets itself (an option on the command line wins over the file,
    and a look-ahead sweep refuses a file that sets the look-ahead)."""
    import yaml

    from qcarlab.errors import InputError
    from qcarlab.yamlio import load_yaml

    data = load_yaml(source, "parameter file")
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise InputError(f"{source.name}: expected a mapping with a lab: section")
    lab = data.get("lab") or {}
    if not isinstance(lab, dict):
        raise InputError(f"{source.name}: lab: expected a mapping of tunable: value")
    given = {w.split("=", 1)[0] for w in argv if w.startswith("--")}
    lab = {k: v for k, v in lab.items() if "--" + str(k).replace("_", "-") not in given}
    target.write_text(yaml.safe_dump({"lab": lab}, sort_keys=False), encoding="utf-8")


def run_scenario(spec: dict[str, Any]) -> None:
    from qcarlab.cli import main
    from qcarlab.errors import QcarlabError

    argv = list(spec["argv"])
    if spec.get("params"):
        try:
            lab_only_params(Path(spec["params"]), Path("grader-params.yaml"), argv)
        except QcarlabError as exc:
            sys.stderr.write(f"error: {exc}\n")
            sys.exit(2)
        argv += ["--params", "grader-params.yaml"]
    main(argv)


def run_block(spec: dict[str, Any]) -> None:
    from qcarlab.blocks import resolve_student_blocks
    from qcarlab.errors import QcarlabError
    from qcarlab.experiments.labs import find_lab
    from qcarlab.grading.checks import expand_args

    lab = find_lab(spec["lab"])
    specs = {b.name: b for b in lab.blocks}
    name = spec["block"]
    out = open(spec["results"], "a", encoding="utf-8")  # noqa: SIM115 - kept open for the whole run

    def put(item: dict[str, Any]) -> None:
        out.write(json.dumps(item) + "\n")
        out.flush()

    try:
        block = resolve_student_blocks(specs, lab.command, block=[f"{name}={spec['file']}:{name}"])[name]
    except QcarlabError as exc:
        put({"load_error": _one_line(str(exc)), "detail": str(exc)})
        return
    for case in spec["cases"]:
        try:
            block.start()  # a class: a fresh instance (and reset) per case
            calls = case.get("calls") or [case["args"]]
            value = None
            for args in calls:
                value = block(*expand_args(args))
            put({"value": _jsonable(value)})
        except QcarlabError as exc:
            put({"error": _one_line(str(exc)), "detail": str(exc)})


def _one_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1].strip() if lines else text.strip()


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    spec = json.loads(Path(args[0]).read_text(encoding="utf-8"))
    from qcarlab.grading.limits import Limits, apply

    apply(Limits(**spec["limits"]))
    if spec["kind"] == "scenario":
        run_scenario(spec)
    else:
        run_block(spec)


if __name__ == "__main__":
    main()
