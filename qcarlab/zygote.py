"""What a forking server (a *zygote*) shares: the warm-up it does once, and how a forked process ends.

Two servers fork processes that are already warm: the grader's (:mod:`qcarlab.grading.warm`: one
process per graded task) and the student's (:mod:`qcarlab.warm`: one process per command typed
at a terminal). Both load here, once, what a cold ``qcarlab`` process pays for on every start
(the interpreter's imports, numba and its compiled kernels, the CLI's parsers, matplotlib's
fonts), and both end a forked process as the interpreter would end a cold one
(:func:`run_as_interpreter`). A zygote runs no OpenCV code and starts no thread: a fork keeps only
the forking thread, and another thread's locks would hang the child.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

#: What a lab's process imports besides its command's module (measured: some 0.7 s a process).
MODULES = ("qcarlab.cli", "qcarlab.cli.invocation", "qcarlab.cli.recording", "qcarlab.experiments.labs",
           "qcarlab.experiments.worlds", "qcarlab.grading.child", "qcarlab.plots", "qcarlab.car.replay",
           "qcarlab.recording.reader", "qcarlab.sim.world", "qcarlab.sim.raster", "qcarlab.sim.render",
           "qcarlab.sim.lidar", "qcarlab.sim.camera",
           "qcarlab.control._kernels",  # (the labs import it where first called: its cached kernels loaded here)
           # a graded task's: the student's process and its channel, the run's progress line (and rich's
           # emoji table, which its markup loads), the trials and the HSV tuner (measured: some 10 ms a task)
           "qcarlab.sandbox.client", "qcarlab.sandbox.codec", "qcarlab.sandbox.cgroup", "qcarlab.sandbox.host",
           "qcarlab.cli.progress", "qcarlab.wire.interrupts", "rich._emoji_codes", "mmap", "qcarlab.experiments.trials",
           "qcarlab.cli.hsv_tune", "qcarlab.perception.tuner")


def lab_modules() -> tuple[str, ...]:
    """Every module of the packages a lab command draws on (experiments, perception, control, the
    simulator, the cars), for a zygote whose processes run any lab."""
    import importlib
    import pkgutil

    names: list[str] = []
    for package in ("qcarlab.experiments", "qcarlab.perception", "qcarlab.control", "qcarlab.sim", "qcarlab.car"):
        try:
            path = importlib.import_module(package).__path__
        except ImportError:
            continue
        names += [f"{package}.{m.name}" for m in pkgutil.iter_modules(path) if not m.ispkg]
    return tuple(names)


def warm_up(modules: tuple[str, ...] = MODULES) -> None:
    """Load once what every lab process loads: ``modules`` and every command of the CLI with its
    click group (every command's parser), numba and the compiled physics, every kernel numba has
    compiled code for in its cache (:func:`load_cached_kernels`), the avoidance controller's kernels
    (compiled if they never were: :func:`qcarlab.control._kernels.warm`), the sandbox's libc and its probe
    (:func:`qcarlab.sandbox.jail.probe`), matplotlib's Agg canvas with its fonts, glibc's heap
    thresholds (:func:`qcarlab.heap.keep_heap`). No OpenCV call,
    no sensor frame, no thread. What fails here is left for the forked process to load itself.

    The cyclic garbage collector is paused meanwhile: the imports make objects by the hundred
    thousand and few cycles, and its passes over the growing heap cost some 0.25 s of the 1.2 s
    (the same peak memory; both servers collect and freeze what they loaded afterwards)."""
    import gc

    paused = gc.isenabled()
    gc.disable()
    try:
        _warm_up(modules)
    finally:
        if paused:
            gc.enable()


def _warm_up(modules: tuple[str, ...]) -> None:
    import importlib

    from qcarlab.heap import keep_heap

    keep_heap()  # every forked process (a lab, a graded task, the student's process) reuses its heap
    for name in modules:
        try:
            importlib.import_module(name)
        except ImportError:
            pass
    try:
        from qcarlab.cli.invocation import parse_command

        # every command loaded and its click parser built (cli.app.click_group), typer's runtime parameters
        parse_command(["path-follow", "line", "--speed", "0.5"])
    except Exception:  # noqa: BLE001 - a forked process then loads them itself
        pass
    try:
        from qcarlab.car.sim import SimCar

        SimCar().warm_physics()  # numba, and the compiled physics kernel loaded from its cache
    except Exception:  # noqa: BLE001
        pass
    load_cached_kernels()
    try:
        from qcarlab.control import _kernels

        _kernels.warm()  # compiled here if never before: a student's process (no cache it can write) calls them
    except Exception:  # noqa: BLE001
        pass
    try:
        from qcarlab.sandbox import jail

        if sys.platform.startswith("linux"):
            jail.libc()  # ctypes' find_library runs ``ldconfig -p``: once here, not in each student's process
            jail.probe()  # whether this machine can sandbox (a fork that unshares): once, not once per task
    except Exception:  # noqa: BLE001
        pass
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        fig = Figure(figsize=(1, 1))
        FigureCanvasAgg(fig)
        fig.add_subplot(1, 1, 1).set_title("warm")
        fig.canvas.draw()  # the font cache and the text renderer
    except Exception:  # noqa: BLE001
        pass


def load_cached_kernels() -> int:
    """Load, from numba's on-disk cache, every signature of every compiled kernel of qcarlab's
    imported modules that the cache holds for this machine and this source: what each first call
    in a cold process does (some 0.2 s for numba's code generator on the first, 20-60 ms each
    after). A kernel never compiled stays lazy (its first call compiles it, as before). Returns how
    many signatures were loaded. Uses numba's cache index (``Dispatcher._cache``): where that
    changes, nothing is loaded here and every process loads its kernels itself."""
    try:
        from numba.core.dispatcher import Dispatcher
    except ImportError:
        return 0
    seen: set[int] = set()
    loaded = 0
    for name, module in list(sys.modules.items()):
        if not name.startswith("qcarlab.") or module is None:
            continue
        for value in list(vars(module).values()):
            if not isinstance(value, Dispatcher) or id(value) in seen:
                continue
            seen.add(id(value))
            try:
                magic = value.targetctx.codegen().magic_tuple()
                index = value._cache._cache_file._load_index()
                for key in index:
                    if key[1] == magic and key[0] not in value.overloads:
                        value.compile(key[0])
                        loaded += 1
            except Exception:  # noqa: BLE001 - numba's internals moved, or a stale entry: stays lazy
                continue
    return loaded


def after_fork() -> None:
    """In a forked process, first: what it must not share with the zygote and its siblings.
    matplotlib's fonts are open files read through a shared file offset: two processes drawing
    text at once would read each other's bytes; the process opens its own."""
    font_manager = sys.modules.get("matplotlib.font_manager")
    get_font = getattr(font_manager, "_get_font", None)
    if get_font is not None and hasattr(get_font, "cache_clear"):
        get_font.cache_clear()


class Lines:
    """The lines a zygote sends on one connection (its replies: ``pid N``, ``exit RC``, ...)."""

    def __init__(self, conn):
        self.conn, self.buf = conn, b""

    def next(self) -> str:
        """The next line, without its newline; "" when the connection closed first."""
        while b"\n" not in self.buf:
            chunk = self.conn.recv(4096)
            if not chunk:
                return ""
            self.buf += chunk
        line, self.buf = self.buf.split(b"\n", 1)
        return line.decode(errors="replace")


def reap(sel, pid: int, pidfd: int, conn) -> None:
    """A forked process has ended (its ``pidfd`` is readable): collect it, take its pidfd and its
    connection off the selector ``sel``, tell the connection ``exit RC`` (negative: the signal)
    and close both."""
    _, status = os.waitpid(pid, 0)
    sel.unregister(pidfd)
    os.close(pidfd)
    try:
        sel.unregister(conn)
    except (KeyError, ValueError):
        pass
    try:
        conn.sendall(f"exit {os.waitstatus_to_exitcode(status)}\n".encode())
    except OSError:
        pass
    conn.close()


def _exit_code_of(exc: SystemExit) -> int:
    """The status the interpreter exits with for ``SystemExit(exc.code)`` (a text is printed, 1)."""
    if exc.code is None:
        return 0
    if isinstance(exc.code, int):
        return exc.code
    sys.stderr.write(f"{exc.code}\n")
    return 1


def run_as_interpreter(body: Callable[[], object]) -> None:
    """In a forked process: run ``body`` and end as ``python`` would after it (its ``SystemExit``'s
    status, or the traceback and 1; the non-daemon threads joined, the atexit handlers run), then
    leave at once (``os._exit``: nothing of the zygote's runs again). Never returns."""
    import signal

    code = 1
    interrupted = False
    try:
        try:
            body()
            code = 0
        except SystemExit as exc:
            code = _exit_code_of(exc)
        except KeyboardInterrupt:  # as the interpreter: the traceback, then ended by SIGINT
            sys.excepthook(*sys.exc_info())
            interrupted = True
        except BaseException:  # noqa: BLE001 - as the interpreter: the traceback, exit 1
            sys.excepthook(*sys.exc_info())
            code = 1
        import threading

        shutdown = getattr(threading, "_shutdown", None)
        if shutdown is not None:
            shutdown()  # wait for the process's non-daemon threads, as the interpreter does
        import atexit

        atexit._run_exitfuncs()
    except BaseException:  # noqa: BLE001
        code = 1
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001 - as the interpreter: a failed flush at exit is status 120
                code = code or 120
        if interrupted:
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGINT)
        os._exit(code & 0xFF)


__all__ = ["Lines", "MODULES", "after_fork", "lab_modules", "load_cached_kernels", "reap", "run_as_interpreter", "warm_up"]
