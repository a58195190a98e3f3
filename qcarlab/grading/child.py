"""The trusted process of a graded task: ``python -m qcarlab.grading.child SPEC.json``.

The grader (:mod:`qcarlab.grading.runner`) starts one of these per task, in a fresh folder, with
no shell. It is qcarlab's side of the task: the simulator, the lab's diagram, the referee and the
results writer run here, and **no student code ever does**. When the task has student code, it
first starts the student's own process (:mod:`qcarlab.sandbox`: confined when ``SPEC["sandbox"]``
is on), where the student's files are loaded and their blocks called; here they are remote blocks
whose every value is checked. Then it sets the task's limits on itself (:mod:`.limits`) and runs,
depending on ``SPEC["kind"]``:

- ``scenario``: the lab command ``SPEC["argv"]`` exactly as ``qcarlab ...`` would (the student's
  blocks come in through ``--block``). The student's ``params.yaml`` is cut to its ``lab:``
  section first (the tunables), so a submission cannot change the car's physics. The command
  writes its results to ``$QCARLAB_RESULTS``, a file of this task's folder, which the student's
  process cannot see; its ``--out`` (the grader's, for the figures) gets no CSV logs.
- ``block``: the student's block ``SPEC["block"]`` from ``SPEC["file"]``, called on each case's
  inputs through :class:`qcarlab.blocks.StudentBlock` (so a wrong type, NaN, an exception or a
  ``sys.exit`` is one line naming the block); one JSON line per case is appended to
  ``SPEC["results"]`` as soon as it is known, so a case that hangs leaves the earlier ones graded.

``sandbox.txt`` in the task's folder says how the student's process ran: ``sandboxed``, or
``not sandboxed: WHY``. The grader's own failure (the sandbox could not be set up) exits 75.
"""

from __future__ import annotations

import json
import math
import os
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
    # a choice left empty is graded by the tasks that use it (qcarlab.grading.grader); the others run with qcarlab's
    lab = {k: v for k, v in lab.items() if "--" + str(k).replace("_", "-") not in given and v is not None}
    target.write_text(yaml.safe_dump({"lab": lab}, sort_keys=False), encoding="utf-8")


def run_scenario(spec: dict[str, Any]) -> None:
    from qcarlab.cli import main
    from qcarlab.errors import QcarlabError
    from qcarlab.experiments import result

    result.WRITE_LOGS = False  # the grader keeps only the figures of --out (and reads $QCARLAB_RESULTS)

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
    from qcarlab.errors import GraderFault, QcarlabError
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
    except GraderFault:
        raise
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
        except GraderFault:
            raise
        except QcarlabError as exc:
            put({"error": _one_line(str(exc)), "detail": str(exc)})


def _one_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1].strip() if lines else text.strip()


def student_process(spec: dict[str, Any], limits: Any) -> Any:
    """The student's process for this task: confined when ``spec["sandbox"]`` is ``required``, or
    ``auto`` and this machine can (see :func:`qcarlab.sandbox.jail.probe`); None where there is no
    fork (Windows: the student's code then runs here, marked not sandboxed). Writes ``sandbox.txt``."""
    from qcarlab.errors import GraderFault
    from qcarlab.sandbox import jail
    from qcarlab.sandbox.client import BlockHost, HostPlan

    mode = spec.get("sandbox", "auto")
    why = jail.unavailable(mode)
    if why is not None and mode == "required":
        raise GraderFault(f"--sandbox required: {why}")
    if not hasattr(os, "fork"):  # Windows: the student's code runs in this process (and says so)
        Path("sandbox.txt").write_text(f"not sandboxed: {why}; the student's code ran in the task's own process",
                                       encoding="utf-8")
        return None
    Path("sandbox.txt").write_text("sandboxed" if why is None else f"not sandboxed: {why}", encoding="utf-8")
    import qcarlab.cli  # loaded before the fork (the student's process has it: a warm start)

    qcarlab.cli.load_commands()

    _hold_to_one_core(spec.get("cpu"))
    work = Path.cwd()
    return BlockHost.start(HostPlan(work, work / "submission", work / "student-stdout.txt",
                                    work / "student-stderr.txt", sandbox=why is None, memory_mb=limits.memory_mb,
                                    output_bytes=limits.output_bytes, cpu_s=limits.cpu_s))


def _hold_to_one_core(cpu: int | None) -> None:
    """This process (and so the student's, forked from it) on one core: ``cpu``, or the one it
    runs on. A block call is then a hand-over between two processes on one core, some 7 us,
    where a wake-up on the other core costs 50-90 us on a VM (a 75 s path-follow run makes
    15,000 calls). Nothing is lost: the task's two processes never compute at the same time."""
    if not hasattr(os, "sched_setaffinity"):
        return
    try:
        if cpu is None:
            cpu = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[36])  # field 39: the CPU
        if cpu in os.sched_getaffinity(0):
            os.sched_setaffinity(0, {cpu})
    except (OSError, ValueError, IndexError):
        pass


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    spec = json.loads(Path(args[0]).read_text(encoding="utf-8"))
    from qcarlab import blocks
    from qcarlab.errors import GraderFault
    from qcarlab.grading.limits import Limits, apply

    limits = Limits(**spec["limits"])
    host = None
    try:
        if spec.get("student"):
            host = student_process(spec, limits)
            if host is not None:
                blocks.load_with(host.load)
        apply(limits)
        if spec["kind"] == "scenario":
            run_scenario(spec)
        else:
            run_block(spec)
    except GraderFault as exc:
        sys.stderr.write(f"qcarlab grader: error: {exc}\n")
        sys.exit(GraderFault.exit_code)
    finally:
        blocks.unwatch()  # (a block task's calls leave the watchdog's alarm set: see qcarlab.blocks)
        blocks.load_with(None)
        if host is not None:
            host.close()


if __name__ == "__main__":
    main()
