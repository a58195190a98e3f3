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

import os
import queue
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


def connect_ray(address: str) -> Any:
    """Ray, connected: to ``address`` (``auto``, ``ray://HOST:10001``, ``HOST:6379``), or a Ray this
    process already started (``ray.init()``), or a new local one for ``local``."""
    ray = _ray()
    if ray.is_initialized():
        return ray
    try:
        if address == "local":
            ray.init(include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    except Exception as exc:  # noqa: BLE001 - ray's ConnectionError and friends
        raise InputError(f"--ray {address}: cannot connect to a Ray cluster ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0] if str(exc) else ''})") from None
    return ray


def run_ray(jobs: list[Job], address: str, done: Progress | None = None) -> list[dict[str, Any]]:
    """The jobs on a Ray cluster (one CPU each); outcomes in the jobs' order."""
    ray = connect_ray(address)
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


__all__ = ["connect_ray", "run_jobs", "run_local", "run_ray"]
