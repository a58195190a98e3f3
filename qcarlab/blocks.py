"""The lab's blocks by their sheet names, and the student's own blocks plugged in from a file.

Every lab is a block diagram (:mod:`qcarlab.experiments.models`): each Simulink block of the
sheet is one function (or small class) looked up by its sheet name in snake_case. A student
replaces any of them without touching the package::

    qcarlab stop-sign --use mylab/stop_sign.py              # every block named in the file
    qcarlab avoid --block lidar_stop=mine.py:my_stop         # one block, any function name
    follow_path(car, path, cfg, blocks={"pure_pursuit": my_fn})   # the Python API

A student's block is called through :class:`StudentBlock`, which makes student code fail like
student code: an exception inside it stops the run (the car is stopped by the loop) and is
reported with the student's own frames only (file:line) and the block's name, exit 1; a return
value of the wrong type, NaN or out of the block's range is one line naming the block and the
value, exit 1; an unfilled template (a body that still raises ``NotImplementedError``) is found
before the car moves: one line naming the file, the block and the sheet task, exit 2. Each call
is timed, so a block slower than the tick on a real-time car is reported, not silently lagged.

A stateful block may be a class: it is instantiated once per run (no arguments), its instance is
called like the function (``__call__``), and ``reset()`` is called at the start if it has one.
"""

from __future__ import annotations

import ast
import importlib.util
import inspect
import math
import numbers
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from qcarlab.errors import InputError, QcarlabError

_clock = time.perf_counter

__all__ = [
    "BLOCK_TIMEOUT_S",
    "BlockSpec",
    "BlockTimeout",
    "RaisedInBlock",
    "StudentBlock",
    "StudentBlockError",
    "load_block_file",
    "parse_block_option",
    "resolve_student_blocks",
    "together",
    "unwatch",
]


class StudentBlockError(QcarlabError):
    """A student's block raised or returned something unusable. Exit code 1 (the run failed)."""

    exit_code = 1


class BlockTimeout(BaseException):
    """Raised inside a student's block that has run longer than :func:`block_timeout` (an endless
    loop?), by the watchdog's alarm on the main thread. A BaseException, so the student's own
    ``except Exception`` does not swallow it; :class:`StudentBlock` turns it into one line."""


#: Seconds a student's block may run in one call before it is taken for stuck (internal: the
#: environment's QCARLAB_BLOCK_TIMEOUT_S, or this; tests lower it).
BLOCK_TIMEOUT_S = 5.0


def block_timeout() -> float:
    """The watchdog's limit for one call of a student's block, s."""
    text = os.environ.get("QCARLAB_BLOCK_TIMEOUT_S")
    try:
        value = float(text) if text else BLOCK_TIMEOUT_S
    except ValueError:
        value = BLOCK_TIMEOUT_S
    return value if math.isfinite(value) and value > 0 else BLOCK_TIMEOUT_S


