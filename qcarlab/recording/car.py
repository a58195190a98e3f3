""":class:`RecordingCar`: any :class:`~qcarlab.car.base.Car`, recorded as it is used.

    from qcarlab.recording import Recorder, RecordingCar
    with RecordingCar(open_car("sim", world="track"), Recorder("run.mcap")) as car:
        run_lane_follow(car, cfg)          # the lab neither knows nor cares

Every readout, command (and stop), ground truth, LIDAR scan and camera frame that passes through
is handed to the :class:`~qcarlab.recording.writer.Recorder`; a frame read twice is recorded once.
The lab's own values go to ``car.recorder.log_values(t, {...})`` (the control loop does it).
Anything else (``pose_at``, ``lidar_beams``, ``ping``, ``warm_physics``, ``sensor_recipe``, ...)
is the wrapped car's: reading or setting it reaches the car underneath. Closing the car stops it,
then finishes the recording.

Served (``qcarlab serve --live``): the server takes sensor frames through :meth:`sensor_job`,
which is the wrapped car's own job (the frame's time and pose fixed under the server's drive lock,
the drawing done off it, or in the server's render process), recorded when it has been drawn; so
a recorded car's sensors never hold up a command or the watchdog either. ``follow_truth=True``
(a served car, whose clients need not ask for the ground truth) records the truth with every read
and every :meth:`heartbeat` (the server's housekeeping), at most at the recorder's pose rate, so
the live view's car moves whoever drives it.
"""

from __future__ import annotations

from typing import Any

from qcarlab.car.base import Car, Command, Identity, Readout, Truth
from qcarlab.car.lamps import ALL_OFF
from qcarlab.wire.frames import make_frame
from qcarlab.wire.protocol import MsgType as M

_OWN = frozenset({"inner", "recorder", "closed", "_t", "_last", "follow_truth", "_step", "_truth_tick"})
_CLOSED = object()  # _truth_tick after stop(): the tick is over, the next truth is recorded
_REPLY = {"lidar": M.LIDAR, "rgbd": M.RGBD, "csi": M.CSI}
TRUTH_PERIOD_S = 0.02  # follow_truth: the truth recorded at most this often (the recorder's pose rate)


