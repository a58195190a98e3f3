"""The one control loop every lab uses: read the sensors, call the lab's step, write, wait.

    class MyLab:                                  # or any model of qcarlab.experiments.models
        def step(self, t, readout, dt):           # the lab's diagram, once per tick
            return Step(Command(0.1, 0.0), log={"v": 0.0})   # or STOP to end the run

    log = run_loop(car, MyLab(), duration=5.0, rate=100.0)

A plain function ``step(t, readout) -> Command`` works too (the five-line scripts of the API).
``Step.log`` holds the lab's own values (v_ref, cross-track error, state, ...): the loop records
them beside what it logs itself, one row per tick, so no lab keeps state dicts of its own logs.

The clock follows the car: a stepped simulator is advanced by exactly ``dt = 1/rate`` per tick
(as fast as the CPU allows, deterministic); anything else (a real car, a real-time simulator, a
TCP car) is paced against the wall clock. A late tick on a paced car is not followed by a burst
of catch-up ticks: the schedule restarts from now, the step is told the real ``dt`` since the
last tick, and the late ticks are counted (``overruns``, ``worst_tick_s``). Whatever happens (the
end, an exception, a student's block failing, Ctrl-C) the car is left stopped; Ctrl-C returns the
log so far with ``interrupted`` set, so the run's results can still be saved.

Recorded and replayed runs: before each step the loop hands a recording car (``note_step``) the
``t`` and ``dt`` it gives the step, which go into the recording with the tick's command; a replay
of a real-time run (``recorded_step``) gives the step the ``t`` and ``dt`` it was given then, so
the lab computes the same commands from the same inputs.
"""

from __future__ import annotations

import contextvars
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from qcarlab.blocks import unwatch
from qcarlab.car.base import Car, Command, Readout
from qcarlab.errors import CarError, InputError
from qcarlab.heap import keep_heap

_log = logging.getLogger("qcarlab")

STOP = object()  # returned by a step function to end the run

#: Set by the CLI on a terminal (:mod:`qcarlab.cli.progress`): ``factory(duration_s)`` returns a
#: tracker for one run, called as ``tracker(t)`` with the run's time after a tick and
#: ``tracker.close()`` when the run ends, however it ends. Unset (the Python API, --json, CI), the
#: loop pays nothing for it.
PROGRESS: contextvars.ContextVar[Callable[[float], Any] | None] = contextvars.ContextVar("qcarlab_progress",
                                                                                         default=None)


@dataclass(slots=True)
class Step:
    """What a lab's step returns: the command for the car and the values to log this tick."""

    command: Command
    log: dict[str, Any] | None = None


@dataclass
class LoopLog:
    """What the loop saw and did, one row per tick (SI units)."""

    columns: dict[str, list[Any]] = field(default_factory=dict)
    ticks: int = 0
    stopped_early: bool = False  # the step returned STOP
    interrupted: bool = False  # Ctrl-C (or SIGTERM through the CLI) ended the run
    overruns: int = 0  # paced cars: ticks that started more than one period late
    worst_tick_s: float = 0.0  # paced cars: the longest gap between two ticks

    def add(self, **values: Any) -> None:
        for key, value in values.items():
            self.columns.setdefault(key, []).append(value)

    def arrays(self, keys: Any = None) -> dict[str, np.ndarray]:
        """The columns as numpy arrays (only those of ``keys`` that exist, when given: turning a
        column of thousands of Python floats into an array costs about as much as logging it)."""
        n = self.ticks
        cols = self.columns
        if keys is None:
            return {k: np.asarray(v[:n]) for k, v in cols.items()}
        return {k: np.asarray(cols[k][:n]) for k in keys if k in cols}


def check_rate(rate: float) -> float:
    if not (math.isfinite(rate) and 1.0 <= rate <= 2000.0):
        raise InputError(f"--rate must be between 1 and 2000 Hz, got {rate}")
    return float(rate)