class _Watchdog:
    """Interrupts a student's block that has not returned after :func:`block_timeout` s: a real-time
    alarm (SIGALRM through ``setitimer``, armed around each call on the main thread; it fires again
    every half second should the student's code swallow the first) raises :class:`BlockTimeout`
    in the block, wherever it is (a Python loop, a sleep, waiting for the student's process). The
    alarm is ours only where nothing else handles SIGALRM; elsewhere (another thread, a host
    program's own alarm) blocks run unwatched, as before.

    Two ways to arm it. Where the student's blocks run in this process (a lab run, on the
    simulator or a car), each call sets the alarm and cancels it when it returns: no alarm fires
    unless a block overruns, so none interrupts what a car's C library (a HIL read on the QCar)
    is doing. Where they run in the student's own process (:attr:`lazy`, set by :func:`load_with`:
    a graded task, whose car is the simulator), a call costs no system call: an alarm set for an
    earlier call is left to fire and sets itself again for the call running then."""

    def __init__(self) -> None:
        self.main = threading.main_thread().ident
        self.limit = BLOCK_TIMEOUT_S
        self.running: StudentBlock | None = None  # the block in a watched call
        self.deadline = 0.0  # when its time is up (time.monotonic)
        self.pending = False  # an alarm is set (for this call or an earlier one)
        self.alarm_at = 0.0  # when it fires (time.monotonic)
        self.later: Callable[[], int] | None = None  # a batch's: the index of its call now running
        self.lazy = False  # the blocks run in the student's process: alarms are left set (see above)
        self.handler = self._alarm  # one bound method, so that ``is`` recognises it

    def ready(self) -> bool:
        """Install the handler (at a run's start, on the main thread); True when calls are watched."""
        if threading.get_ident() != self.main:
            return False
        handler = signal.getsignal(signal.SIGALRM)
        if handler is not self.handler:
            if handler not in (signal.SIG_DFL, None):
                return False
            signal.signal(signal.SIGALRM, self.handler)
            self.pending = False  # an alarm set before went to another handler
        self.limit = block_timeout()
        return True

    def _alarm(self, signum: int, frame: Any) -> None:
        self.pending = False
        if self.running is None:  # set for a call that returned: it lapses (the next call sets another)
            return
        now = _monotonic()
        left = self.deadline - now
        if left <= 0.0 and self.later is not None and self.later() > 0:
            # a batch (see together) whose first call returned in its time: the second call began
            # before this deadline, so one more limit from it gives the second at least its own
            self.later = None
            self.deadline += self.limit
            left = self.deadline - now
        self.pending = True
        if left > 0.0:  # set for an earlier call: this one's time is not up yet
            self.alarm_at = now + left
            _setitimer(_REAL, left)
            return
        self.alarm_at = now + 0.5
        _setitimer(_REAL, 0.5)  # and again every half second, should the student's code swallow it
        raise BlockTimeout()

    def arm(self, block: StudentBlock) -> bool:
        """Watch ``block``'s call (the handler was installed by :meth:`ready`): its deadline, and an
        alarm. When :attr:`lazy`, an alarm set for an earlier call is left to fire and set itself
        again for this one's deadline, so that a call costs no system call here (two otherwise:
        a block called every tick of a graded run through its student's process)."""
        if _get_ident() != self.main:
            return False
        self.deadline = deadline = _monotonic() + self.limit
        self.running = block
        if not self.lazy or not self.pending or deadline < self.alarm_at:  # (or the limit was lowered)
            self.pending = True
            self.alarm_at = deadline
            _setitimer(_REAL, self.limit)
        return True

    def disarm(self) -> None:
        """The call returned: its alarm is cancelled, or, when :attr:`lazy`, left to find no call
        and lapse (or set itself again for the next call's deadline)."""
        self.running = None
        if not self.lazy and self.pending:
            self.pending = False
            _setitimer(_REAL, 0.0)

    def stop(self) -> None:
        """No call watched and no alarm set (a run ends, a stuck block's process is ended)."""
        self.running, self.later = None, None
        self.pending = False
        _setitimer(_REAL, 0.0)

    def _forked(self) -> None:
        self.running, self.later, self.pending = None, None, False  # a fork's child has no alarm set


_get_ident, _setitimer, _REAL, _monotonic = threading.get_ident, signal.setitimer, signal.ITIMER_REAL, time.monotonic
_watchdog = _Watchdog()
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_watchdog._forked)


def unwatch() -> None:
    """No watchdog alarm left set (a run's end: one set for its last calls would otherwise fire
    into whatever handles SIGALRM next, up to the block time limit later)."""
    if _watchdog.pending:
        _watchdog.stop()


class RaisedInBlock(Exception):
    """What a student's block did in the student's own process (:mod:`qcarlab.sandbox`), as the
    trusted side learns it: ``kind`` is ``exception``, ``not_implemented``, ``system_exit`` (then
    ``message`` is the exit code), ``value`` (a value that cannot be passed back), ``output`` (it printed
    more than the cap) or ``died`` (the process ended: ``message`` says how); ``traceback`` is the student's frames only."""

    def __init__(self, kind: str, type_name: str, message: str, traceback: str = ""):
        super().__init__(message)
        self.kind, self.type_name, self.message, self.traceback = kind, type_name, message, traceback

    @classmethod
    def of(cls, exc: BaseException, file: Path) -> RaisedInBlock:
        """What the student's exception ``exc`` (raised by their code in ``file``) was, as data."""
        if isinstance(exc, SystemExit):
            return cls("system_exit", "SystemExit", repr(exc.code))
        kind = "not_implemented" if isinstance(exc, NotImplementedError) else "exception"
        return cls(kind, type(exc).__name__, str(exc)[:2000], student_traceback(exc, file))


