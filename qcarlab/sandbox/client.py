"""The trusted side's handle on the student's process: start it, load the student's files there, call their blocks.

    host = BlockHost.start(plan)                 # the student's process (confined when plan.sandbox)
    blocks.load_with(host.load)                  # --use/--block files load there, as remote blocks
    main(argv)                                   # the lab runs here; each student block call is a round trip
    host.close()                                 # that process and everything it started are gone

The lab, the simulator, the referee and the results stay in the trusted process; the student's
process gets a block's arguments and gives back its value, decoded by :mod:`.codec` (plain values
only) and checked by :class:`qcarlab.blocks.StudentBlock` like any student block's. Three forks
make it: ``A`` joins the task's cgroup and unshares the namespaces, then forks ``B``, the PID 1 of
the new PID namespace, which confines itself (:func:`qcarlab.sandbox.jail.confine`) and forks
``C``, which serves (:mod:`.host`); ``B`` reaps orphans until ``C`` ends. ``A`` only waits for
``B`` and reports how it ended. Without the sandbox
(``plan.sandbox`` False) ``A`` serves itself, under rlimits only.
"""

from __future__ import annotations

import mmap
import os
import signal
import socket
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

from qcarlab.blocks import BlockTimeout, RaisedInBlock, _watchdog, check_block_file
from qcarlab.errors import GraderFault, InputError
from qcarlab.sandbox import codec
from qcarlab.sandbox.host import READY

SETUP_FAILED = 71  #: the exit code of a student's process that could not be confined (nothing of theirs ran)
SOCKET_BUFFER = 4 << 20  #: bytes: each end's send and receive buffer (the kernel caps it at wmem_max)


@dataclass
class HostPlan:
    """How to start the student's process for one task."""

    folder: Path  # the task's folder (the jail's empty root is made in it)
    submission: Path  # the student's files (read-only in the jail)
    stdout: Path  # where the student's prints go (capped by output_bytes)
    stderr: Path
    sandbox: bool = True
    memory_mb: float = 2048.0
    output_bytes: int = 10 * 2**20
    cpu_s: int = 305
    processes: int = 64


def _student_env() -> dict[str, str]:
    from qcarlab.grading.limits import THREAD_VARS
    from qcarlab.sandbox.jail import HOME

    env = {"HOME": HOME, "TMPDIR": "/tmp", "PATH": "/usr/local/bin:/usr/bin:/bin", "LANG": "C.UTF-8",
           "MPLBACKEND": "Agg", "MPLCONFIGDIR": "/tmp/matplotlib", "PYTHONDONTWRITEBYTECODE": "1",
           "PYTHONHASHSEED": "0", "PYTHONUNBUFFERED": "1"}
    env.update({v: "1" for v in THREAD_VARS})
    return env