class RecordingCar(Car):
    """Wraps ``car``; records what passes through into ``recorder``."""

    def __init__(self, car: Car, recorder: Any, *, follow_truth: bool = False):
        object.__setattr__(self, "inner", car)
        object.__setattr__(self, "recorder", recorder)
        object.__setattr__(self, "closed", False)
        object.__setattr__(self, "follow_truth", bool(follow_truth))
        object.__setattr__(self, "_t", None)  # time of the latest readout: the tick commands belong to
        object.__setattr__(self, "_last", {})  # sensor -> the latest recorded frame
        object.__setattr__(self, "_step", None)  # (t, dt) the lab's step is given this tick (note_step)
        object.__setattr__(self, "_truth_tick", None)  # the tick whose truth is recorded (one a tick)
        ident = car.identity()
        recorder.metadata("qcarlab.car", {"name": ident.name, "backend": ident.backend,
                                          "throttle_limit": car.throttle_limit, "stepped": car.stepped})
        truth = car.truth()
        if truth is not None:
            recorder.start_pose((truth.x, truth.y, truth.yaw))
            recorder.truth(truth)
            self._last["truth"] = truth.t

    # --- the wrapped car's attributes ----------------------------------------------------------
    def __getattr__(self, name: str) -> Any:
        return getattr(object.__getattribute__(self, "inner"), name)

    def __setattr__(self, name: str, value: Any) -> None:
        if name in _OWN:
            object.__setattr__(self, name, value)
        else:
            setattr(self.inner, name, value)

    @property
    def params(self):  # type: ignore[override]
        return self.inner.params

    @property
    def ended(self) -> bool:
        """A replayed car's recording has run out (the control loop asks every tick)."""
        return getattr(self.inner, "ended", False)

    @property
    def throttle_limit(self) -> float:  # type: ignore[override]
        return self.inner.throttle_limit

    @property
    def steering_limit(self) -> float:  # type: ignore[override]
        return self.inner.steering_limit

    @property
    def time(self) -> float:
        return self.inner.time

    @property
    def stepped(self) -> bool:
        return self.inner.stepped

    def identity(self) -> Identity:
        return self.inner.identity()

    # --- commands -------------------------------------------------------------------------------
    def _tick(self) -> float:
        return self._t if self._t is not None else self.inner.time

    def validate(self, throttle, steering, leds=None) -> Command:
        return self.inner.validate(throttle, steering, leds)

    def note_step(self, t: float, dt: float) -> None:
        """The control loop, each tick before the lab's step: the ``t`` and ``dt`` it gives the step,
        recorded with the tick's command (a replay gives the step the same again; on a real-time
        car, dt is the wall clock's gap, which nothing else records)."""
        object.__setattr__(self, "_step", (float(t), float(dt)))

    def write(self, throttle, steering, leds=None) -> Command:
        cmd = self.inner.write(throttle, steering, leds)
        step = self._step
        if step is not None:
            object.__setattr__(self, "_step", None)
        self.recorder.command(self._tick(), cmd, step=step)
        return cmd

    def stop(self) -> None:
        self.inner.stop()
        self.recorder.command(self._tick(), Command(0.0, 0.0, ALL_OFF), stop=True)
        object.__setattr__(self, "_truth_tick", _CLOSED)  # the run's end: the truth after it is recorded

    def _apply(self, cmd: Command) -> None:  # not reached: write() and stop() go to the car
        self.inner._apply(cmd)

    def advance(self, dt: float) -> None:
        self.inner.advance(dt)

    # --- sensors --------------------------------------------------------------------------------
    def read(self) -> Readout:
        r = self.inner.read()
        object.__setattr__(self, "_t", r.t)  # (not through __setattr__: every tick)
        self.recorder.readout(r)
        if self.follow_truth:
            self._follow(r.t)
        return r

    def _follow(self, t: float) -> None:
        last = self._last.get("truth")
        if last is not None and t - last >= TRUTH_PERIOD_S:
            self.truth()

    def heartbeat(self) -> None:
        """A served car, idle or not: the truth recorded when due (``follow_truth``). The server
        calls it with its drive lock held, a few times a second."""
        if self.follow_truth and "truth" in self._last:
            self._follow(self.inner.time)

    def truth(self) -> Truth | None:
        """The wrapped car's truth, recorded once a tick (the first asked for after the tick's
        read: on a real-time car every call has a time of its own, and a lab and its referee both
        ask), or, following the truth (a served car), when due."""
        tr = self.inner.truth()
        if tr is None or self._last.get("truth") == tr.t:
            return tr
        tick = self._t
        if tick is not None and not self.follow_truth:
            if self._truth_tick == tick:
                return tr  # this tick's truth is recorded
            object.__setattr__(self, "_truth_tick", tick)  # (after stop(): one more, the run's last)
        self._last["truth"] = tr.t
        self.recorder.truth(tr)
        return tr

    def _frame(self, kind: str, frame: Any, record) -> Any:
        last = self._last.get(kind)
        if frame is not None and frame is not last and (last is None or getattr(last, "t", None) != frame.t):
            self._last[kind] = frame
            record(frame, self._t)  # (the tick at which the lab first had it: a replay gives it then)
        return frame

    def read_lidar(self) -> Any:
        return self._frame("lidar", self.inner.read_lidar(), self.recorder.scan)

    def read_rgbd(self) -> Any:
        return self._frame("rgbd", self.inner.read_rgbd(), self.recorder.rgbd)

    def read_csi(self) -> Any:
        return self._frame("csi", self.inner.read_csi(), self.recorder.csi)

    def _record(self, kind: str, frame: Any) -> Any:
        return self._frame(kind, frame, getattr(self.recorder, "scan" if kind == "lidar" else kind))

    # --- served: the wrapped car's own sensor path ------------------------------------------------
    def sensor_job(self, kind: str) -> Any:
        """The wrapped car's job for a ``kind`` frame (called under a server's drive lock, run off
        it), recording the frame once drawn. Not the Car default, which would read the frame at
        once, under the drive lock, and let a slow render delay the watchdog."""
        return _RecordedJob(self, kind, self.inner.sensor_job(kind))

    def prepare_sensors(self) -> None:
        self.inner.prepare_sensors()

    # --- lifecycle ------------------------------------------------------------------------------
    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            try:
                self.stop()
            finally:
                self.inner.close()
        finally:
            self.recorder.close()

    def __enter__(self) -> RecordingCar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _RecordedJob:
    """A wrapped car's sensor job whose frame is recorded once drawn: by calling it (here), or by a
    server's render process from the job's ``pose`` and ``t`` (:meth:`drawn`). ``key``, ``pose`` and
    ``t`` are the wrapped job's, so the server treats it as it would the car's own."""

    __slots__ = ("car", "kind", "job")

    def __init__(self, car: RecordingCar, kind: str, job: Any):
        self.car, self.kind, self.job = car, kind, job

    @property
    def key(self) -> Any:
        return getattr(self.job, "key", None)

    @property
    def pose(self) -> Any:
        return getattr(self.job, "pose", None)

    @property
    def t(self) -> Any:
        return getattr(self.job, "t", None)

    def __call__(self) -> Any:
        return self.car._record(self.kind, self.job())

    def drawn(self, t: float, arrays: list[Any]) -> None:
        """The frame as another process drew it (its arrays in the wire's field order)."""
        self.car._record(self.kind, make_frame(_REPLY[self.kind], t, arrays))
