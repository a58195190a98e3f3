"""A warm start for graded tasks: a zygote process that has loaded qcarlab once forks each task.

A graded task's process spends most of a second before its run starts: the interpreter, the
imports (numpy, OpenCV, typer, rich, qcarlab's commands), numba's start-up and its compiled
physics kernel, matplotlib for the figures. A class times five sheets pays that for every task.
With :class:`WarmStart` the grader starts one zygote (``python -m qcarlab.grading.warm``) with
the tasks' environment; it does all of that once and then, for each task, forks::

    grader --(Unix socket: the task's spec)--> zygote --fork--> task process
                                                  |                |  new session, its own folder,
           <--"pid N" ... "exit RC"---------------+                |  stdout/stderr to files,
                                                                   |  the limits, then the task
                                                                   v
                                                         qcarlab.grading.child.main(spec)

Each task is still its own process, in its own session (its group is what a timeout kills),
under its own limits (set by :mod:`.child` in the task process before any student code), and
the student's code never runs in the grader or in the zygote. The zygote's state is the start
state of every task (fork copies it; no task sees another's), and it was made with the same
environment as a cold task process (one thread per numerical library, ``PYTHONHASHSEED=0``,
the Agg backend), so a warm task's results are a cold one's. The zygote runs no OpenCV code
and starts no thread (a fork keeps only the forking thread). It exits when the grader closes
its stdin, killing the tasks still running.

Linux only (``os.pidfd_open``); elsewhere, or with ``QCARLAB_GRADE_COLD=1``, or when the zygote
does not start, every task is a fresh ``python -m qcarlab.grading.child`` as before.
"""

from __future__ import annotations

import gc
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

from qcarlab.zygote import Lines, after_fork, reap, run_as_interpreter, warm_up

READY = "ready"
COLD_ENV = "QCARLAB_GRADE_COLD"