class BlockHost:
    """The student's process, seen from the trusted side."""

    def __init__(self, sock: socket.socket, pid: int, plan: HostPlan, cgroup: Any, progress: Any = None):
        self.sock, self.pid, self.plan, self.cgroup = sock, pid, plan, cgroup
        self.progress = progress if progress is not None else bytearray(1)
        self.channel = codec.Channel(sock, trusted_peer=False)
        self.status: int | None = None
        self.dead: str | None = None
        self.confined = False  # the student's process said it is ready (host.READY): its exits are its own

    @classmethod
    def start(cls, plan: HostPlan) -> BlockHost:
        """Fork the student's process (see the module docstring); it loads nothing until asked."""
        from qcarlab.sandbox import jail
        from qcarlab.sandbox.cgroup import Cgroup

        ours, theirs = socket.socketpair()
        for end in (ours, theirs):  # an image (0.9 MB) in one send, not five turns of a one-core pair
            for opt in (socket.SO_SNDBUF, socket.SO_RCVBUF):
                try:
                    end.setsockopt(socket.SOL_SOCKET, opt, SOCKET_BUFFER)
                except OSError:
                    pass
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW
        out_fd, err_fd = os.open(plan.stdout, flags, 0o600), os.open(plan.stderr, flags, 0o600)
        memory = int(plan.memory_mb * 2**20)
        cgroup = Cgroup.create(f"qcarlab-{os.getpid()}", memory, plan.processes) if plan.sandbox else None
        root = plan.folder / "jail"
        root.mkdir(exist_ok=True)
        confinement = jail.Plan(str(root), str(plan.submission.resolve()), jail.BASE_UID + os.getpid(), memory,
                                plan.output_bytes, plan.cpu_s, cgroup is not None, plan.processes,
                                visible=jail.python_paths()) if plan.sandbox else None
        progress = mmap.mmap(-1, 1)  # shared with the student's process (qcarlab.sandbox.host.progress)
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        pid = os.fork()
        if pid == 0:  # A
            _student_side(theirs.fileno(), out_fd, err_fd, confinement, cgroup, plan, progress)  # never returns
        theirs.close()
        os.close(out_fd)
        os.close(err_fd)
        return cls(ours, pid, plan, cgroup, progress)

    # ---------------------------------------------------------------- requests
    def request(self, *msg: Any) -> Any:
        """Send one request, return the value of its ``("ok", value)`` reply; the student's
        exception (or their process's death) as :class:`~qcarlab.blocks.RaisedInBlock`."""
        if self.dead is not None:
            raise RaisedInBlock("died", "", self.dead)
        try:
            self.channel.send(msg)
            reply = self.channel.recv()
        except BlockTimeout:  # the block has not returned (qcarlab.blocks' watchdog): its process is ended
            _watchdog.stop()  # no second alarm while it is
            if self.cgroup is not None and self.cgroup.at_limit():
                # at its memory limit, the kernel's reclaim before the kill can outlast the watchdog on
                # a loaded machine: the block ran out of memory, whichever of the two came first
                self.kill()
                self.dead = self.out_of_memory()
                raise RaisedInBlock("died", "", self.dead) from None
            self.dead = "the process running your blocks was stopped: a block of yours had not returned"
            self.kill()
            raise
        except codec.CodecError as exc:  # (our own arguments always encode: this is their reply)
            self._broken(f"the process running your blocks sent something that is not a value ({exc})")
        except (EOFError, OSError):
            self.dead = self.death()
            raise RaisedInBlock("died", "", self.dead) from None
        return self.value(reply)

    def value(self, reply: Any) -> Any:
        """The value of one reply (a request's, or one of a ``calls`` request's)."""
        if not isinstance(reply, tuple) or not reply:
            self._broken("replied with something that is not a reply")
        if reply[0] == "ok" and len(reply) == 2:
            return reply[1]
        if reply[0] == "raised" and len(reply) == 5:
            if reply[2] == "OSError" and str(reply[3]).startswith("[Errno 27]"):  # EFBIG: over RLIMIT_FSIZE
                raise RaisedInBlock("output", "", f"printed more than {self.plan.output_bytes / 2**20:g} MB "
                                    "(output is capped)")
            raise RaisedInBlock(*(str(x) for x in reply[1:]))
        if reply[0] == "input" and len(reply) == 2:
            raise InputError(str(reply[1]))
        if reply[0] == "value" and len(reply) == 2:
            raise RaisedInBlock("value", "", f"returned a value that cannot be passed back: {reply[1]}")
        self._broken("replied with something that is not a reply")

    def calls(self, calls: list[tuple]) -> tuple[list[Any], list[float]]:
        """Several calls ``(id, args, method, kwargs)`` in one round trip, run in order in the
        student's process: their replies (for :meth:`value`; the list ends at the first that
        raised) and the seconds each took there (as the student's process says: a split of the
        round trip's time, not a measure of it). While they run, :meth:`running` says which."""
        self.progress[0] = 0
        got = self.request("calls", calls)
        if not (type(got) is tuple and len(got) == 2 and type(got[0]) is list and type(got[1]) is list
                and 1 <= len(got[0]) <= len(calls) and len(got[1]) == len(got[0])):
            self._broken("replied with something that is not a reply")
        return got

    def running(self) -> int:
        """The index of the call of the last ``calls`` request that was running (or ran last)."""
        return self.progress[0]

    def _broken(self, why: str) -> NoReturn:
        """The student's process broke the protocol: it is ended, and every later call fails with ``why``."""
        self.dead = why
        self.kill()
        raise RaisedInBlock("died", "", why) from None

    def _ready(self) -> None:
        """Wait for the student's process to say it is confined (:data:`qcarlab.sandbox.host.READY`,
        sent before any of the student's code runs). Until then, its exit with :data:`SETUP_FAILED`
        is the sandbox's failure (the grader's fault); after it, an exit is the student's own
        (``os._exit(71)`` in their code is their block's death, not a grader fault to be rerun)."""
        try:
            msg = self.channel.recv()
        except codec.CodecError as exc:
            self._broken(f"the process running your blocks sent something that is not a value ({exc})")
        except (EOFError, OSError):
            self.dead = self.death()
            raise RaisedInBlock("died", "", self.dead) from None
        if msg != READY:
            self._broken("did not start as the sandbox starts it")
        self.confined = True

    def load(self, path: Path) -> dict[str, Any]:
        """The top-level functions and classes of the student's file ``path``, as remote blocks."""
        check_block_file(path)
        if not self.confined:
            self._ready()
        try:
            found = self.request("load", str(path.resolve()))
        except RaisedInBlock as exc:
            raise InputError(f"{path}: loading it {exc.message}") from None
        blocks = {}
        for name, entry in (found.items() if isinstance(found, dict) else ()):
            if isinstance(entry, tuple) and len(entry) == 2 and type(entry[0]) is int:
                blocks[str(name)] = (RemoteClass if entry[1] == "class" else RemoteFunction)(self, entry[0], str(name))
        return blocks

    # ---------------------------------------------------------------- the end
    def wait(self, timeout: float = 2.0) -> int | None:
        """The student's process's exit code (negative: the signal), waiting at most ``timeout``."""
        import time

        if self.status is not None:
            return self.status
        deadline = time.monotonic() + timeout
        while True:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                code = os.waitstatus_to_exitcode(status)
                self.status = -(code - 128) if code > 128 else code  # A reports B's signal as 128 + N
                return self.status
            if time.monotonic() > deadline:
                return None
            time.sleep(0.002)

    def death(self) -> str:
        """Why the student's process ended, in words, for the block that was running."""
        code = self.wait()
        if self.cgroup is not None and self.cgroup.oom_killed():
            return self.out_of_memory()
        if code is None:
            self.kill()
            return "closed its connection (the process running your blocks stopped answering)"
        if code == SETUP_FAILED and not self.confined:
            text = ""
            try:
                text = self.plan.stderr.read_text(errors="replace").strip().splitlines()[-1]
            except (OSError, IndexError):
                pass
            raise SandboxFailed(f"the sandbox could not be set up: {text or 'no reason given'}")
        if code < 0:
            try:
                name = signal.Signals(-code).name
            except ValueError:
                name = f"signal {-code}"
            return f"the process running your blocks was killed ({name})"
        return f"the process running your blocks exited with code {code} (os._exit in your code?)"

    def out_of_memory(self) -> str:
        return (f"ran out of memory: the process running your blocks was killed (the limit is "
                f"{self.plan.memory_mb:g} MB for all its processes together)")

    def kill(self) -> None:
        try:
            os.kill(self.pid, signal.SIGKILL)  # A: B then gets its parent-death SIGKILL, and its namespace goes
        except ProcessLookupError:
            pass

    def close(self) -> None:
        """End the student's process and everything it started; remove its cgroup."""
        try:
            self.sock.close()
        except OSError:
            pass
        if self.wait(0.5) is None:
            self.kill()
            self.wait(5.0)
        if self.cgroup is not None:
            self.cgroup.remove()
        if isinstance(self.progress, mmap.mmap):
            self.progress.close()


