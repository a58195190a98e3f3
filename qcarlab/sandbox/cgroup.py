"""One cgroup per student process: a memory limit for all its processes together, a cap on their number.

Made under the cgroup the trusted task is in (so a machine's own limits still hold), for cgroup
v2 (``memory.max``, ``memory.swap.max``, ``pids.max``, ``cgroup.kill``) or v1 (the ``memory``
and ``pids`` hierarchies: ``memory.limit_in_bytes``, ``memory.memsw.limit_in_bytes``,
``pids.max``). The kernel charges the student's tmpfs files to it too. After the run,
:meth:`Cgroup.oom_killed` says whether the kernel killed a process for memory, and
:meth:`Cgroup.remove` kills whatever is left and removes it. :meth:`Cgroup.create` returns None
where no cgroup can be made (not root, a read-only /sys/fs/cgroup, v2 with the controllers
unavailable); the caller then limits each process's address space instead.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

ROOT = Path("/sys/fs/cgroup")


def _own() -> dict[str, str]:
    """controller (or "" for v2) -> this process's cgroup path, from /proc/self/cgroup."""
    out: dict[str, str] = {}
    try:
        text = Path("/proc/self/cgroup").read_text()
    except OSError:
        return out
    for line in text.splitlines():
        parts = line.split(":", 2)
        if len(parts) == 3:
            for name in parts[1].split(",") if parts[1] else [""]:
                out[name] = parts[2]
    return out


def _write(path: Path, value: str) -> None:
    with open(path, "w") as f:
        f.write(value)


class Cgroup:
    def __init__(self, dirs: list[Path], v2: bool):
        self.dirs, self.v2 = dirs, v2

    @classmethod
    def create(cls, name: str, memory_bytes: int, processes: int) -> Cgroup | None:
        own = _own()
        if "memory" in own and (ROOT / "memory").is_dir():  # v1
            dirs = [ROOT / "memory" / own["memory"].lstrip("/") / name]
            if "pids" in own and (ROOT / "pids").is_dir():
                dirs.append(ROOT / "pids" / own["pids"].lstrip("/") / name)
            group = cls(dirs, v2=False)
            settings = [("memory.limit_in_bytes", str(memory_bytes)), ("memory.memsw.limit_in_bytes", str(memory_bytes)),
                        ("pids.max", str(processes))]
        elif "" in own and (ROOT / "cgroup.controllers").exists():  # v2
            parent = ROOT / own[""].lstrip("/")
            try:
                wanted = {"memory", "pids"} & set((parent / "cgroup.controllers").read_text().split())
                if "memory" not in wanted:
                    return None
                enabled = set((parent / "cgroup.subtree_control").read_text().split())
                if not wanted <= enabled:
                    _write(parent / "cgroup.subtree_control", " ".join("+" + c for c in sorted(wanted - enabled)))
            except OSError:
                return None
            group = cls([parent / name], v2=True)
            settings = [("memory.max", str(memory_bytes)), ("memory.swap.max", "0"), ("pids.max", str(processes))]
        else:
            return None
        try:
            for d in group.dirs:
                d.mkdir()
        except OSError:
            group.remove()
            return None
        try:
            for fname, value in settings:
                for d in group.dirs:
                    if (d / fname).exists():
                        _write(d / fname, value)
        except OSError:
            group.remove()
            return None
        return group

    def join(self, pid: int) -> None:
        """Put process ``pid`` (and the children it starts from now on) in the cgroup."""
        for d in self.dirs:
            _write(d / "cgroup.procs", str(pid))

    def oom_killed(self) -> bool:
        """Whether the kernel killed a process of the cgroup for memory."""
        d = self.dirs[0]
        fname = "memory.events" if self.v2 else "memory.oom_control"
        try:
            for line in (d / fname).read_text().splitlines():
                key, _, value = line.partition(" ")
                if key == "oom_kill" and int(value) > 0:
                    return True
            if not self.v2:
                return int((d / "memory.failcnt").read_text()) > 0 and \
                    int((d / "memory.max_usage_in_bytes").read_text()) >= int((d / "memory.limit_in_bytes").read_text()) - 2**20
        except (OSError, ValueError):
            pass
        return False

    def at_limit(self) -> bool:
        """Whether the cgroup's memory use has reached its limit (the kernel then reclaims, and a
        process with nothing left to give back is killed: on a loaded machine that can take
        seconds, during which the process is starved, not looping) or it was killed for memory."""
        if self.oom_killed():
            return True
        d = self.dirs[0]
        try:
            if self.v2:
                for line in (d / "memory.events").read_text().splitlines():
                    key, _, value = line.partition(" ")
                    if key == "max" and int(value) > 0:
                        return True
                return False
            return int((d / "memory.failcnt").read_text()) > 0
        except (OSError, ValueError):
            return False

    def pids(self) -> list[int]:
        out: set[int] = set()
        for d in self.dirs:
            try:
                out.update(int(p) for p in (d / "cgroup.procs").read_text().split())
            except (OSError, ValueError):
                pass
        return sorted(out)

    def remove(self) -> None:
        """Kill every process left in it, then remove it."""
        deadline = time.monotonic() + 2.0
        for d in reversed(self.dirs):
            while d.exists():
                if self.v2 and (d / "cgroup.kill").exists():
                    try:
                        _write(d / "cgroup.kill", "1")
                    except OSError:
                        pass
                for pid in self.pids():
                    try:
                        os.kill(pid, signal.SIGKILL)
                    except OSError:
                        pass
                try:
                    d.rmdir()
                except FileNotFoundError:
                    break
                except OSError:
                    if time.monotonic() > deadline:
                        break
                    time.sleep(0.002)


def sweep(prefix: str = "qcarlab-") -> None:
    """Remove the cgroups of student processes whose trusted process is gone (``PREFIX<pid>`` under
    this process's own cgroups: a task killed at its time limit cannot remove its own)."""
    own = _own()
    parents = [(ROOT / c / own[c].lstrip("/"), False) for c in ("memory", "pids") if c in own]
    if "" in own and (ROOT / "cgroup.controllers").exists():
        parents.append((ROOT / own[""].lstrip("/"), True))
    for parent, v2 in parents:
        try:
            children = [d for d in parent.iterdir() if d.name.startswith(prefix) and d.is_dir()]
        except OSError:
            continue
        for d in children:
            pid = d.name[len(prefix):]
            if pid.isdigit() and Path(f"/proc/{pid}").exists():
                continue  # its task is still running
            Cgroup([d], v2).remove()


__all__ = ["Cgroup", "sweep"]
