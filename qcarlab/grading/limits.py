"""The limits a graded task runs under, set inside the task's own process before any student code.

- memory: the address space (``RLIMIT_AS``), so an allocation without bound raises MemoryError
  in the student's block (reported like any exception of theirs) instead of swapping the machine;
- CPU time (``RLIMIT_CPU``): a backstop to the grader's wall-time limit, which kills the task's
  whole process group;
- output (``RLIMIT_FSIZE``): no file the task writes (its stdout and stderr are files) grows past
  the cap; a print past it fails inside the student's code ("File too large");
- no core files (``RLIMIT_CORE`` = 0).

The numerical libraries are held to one thread each (``OMP_NUM_THREADS`` and friends) so N tasks
use N cores and thread stacks do not eat the address-space budget.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from qcarlab.errors import InputError

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
               "NUMBA_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")


@dataclass(frozen=True)
class Limits:
    """Per task: wall time (s), memory (MB of address space), output per file (MB)."""

    timeout: float = 300.0
    memory_mb: float = 2048.0
    output_mb: float = 10.0

    def check(self) -> Limits:
        """One line naming the option for a limit that is not a positive finite number."""
        for option, value, low in (("--timeout", self.timeout, 0.0), ("--memory", self.memory_mb, 256.0),
                                   ("--max-output", self.output_mb, 0.0)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value <= low:
                unit = {"--timeout": "seconds", "--memory": "MB", "--max-output": "MB"}[option]
                floor = f" above {low:g}" if low else ""
                raise InputError(f"{option} must be a positive number of {unit}{floor}, got {value}")
        return self

    def as_dict(self) -> dict[str, float]:
        return asdict(self)

    @property
    def cpu_s(self) -> int:
        return int(math.ceil(self.timeout)) + 5

    @property
    def output_bytes(self) -> int:
        return int(self.output_mb * 2**20)


def apply(limits: Limits) -> None:
    """Set the limits on the calling process (the task's own, never the grader's)."""
    import resource

    def lower(which: int, value: int) -> None:  # soft = hard: the task cannot raise it again
        _, hard = resource.getrlimit(which)
        if hard != resource.RLIM_INFINITY:
            value = min(value, hard)
        resource.setrlimit(which, (value, value))

    lower(resource.RLIMIT_AS, int(limits.memory_mb * 2**20))
    lower(resource.RLIMIT_CPU, limits.cpu_s)
    lower(resource.RLIMIT_FSIZE, limits.output_bytes)
    lower(resource.RLIMIT_CORE, 0)


__all__ = ["Limits", "THREAD_VARS", "apply"]
