"""numba, where qcarlab compiles its inner loops (the simulator's sensors and physics, the
obstacle-avoidance controller's scan matching and look-ahead): ``njit`` with :data:`JIT`'s
options, compiled once per machine and then loaded from numba's on-disk cache (``__pycache__``
beside the source). Without numba, ``njit`` returns the function itself: the same code runs as
plain Python, correct but far slower (:data:`HAVE_NUMBA` says which).

:data:`COMPILE_NOTICE`: on the first run after an install or an upgrade the cache is empty and the
first kernels compile for some 10-30 s; a person waiting at a terminal is told why, once a process.
"""

from __future__ import annotations

import sys

try:  # pragma: no cover - which branch runs depends on the install
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False

    def njit(*args, **kwargs):  # type: ignore[no-redef]
        if args and callable(args[0]):
            return args[0]
        return lambda f: f


#: IEEE arithmetic as written (no fast-math), numpy's error model (a division by zero gives inf or
#: NaN, as numpy's does, instead of raising), on-disk cache.
JIT = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}


def _say_when_compiling() -> object | None:
    """The listener of numba's ``numba:compile`` event (a kernel loaded from the cache raises none)
    that says, once a process, on a terminal's stderr, why the first run waits. Captured or
    redirected stderr (tests, CI logs, the grader) gets nothing. None without numba."""
    if not HAVE_NUMBA:  # pragma: no cover
        return None
    import logging

    from numba.core import event

    class FirstCompile(event.Listener):
        said = False

        def on_start(self, ev: object) -> None:
            if self.said:
                return
            self.said = True
            if sys.stderr is not None and sys.stderr.isatty():
                logging.getLogger("qcarlab.sim").info(
                    "compiling qcarlab's kernels for this machine (once after an install; "
                    "about 10-30 s, later runs load them from the cache)")

        def on_end(self, ev: object) -> None:
            pass

    listener = FirstCompile()
    event.register("numba:compile", listener)
    return listener


COMPILE_NOTICE = _say_when_compiling()

__all__ = ["COMPILE_NOTICE", "HAVE_NUMBA", "JIT", "njit"]