#: Where the student's files are loaded: None = in this process (a lab run); a grader's task sets
#: its sandboxed student process's loader (:meth:`qcarlab.sandbox.client.BlockHost.load`).
_loader: Callable[[Path], dict[str, Any]] | None = None


def load_with(loader: Callable[[Path], dict[str, Any]] | None) -> None:
    """Load the student's files with ``loader`` (path -> {name: function or class}) from now on;
    None: in this process again."""
    global _loader
    _loader = loader
    _watchdog.lazy = loader is not None  # (the calls are round trips to the student's process)


def _is_class(target: Any) -> bool:
    """A class (a stateful block), here or in the student's process."""
    return inspect.isclass(target) or getattr(target, "block_class", False) is True


@dataclass(frozen=True)
class BlockSpec:
    """One block of a lab's diagram: the sheet's name, its fixed signature and units.

    ``returns`` names the check applied to a student's return value: ``speed`` (m/s, finite,
    |v| <= 10), ``steering`` (rad, finite, |delta| <= pi/2), ``throttle`` (duty, finite,
    |u| <= 1), ``speed_steering`` (a pair of those), ``pose`` (three finite numbers), ``image``
    (uint8, the shape of the block's input image), ``mask`` (uint8, its height and width), or ``any``.
    ``fill`` is the sheet's task text when the block is one the student fills in (the template
    writes a file for it); ``stub`` is the body the template gives it.
    """

    name: str
    signature: str  # e.g. "stop_sign(distance_to_sign, desired_speed) -> speed_cmd"
    units: str  # e.g. "m, m/s -> m/s"
    section: str  # e.g. "5.2 Task 1, Figure 51"
    doc: str  # one line: what it does
    returns: str = "any"
    stateful: bool = False
    fill: str | None = None  # the sheet's task text, for blocks the student fills in
    args: tuple[str, ...] = ()  # the parameter names (from the signature)
    example: str = ""  # a call with its reference result, for the template's docstring

    @property
    def params(self) -> tuple[str, ...]:
        if self.args:
            return self.args
        inside = self.signature.split("(", 1)[1].split(")", 1)[0]
        return tuple(a.strip() for a in inside.split(",") if a.strip())


# --------------------------------------------------------------------------------------------
# return-value checks
# --------------------------------------------------------------------------------------------
_LIMITS = {"speed": (10.0, "m/s"), "steering": (math.pi / 2.0, "rad"), "throttle": (1.0, "(duty fraction)")}


def _number(block: str, value: Any, kind: str, what: str = "") -> float:
    limit, unit = _LIMITS[kind]
    if type(value) is float and -limit <= value <= limit:  # the usual case, in plain comparisons (NaN fails them)
        return value
    label = f"{what} " if what else ""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        shape = getattr(value, "shape", None)
        if shape == () or (shape is not None and len(shape) == 1 and shape[0] == 1):
            value = float(value.reshape(-1)[0]) if shape else float(value)  # a numpy scalar or 1-element array
        else:
            raise StudentBlockError(f"block {block} returned {_short(value)} ({type(value).__name__}); "
                                    f"expected {label}a number in {unit}")
    v = float(value)
    if not math.isfinite(v):
        raise StudentBlockError(f"block {block} returned {label}{v}; expected a finite number in {unit}")
    if abs(v) > limit:
        raise StudentBlockError(f"block {block} returned {label}{v:g} {unit}, out of range (|value| <= {limit:g})")
    return v


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _image(block: str, value: Any, like: Any, kind: str) -> Any:
    """An image block's value: uint8, the shape of the block's input image (``image``: (H, W, 3)
    for a BGR input; ``mask``: (H, W))."""
    want = tuple(getattr(like, "shape", ()))
    if kind == "mask":
        want = want[:2]
    shape, dtype = getattr(value, "shape", None), getattr(value, "dtype", None)
    if shape is None or tuple(shape) != want or str(dtype) != "uint8":
        got = f"an array of shape {tuple(shape)} and dtype {dtype}" if shape is not None else _short(value)
        what = "a uint8 mask (0/255)" if kind == "mask" else "a uint8 BGR image"
        raise StudentBlockError(f"block {block} returned {got}; expected {what} of shape {want}, like its input")
    return value


