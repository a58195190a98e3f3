"""Running many jobs: one after the other, N at a time on this machine, or on a Ray cluster.

Every job is :func:`qcarlab.grading.runner.execute`, which starts the task's own process and
waits for it; so ``--jobs N`` is N threads here, each waiting on one task process (N task
processes at a time, each on its own core: the grader itself computes nothing). ``--ray ADDRESS``
hands the same jobs to Ray (``ray.remote(execute)``), which places them on the cluster's
workers: no scheduler of ours. A job carries the submission's files and brings back the results
and figures as bytes, so workers need no shared file system, only the same qcarlab installed.

Outcomes come back in the jobs' order whatever order they finished in, so a gradebook made with
``--jobs 4`` or on Ray is the one ``--jobs 1`` makes (the simulator is seeded; nothing depends on
timing except the wall-time limit).
"""

from __future__ import annotations

import contextlib
import os
import queue
import sys
import tempfile
from pathlib import Path
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, as_completed
from typing import Any

from qcarlab.errors import InputError
from qcarlab.grading.runner import Job, execute, task_env
from qcarlab.grading.warm import WarmStart

Progress = Callable[[Job, dict[str, Any]], None]


#: Scenario tasks from which a warm zygote pays for its own start (about one task's start-up).
WARM_FROM = 2


def run_local(jobs: list[Job], workers: int = 1, done: Progress | None = None) -> list[dict[str, Any]]:
    """Each job in its own process, ``workers`` at a time; outcomes in the jobs' order. With
    several scenario tasks the processes are forked from a warm zygote (:mod:`.warm`)."""
    warm = WarmStart.start(task_env()) if sum(j.kind == "scenario" for j in jobs) >= WARM_FROM else None
    try:
        return _run_local(jobs, workers, done, warm)
    finally:
        if warm is not None:
            warm.close()


def _run_local(jobs: list[Job], workers: int, done: Progress | None, warm: WarmStart | None) -> list[dict[str, Any]]:
    outcomes: list[dict[str, Any] | None] = [None] * len(jobs)
    if workers <= 1:
        for i, job in enumerate(jobs):
            outcomes[i] = execute(job, warm)
            if done:
                done(job, outcomes[i])  # type: ignore[arg-type]
        return outcomes  # type: ignore[return-value]
    cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    slots: queue.SimpleQueue[int] = queue.SimpleQueue()
    for slot in range(workers):
        slots.put(slot)

    def run(job: Job) -> dict[str, Any]:
        """One job on a core of its own (slot k on core k, as long as there are cores)."""
        slot = slots.get()
        try:
            return execute(job, warm, cores[slot % len(cores)] if cores else None)
        finally:
            slots.put(slot)

    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="qcarlab-grade") as pool:
        futures = {pool.submit(run, job): i for i, job in enumerate(jobs)}
        for fut in as_completed(futures):
            i = futures[fut]
            try:
                outcomes[i] = fut.result()
            except Exception as exc:  # noqa: BLE001 - the grader's own failure, reported per task
                outcomes[i] = {"status": "error", "reason": f"the grader could not run the task: {exc}"}
            if done:
                done(jobs[i], outcomes[i])  # type: ignore[arg-type]
    return outcomes  # type: ignore[return-value]


def _ray():
    try:
        import ray
    except ImportError:
        raise InputError("--ray needs Ray installed: pip install 'qcarlab[ray]'") from None
    return ray


@contextlib.contextmanager
def _ray_output():
    """What Ray writes on stderr while it connects (file descriptor 2: its C++ core's warnings, a
    refused token's one line a second for 20 s, and its Python log lines), kept out of the
    grader's output and handed back (``box["text"]``) to name the cause of a failure in one line.
    With QCARLAB_DEBUG set it is left on stderr."""
    box = {"text": ""}
    if os.environ.get("QCARLAB_DEBUG", "") not in ("", "0"):
        yield box
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no file descriptor 2 to borrow
        yield box
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield box
        finally:
            try:
                sys.stderr.flush()
            except (OSError, ValueError):
                pass
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            box["text"] = tmp.read()[-65536:].decode("utf-8", "replace")


#: Ray's own variables for its token authentication (Ray >= 2.52): the token itself, or a file
#: holding it; Ray reads them when ``RAY_AUTH_MODE=token``
RAY_TOKEN_VARS = ("RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")


