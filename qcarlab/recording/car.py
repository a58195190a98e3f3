""":class:`RecordingCar`: any :class:`~qcarlab.car.base.Car`, recorded as it is used.

    from qcarlab.recording import Recorder, RecordingCar
    with RecordingCar(open_car("sim", world="track"), Recorder("run.mcap")) as car:
        run_lane_follow(car, cfg)          # the lab neither knows nor cares

Every readout, command (and stop), ground truth, LIDAR scan and camera frame that passes through
is handed to the :class:`~qcarlab.recording.writer.Recorder`; a frame read twice is recorded once.
The lab's own values go to ``car.recorder.log_values(t, {...})`` (the control loop does it).
Anything else (``pose_at``, ``lidar_beams``, ``ping``, ...) is the wrapped car's: reading or
setting it reaches the car underneath. Closing the car stops it, then finishes the recording.
"""

from __future__ import annotations

from typing import Any

from qcarlab.car.base import Car, Command, Identity, Readout, Truth
from qcarlab.car.lamps import ALL_OFF

_OWN = frozenset({"inner", "recorder", "closed", "_t", "_last"})


class RecordingCar(Car):
    """Wraps ``car``; records what passes through into ``recorder``."""

    def __init__(self, car: Car, recorder: Any):
        object.__setattr__(self, "inner", car)
        object.__setattr__(self, "recorder", recorder)
        object.__setattr__(self, "closed", False)
        object.__setattr__(self, "_t", None)  # time of the latest readout: the tick commands belong to
        object.__setattr__(self, "_last", {})  # sensor -> the latest recorded frame
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

    def write(self, throttle, steering, leds=None) -> Command:
        cmd = self.inner.write(throttle, steering, leds)
        self.recorder.command(self._tick(), cmd)
        return cmd

    def stop(self) -> None:
        self.inner.stop()
        self.recorder.command(self._tick(), Command(0.0, 0.0, ALL_OFF), stop=True)

    def _apply(self, cmd: Command) -> None:  # not reached: write() and stop() go to the car
        self.inner._apply(cmd)

    def advance(self, dt: float) -> None:
        self.inner.advance(dt)

    # --- sensors --------------------------------------------------------------------------------
    def read(self) -> Readout:
        r = self.inner.read()
        self._t = r.t
        self.recorder.readout(r)
        return r

    def truth(self) -> Truth | None:
        tr = self.inner.truth()
        if tr is not None and self._last.get("truth") != tr.t:
            self._last["truth"] = tr.t
            self.recorder.truth(tr)
        return tr

    def _frame(self, kind: str, frame: Any, record) -> Any:
        last = self._last.get(kind)
        if frame is not None and frame is not last and (last is None or getattr(last, "t", None) != frame.t):
            self._last[kind] = frame
            record(frame)
        return frame

    def read_lidar(self) -> Any:
        return self._frame("lidar", self.inner.read_lidar(), self.recorder.scan)

    def read_rgbd(self) -> Any:
        return self._frame("rgbd", self.inner.read_rgbd(), self.recorder.rgbd)

    def read_csi(self) -> Any:
        return self._frame("csi", self.inner.read_csi(), self.recorder.csi)

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