class SandboxFailed(GraderFault):
    """The student's process could not be confined: the grader's problem, not the student's."""


class RemoteFunction:
    """A student's function in their process; called like it."""

    block_class = False

    def __init__(self, host: BlockHost, key: int, name: str):
        self.host, self.key, self.name = host, key, name

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.host.request("call", self.key, args, None, kwargs or None)

    def _remote(self) -> tuple[BlockHost, int]:
        """Its process and its id there (for :meth:`BlockHost.calls`)."""
        return self.host, self.key

    def __repr__(self) -> str:
        return f"<student function {self.name}>"


class RemoteClass(RemoteFunction):
    """A student's class in their process; calling it makes an instance there."""

    block_class = True

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        key, is_callable, methods = self.host.request("new", self.key)
        return RemoteInstance(self.host, int(key), [str(m) for m in methods]) if is_callable else NotCallable()


class NotCallable:
    """An instance without ``__call__`` (StudentBlock says so, naming the block)."""


class RemoteInstance:
    """An instance of a student's class in their process: called like it, its methods and attributes read there."""

    def __init__(self, host: BlockHost, key: int, methods: list[str]):
        self._host, self._key, self._methods = host, key, set(methods)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._host.request("call", self._key, args, None, kwargs or None)

    def _remote(self) -> tuple[BlockHost, int]:
        """Its process and its id there (for :meth:`BlockHost.calls`)."""
        return self._host, self._key

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        if name in self._methods:
            return lambda *args, **kwargs: self._host.request("call", self._key, args, name, kwargs or None)
        try:
            return self._host.request("get", self._key, name)
        except RaisedInBlock as exc:
            if exc.type_name == "AttributeError":
                raise AttributeError(name) from None
            raise