def _caller(model: Any) -> Callable[[float, Readout, float], Any]:
    step = getattr(model, "step", None)
    if callable(step):
        return step
    if callable(model):
        return lambda t, r, dt: model(t, r)
    raise InputError(f"run_loop: expected a lab model with step(t, readout, dt) or a function, got {model!r}")


def run_loop(
    car: Car,
    model: Any,
    duration: float,
    rate: float = 100.0,
    on_tick: Callable[[float, Readout, Command], None] | None = None,
    record_truth: bool = True,
    pace: bool = False,
    keep_rows: bool = True,
) -> LoopLog:
    """Run the model at ``rate`` Hz for ``duration`` s (or until its step returns STOP).

    Each tick logs: t, the applied throttle and steering, encoder counts, tach (counts/s), motor
    current, battery voltage, gyro z, on a simulator the true pose and speed, and the step's own
    values (``Step.log``). ``model`` is a lab model (``step(t, readout, dt)``, with optional
    ``start(car, dt)``) or a function ``(t, readout) -> Command | Step | STOP``. ``pace`` paces
    even a stepped simulator against the wall clock (keyboard drive: a person is in the loop);
    ``keep_rows=False`` keeps only the counts (a drive of hours needs no per-tick log).
    """
    if not (math.isfinite(duration) and duration > 0.0):
        raise InputError(f"duration must be a positive number of seconds, got {duration}")
    period = 1.0 / check_rate(rate)
    n_ticks = max(1, round(duration * rate))
    keep_heap()  # a camera's frames from the heap, not fresh pages each (qcarlab.heap)
    log = LoopLog()
    cols = log.columns
    step = _caller(model)
    start = getattr(model, "start", None)
    if callable(start):
        start(car, period)
    has_truth = record_truth and car.truth() is not None
    stepped = car.stepped
    read, write, truth, advance = car.read, car.write, car.truth, car.advance
    base = ("t", "throttle", "steering", "encoder_counts", "tach", "motor_current", "battery_voltage", "gyro_z")
    tcols = ("true_x", "true_y", "true_yaw", "true_speed", "true_steering") if has_truth else ()
    for key in (base + tcols) if keep_rows else ():
        cols[key] = []
    n_fixed = len(cols)  # the loop's own columns; the rest are the step's (Step.log)
    # each column's append, bound once (the tick runs thousands of times a second)
    a_t, a_th, a_st, a_enc, a_tach, a_cur, a_bat, a_gz, a_x, a_y, a_yaw, a_v, a_d = _appends(cols, base, tcols)
    lab_append: dict[str, Callable[[Any], None]] = {}  # the step's columns' appends
    t0 = car.time
    dt = period
    next_wall = last_wall = time.monotonic()
    k = ticks = 0  # (log.ticks is set from ticks when the loop ends)
    recorder = getattr(car, "recorder", None)  # --record/--live (qcarlab.recording): the lab's values too
    progress = PROGRESS.get()
    tracker = None
    if progress is not None:  # a progress display (the CLI on a terminal): told after each tick
        tracker = progress(n_ticks * period)
        on_tick = _with_progress(on_tick, tracker)
    ends = hasattr(car, "ended")  # --car replay: the recording runs out
    note_step = getattr(car, "note_step", None)  # --record: the step's t and dt go with the tick's command
    recorded_step = getattr(car, "recorded_step", None)  # --car replay: the t and dt the step was given then
    try:
        for k in range(n_ticks):
            if ends and car.ended:  # the recording has run out
                log.stopped_early = True
                break
            readout = read()
            t, step_dt = readout.t - t0, dt
            if recorded_step is not None:  # a real-time run's recording: its ticks, as they were
                given = recorded_step()
                if given is not None:
                    t, step_dt = given
            if note_step is not None:
                note_step(t, step_dt)
            out = step(t, readout, step_dt)
            if out is STOP:
                log.stopped_early = True
                break
            if type(out) is Step:
                values, out = out.log, out.command
            else:
                values = None
            cmd = write(out.throttle, out.steering, out.leds)
            if keep_rows:
                a_t(t)
                a_th(cmd.throttle)
                a_st(cmd.steering)
                a_enc(readout.encoder_counts)
                a_tach(readout.tach)
                a_cur(readout.motor_current)
                a_bat(readout.battery_voltage)
                gyro = readout.gyro
                a_gz(float(gyro.item(2) if type(gyro) is np.ndarray else gyro[2]))
                if has_truth:
                    tr = truth()
                    a_x(tr.x)
                    a_y(tr.y)
                    a_yaw(tr.yaw)
                    a_v(tr.speed)
                    a_d(tr.steering)
                if values:
                    for key, value in values.items():
                        append = lab_append.get(key)
                        if append is None:  # a value first logged late: None for the ticks before
                            column = cols.get(key)
                            if column is None:
                                column = cols[key] = [None] * ticks
                            append = lab_append[key] = column.append
                        append(value)
            if recorder is not None and values:  # the lab's own values (a step's ``log``)
                recorder.log_values(readout.t, {"t": t, **values})
            ticks += 1
            if keep_rows and (len(values) if values else 0) != len(cols) - n_fixed:
                _pad(cols, ticks)  # a step's column not logged this tick
            if on_tick is not None:
                on_tick(t, readout, cmd)
            if stepped:
                advance(period)
            if pace or not stepped:
                next_wall += period
                now = time.monotonic()
                if now < next_wall:
                    time.sleep(next_wall - now)
                now = time.monotonic()
                if not stepped:  # a stepped car's time moved by exactly one period
                    dt = now - last_wall
                gap = now - last_wall
                last_wall = now
                if gap > log.worst_tick_s:
                    log.worst_tick_s = gap
                if now - next_wall > period:  # more than a period late: no burst of catch-up ticks
                    log.overruns += 1
                    next_wall = now
    except KeyboardInterrupt:
        log.interrupted = True
    except BaseException:
        _stop_quietly(car)  # the error in flight is the one to report, not a failing stop
        raise
    finally:
        log.ticks = ticks
        unwatch()  # (the student's blocks' watchdog)
        if tracker is not None:
            tracker.close()
    if log.interrupted:
        _stop_after_interrupt(car)
    else:
        car.stop()
    if keep_rows:
        _pad(cols, log.ticks)
    return log