def check_return(block: str, kind: str, value: Any, args: tuple = ()) -> Any:
    """``value`` as the lab uses it, or :class:`StudentBlockError` naming the block and the value
    (``args``: the block's arguments, for the checks that compare with its input)."""
    if kind in _LIMITS:
        return _number(block, value, kind)
    if kind in ("image", "mask"):
        return _image(block, value, args[0] if args else None, kind)
    if kind == "speed_steering":
        if not (isinstance(value, (tuple, list)) and len(value) == 2):
            raise StudentBlockError(f"block {block} returned {_short(value)}; expected a pair "
                                    "(speed_cmd in m/s, steering_cmd in rad)")
        return (_number(block, value[0], "speed", "speed_cmd"), _number(block, value[1], "steering", "steering_cmd"))
    if kind == "pose":
        try:
            x, y, yaw = (float(v) for v in value)
        except (TypeError, ValueError):
            raise StudentBlockError(f"block {block} returned {_short(value)}; expected (x, y, yaw) in m, m, rad") \
                from None
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            raise StudentBlockError(f"block {block} returned {_short(value)}; expected finite (x, y, yaw)")
        return (x, y, yaw)
    return value


# --------------------------------------------------------------------------------------------
# the student's block
# --------------------------------------------------------------------------------------------
@dataclass
class StudentBlock:
    """A student's function (or class) in place of a reference block; called like the block.

    ``source`` is ``file.py:function``. Every call is checked (see the module docstring) and
    timed: ``calls``, ``worst_s`` and the number of calls over ``budget_s`` (when set).
    """

    spec: BlockSpec
    target: Any  # the function, or the class (instantiated by start())
    source: str
    file: Path
    calls: int = 0
    worst_s: float = 0.0
    total_s: float = 0.0
    over_budget: int = 0
    budget_s: float | None = None
    fn: Callable[..., Any] | None = field(default=None, repr=False)
    watched: bool = field(default=False, repr=False)  # its calls are under the watchdog (see _Watchdog)

    def start(self) -> StudentBlock:
        """Ready for a run: instantiate a class (once), call its ``reset()`` if it has one."""
        self.calls, self.worst_s, self.total_s, self.over_budget = 0, 0.0, 0.0, 0
        self.watched = _watchdog.ready()
        if _is_class(self.target):
            obj = self._guard(self.target, ())
            if not callable(obj):
                raise StudentBlockError(f"block {self.spec.name} ({self.source}): the class has no __call__ method; "
                                        f"give it one with the block's signature {self.spec.signature}")
            self.fn = obj
        else:
            self.fn = self.target
        reset = getattr(self.fn, "reset", None)
        if _is_class(self.target) and callable(reset):
            self._guard(reset, ())
        return self

    def _guard(self, fn: Callable[..., Any], args: tuple, kwargs: Mapping[str, Any] | None = None) -> Any:
        armed = self.watched and _watchdog.arm(self)
        try:
            return fn(*args, **(kwargs or {}))
        except BaseException as exc:  # noqa: BLE001 - the student's code may raise anything
            self._failed(exc)
        finally:
            if armed:
                _watchdog.disarm()

    def _failed(self, exc: BaseException) -> None:
        """Raise what the student's exception ``exc`` means for the run (see the module docstring):
        raised here, or in the student's own process (:class:`RaisedInBlock`)."""
        if isinstance(exc, (KeyboardInterrupt, QcarlabError)):
            raise exc
        where = f"block {self.spec.name} ({self.source})"
        if isinstance(exc, BlockTimeout):
            _watchdog.stop()  # no second alarm while the run ends
            at = [f for f in traceback.extract_tb(exc.__traceback__)
                  if Path(f.filename).resolve() == Path(self.file).resolve()]
            line = f", at {self.file}:{at[-1].lineno}" if at else ""
            raise StudentBlockError(f"{where} has not returned after {_watchdog.limit:g} s: an endless loop?"
                                    + (f" (at {line.removeprefix(', at ')})" if line else "")) from None
        what = exc if isinstance(exc, RaisedInBlock) else RaisedInBlock.of(exc, self.file)
        if what.kind == "not_implemented":
            raise InputError(f"{self.file}: {self.spec.name} is not filled in yet (sheet {self.spec.section}); "
                             "write its body, then run again") from None
        if what.kind == "system_exit":
            raise StudentBlockError(f"{where} called sys.exit({what.message}); a block returns its value instead") \
                from None
        if what.kind in ("died", "value", "output"):
            raise StudentBlockError(f"{where}: {what.message}") from None
        raise StudentBlockError(f"{what.traceback or _NO_LINE}\n{where} raised {what.type_name}: {what.message}") \
            from None

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        fn = self.fn
        if fn is None:
            fn = self.start().fn
        armed = self.watched and _watchdog.arm(self)
        t0 = _clock()
        try:  # (self._guard written out: this runs every tick)
            value = fn(*args, **kwargs)
        except BaseException as exc:  # noqa: BLE001 - the student's code may raise anything
            self._failed(exc)
        finally:
            if armed:
                _watchdog.disarm()
        return self._done(value, _clock() - t0, args)

    def _done(self, value: Any, spent: float, args: tuple) -> Any:
        """A call's bookkeeping (its time) and its checked value."""
        self.calls += 1
        self.total_s += spent
        if spent > self.worst_s:
            self.worst_s = spent
        if self.budget_s is not None and spent > self.budget_s:
            self.over_budget += 1
        return check_return(self.spec.name, self.spec.returns, value, args)

    def __getattr__(self, name: str) -> Any:  # e.g. a class's .state, read for the log
        if name.startswith("__") or self.__dict__.get("fn") is None:
            raise AttributeError(name)
        return getattr(self.__dict__["fn"], name)

    def timing(self) -> dict[str, Any]:
        return {"source": self.source, "calls": self.calls, "worst_s": self.worst_s,
                "mean_s": self.total_s / self.calls if self.calls else 0.0, "over_budget": self.over_budget,
                "budget_s": self.budget_s}