# --------------------------------------------------------------------------------------------
# the student's side of the fork
# --------------------------------------------------------------------------------------------
def _student_side(fd: int, out_fd: int, err_fd: int, confinement: Any, cgroup: Any, plan: HostPlan,
                  progress: Any = None) -> None:
    """Process A (and B): never returns."""
    code = SETUP_FAILED
    try:
        os.dup2(out_fd, 1)
        os.dup2(err_fd, 2)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.closerange(3, fd)
        os.closerange(fd + 1, 65536)
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.environ.clear()
        os.environ.update(_student_env())
        sys.path[:] = [p for p in sys.path if p and os.path.isabs(p) and not p.startswith(str(plan.folder))]
        from qcarlab.sandbox import host, jail

        host.progress = progress
        if sys.platform.startswith("linux"):
            jail.prctl(jail.PR_SET_PDEATHSIG, signal.SIGKILL)
        if confinement is None:
            _rlimits(plan)
            host.main(fd)  # never returns
        if cgroup is not None:
            cgroup.join(os.getpid())
        jail.unshare(jail.NAMESPACES)
        jail.mount(None, "/", None, jail.MS_REC | jail.MS_PRIVATE)
        b = os.fork()
        if b == 0:  # B: PID 1 of the new PID namespace
            try:
                jail.confine(confinement)
            except BaseException as exc:  # noqa: BLE001 - nothing of the student's runs unconfined
                os.write(2, f"qcarlab sandbox: {exc}\n".encode(errors="replace"))
                os._exit(SETUP_FAILED)
            _init(fd, host.main)  # never returns
        os.close(fd)
        _, status = os.waitpid(b, 0)
        code = os.waitstatus_to_exitcode(status)
        code = 128 - code if code < 0 else code
    except BaseException as exc:  # noqa: BLE001
        try:
            os.write(2, f"qcarlab sandbox: {exc}\n".encode(errors="replace"))
        except OSError:
            pass
    finally:
        os._exit(code & 0xFF)


def _init(fd: int, serve: Any) -> None:
    """B, the namespace's PID 1: fork C, which serves (the student's code runs as an ordinary
    process, signals and all), reap every orphan until C ends, then end with C's status
    (when PID 1 ends, the kernel kills what is left in the namespace)."""
    c = os.fork()
    if c == 0:
        serve(fd)  # never returns
    os.close(fd)
    code = 1
    while True:
        try:
            pid, status = os.waitpid(-1, 0)
        except ChildProcessError:
            break
        except InterruptedError:
            continue
        if pid == c:
            code = os.waitstatus_to_exitcode(status)
            code = 128 - code if code < 0 else code
            break
    os._exit(code & 0xFF)


def _rlimits(plan: HostPlan) -> None:
    """The unsandboxed student's process: its own limits (address space, file size, CPU, no core)."""
    import resource

    for which, value in ((resource.RLIMIT_AS, int(plan.memory_mb * 2**20)), (resource.RLIMIT_FSIZE, plan.output_bytes),
                         (resource.RLIMIT_CPU, plan.cpu_s), (resource.RLIMIT_CORE, 0)):
        _, hard = resource.getrlimit(which)
        value = value if hard == resource.RLIM_INFINITY else min(value, hard)
        try:
            resource.setrlimit(which, (value, value))
        except (ValueError, OSError):
            pass


#: the types whose calls run in the student's process (:func:`qcarlab.blocks.together` sends two at once)
REMOTE = (RemoteFunction, RemoteInstance)

__all__ = ["REMOTE", "BlockHost", "HostPlan", "RemoteClass", "RemoteFunction", "RemoteInstance", "SandboxFailed"]
