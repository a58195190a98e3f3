"""The on-car driver: the physical QCar 1 through Quanser's Python API, served by ``qcarlab serve``.

On the car's Jetson::

    qcarlab serve --backend quanser --host 0.0.0.0 --token SECRET

Quanser's modules (``quanser.hardware``, ``quanser.devices``, ``quanser.multimedia``, from the
Quanser SDK / ``quanser-api``) are imported only when this car is opened; without them opening
fails with one clear line. The driver talks to the HIL board with the lab sheet's channels:

=========  ==========================================================================
write      PWM 0 throttle (duty fraction); other 1000 steering (rad); other 11000-11011 lamps
read       analog 5 motor current (A), analog 6 battery (V); encoder 0 (counts);
           other 3000-3002 gyro (rad/s), 4000-4002 accelerometer (m/s^2), 14000 tach (counts/s)
=========  ==========================================================================

Conventions it hides (DESIGN.md section 3): the QCar 1's board takes throttle and steering
negated (``THROTTLE_SIGN``/``STEERING_SIGN``), so users write + = forward, + = left as everywhere
else; the RPLidar reports clockwise headings from its own zero, which become counter-clockwise
body-frame angles in [0, 2 pi) as the simulator gives them: ``angle = (LIDAR_ZERO - heading) mod 2 pi``,
sorted ascending.

Sensors are optional: a LIDAR or camera that fails to open is logged once and left out of the
car's capabilities (the server then answers ``unsupported`` for it); drive I/O must open.
"""

from __future__ import annotations

import importlib
import logging
import math
import socket
import time
from typing import Any

import numpy as np

from qcarlab.car.base import Car, Command, Identity, Readout
from qcarlab.car.lamps import ALL_OFF, N_LAMPS
from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.errors import CarError, NotBuiltError

log = logging.getLogger("qcarlab")

# the QCar 1's sign conventions at the HIL board (see the module docstring)
THROTTLE_SIGN = -1.0
STEERING_SIGN = -1.0
ENCODER_SIGN = 1  # encoder and tach as the board reports them
LIDAR_ZERO = 0.0  # rad: body-frame direction of the RPLidar's heading 0 (its zero faces forward)

# HIL channels (lab sheet, HIL-Read / HIL-Write)
PWM_CHANNELS = np.array([0], dtype=np.uint32)
WRITE_OTHER_CHANNELS = np.array([1000] + [11000 + i for i in range(N_LAMPS)], dtype=np.uint32)
READ_ANALOG_CHANNELS = np.array([5, 6], dtype=np.uint32)
READ_ENCODER_CHANNELS = np.array([0], dtype=np.uint32)
READ_OTHER_CHANNELS = np.array([3000, 3001, 3002, 4000, 4001, 4002, 14000], dtype=np.uint32)

RPLIDAR_URL = "serial-cpu://localhost:2?baud='115200',word='8',parity='none',stop='1',flow='none',dsr='on'"
LIDAR_POINTS = 720
CSI_CAMERA_IDS = {"right": 0, "rear": 1, "left": 2, "front": 3}  # the QCar 1's video://localhost:N


def _quanser(module: str) -> Any:
    try:
        return importlib.import_module(module)
    except ImportError:
        raise CarError(
            f"--backend quanser: Quanser's Python API ({module}) is not installed here; run this on the QCar "
            "with the Quanser SDK (python3 -m pip install quanser-api from Quanser's package index), "
            "or serve the simulator with --backend sim"
        ) from None


def _message(exc: BaseException) -> str:
    get = getattr(exc, "get_error_message", None)
    try:
        text = get() if callable(get) else str(exc)
    except Exception:
        text = str(exc)
    return str(text).strip() or type(exc).__name__


def wrap_to_2pi(angles: np.ndarray) -> np.ndarray:
    """Angles wrapped into [0, 2 pi)."""
    wrapped = np.mod(np.asarray(angles, dtype=np.float64), 2.0 * math.pi)
    return np.where(wrapped >= 2.0 * math.pi, 0.0, wrapped)  # -1e-17 mod 2 pi rounds up to 2 pi