def together(first: Any, first_args: tuple, second: Any, second_args: tuple) -> tuple[Any, Any]:
    """``(first(*first_args), second(*second_args))``, called in that order, for two calls of a
    tick where the second's arguments do not depend on the first's value (path following's
    steering and speed controller without turn_speed_handling). Two student blocks in the same
    student process (a graded run's :mod:`qcarlab.sandbox`) go there in one round trip instead of
    two; each is checked as :meth:`StudentBlock.__call__` checks it (a first block that raises or
    returns what cannot be passed back is the one named; the second is not called after a first
    that raised) and each has the watchdog's whole limit. Anything else is called one after the
    other."""
    if type(first) is StudentBlock and type(second) is StudentBlock:
        client = sys.modules.get("qcarlab.sandbox.client")
        a, b = first.fn, second.fn
        if client is not None and type(a) in client.REMOTE and type(b) in client.REMOTE:
            (host, key_a), (host_b, key_b) = a._remote(), b._remote()
            if host is host_b:
                return _together_remote(host, first, first_args, key_a, second, second_args, key_b)
    return first(*first_args), second(*second_args)


def _together_remote(host: Any, first: StudentBlock, first_args: tuple, key_a: int, second: StudentBlock,
                     second_args: tuple, key_b: int) -> tuple[Any, Any]:
    blocks = (first, second)
    armed = first.watched and _watchdog.arm(first)
    if armed:
        _watchdog.later = host.running  # the second call has a limit of its own (see _Watchdog._alarm)
    t0 = _clock()
    try:
        replies, seconds = host.calls([(key_a, first_args, None, None), (key_b, second_args, None, None)])
    except BaseException as exc:  # noqa: BLE001 - the timeout, or the student's process died
        blocks[min(host.running(), 1)]._failed(exc)
    finally:
        if armed:
            _watchdog.later = None
            _watchdog.disarm()
    spent = _clock() - t0
    # the round trip's time, split as the student's process says its calls took (evenly, should it
    # say something that is not a time): a split of what was measured here, never more than it
    told = [s if type(s) is float and 0.0 <= s < math.inf else math.nan for s in seconds]
    total = sum(told)
    shares = [s / total for s in told] if total > 0.0 else [1.0 / len(told)] * len(told)
    values = []
    for block, args, reply, share in zip(blocks, (first_args, second_args), replies, shares):
        try:
            value = host.value(reply)
        except BaseException as exc:  # noqa: BLE001
            block._failed(exc)
        values.append(block._done(value, spent * share, args))
    if len(values) < 2:  # (the first returned, so the second ran: its reply is missing)
        try:
            host.value(None)
        except BaseException as exc:  # noqa: BLE001
            second._failed(exc)
    return values[0], values[1]


