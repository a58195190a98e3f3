"""The physical QCar 1 or QCar 2 as a :class:`Car`, for ``qcarlab serve --backend quanser``.

On a car as Quanser ships it (Python 3.6 on a QCar 1, 3.8 on a QCar 2) qcarlab itself does not
install; run the car-side server instead (``qcarlab onboard --write FILE`` or ``qcarlab deploy``,
docs/how-to/real-car.md). This backend is for a car that has a Python >= 3.11 with qcarlab.

Both share one driver: :class:`qcarlab.onboard.car_server.QuanserCar` (the board names, channel
tables, signs, LIDAR angles and start-up of each car, with Quanser's sources). This class only
adapts it to the :class:`Car` interface: SI readouts, sensor frames, the car's own parameters
(:data:`~qcarlab.constants.QCAR1_PARAMS` or :data:`~qcarlab.constants.QCAR2_PARAMS`), and a
thread that reloads the board's own watchdog (``qcarlab serve``'s server does not know it).
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np

from qcarlab.car.base import Car, Command, Identity, Readout
from qcarlab.constants import DEFAULT_PARAMS, QCAR1_PARAMS, QCAR2_PARAMS, QCarParams
from qcarlab.errors import CarError, InputError, NotBuiltError
from qcarlab.onboard import car_server as onboard

CAR_PARAMS = {1: QCAR1_PARAMS, 2: QCAR2_PARAMS}


def lidar_to_body(headings: Any, distances: Any, qualities: Any = None, car_type: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """RPLidar clockwise headings -> body-frame CCW angles in [0, 2 pi), sorted, for ``car_type``:
    ``angle = (zero - heading) mod 2 pi``, zero = pi/2 on a QCar 1, pi on a QCar 2."""
    return onboard.lidar_to_body(headings, distances, qualities, onboard.CARS[car_type]["lidar_zero"])


class QuanserCar(Car):
    """A QCar 1 or 2 through Quanser's HIL and device classes (``car_type`` "auto", 1 or 2)."""

    def __init__(
        self,
        params: QCarParams | None = None,
        throttle_limit: float | None = None,
        *,
        car_type: str | int = "auto",
        lidar: bool = True,
        rgbd: bool = True,
        csi: bool = True,
        watchdog: float = 0.25,
        modules: dict[str, Any] | None = None,
        **_ignored: Any,
    ):
        limit = (params or DEFAULT_PARAMS).throttle_limit if throttle_limit is None else float(throttle_limit)
        if not (math.isfinite(limit) and 0.0 < limit <= 1.0):
            raise InputError(f"throttle limit must be in (0, 1], got {limit}")
        if car_type not in ("auto", 1, 2, "1", "2"):
            raise InputError(f"car type must be auto, 1 or 2, got {car_type!r}")
        try:
            self.hw = onboard.QuanserCar(car_type, throttle_limit=limit, watchdog=watchdog, lidar=lidar, rgbd=rgbd,
                                         csi=csi, modules=modules)
        except onboard.CarError as exc:
            raise CarError(f"--backend quanser: {exc}") from None
        if params is None or params is DEFAULT_PARAMS:
            params = CAR_PARAMS[self.hw.car_type]
        super().__init__(params, limit)
        self.steering_limit = min(self.steering_limit, onboard.MAX_STEERING)
        self._stop_kicking = threading.Event()
        self._kicker = threading.Thread(target=self._kick_loop, name="qcarlab-board-watchdog", daemon=True)
        self._kicker.start()

    @property
    def car_type(self) -> int:
        return self.hw.car_type

    def _kick_loop(self) -> None:
        period = max(0.005, self.hw.watchdog_s / 5.0)
        while not self._stop_kicking.wait(period):
            try:
                self.hw.kick()
            except Exception:  # a closed board: nothing to reload
                pass

    # --- drive ----------------------------------------------------------------------------------
    def _apply(self, cmd: Command) -> None:
        try:
            self.hw.write(cmd.throttle, cmd.steering, cmd.leds)
        except onboard.CarError as exc:
            raise CarError(f"QCar: {exc}") from None

    def stop(self) -> None:
        """Throttle 0, wheels straight, brake lamp; after a board fault it reopens the board first."""
        if self.hw.fault:
            try:
                self.hw.reopen()
            except onboard.CarError as exc:
                raise CarError(f"QCar: {exc}") from None
        super().stop()

    def read(self) -> Readout:
        try:
            r = self.hw.read()
        except onboard.CarError as exc:
            raise CarError(f"QCar: {exc}") from None
        throttle, steering, leds = self.hw.applied
        return Readout(
            t=r.t, encoder_counts=int(r.encoder), tach=float(r.tach), motor_current=float(r.current),
            battery_voltage=float(r.battery), gyro=np.array(r.gyro, dtype=np.float64),
            accel=np.array(r.accel, dtype=np.float64), steering=float(steering), throttle=float(throttle),
            leds=tuple(float(v) for v in leds),
        )

    @property
    def time(self) -> float:
        return self.hw.time

    def advance(self, dt: float) -> None:
        if dt > 0:
            threading.Event().wait(dt)

    def identity(self) -> Identity:
        return Identity(name=self.hw.name(), backend="quanser", capabilities=list(self.hw.capabilities),
                        extra=dict(self.hw.extra()))

    # --- sensors --------------------------------------------------------------------------------
    def _need(self, name: str, what: str) -> None:
        if name not in self.hw.sensors:
            raise NotBuiltError(f"QCar: the {what} is not available ({self.hw.missing.get(name, 'not opened')})")

    def read_lidar(self) -> Any:
        from qcarlab.wire.frames import make_frame
        from qcarlab.wire.protocol import MsgType

        self._need("lidar", "LIDAR")
        try:
            t, angles, ranges = self.hw.lidar_arrays()
        except onboard.CarError as exc:
            raise CarError(f"QCar: {exc}") from None
        return make_frame(MsgType.LIDAR, t, [angles.copy(), ranges.copy()])

    def read_rgbd(self) -> Any:
        """Colour and depth; depth is NOT aligned to colour on the car (see docs/how-to/real-car.md)."""
        from qcarlab.wire.frames import make_frame
        from qcarlab.wire.protocol import MsgType

        self._need("rgbd", "RGBD camera")
        try:
            t, color, depth = self.hw.rgbd_arrays()
        except onboard.CarError as exc:
            raise CarError(f"QCar: {exc}") from None
        return make_frame(MsgType.RGBD, t, [color.copy(), depth.copy()])

    def read_csi(self) -> Any:
        from qcarlab.wire.frames import make_frame
        from qcarlab.wire.protocol import MsgType

        self._need("csi", "CSI cameras")
        try:
            t, views = self.hw.csi_arrays()
        except onboard.CarError as exc:
            raise CarError(f"QCar: {exc}") from None
        return make_frame(MsgType.CSI, t, [v.copy() for v in views])

    # --- lifecycle ------------------------------------------------------------------------------
    def close(self) -> None:
        if self.closed:
            return
        try:
            if not self.hw.fault:
                super().stop()
        except CarError:
            pass
        finally:
            self.closed = True
            self._close()

    def sensor_job(self, kind: str) -> Any:
        # the LIDAR and cameras are their own devices, never the HIL board: read them off the drive lock
        return getattr(self, f"read_{kind}")

    def _close(self) -> None:
        self._stop_kicking.set()
        self.hw.close()
