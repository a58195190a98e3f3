"""One graded task in its own processes: :func:`execute` a :class:`Job`, get an outcome back.

The grader never runs a student's code in its own process and never through a shell. A job
carries everything its processes need (the command's words, the submission's files as bytes, the
limits), so the same :func:`execute` runs it in a local thread pool or on a Ray worker on another
machine. It makes a fresh folder, writes the submission's files into ``submission/``, and starts
the task's trusted process, ``python -m qcarlab.grading.child spec.json``, there in a new process
group, stdout and stderr to files (or, given a :class:`~qcarlab.grading.warm.WarmStart`, forks the
same from a zygote that has loaded qcarlab already). That process runs the simulator and the
referee and writes the results; the student's code runs in a process of its own that it starts
(:mod:`qcarlab.sandbox`), which sees none of this folder but the submission. The grader waits at
most the wall-time limit, then kills the group. The outcome says what came back (the results, or
each case's value) or, in one line, why nothing did:

    did not finish within 5 s (stopped)          a hang (the whole process group is killed)
    ran out of memory: ... (limit 2048 MB ...)   the student's processes together, over the limit
    exited with code 3 and no results (os._exit?) an exit that skipped qcarlab's own
    qcarlab stop-sign: error: block stop_sign ... the student's exception, named by qcarlab

What the student's code printed comes back apart (``student_stdout``, ``student_stderr``), never
as the grader's reason.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from qcarlab.grading.limits import THREAD_VARS, Limits
from qcarlab.grading.warm import WarmStart

TAIL = 4096  # bytes of stdout/stderr kept for the report
FIGURES = (".png",)


@dataclass
class Job:
    """A task to run for one student: picklable, self-contained."""

    key: tuple[str, str, str]  # (student, sheet, task)
    kind: str  # "scenario" | "block"
    limits: dict[str, float]
    argv: list[str] = field(default_factory=list)  # scenario: the words after "qcarlab"
    params: str | None = None  # scenario: the submission's params.yaml (its lab: section is used)
    lab: str | None = None  # block: the lab whose block it is
    block: str | None = None
    file: str | None = None  # block: the submission's file that defines it
    cases: list[dict[str, Any]] = field(default_factory=list)
    files: dict[str, bytes] = field(default_factory=dict)  # the submission: name -> content
    figures: bool = False  # keep the figures (the command has --out)
    qcarlab: str = ""  # the grader's version; a worker with another one refuses the job
    sandbox: str = "auto"  # the student's process: "required", "auto" (where this machine can) or "off"

    @property
    def student_code(self) -> bool:
        """Whether the task runs any of the student's code (a block task, or --block in the command)."""
        return self.kind == "block" or "--block" in self.argv


def _signal_name(code: int) -> str:
    try:
        return signal.Signals(code).name
    except ValueError:
        return f"signal {code}"


def _tail(path: Path) -> str:
    try:
        with open(path, "rb") as f:
            size = f.seek(0, os.SEEK_END)
            f.seek(max(0, size - TAIL))
            return f.read().decode("utf-8", errors="replace")
    except OSError:
        return ""


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


_PREFIX = re.compile(r"^qcarlab [\w-]+: (internal )?error: ")
_INFO = re.compile(r"^([\w-]+: your blocks: |[\w-]+: warning: |warning: )")