# --------------------------------------------------------------------------------------------
# the grader's side
# --------------------------------------------------------------------------------------------
class WarmStart:
    """The grader's handle on a zygote: ``run(...)`` one task in a forked process, ``close()``."""

    def __init__(self, proc: subprocess.Popen, folder: Path, address: str):
        self.proc, self.folder, self.address = proc, folder, address
        self.lock = threading.Lock()
        self.broken = False

    @classmethod
    def start(cls, env: dict[str, str], timeout: float = 120.0) -> WarmStart | None:
        """A ready zygote with the tasks' environment ``env``, or None (not Linux, switched off,
        or it did not come up: the tasks then start cold)."""
        if not hasattr(os, "pidfd_open") or os.environ.get(COLD_ENV, "") not in ("", "0"):
            return None
        folder = Path(tempfile.mkdtemp(prefix="qcarlab-warm-"))
        os.chmod(folder, 0o700)
        address = str(folder / "zygote.sock")
        try:
            proc = subprocess.Popen([sys.executable, "-m", "qcarlab.grading.warm", address], cwd=folder,
                                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                    env=env, start_new_session=True, close_fds=True)
        except OSError:
            _remove(folder)
            return None
        ready: list[str] = []
        reader = threading.Thread(target=lambda: ready.append(proc.stdout.readline().decode(errors="replace")),
                                  daemon=True)
        reader.start()
        reader.join(timeout)
        if not ready or ready[0].strip() != READY:
            proc.kill()
            proc.wait()
            _remove(folder)
            return None
        return cls(proc, folder, address)

    def run(self, spec: Path, cwd: Path, stdout: Path, stderr: Path, env: dict[str, str],
            timeout: float) -> tuple[int, bool] | None:
        """Run the task ``spec`` in a forked process; (exit code, timed out), or None when the
        zygote could not start it (the caller then starts it cold). On a timeout the task's
        whole process group is killed, as for a cold task."""
        if self.broken:
            return None
        request = {"spec": str(spec), "cwd": str(cwd), "stdout": str(stdout), "stderr": str(stderr), "env": env}
        try:
            conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            conn.settimeout(30.0)
            conn.connect(self.address)
            conn.sendall(json.dumps(request).encode() + b"\n")
            reply = Lines(conn)
            started = reply.next()
        except OSError:
            self.broken = True
            return None
        if not started.startswith("pid "):
            conn.close()
            self.broken = True
            return None
        timed_out = False
        try:
            conn.settimeout(timeout)
            try:
                done = reply.next()
            except TimeoutError:
                timed_out = True
                conn.settimeout(60.0)
                conn.sendall(b"kill\n")  # the zygote kills the group (it knows the task is not reaped yet)
                done = reply.next()
        except OSError:
            done = ""
        finally:
            conn.close()
        if not done.startswith("exit "):  # the zygote died under the task
            self.broken = True
            return (-signal.SIGKILL, timed_out)
        return (int(done.split()[1]), timed_out)

    def close(self) -> None:
        """Stop the zygote (it kills any task still running) and remove its folder."""
        try:
            if self.proc.stdin:
                self.proc.stdin.close()
            self.proc.wait(timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()
        finally:
            _remove(self.folder)


def _remove(folder: Path) -> None:
    import shutil

    shutil.rmtree(folder, ignore_errors=True)


# --------------------------------------------------------------------------------------------
# the zygote
# --------------------------------------------------------------------------------------------
def serve(address: str) -> None:
    """The zygote's loop: accept a task's spec, fork it, report its pid and its exit code."""
    import selectors

    warm_up()
    gc.collect()
    gc.freeze()  # what the zygote loaded is left out of every task's collections (and its pages unwritten)
    if threading.active_count() > 1:  # a fork keeps one thread: the others' locks would hang a task
        sys.stdout.write("not ready: the warm-up started a thread\n")
        sys.stdout.flush()
        return
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(address)
    listener.listen(64)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the grader stops it (stdin closed), not Ctrl-C
    sel = selectors.DefaultSelector()
    sel.register(listener, selectors.EVENT_READ, ("accept", None))
    sel.register(sys.stdin.fileno(), selectors.EVENT_READ, ("grader", None))
    tasks: dict[int, dict[str, Any]] = {}  # pid -> {"conn", "pidfd"}
    sys.stdout.write(READY + "\n")
    sys.stdout.flush()
    while True:
        for key, _ in sel.select():
            what, data = key.data
            if what == "accept":
                conn, _ = listener.accept()
                sel.register(conn, selectors.EVENT_READ, ("request", Lines(conn)))
            elif what == "request":
                conn = key.fileobj
                sel.unregister(conn)
                try:
                    conn.settimeout(30.0)
                    request = json.loads(data.next())
                except (OSError, ValueError):
                    conn.close()
                    continue
                keep = [listener.fileno(), sys.stdin.fileno(), sel.fileno()] + [t["pidfd"] for t in tasks.values()] \
                    + [t["conn"].fileno() for t in tasks.values()] + [conn.fileno()]
                sys.stdout.flush()
                sys.stderr.flush()
                pid = os.fork()
                if pid == 0:
                    _task(request, keep)  # never returns
                pidfd = os.pidfd_open(pid)
                tasks[pid] = {"conn": conn, "pidfd": pidfd}
                try:
                    conn.sendall(f"pid {pid}\n".encode())
                except OSError:
                    pass
                sel.register(pidfd, selectors.EVENT_READ, ("exit", pid))
                sel.register(conn, selectors.EVENT_READ, ("control", pid))
            elif what == "control":  # "kill" (the task's time is up) or the grader gone
                try:
                    key.fileobj.recv(64)
                except OSError:
                    pass
                sel.unregister(key.fileobj)
                if data in tasks:
                    _kill_group(data)  # not reaped yet: the pid is still this task's
            elif what == "exit":
                pid = data
                task = tasks.pop(pid)
                _kill_group(pid)  # anything the task left running (its zombie keeps the pid)
                reap(sel, pid, task["pidfd"], task["conn"])
            elif what == "grader" and not os.read(sys.stdin.fileno(), 4096):  # EOF: the grader is done (or gone)
                for pid in list(tasks):
                    _kill_group(pid)
                    os.waitpid(pid, 0)
                listener.close()
                return


def _kill_group(pid: int) -> None:
    for kill in (os.killpg, os.kill):  # the group (after setsid), else the task alone
        try:
            kill(pid, signal.SIGKILL)
            return
        except (ProcessLookupError, PermissionError):
            continue


def _task(request: dict[str, Any], inherited: list[int]) -> None:
    """In the forked task process: its own session, folder, output files and environment, then
    the task as ``python -m qcarlab.grading.child SPEC`` would run it; exits like the interpreter."""
    try:
        os.setsid()
        after_fork()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        for fd in inherited:
            try:
                os.close(fd)
            except OSError:
                pass
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.close(null)
        for fd, path in ((1, request["stdout"]), (2, request["stderr"])):
            f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            os.dup2(f, fd)
            os.close(f)
        os.chdir(request["cwd"])
        os.environ.update(request["env"])
        sys.argv = [str(Path(__file__).with_name("child.py")), request["spec"]]
        if sys.path:
            sys.path[0] = request["cwd"]  # as ``python -m`` in the task's folder has it
        from qcarlab.grading.child import main
    except BaseException:  # noqa: BLE001
        os._exit(1)
    run_as_interpreter(lambda: main([request["spec"]]))


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    serve(args[0])


if __name__ == "__main__":
    main()