_NO_LINE = "  (no line of your file in the traceback: the error came from a call your block made)"


def student_traceback(exc: BaseException, file: Path) -> str:
    """The traceback of ``exc`` cut to the frames in the student's ``file`` (file:line and code)."""
    want = str(Path(file).resolve())
    lines = []
    for frame in traceback.extract_tb(exc.__traceback__):
        if str(Path(frame.filename).resolve()) == want:
            lines.append(f"  {file}:{frame.lineno} in {frame.name}")
            if frame.line:
                lines.append(f"    {frame.line.strip()}")
    if not lines:
        return _NO_LINE
    return "\n".join(["traceback (your code only):"] + lines)


# --------------------------------------------------------------------------------------------
# loading a student's file
# --------------------------------------------------------------------------------------------
def check_block_file(path: Path) -> None:
    """A student's file must be a Python file that is there (one line otherwise)."""
    if not path.is_file():
        raise InputError(f"{path}: no such file (expected a Python file with your blocks)")
    if path.suffix != ".py":
        raise InputError(f"{path}: expected a Python file (.py)")


def _import_file(path: Path) -> Any:
    check_block_file(path)
    name = f"qcarlab_student_{abs(hash(str(path.resolve())))}"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise InputError(f"{path}: cannot be loaded as a Python module")
    module = importlib.util.module_from_spec(spec)
    folder = str(path.resolve().parent)
    added = folder not in sys.path
    if added:
        sys.path.insert(0, folder)  # so the student's file can import its neighbours
    try:
        spec.loader.exec_module(module)
    except SyntaxError as exc:
        raise InputError(f"{path} line {exc.lineno}: syntax error: {exc.msg}") from None
    except (KeyboardInterrupt, QcarlabError):
        raise
    except SystemExit:
        raise InputError(f"{path}: calls sys.exit when it is imported; put the code in functions") from None
    except BaseException as exc:  # noqa: BLE001
        raise InputError(f"{path}: importing it raised {type(exc).__name__}: {exc}\n"
                         + student_traceback(exc, path)) from None
    finally:
        if added:
            try:
                sys.path.remove(folder)
            except ValueError:
                pass
    return module


def _members(path: Path) -> dict[str, Any]:
    """The top-level functions and classes of a student's file, loaded in this process or, in a
    graded task, in the student's own (see :func:`load_with`)."""
    if _loader is not None:
        return _loader(path)
    module = _import_file(path)
    return {k: v for k, v in vars(module).items() if inspect.isfunction(v) or inspect.isclass(v)}


def is_stub(tree: ast.Module, name: str) -> bool:
    """True when ``name`` in the parsed module still has a template's body: only ``raise
    NotImplementedError`` (after its docstring), or a class whose ``__call__`` is like that."""
    def stub(fn: ast.AST) -> bool:
        body = [s for s in fn.body if not (isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant))]
        if len(body) != 1 or not isinstance(body[0], ast.Raise) or body[0].exc is None:
            return False
        exc = body[0].exc
        called = exc.func if isinstance(exc, ast.Call) else exc
        return isinstance(called, ast.Name) and called.id == "NotImplementedError"

    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name == name:
            return stub(node)
        if isinstance(node, ast.ClassDef) and node.name == name:
            return any(isinstance(m, ast.FunctionDef) and m.name == "__call__" and stub(m) for m in node.body)
    return False


def _unfilled(path: Path, name: str) -> bool:
    """True when ``name`` in ``path`` still has a template's body: only ``raise NotImplementedError``
    (after its docstring), or a class whose ``__call__`` is like that."""
    try:
        tree = ast.parse(path.read_text(encoding="utf-8"))
    except (OSError, SyntaxError, ValueError):
        return False

    return is_stub(tree, name)


def _defined_names(path: Path) -> set[str]:
    """The top-level function and class names of a Python file (without running it)."""
    try:
        tree = ast.parse(path.read_text(encoding="utf-8"))
    except SyntaxError as exc:
        raise InputError(f"{path} line {exc.lineno}: syntax error: {exc.msg}") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read it ({exc})") from None
    return {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))}