def use_ray_token(token_file: str | Path | None = None) -> str | None:
    """Set this process up for a cluster with Ray's token authentication (``ray start --head`` turns
    it on since Ray 2.59 once a token exists): with ``token_file`` (``--ray-token-file``: the head's
    ``~/.ray/auth_token``, or what ``ray get-auth-token`` prints, in a file), Ray is told to read
    the token from it; without, a token in Ray's own variables (``RAY_AUTH_TOKEN``,
    ``RAY_AUTH_TOKEN_PATH``) is used. Ray itself sends a token to an address given explicitly only
    when ``RAY_AUTH_MODE=token``: this sets it in either case. Returns where the token comes from
    (for the error if the cluster still refuses it), or None for no token."""
    if token_file is not None:
        path = Path(token_file).expanduser()
        try:
            text = path.read_text(encoding="utf-8").strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"--ray-token-file {token_file}: {getattr(exc, 'strerror', None) or exc}") from None
        if not text:
            raise InputError(f"--ray-token-file {token_file}: the file is empty (on the head, ray get-auth-token "
                             "prints the cluster's token)")
        os.environ["RAY_AUTH_TOKEN_PATH"] = str(path.resolve())
        os.environ.pop("RAY_AUTH_TOKEN", None)  # Ray prefers it to the file: the file given wins
        os.environ["RAY_AUTH_MODE"] = "token"
        return f"--ray-token-file {token_file}"
    given = next((v for v in RAY_TOKEN_VARS if os.environ.get(v)), None)
    if given is None:
        return None
    if os.environ.get("RAY_AUTH_MODE", "").lower() != "disabled":  # an explicit opt-out is kept
        os.environ["RAY_AUTH_MODE"] = "token"
    return given


def connect_ray(address: str, token_file: str | Path | None = None) -> Any:
    """Ray, connected: to ``address`` (``auto``, ``ray://HOST:10001``, ``HOST:6379``), or a Ray this
    process already started (``ray.init()``), or a new local one for ``local``; with the cluster's
    token when one is given (:func:`use_ray_token`)."""
    # the token's variables before Ray loads: it reads its authentication settings then
    token = use_ray_token(token_file) if address != "local" else None
    ray = _ray()
    if ray.is_initialized():
        return ray
    with _ray_output() as said:
        try:
            if address == "local":
                ray.init(include_dashboard=False, log_to_driver=False)
            else:
                ray.init(address=address, log_to_driver=False)
            failed = None
        except Exception as exc:  # noqa: BLE001 - ray's ConnectionError and friends
            failed = exc
    if failed is not None:
        raise InputError(_connect_error(address, token, failed, said["text"])) from None
    return ray


def _connect_error(address: str, token: str | None, exc: BaseException, said: str) -> str:
    """One line: why Ray could not connect, the token named when the cluster refused one."""
    refused = "InvalidAuthToken" in said or "Unauthenticated" in said or "AuthenticationError" in type(exc).__name__
    if refused and token is None:
        return (f"--ray {address}: the cluster uses Ray's token authentication (ray start --head turns it on) and "
                "no token was given: pass --ray-token-file FILE (the head's ~/.ray/auth_token; on the head, ray "
                "get-auth-token prints it) or set RAY_AUTH_TOKEN")
    if refused:
        return (f"--ray {address}: the cluster refused the token of {token} (InvalidAuthToken); on the head, "
                "ray get-auth-token prints the cluster's")
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"--ray {address}: cannot connect to a Ray cluster ({type(exc).__name__}: {first})"


def run_ray(jobs: list[Job], address: str, done: Progress | None = None,
            token_file: str | Path | None = None) -> list[dict[str, Any]]:
    """The jobs on a Ray cluster (one CPU each); outcomes in the jobs' order. ``token_file``: the
    cluster's token for Ray's token authentication (:func:`use_ray_token`)."""
    ray = connect_ray(address, token_file)
    remote = ray.remote(num_cpus=1, max_retries=0)(execute)
    refs = [remote.remote(job) for job in jobs]
    index = {ref: i for i, ref in enumerate(refs)}
    outcomes: list[dict[str, Any] | None] = [None] * len(jobs)
    pending = list(refs)
    while pending:
        ready, pending = ray.wait(pending, num_returns=len(pending), timeout=0.5)  # all that are done
        for ref in ready:
            i = index[ref]
            try:
                outcomes[i] = ray.get(ref)
            except Exception as exc:  # noqa: BLE001 - a worker that died, a node lost
                first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                outcomes[i] = {"status": "error", "reason": f"the Ray worker failed: {first}"}
            if done:
                done(jobs[i], outcomes[i])  # type: ignore[arg-type]
    return outcomes  # type: ignore[return-value]


def run_jobs(jobs: list[Job], workers: int = 1, ray_address: str | None = None,
             done: Progress | None = None) -> list[dict[str, Any]]:
    if ray_address:
        return run_ray(jobs, ray_address, done)
    return run_local(jobs, workers, done)


__all__ = ["RAY_TOKEN_VARS", "connect_ray", "run_jobs", "run_local", "run_ray", "use_ray_token"]
