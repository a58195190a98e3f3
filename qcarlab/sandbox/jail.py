"""The student's process confined with what Linux gives: namespaces, a read-only view, another user, a cgroup.

:func:`confine` runs in the process that will run the student's code, forked from the trusted
task (see :mod:`qcarlab.sandbox.client`), before any student code is loaded. In that order:

1. **namespaces** (``unshare(2)``, the call util-linux's ``unshare`` makes, done by the caller
   before the fork that makes this process): a PID namespace (this process is its PID 1: it sees
   no other process, and when it ends the kernel kills everything it started), a network
   namespace (no interface but a loopback that is down: no network at all), and mount, IPC and
   UTS namespaces;
2. **a file system of its own**: a fresh tmpfs as its root, into which only what Python needs is
   bind-mounted read-only (``/usr``, ``/lib*``, the Python installation and its site-packages, the
   ``qcarlab`` package itself) plus the submission (read-only), a fresh ``/proc`` of its PID
   namespace, a minimal ``/dev``, and writable ``/tmp`` and ``HOME`` on the tmpfs; then
   ``chroot``. The sheets, other submissions, the grader's output folder, the task's folder and
   the rest of the machine are not there at all;
3. **a cgroup** (v1 or v2; joined by the caller): one memory limit for every process it starts
   together (its tmpfs files count too), and a cap on their number;
4. **rlimits**: open files, processes (per user id: one per task), file size (the output cap), CPU
   time, no core files; the address space (the memory limit without a cgroup, with one that
   limit plus ``ADDRESS_HEADROOM``: an allocation mapped and never touched fails at once);
5. **another user**: a user and group id of its own per task (``BASE_UID`` + the task's PID), no
   supplementary groups, no capabilities, ``no_new_privs`` (no set-uid program can give any back),
   and the parent-death signal (SIGKILL when the trusted side goes).

:func:`probe` says in one line why this cannot be had on this machine (not Linux, not root, no
namespaces), or None when it can. Without it the student's code still runs in a process of its
own, but with only its rlimits: ``qcarlab grade`` reports those grades as "not sandboxed".
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import resource
import signal
import sys
from dataclasses import dataclass, field
from pathlib import Path

CLONE_NEWNS, CLONE_NEWUTS, CLONE_NEWIPC = 0x00020000, 0x04000000, 0x08000000
CLONE_NEWPID, CLONE_NEWNET = 0x20000000, 0x40000000
NAMESPACES = CLONE_NEWNS | CLONE_NEWUTS | CLONE_NEWIPC | CLONE_NEWPID | CLONE_NEWNET
MS_RDONLY, MS_NOSUID, MS_NODEV, MS_NOEXEC = 1, 2, 4, 8
MS_REMOUNT, MS_BIND, MS_REC, MS_PRIVATE = 32, 4096, 16384, 1 << 18
PR_SET_PDEATHSIG, PR_SET_NO_NEW_PRIVS = 1, 38

BASE_UID = 1_500_000_000  #: + the task's PID: a user id no account and no other task has
SYSTEM = ("/usr", "/lib", "/lib64", "/lib32", "/libx32", "/bin", "/sbin")
SYSTEM_FILES = ("/etc/ld.so.cache", "/etc/localtime", "/etc/nsswitch.conf")
DEVICES = ("null", "zero", "full", "random", "urandom")
HOME = "/home/student"

_libc = None


def libc() -> ctypes.CDLL:
    global _libc
    if _libc is None:
        _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    return _libc


def _check(rc: int, what: str) -> None:
    if rc != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"{what}: {os.strerror(err)}")


def unshare(flags: int) -> None:
    """``unshare(2)`` (``os.unshare`` from Python 3.12)."""
    if hasattr(os, "unshare"):
        os.unshare(flags)
    else:
        _check(libc().unshare(ctypes.c_int(flags)), "unshare")


def mount(source: str | None, target: str, fstype: str | None, flags: int, data: str | None = None) -> None:
    enc = (lambda s: s.encode() if s is not None else None)
    _check(libc().mount(enc(source), enc(target), enc(fstype), ctypes.c_ulong(flags), enc(data)),
           f"mount {target}")


def prctl(option: int, value: int) -> None:
    _check(libc().prctl(ctypes.c_int(option), ctypes.c_ulong(value), ctypes.c_ulong(0), ctypes.c_ulong(0),
                        ctypes.c_ulong(0)), "prctl")


@dataclass
class Plan:
    """What the confined process may see and use."""

    root: str  # an empty folder: the jail's root is mounted over it (inside its mount namespace only)
    submission: str  # the submission's folder, seen read-only at the same path
    uid: int
    memory_bytes: int  # the tmpfs's size; the address space too (plus ADDRESS_HEADROOM with a cgroup)
    output_bytes: int
    cpu_s: int
    cgroup: bool  # the caller put the process in a cgroup with the memory and process limits
    processes: int = 64
    files: int = 256
    visible: list[str] = field(default_factory=list)  # read-only, at the same paths


#: Address space beyond the memory limit, for what a process maps and never touches (numpy, numba,
#: OpenCV and matplotlib imported: some 0.7 GB; thread stacks and malloc arenas)
ADDRESS_HEADROOM = 2 * 2**30


def python_paths() -> list[str]:
    """What the Python running qcarlab needs to import: its installation(s), and the ``qcarlab``
    package (alone: from a checkout, not the checkout's other files)."""
    import qcarlab

    seen: list[str] = []
    for p in (sys.base_prefix, sys.prefix, sys.exec_prefix, sys.base_exec_prefix):
        if p and os.path.isdir(p) and p not in seen:
            seen.append(os.path.realpath(p))
    package = str(Path(qcarlab.__file__).resolve().parent)
    if not any(package.startswith(p + os.sep) for p in seen):
        seen.append(package)
    for entry in sys.path:  # site-packages outside the prefixes (a user site, a --target install)
        real = os.path.realpath(entry) if entry else ""
        if real.endswith(("site-packages", "dist-packages")) and os.path.isdir(real) \
                and not any(real == p or real.startswith(p + os.sep) for p in seen):
            seen.append(real)
    return seen


def confine(plan: Plan) -> None:
    """Confine this process (PID 1 of its new namespaces, still root); see the module docstring.
    Raises OSError when a step fails: the caller then ends the process (nothing runs unconfined)."""
    mount("tmpfs", plan.root, "tmpfs", MS_NOSUID | MS_NODEV, f"size={plan.memory_bytes // 2**20}m,mode=755")
    root = plan.root
    for path in SYSTEM + tuple(plan.visible) + (plan.submission,):
        _show(root, path, read_only=True)
    for path in SYSTEM_FILES:
        if os.path.isfile(path):
            _show(root, path, read_only=True)
    os.makedirs(root + "/proc", exist_ok=True)
    mount("proc", root + "/proc", "proc", MS_NOSUID | MS_NODEV | MS_NOEXEC)
    dev = root + "/dev"
    os.makedirs(dev, exist_ok=True)
    mount("tmpfs", dev, "tmpfs", MS_NOSUID | MS_NOEXEC, "size=64k,mode=755")
    for name in DEVICES:
        with open(f"{dev}/{name}", "w"):
            pass
        mount(f"/dev/{name}", f"{dev}/{name}", None, MS_BIND)
    os.makedirs(dev + "/shm")
    mount("tmpfs", dev + "/shm", "tmpfs", MS_NOSUID | MS_NODEV, f"size={plan.memory_bytes // 2**20}m,mode=1777")
    for folder, mode in (("/tmp", 0o1777), (HOME, 0o700)):
        os.makedirs(root + folder, exist_ok=True)
        os.chmod(root + folder, mode)
    os.chown(root + HOME, plan.uid, plan.uid)
    os.chroot(root)
    os.chdir(HOME)
    _limits(plan)
    os.setgroups([])
    os.setresgid(plan.uid, plan.uid, plan.uid)
    os.setresuid(plan.uid, plan.uid, plan.uid)  # every capability is gone with root
    prctl(PR_SET_NO_NEW_PRIVS, 1)
    prctl(PR_SET_PDEATHSIG, signal.SIGKILL)  # (cleared by the uid change: set after it)
    if os.getuid() == 0 or os.geteuid() == 0:
        raise OSError("still root after setresuid")


def _show(root: str, path: str, read_only: bool) -> None:
    """``path`` at the same place under ``root``: a symbolic link as such (``/bin -> usr/bin``),
    a folder or file bind-mounted (read-only)."""
    if not os.path.lexists(path):
        return
    target = root + path
    if os.path.lexists(target):
        return  # already there (inside a folder shown before)
    os.makedirs(os.path.dirname(target), exist_ok=True)
    if os.path.islink(path) and os.path.dirname(path) == "/":
        os.symlink(os.readlink(path), target)
        return
    if os.path.isdir(path):
        os.makedirs(target)
    else:
        with open(target, "w"):
            pass
    mount(path, target, None, MS_BIND | MS_REC)
    if read_only:
        mount(None, target, None, MS_REMOUNT | MS_BIND | MS_RDONLY | MS_NOSUID | MS_NODEV)


def _limits(plan: Plan) -> None:
    def set_limit(which: int, value: int) -> None:
        _, hard = resource.getrlimit(which)  # (never above what the grader itself runs under)
        value = value if hard == resource.RLIM_INFINITY else min(value, hard)
        resource.setrlimit(which, (value, value))  # soft = hard: the student cannot raise it again

    set_limit(resource.RLIMIT_NOFILE, plan.files)
    set_limit(resource.RLIMIT_NPROC, plan.processes)  # counted per user id: this task's alone
    set_limit(resource.RLIMIT_FSIZE, plan.output_bytes)
    set_limit(resource.RLIMIT_CORE, 0)
    set_limit(resource.RLIMIT_CPU, plan.cpu_s)
    if not plan.cgroup:  # the next best thing: each process's address space
        set_limit(resource.RLIMIT_AS, plan.memory_bytes)
    else:  # memory is the cgroup's; the address space only stops mapping without touching (np.empty
        # in a loop maps terabytes, charged nothing, until the kernel's map count runs out seconds later)
        set_limit(resource.RLIMIT_AS, plan.memory_bytes + ADDRESS_HEADROOM)


# --------------------------------------------------------------------------------------------
# what this machine can do
# --------------------------------------------------------------------------------------------
_probed: list[str | None] = []


def unavailable(mode: str) -> str | None:
    """Why the student's code will not be sandboxed under ``--sandbox MODE`` here (None: it will)."""
    return "switched off (--sandbox off)" if mode == "off" else probe()


def probe() -> str | None:
    """None when :func:`confine` works here; else why not, in one line. Only a success is kept
    (the grader's warm process probes once for all the tasks it forks): a probe that failed once
    (a namespace limit hit under load) is tried again by the next caller instead of leaving every
    later student unconfined."""
    if not _probed:
        why = _probe()
        if why is not None:
            return why
        _probed.append(why)
    return _probed[0]


def _probe() -> str | None:
    if not sys.platform.startswith("linux"):
        return f"the sandbox needs Linux (this is {sys.platform})"
    if os.geteuid() != 0:
        return ("the sandbox needs the grader to run as root (as in CI), to give each task a user id of its own; "
                "this grader runs as an ordinary user")
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            unshare(NAMESPACES)
            mount(None, "/", None, MS_REC | MS_PRIVATE)
            code = 0
        except BaseException:  # noqa: BLE001 - the answer is the exit code
            code = 1
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        return "the sandbox needs Linux namespaces (PID, mount, network), which this machine or container refuses"
    return None


__all__ = ["BASE_UID", "NAMESPACES", "Plan", "confine", "probe", "python_paths", "unavailable", "unshare"]