def _make(spec: BlockSpec, target: Any, path: Path, func: str, stubs_when_called: bool = False) -> StudentBlock:
    """The student's block; a template's body still unfilled is refused now, or, with
    ``stubs_when_called`` (a workspace folder: the template writes every block of the lab, and a
    run calls some), when the run first calls it, with the same message."""
    if not callable(target):
        raise InputError(f"{path}: {func} is not a function or class")
    if not stubs_when_called and _unfilled(path, func):
        raise InputError(f"{path}: {spec.name} is not filled in yet (sheet {spec.section}); "
                         "write its body, then run again")
    return StudentBlock(spec, target, f"{path}:{func}", path)


def load_block_file(path: str | Path, specs: Mapping[str, BlockSpec], lab: str,
                    stubs_when_called: bool = False) -> dict[str, StudentBlock]:
    """Every top-level function or class of the file named like one of the lab's blocks (an
    unfilled one refused now, or when called: see :func:`_make`)."""
    p = Path(path)
    members = _members(p)
    found = {}
    for name, spec in specs.items():
        target = members.get(name)
        if target is not None:
            found[name] = _make(spec, target, p, name, stubs_when_called)
    if not found:
        raise InputError(f"{p}: defines none of the {lab} blocks ({', '.join(specs)}); "
                         f"see: qcarlab blocks {lab}")
    return found


def parse_block_option(text: str) -> tuple[str, Path, str]:
    """``NAME=FILE.py:FUNC`` (``:FUNC`` optional, default NAME) -> (NAME, FILE, FUNC)."""
    name, sep, rest = text.partition("=")
    name, rest = name.strip(), rest.strip()
    if not sep or not name or not rest:
        raise InputError(f"--block {text!r}: expected NAME=FILE.py:FUNCTION (e.g. stop_sign=mylab/stop.py:stop_sign)")
    file, colon, func = rest.rpartition(":")
    if not colon or not file.endswith(".py"):
        file, func = rest, name
    if not func.isidentifier():
        raise InputError(f"--block {text!r}: {func!r} is not a Python function name")
    return name, Path(file), func


def resolve_student_blocks(
    specs: Mapping[str, BlockSpec],
    lab: str,
    use: Iterable[str | Path] = (),
    block: Iterable[str] = (),
) -> dict[str, StudentBlock]:
    """The student's blocks from ``--use FILE`` (all matching names) and ``--block NAME=FILE:FUNC``
    (later options win); unknown block names are refused with the lab's list."""
    out: dict[str, StudentBlock] = {}
    for file in use:
        folder = Path(file)
        if folder.is_dir():  # a workspace: every .py file in it that defines blocks of this lab
            found: dict[str, StudentBlock] = {}
            for path in sorted(folder.glob("*.py")):
                names = _defined_names(path) & set(specs)
                if names:  # (a block still as the template wrote it stops the run only if the run calls it)
                    found.update(load_block_file(path, {n: specs[n] for n in names}, lab, stubs_when_called=True))
            if not found:
                raise InputError(f"--use {folder}: no .py file there defines one of the {lab} blocks "
                                 f"({', '.join(specs)}); see: qcarlab blocks {lab}")
            out.update(found)
        else:
            out.update(load_block_file(file, specs, lab))
    for text in block:
        name, file, func = parse_block_option(text)
        if name not in specs:
            raise InputError(f"--block {text!r}: {lab} has no block {name!r} (its blocks: {', '.join(specs)})")
        target = _members(file).get(func)
        if target is None:
            raise InputError(f"--block {text!r}: {file} has no function or class {func!r}")
        out[name] = _make(specs[name], target, file, func)
    return out


def as_block(spec: BlockSpec, value: Any, where: str = "blocks") -> Any:
    """A block given through the Python API (``blocks={"pure_pursuit": fn}``): a StudentBlock is
    kept, a plain function or class is wrapped so it is checked and timed like one from a file."""
    if isinstance(value, StudentBlock):
        return value
    if not callable(value):
        raise InputError(f"{where}[{spec.name!r}]: expected a function or class, got {type(value).__name__}")
    inner = getattr(value, "func", value)  # a functools.partial's function
    try:
        src = inspect.getsourcefile(inner)
    except TypeError:  # a builtin or a C function
        src = None
    file = Path(src) if src else Path("<python>")
    name = getattr(inner, "__qualname__", getattr(inner, "__name__", spec.name))
    return StudentBlock(spec, value, f"{file}:{name}", file)