def _last_line(text: str) -> str:
    """The line of stderr that says what went wrong: qcarlab's own error line (``qcarlab LAB:
    error: ...``, its prefix cut) or the last line of its message (``block stop_sign ... raised
    ...``); "" when qcarlab said nothing (the process was cut short)."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    start = max((i for i, ln in enumerate(lines) if _PREFIX.match(ln) or ln.startswith("error: ")), default=None)
    if start is None:
        return ""
    msg = [ln for ln in lines[start:] if not (ln.startswith("(") and ln.endswith(")"))]
    blocks = [ln for ln in msg if ln.startswith("block ")]
    line = blocks[-1] if blocks else msg[0]
    return _PREFIX.sub("", line).removeprefix("error: ")


def task_env(results: Path | None = None) -> dict[str, str]:
    """The environment of a task's process (a warm zygote's too, without ``results``)."""
    import qcarlab

    env = {k: v for k, v in os.environ.items() if k not in ("QCARLAB_DEBUG", "QCARLAB_RESULTS", "PYTHONSTARTUP")}
    for var in THREAD_VARS:
        env[var] = "1"
    root = Path(qcarlab.__file__).resolve().parents[1]  # the qcarlab the grader runs, also from a checkout
    if root.name not in ("site-packages", "dist-packages"):
        env["PYTHONPATH"] = str(root) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.update({"MPLBACKEND": "Agg", "PYTHONDONTWRITEBYTECODE": "1", "PYTHONUNBUFFERED": "1", "COLUMNS": "120",
                "NO_COLOR": "1", "TERM": "dumb", "PYTHONHASHSEED": "0"})
    if results is not None:
        env["QCARLAB_RESULTS"] = str(results)
    return env


def _spec(job: Job, work: Path, results: Path, cpu: int | None) -> dict[str, Any]:
    spec: dict[str, Any] = {"kind": job.kind, "limits": job.limits, "results": str(results),
                            "sandbox": job.sandbox, "student": job.student_code, "cpu": cpu}
    if job.kind == "scenario":
        argv = list(job.argv)
        if job.figures:
            argv += ["--out", str(work / "out")]
        spec.update(argv=argv, params=str(work / "submission" / job.params) if job.params else None)
    else:
        spec.update(lab=job.lab, block=job.block, file=str(work / "submission" / str(job.file)), cases=job.cases)
    return spec


def execute(job: Job, warm: WarmStart | None = None, cpu: int | None = None) -> dict[str, Any]:
    """Run ``job`` in its own process under its limits; the outcome as a JSON-able dict (figures as bytes).

    With ``warm`` (:class:`~qcarlab.grading.warm.WarmStart`) the process is forked from a zygote that
    has loaded qcarlab already; without it (or when the zygote cannot), a fresh interpreter. A task
    that fails for the grader's own reasons (status ``infrastructure``: its process killed from
    outside, the zygote gone, the sandbox not set up) is run once more, cold. ``cpu``: the core
    the task's processes (the trusted one and the student's) are held to, so that a call of a
    student's block is a hand-over on one core (some 7 us) rather than a wake-up on another (50-90
    us on a VM); None: the core the task starts on."""
    import qcarlab

    if job.qcarlab and job.qcarlab != qcarlab.__version__:
        return {"status": "error", "reason": f"this worker has qcarlab {qcarlab.__version__}, the grader "
                f"{job.qcarlab}", "seconds": 0.0}
    outcome = _attempt(job, warm, cpu)
    if outcome["status"] == "infrastructure":
        again = _attempt(job, None, cpu)
        again["seconds"] = round(again["seconds"] + outcome["seconds"], 3)
        if again["status"] == "infrastructure":
            again["reason"] = f"not graded: the grader failed twice ({again['reason']}); run it again"
        outcome = again
    return outcome


def _attempt(job: Job, warm: WarmStart | None, cpu: int | None) -> dict[str, Any]:
    limits = Limits(**job.limits)
    work = Path(tempfile.mkdtemp(prefix="qcarlab-grade-"))
    t0 = time.monotonic()
    try:
        sub = work / "submission"
        sub.mkdir()
        for name, data in job.files.items():
            (sub / Path(name).name).write_bytes(data)
        results = work / ("cases.jsonl" if job.kind == "block" else "results.json")
        spec_path = work / "spec.json"
        spec_path.write_text(json.dumps(_spec(job, work, results, cpu)), encoding="utf-8")
        out_path, err_path = work / "stdout.txt", work / "stderr.txt"
        ran = warm.run(spec_path, work, out_path, err_path, {"QCARLAB_RESULTS": str(results)}, limits.timeout) \
            if warm is not None else None
        rc, timed_out = ran if ran is not None else _cold(spec_path, work, out_path, err_path, results, limits)
        outcome = _classify(job, limits, rc, timed_out, work, results, out_path, err_path)
        outcome["seconds"] = round(time.monotonic() - t0, 3)
        return _relative(outcome, str(sub) + os.sep)
    finally:
        shutil.rmtree(work, ignore_errors=True)
        if job.student_code and sys.platform.startswith("linux"):
            from qcarlab.sandbox.cgroup import sweep

            sweep()  # the student's cgroup of a task killed at its time limit


def _cold(spec_path: Path, work: Path, out_path: Path, err_path: Path, results: Path,
          limits: Limits) -> tuple[int, bool]:
    """``python -m qcarlab.grading.child SPEC`` in a new session; (exit code, timed out)."""
    timed_out = False
    with open(out_path, "wb") as out, open(err_path, "wb") as err:
        proc = subprocess.Popen([sys.executable, "-m", "qcarlab.grading.child", str(spec_path)], cwd=work,
                                stdin=subprocess.DEVNULL, stdout=out, stderr=err, env=task_env(results),
                                start_new_session=True, close_fds=True)
        try:
            proc.wait(timeout=limits.timeout)
        except subprocess.TimeoutExpired:
            timed_out = True
        finally:
            try:
                os.killpg(proc.pid, signal.SIGKILL)  # the task and anything it started
            except (ProcessLookupError, PermissionError):
                pass
            proc.wait()
    return proc.returncode, timed_out


def _classify(job: Job, limits: Limits, rc: int, timed_out: bool, work: Path, results: Path,
              out_path: Path, err_path: Path) -> dict[str, Any]:
    stderr_tail, stdout_tail = _tail(err_path), _tail(out_path)
    outcome: dict[str, Any] = {"status": "ok", "reason": None, "rc": rc, "stderr": stderr_tail,
                               "stdout": stdout_tail, "figures": {}, "sandboxed": True}
    if job.student_code:
        said = _tail(work / "sandbox.txt")
        outcome.update(sandboxed=said == "sandboxed", sandbox=said or None,
                       student_stdout=_tail(work / "student-stdout.txt"),
                       student_stderr=_tail(work / "student-stderr.txt"))
    infra = _infrastructure(rc, timed_out, stderr_tail)
    if infra is not None:
        outcome.update(status="infrastructure", reason=_clip(infra))
        return outcome
    capped = _size(out_path) >= limits.output_bytes or _size(err_path) >= limits.output_bytes
    if job.kind == "block":
        cases = []
        if results.exists():
            for line in results.read_text(encoding="utf-8", errors="replace").splitlines():
                try:
                    cases.append(json.loads(line))
                except json.JSONDecodeError:
                    break
        outcome["cases"] = cases
    else:
        data = None
        if results.exists():
            try:
                data = json.loads(results.read_text(encoding="utf-8"))
            except (OSError, json.JSONDecodeError, UnicodeDecodeError):
                data = None
        if data is None and "--json" in job.argv:  # a command without results files (ping): its stdout
            try:
                data = json.loads(out_path.read_text(encoding="utf-8", errors="replace"))
            except (OSError, json.JSONDecodeError):
                data = None
        outcome["results"] = data if isinstance(data, dict) else None
        if job.figures and (work / "out").is_dir():
            for f in sorted((work / "out").iterdir()):
                if f.suffix in FIGURES and f.is_file() and _size(f) <= limits.output_bytes:
                    outcome["figures"][f.name] = f.read_bytes()
    reason = None
    said = _last_line(stderr_tail)
    if not said and rc == 1:  # an uncaught exception outside qcarlab's error handling: its last line
        rest = [ln.strip() for ln in stderr_tail.splitlines() if ln.strip() and not _INFO.match(ln.strip())]
        said = rest[-1] if rest else ""
    memory = f"ran out of memory (the limit is {limits.memory_mb:g} MB)"
    if timed_out:
        reason = f"did not finish within {limits.timeout:g} s (stopped)"
    elif capped:
        reason = f"printed more than {limits.output_mb:g} MB (output is capped)"
    elif rc < 0:
        sig = _signal_name(-rc)
        reason = {"SIGXCPU": f"used more than {limits.cpu_s} s of CPU (stopped)",
                  "SIGXFSZ": f"wrote more than {limits.output_mb:g} MB to a file (stopped)",
                  }.get(sig, f"crashed ({sig})")
    elif "MemoryError" in said or "Cannot allocate memory" in said:
        reason = f"{memory}: {said}"
    has_results = outcome.get("results") is not None or bool(outcome.get("cases"))
    if reason is None and rc != 0 and not (job.kind == "scenario" and has_results and rc == 1):
        if said:
            reason = said
        elif job.kind == "block" and outcome.get("cases"):
            reason = f"exited with code {rc} before the last case returned (os._exit in the code?)"
        else:
            reason = f"exited with code {rc} and no results (os._exit in the code?)"
    if reason is None and not has_results:
        reason = f"finished (exit code {rc}) without results" + (f": {said}" if said else " (os._exit in the code?)")
    for case in outcome.get("cases") or []:
        if "MemoryError" in str(case.get("error", "")):
            case["error"] = f"{memory}: {case['error']}"
    if reason is not None:
        outcome.update(status="timeout" if timed_out else "error", reason=_clip(reason))
    return outcome


def _infrastructure(rc: int, timed_out: bool, stderr_tail: str) -> str | None:
    """Why the task failed for the grader's own reasons, or None. The trusted process runs no
    student code, so its death by a signal (other than its own CPU and file-size limits) came from
    outside: another process, the machine, a dead zygote."""
    if timed_out:
        return None
    if rc == 75:  # GraderFault.exit_code
        line = next((ln for ln in reversed(stderr_tail.splitlines()) if "error:" in ln), "")
        return line.split("error:", 1)[1].strip() if line else "the grader's task process failed"
    if rc < 0 and _signal_name(-rc) not in ("SIGXCPU", "SIGXFSZ"):
        return f"the task's process was killed from outside ({_signal_name(-rc)})"
    return None


_SUBMISSION = re.compile(r"(?<![\w/.-])submission/")


def _relative(value: Any, prefix: str) -> Any:
    """The outcome with the task folder's path cut from every message (``stop_sign.py:3``, not
    ``/tmp/qcarlab-grade-x/submission/stop_sign.py:3``)."""
    if isinstance(value, str):
        return _SUBMISSION.sub("", value.replace(prefix, ""))
    if isinstance(value, dict):
        return {k: v if isinstance(v, bytes) else _relative(v, prefix) for k, v in value.items()}
    if isinstance(value, list):
        return [_relative(v, prefix) for v in value]
    return value


def _clip(text: str, limit: int = 300) -> str:
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


__all__ = ["Job", "execute", "task_env"]