def lidar_to_body(headings: Any, distances: Any) -> tuple[np.ndarray, np.ndarray]:
    """RPLidar clockwise headings (rad) -> body-frame CCW angles in [0, 2 pi), sorted; ranges in m."""
    heading = np.asarray(headings, dtype=np.float64).reshape(-1)
    ranges = np.asarray(distances, dtype=np.float64).reshape(-1)
    n = min(heading.size, ranges.size)
    angles = wrap_to_2pi(LIDAR_ZERO - heading[:n])
    order = np.argsort(angles, kind="stable")
    return angles[order], ranges[:n][order]


class QuanserCar(Car):
    """The physical QCar 1 (drive I/O through the HIL board; LIDAR, RGBD and CSI when present)."""

    def __init__(
        self,
        params: QCarParams = DEFAULT_PARAMS,
        throttle_limit: float | None = None,
        *,
        board: str = "qcar",
        board_id: str = "0",
        lidar: bool = True,
        rgbd: bool = True,
        csi: bool = True,
        lidar_url: str = RPLIDAR_URL,
        **_ignored: Any,
    ):
        super().__init__(params, throttle_limit)
        hw = _quanser("quanser.hardware")
        self._hw = hw
        self._hil_error = getattr(hw, "HILError", Exception)
        self._t0 = time.monotonic()
        self._cmd = Command()
        self._pwm = np.zeros(1, dtype=np.float64)
        self._other_w = np.zeros(WRITE_OTHER_CHANNELS.size, dtype=np.float64)
        self._analog = np.zeros(READ_ANALOG_CHANNELS.size, dtype=np.float64)
        self._encoder = np.zeros(READ_ENCODER_CHANNELS.size, dtype=np.int32)
        self._other_r = np.zeros(READ_OTHER_CHANNELS.size, dtype=np.float64)
        self._sensors: dict[str, Any] = {}
        self._missing: dict[str, str] = {}
        self.card = hw.HIL()
        try:
            self.card.open(board, board_id)
            self._configure()
        except self._hil_error as exc:
            self._close_card()
            raise CarError(f"cannot open the QCar's HIL board ({board} {board_id}): {_message(exc)}") from None
        self._apply(Command(0.0, 0.0, ALL_OFF))
        if lidar:
            self._open_sensor("lidar", lambda: self._open_lidar(lidar_url))
        else:
            self._missing["lidar"] = "disabled"
        if rgbd:
            self._open_sensor("rgbd", self._open_rgbd)
        else:
            self._missing["rgbd"] = "disabled"
        if csi:
            self._open_sensor("csi", self._open_csi)
        else:
            self._missing["csi"] = "disabled"

    # --- HIL board --------------------------------------------------------------------------------
    def _configure(self) -> None:
        hw, card = self._hw, self.card
        limit = self.throttle_limit
        card.set_card_specific_options(f"steer_bias=0;motor_limit={limit:.4g};", getattr(hw, "MAX_STRING_LENGTH", 2048))
        pwm_mode = getattr(getattr(hw, "PWMMode", None), "DUTY_CYCLE", 0)
        card.set_pwm_mode(PWM_CHANNELS, 1, np.array([pwm_mode], dtype=np.int32))
        card.set_pwm_frequency(PWM_CHANNELS, 1, np.array([60e6 / 4096], dtype=np.float64))
        card.set_encoder_quadrature_mode(READ_ENCODER_CHANNELS, 1, np.array([4], dtype=np.uint32))
        card.set_encoder_counts(READ_ENCODER_CHANNELS, 1, np.zeros(1, dtype=np.int32))

    def _apply(self, cmd: Command) -> None:
        self._pwm[0] = THROTTLE_SIGN * cmd.throttle
        self._other_w[0] = STEERING_SIGN * cmd.steering
        self._other_w[1:] = cmd.leds
        try:
            self.card.write(
                None, 0,
                PWM_CHANNELS, PWM_CHANNELS.size,
                None, 0,
                WRITE_OTHER_CHANNELS, WRITE_OTHER_CHANNELS.size,
                None, self._pwm, None, self._other_w,
            )
        except self._hil_error as exc:
            raise CarError(f"QCar HIL write failed: {_message(exc)}") from None
        self._cmd = cmd

    def read(self) -> Readout:
        try:
            self.card.read(
                READ_ANALOG_CHANNELS, READ_ANALOG_CHANNELS.size,
                READ_ENCODER_CHANNELS, READ_ENCODER_CHANNELS.size,
                None, 0,
                READ_OTHER_CHANNELS, READ_OTHER_CHANNELS.size,
                self._analog, self._encoder, None, self._other_r,
            )
        except self._hil_error as exc:
            raise CarError(f"QCar HIL read failed: {_message(exc)}") from None
        o = self._other_r
        return Readout(
            t=self.time,
            encoder_counts=ENCODER_SIGN * int(self._encoder[0]),
            tach=ENCODER_SIGN * float(o[6]),
            motor_current=float(self._analog[0]),
            battery_voltage=float(self._analog[1]),
            gyro=o[0:3].astype(np.float64),
            accel=o[3:6].astype(np.float64),
            steering=self._cmd.steering,
            throttle=self._cmd.throttle,
            leds=self._cmd.leds,
        )

    @property
    def time(self) -> float:
        return time.monotonic() - self._t0

    def advance(self, dt: float) -> None:
        if dt > 0:
            time.sleep(dt)

    def identity(self) -> Identity:
        caps = ["drive", "lamps", "encoder", "imu", "battery"] + [k for k in ("lidar", "rgbd", "csi") if k in self._sensors]
        return Identity(
            name=f"QCar 1 ({socket.gethostname()})",
            backend="quanser",
            capabilities=caps,
            extra={"on_stand": None, "sensors_missing": dict(self._missing)},
        )

    # --- sensors ----------------------------------------------------------------------------------
    def _open_sensor(self, name: str, opener: Any) -> None:
        try:
            self._sensors[name] = opener()
        except Exception as exc:  # CarError (API missing), DeviceError, MediaError, ...
            self._missing[name] = _message(exc)
            log.warning("quanser: %s not available (%s); serving without it", name, _message(exc))

    def _open_lidar(self, url: str) -> dict[str, Any]:
        dev = _quanser("quanser.devices")
        lidar = dev.RPLIDAR()
        lidar.open(url, dev.RangingDistance.LONG)
        return {"dev": dev, "lidar": lidar, "meas": dev.RangingMeasurements(LIDAR_POINTS), "last": None}

    def _open_rgbd(self) -> dict[str, Any]:
        mm = _quanser("quanser.multimedia")
        p = self.params
        w, h, fps = p.rgbd_width, p.rgbd_height, float(p.rgbd_rate)
        video = mm.Video3D("0")
        color = video.stream_open(
            mm.Video3DStreamType.COLOR, 0, fps, w, h, mm.ImageFormat.ROW_MAJOR_INTERLEAVED_BGR, mm.ImageDataType.UINT8
        )
        depth = video.stream_open(
            mm.Video3DStreamType.DEPTH, 0, fps, w, h, mm.ImageFormat.ROW_MAJOR_GREYSCALE, mm.ImageDataType.UINT8
        )
        video.start_streaming()
        return {
            "video": video, "streams": (color, depth),
            "color": np.zeros((h, w, 3), dtype=np.uint8), "depth": np.zeros((h, w, 1), dtype=np.float32),
        }

    def _open_csi(self) -> dict[str, Any]:
        mm = _quanser("quanser.multimedia")
        p = self.params
        caps, bufs = {}, {}
        try:
            for name, cam in CSI_CAMERA_IDS.items():
                cap = mm.VideoCapture(
                    f"video://localhost:{cam}", float(p.csi_rate), p.csi_width, p.csi_height,
                    mm.ImageFormat.ROW_MAJOR_INTERLEAVED_BGR, mm.ImageDataType.UINT8, None, 0,
                )
                cap.start()
                caps[name] = cap
                bufs[name] = np.zeros((p.csi_height, p.csi_width, 3), dtype=np.uint8)
        except Exception:
            for cap in caps.values():
                _quietly(cap.stop)
                _quietly(cap.close)
            raise
        return {"captures": caps, "buffers": bufs}

    def _sensor(self, name: str, what: str) -> Any:
        sensor = self._sensors.get(name)
        if sensor is None:
            raise NotBuiltError(f"quanser car: the {what} is not available ({self._missing.get(name, 'not opened')})")
        return sensor

    def read_lidar(self) -> Any:
        from qcarlab.net.frames import make_frame
        from qcarlab.net.protocol import MsgType

        s = self._sensor("lidar", "LIDAR")
        try:
            n = s["lidar"].read(s["dev"].RangingMeasurementMode.NORMAL, 0, 0, s["meas"])
        except Exception as exc:
            raise CarError(f"QCar LIDAR read failed: {_message(exc)}") from None
        if n and n > 0:
            heading = np.asarray(s["meas"].heading, dtype=np.float64).reshape(-1)[:n]
            distance = np.asarray(s["meas"].distance, dtype=np.float64).reshape(-1)[:n]
            s["last"] = (self.time, *lidar_to_body(heading, distance))
        elif s["last"] is None:  # no full scan yet
            s["last"] = (self.time, np.zeros(0), np.zeros(0))
        t, angles, ranges = s["last"]
        return make_frame(MsgType.LIDAR, t, [angles.copy(), ranges.copy()])

    def read_rgbd(self) -> Any:
        from qcarlab.net.frames import make_frame
        from qcarlab.net.protocol import MsgType

        s = self._sensor("rgbd", "RGBD camera")
        color_stream, depth_stream = s["streams"]
        try:
            frame = color_stream.get_frame()
            if frame:
                frame.get_data(s["color"])
                frame.release()
            frame = depth_stream.get_frame()
            if frame:
                frame.get_meters(s["depth"])
                frame.release()
        except Exception as exc:
            raise CarError(f"QCar RGBD read failed: {_message(exc)}") from None
        return make_frame(MsgType.RGBD, self.time, [s["color"].copy(), s["depth"][:, :, 0].copy()])

    def read_csi(self) -> Any:
        from qcarlab.net.frames import make_frame
        from qcarlab.net.protocol import MsgType

        s = self._sensor("csi", "CSI cameras")
        try:
            for name, cap in s["captures"].items():
                cap.read(s["buffers"][name])
        except Exception as exc:
            raise CarError(f"QCar CSI read failed: {_message(exc)}") from None
        b = s["buffers"]
        return make_frame(MsgType.CSI, self.time, [b[k].copy() for k in ("right", "rear", "left", "front")])

    def sensor_job(self, kind: str) -> Any:
        # the LIDAR and cameras are their own devices, never the HIL board: read them off the drive lock
        return getattr(self, f"read_{kind}")

    # --- lifecycle --------------------------------------------------------------------------------
    def _close(self) -> None:
        _quietly(lambda: self._apply(Command(0.0, 0.0, ALL_OFF)))
        lidar = self._sensors.pop("lidar", None)
        if lidar is not None:
            _quietly(lidar["lidar"].close)
        rgbd = self._sensors.pop("rgbd", None)
        if rgbd is not None:
            _quietly(rgbd["video"].stop_streaming)
            for stream in rgbd["streams"]:
                _quietly(stream.close)
            _quietly(rgbd["video"].close)
        csi = self._sensors.pop("csi", None)
        if csi is not None:
            for cap in csi["captures"].values():
                _quietly(cap.stop)
                _quietly(cap.close)
        self._close_card()

    def _close_card(self) -> None:
        _quietly(self.card.close)


def _quietly(fn: Any) -> None:
    try:
        fn()
    except Exception:
        pass