def _with_progress(on_tick: Callable[[float, Readout, Command], None] | None, tracker: Callable[[float], Any]):
    """``on_tick`` that also tells the progress ``tracker`` the run's time after each tick."""
    if on_tick is None:
        return lambda t, readout, cmd: tracker(t)

    def both(t: float, readout: Readout, cmd: Command) -> None:
        on_tick(t, readout, cmd)
        tracker(t)

    return both


def _stop_after_interrupt(car: Car) -> None:
    """Stop the car after Ctrl-C or SIGTERM; the run so far is saved whatever happens here. A
    served car whose connection the interruption broke is stopped by its server (a controller's
    connection closing stops the car), which is said in one line."""
    try:
        car.stop()
    except CarError as exc:
        _log.warning("could not stop the car after the interruption (%s); its server stops it as the connection closes", exc)


def _stop_quietly(car: Car) -> None:
    """Stop the car after an error; when that fails too (the connection is gone), a served car's
    watchdog or the server's drop detection stops it."""
    try:
        car.stop()
    except Exception:  # noqa: BLE001
        pass


def _appends(cols: dict[str, list[Any]], base: tuple[str, ...], tcols: tuple[str, ...]) -> tuple:
    """The loop's columns' append methods, ``base`` then ``tcols`` (None for a column not kept):
    bound once, called every tick."""
    out = [cols[k].append if k in cols else None for k in base + tcols]
    return tuple(out) + (None,) * (13 - len(out))


def _pad(cols: dict[str, list[Any]], n: int) -> None:
    """Columns the step did not fill this tick (a value logged only sometimes) get None."""
    for column in cols.values():
        if len(column) < n:
            column.extend([None] * (n - len(column)))
