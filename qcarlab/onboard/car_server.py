#!/usr/bin/env python3
"""qcarlab's car-side server: serves a Quanser QCar 1 or QCar 2 over the qcarlab protocol v1.

One file, copied to the car as it ships (``qcarlab onboard --write FILE`` or ``qcarlab deploy``):
it runs on the car's own Python (3.6 on a QCar 1, 3.8 on a QCar 2) with the standard library,
the car's NumPy and Quanser's ``quanser.*`` modules (both imported only when the hardware is
opened). The laptop keeps qcarlab (Python >= 3.11) and connects with ``--car tcp://CAR:18960``.

    python3 qcarlab_car_server.py --dry-run                 # no hardware: a stationary car
    sudo PYTHONPATH=$PYTHONPATH python3 qcarlab_car_server.py --host 0.0.0.0 --token-file ~/.qcarlab_token
    python3 qcarlab_car_server.py --new-token               # print a fresh token

It speaks the protocol ``docs/protocol.md`` describes (the same bytes as ``qcarlab serve``) with
the same safety: one controller; a watchdog that stops the car when the controller goes quiet,
on its own thread, which takes no lock but the board's (held for one HIL call at a time); a
controller silent for ``--controller-timeout`` after the watchdog stopped the car loses control
(one that never sent a command too: the watchdog stops its car all the same); a monitor's requests
are served at most 1,000 a second (bursts of 20: a flood waits, it is never refused); a whole
HELLO within 2 s and every frame within 5 s of its first byte; one slot kept for a controller; a
throttle limit applied whatever clients send; a token of 16 or more characters whenever the bound
address is not loopback; SIGINT, SIGTERM, SIGHUP and SIGQUIT stop the car.

Quanser-specific facts (board names, channels, signs, LIDAR URL and angles, camera ids) live in
``CARS`` below, each entry with the Quanser file it comes from. Where the material could not be
checked against a real car, the comment says so.
"""

import argparse
import errno
import hashlib
import hmac
import ipaddress
import json
import logging
import math
import os
import select
import signal
import socket
import struct
import sys
import threading
import time

SERVER_VERSION = "qcarlab-car-server 0.1.0"
log = logging.getLogger("qcarlab.car_server")

# =================================================================================================
# Protocol v1 (docs/protocol.md). The same numbers as qcarlab/wire/protocol.py; a test compares them.
# =================================================================================================
MAGIC = b"QC"
PROTOCOL = 1
DEFAULT_PORT = 18960
HEADER = struct.Struct("<2sBBIII")  # magic, version, type, seq, ref, length
HEADER_SIZE = HEADER.size  # 16
MAX_REQUEST = 64 * 1024
MAX_PING = 64
N_LAMPS = 12

HELLO, WELCOME, OK = 0x01, 0x02, 0x03
COMMAND, APPLIED, READ, READOUT = 0x10, 0x11, 0x12, 0x13
GET_TRUTH, TRUTH, ADVANCE, TIME, GET_TIME, STOP = 0x14, 0x15, 0x16, 0x17, 0x18, 0x19
GET_LIDAR, LIDAR, GET_RGBD, RGBD, GET_CSI, CSI = 0x20, 0x21, 0x22, 0x23, 0x24, 0x25
PING, PONG, ERROR, BYE = 0x30, 0x31, 0x7E, 0x7F
MSG_NAMES = {
    0x01: "HELLO", 0x02: "WELCOME", 0x03: "OK", 0x10: "COMMAND", 0x11: "APPLIED", 0x12: "READ",
    0x13: "READOUT", 0x14: "GET_TRUTH", 0x15: "TRUTH", 0x16: "ADVANCE", 0x17: "TIME", 0x18: "GET_TIME",
    0x19: "STOP", 0x20: "GET_LIDAR", 0x21: "LIDAR", 0x22: "GET_RGBD", 0x23: "RGBD", 0x24: "GET_CSI",
    0x25: "CSI", 0x30: "PING", 0x31: "PONG", 0x7E: "ERROR", 0x7F: "BYE",
}
FLAG_READ_BACK = 0x1
STATUS_WATCHDOG = 0x1
STATUS_CONTROLLED = 0x2

COMMAND_ST = struct.Struct("<2d12dI")  # 116 bytes
APPLIED_ST = struct.Struct("<2d12d")  # 112 bytes
READOUT_ST = struct.Struct("<dqddd3d3d2d12dI")  # 204 bytes
SCALAR_ST = struct.Struct("<d")
ARRAYS_HEAD = struct.Struct("<dII")
ARRAY_DESC = struct.Struct("<BBH3I")
DTYPE_CODES = {"|u1": 1, "<u2": 2, "<i4": 3, "<f4": 4, "<f8": 5}  # numpy dtype.str -> code

FATAL_CODES = frozenset([
    "bad_magic", "bad_version", "oversized", "sequence", "bad_hello", "bad_token", "busy",
    "too_many_clients", "timeout", "shutting_down", "control_lost",
])
HTTP_METHODS = (b"GET ", b"POST", b"HEAD", b"PUT ", b"DELE", b"OPTI", b"PATC", b"CONN", b"TRAC", b"PRI ")
HTTP_REPLY = (
    b"HTTP/1.0 400 Bad Request\r\nContent-Type: text/plain\r\nConnection: close\r\n\r\n"
    b"This is a qcarlab car server: it speaks the qcarlab binary protocol (docs/protocol.md), "
    b"not HTTP. Use `qcarlab ping tcp://HOST:PORT` or --car tcp://HOST:PORT.\n"
)

# the 12 lamps, in the order of the lab sheet's HIL-Write "other" channels 11000-11011 (Figure 19)
LAMP_NAMES = (
    "brake", "reverse", "headlamp_left", "headlamp_right", "user0", "user1", "user2", "user3",
    "indicator_rear_left", "indicator_rear_right", "indicator_front_left", "indicator_front_right",
)
ALL_OFF = (0.0,) * N_LAMPS
STOP_LAMPS = (1.0,) + (0.0,) * 11  # Car.stop(): brake lamp on
WATCHDOG_LAMPS = (1.0,) + (0.0,) * 7 + (1.0,) * 4  # brake + hazard (all four indicators)
MONITOR_REQUESTS_PER_S = 1000.0  # a monitor's requests are served at most this often ...
MONITOR_BURST = 20.0  # ... after a burst of this many (qcarlab/net/server.py: the same numbers)

# =================================================================================================
# The two cars, as Quanser's own code drives them.
#   [qcar.py]        Quanser_Academic_Resources 0_libraries/python/pal/products/qcar.py
#                    (class QCar: _set_options, write, read; QCarCameras; QCarLidar)
#   [qcar_config.py] the same folder's qcar_config.py, class QCar_check (the line numbers below
#                    count from its first line, "import numpy as np", in the copy we read)
#   [lidar.py]       pal/utilities/lidar.py, class Lidar (and quanser/devices' RPLIDAR.read)
#   [hw1]            the QCar 1 hardware/user manual, pages as quoted in qcarlab issue 15
# =================================================================================================
_QCAR1_LIDAR_URL = "serial-cpu://localhost:2?baud='115200',word='8',parity='none',stop='1',flow='none',dsr='on'"
_QCAR2_LIDAR_URL = "serial-cpu://localhost:1?baud='256000',word='8',parity='none',stop='1',flow='none',dsr='on'"
CARS = {
    1: {
        "name": "QCar 1",
        "board": "qcar",  # [qcar_config.py] line 13 'carname':'qcar'; check_car_type opens it first (line 47)
        "python": "3.6",  # Ubuntu 18.04 on a Jetson TX2 (QCar 1 software_python.pdf p.4, per issue 15)
        "sudo": True,  # Quanser runs Python on a QCar 1 under sudo (same manual)
        "throttle": ("pwm", 0, -1.0),  # [qcar_config.py] line 18 PWM [0]; [qcar.py] QCar.write: -clip(throttle)
        "steering": ("other", 1000, -1.0),  # [qcar_config.py] line 19 other 1000; [qcar.py] QCar.write: -clip(steering)
        # lamps: the lab sheet's other channels 11000-11011 one to one (Figure 19); Quanser's QCar
        # class writes 8 of them ([qcar_config.py] line 19: 11008-11011 indicators, 11000-11003)
        "lamps": tuple(("other", 11000 + i) for i in range(N_LAMPS)),
        "coast_pin": 40,  # [qcar.py] QCar._set_options, car type 1: write_digital([40], 0) "motor coast to 0"
        "pwm_setup": True,  # [qcar.py] QCar._set_options, car type 1: PWM 0 duty-cycle mode at 60e6/4096 Hz
        "analog": (5, 6),  # [qcar_config.py] line 25: motor current, battery voltage
        "encoder": 0,  # [qcar_config.py] line 26
        "other_read": (3000, 3001, 3002, 4000, 4001, 4002, 14000),  # line 27: gyro x/y/z, accel x/y/z, tach
        "lidar_url": _QCAR1_LIDAR_URL,  # [qcar_config.py] line 14: serial port 2 at 115200 baud
        # the RPLidar's heading is clockwise from its zero mark, which faces the car's LEFT:
        # body angle = (pi/2 - heading) mod 2 pi ([qcar.py] QCarLidar.filter_rplidar_data's
        # commented "wrap_to_2pi(2.5*np.pi-phiMeas)", Quanser's hardware test plots heading 0 to the
        # left, clockwise; [hw1] p.9)
        "lidar_zero": math.pi / 2.0,
        "csi": {"right": 0, "rear": 1, "left": 2, "front": 3},  # [qcar_config.py] lines 32-35
    },
    2: {
        "name": "QCar 2",
        "board": "qcar2",  # [qcar_config.py] line 59 opens "qcar2" when "qcar" fails; line 62 'carname'
        "python": "3.8",  # Ubuntu 20.04 on a Jetson AGX Orin (QCar 2 software guide, per issue 15)
        "sudo": False,
        "throttle": ("other", 11000, 1.0),  # [qcar_config.py] line 68 other [1000, 11000]; [qcar.py] QCar.write: not negated
        "steering": ("other", 1000, 1.0),  # [qcar_config.py] line 68; [qcar.py] QCar.write: clip(steering), not negated
        # lamps are digital channels 11-26 ([qcar_config.py] line 69, [qcar.py] QCar.write car type 2):
        # Quanser's LEDs[0:4] (the indicators) -> 17, 18, 25, 26; LEDs[4] brake -> 11-14;
        # LEDs[5] reverse -> 15, 16; LEDs[6] -> 19-21; LEDs[7] -> 22-24. Which indicator is which
        # follows the QCar 1's order of the same LEDs[] (11008 rear left ... 11011 front right);
        # that pairing is our reading, not checked on a QCar 2. A QCar 2 has no user LEDs.
        "lamps": (
            ("digital", (11, 12, 13, 14)), ("digital", (15, 16)), ("digital", (19, 20, 21)),
            ("digital", (22, 23, 24)), None, None, None, None,
            ("digital", (17,)), ("digital", (18,)), ("digital", (25,)), ("digital", (26,)),
        ),
        "coast_pin": None,
        "pwm_setup": False,
        "analog": (4, 2),  # [qcar_config.py] line 74: motor current (4), battery voltage (2)
        "encoder": 0,  # line 75
        "other_read": (3000, 3001, 3002, 4000, 4001, 4002, 14000),  # line 76
        "lidar_url": _QCAR2_LIDAR_URL,  # [qcar_config.py] line 63: serial port 1 at 256000 baud
        # body angle = (pi - heading) mod 2 pi: the zero mark faces the rear (issue 15's reading of
        # Quanser's QCar 2 material; Quanser's QCar 2 ROS node reverses the order, CW -> CCW; NOT
        # checked on a QCar 2 here)
        "lidar_zero": math.pi,
        "csi": {"right": 0, "rear": 1, "front": 2, "left": 3},  # [qcar_config.py] lines 81-84
    },
}
ENCODER_FILTER_HZ = 60e6  # [qcar.py] QCar._set_options: set_encoder_filter_frequency(60e6/1)
PWM_FREQUENCY_HZ = 60e6 / 4096  # [qcar.py] QCar._set_options, car type 1
PWM_MODE_DUTY_CYCLE = 0  # quanser.hardware PWMMode.DUTY_CYCLE (used when the enum is missing)
QUADRATURE_4X = 4  # [qcar.py] set_encoder_quadrature_mode(..., [4])
MAX_STEERING = 0.5  # rad at the wheels: the servo takes +-0.5 rad ([hw1] p.11; Quanser's QCar.write clips at 0.6)
LIDAR_POINTS = 2048  # measurement buffer: more than an RPLidar A2's samples in one turn
LIDAR_MAX_RANGE = 18.0  # m, RPLidar range ([hw1]; qcarlab.constants.lidar_max_range)
RGBD_SIZE = (640, 480)  # colour and depth, px; 30 fps
CSI_SIZE = (820, 410)  # px; 30 fps ([qcar.py] QCarCameras defaults)
CAMERA_FPS = 30.0
DRY_RUN_BATTERY = 12.0  # V, the dry run's synthetic battery (a charged 3S pack)
DRY_RUN_GRAVITY = 9.81  # m/s^2 on the dry run's accelerometer z (standing still)
WOULD_BLOCK = -34  # -QERR_WOULD_BLOCK: "no new data" from a device ([lidar.py] Lidar.read passes on it)

# The physical parameters sent in WELCOME ``params`` (a subset of qcarlab.constants.QCarParams:
# the laptop merges them over its defaults). Values and sources: qcarlab/constants.py (a test
# checks these equal QCAR1_PARAMS / QCAR2_PARAMS there).
_COMMON_PARAMS = {
    "wheelbase": 0.256, "wheel_radius": 0.033, "encoder_cpr": 2880.0,
    "gear_ratio": (13.0 * 19.0) / (70.0 * 37.0), "max_steering": MAX_STEERING,
    "lidar_x": -0.0108, "lidar_z": 0.186, "lidar_max_range": LIDAR_MAX_RANGE,
    "rgbd_x": 0.0822, "rgbd_z": 0.1582, "rgbd_width": RGBD_SIZE[0], "rgbd_height": RGBD_SIZE[1],
    "csi_front_x": 0.193, "csi_rear_x": -0.165, "csi_z": 0.0953,
    "csi_width": CSI_SIZE[0], "csi_height": CSI_SIZE[1],
}
CAR_PARAMS = {
    1: dict(_COMMON_PARAMS, height=0.182, motor_resistance=0.47, motor_kt=0.0027, motor_kb=0.0027),
    2: dict(_COMMON_PARAMS, height=0.2, motor_resistance=0.4, motor_kt=0.0047, motor_kb=0.0047),
}


class CarError(Exception):
    """The hardware failed or is missing (exit 1, or ``car_error`` to a client)."""


class CarFault(CarError):
    """A write to the board failed: the car was stopped by another path and the board closed."""


class InputError(Exception):
    """Bad input from the command line (exit 2)."""


class ProtocolError(Exception):
    def __init__(self, code, message):
        Exception.__init__(self, message)
        self.code = code
        self.message = message


def error_payload(code, message):
    return json.dumps({"code": code, "message": message, "fatal": code in FATAL_CODES},
                      separators=(",", ":")).encode("utf-8")


def looks_like_http(data):
    head = bytes(data[:4])
    if not head:
        return False
    return any(m.startswith(head) if len(head) < 4 else head == m for m in HTTP_METHODS)


def array_part(code, shape, data):
    """A sensor array for :func:`pack_arrays`: dtype code, shape (<= 3 dims) and its bytes."""
    return (code, tuple(int(d) for d in shape), data)


def numpy_part(arr):
    """A NumPy array as a sensor array (C order, little-endian; dtypes other than the protocol's
    five travel as float64)."""
    np = _numpy()
    arr = np.asarray(arr)
    dt = arr.dtype.newbyteorder("<") if arr.dtype.byteorder == ">" else arr.dtype
    code = DTYPE_CODES.get(dt.str)
    if code is None:
        arr, dt, code = arr.astype("<f8"), np.dtype("<f8"), 5
    arr = np.ascontiguousarray(arr, dtype=dt)
    return (code, arr.shape, memoryview(arr.reshape(-1).view(np.uint8)))


def pack_arrays(t, arrays):
    """Payload parts of a sensor frame (docs/protocol.md section 4): head, descriptors, then each
    array's bytes padded to a multiple of 8."""
    descs = bytearray()
    data = []
    for code, shape, buf in arrays:
        if len(shape) > 3:
            raise ValueError("sensor arrays have at most 3 dimensions")
        dims = list(shape) + [0] * (3 - len(shape))
        descs += ARRAY_DESC.pack(code, len(shape), 0, *dims)
        n = len(buf)
        if n:
            data.append(buf)
        if n % 8:
            data.append(bytes(8 - n % 8))
    return [ARRAYS_HEAD.pack(float(t), len(arrays), 0) + bytes(descs)] + data


def send_frame(sock, mtype, seq, ref, parts):
    """Send one frame; ``parts`` are bytes-like objects sent without joining large ones."""
    length = sum(len(p) for p in parts)
    header = HEADER.pack(MAGIC, PROTOCOL, mtype, seq & 0xFFFFFFFF, ref & 0xFFFFFFFF, length)
    if length <= 65536:
        sock.sendall(header + b"".join(parts))
        return
    views = [memoryview(header)] + [memoryview(p) for p in parts if len(p)]
    if not hasattr(sock, "sendmsg"):
        for v in views:
            sock.sendall(v)
        return
    while views:
        sent = sock.sendmsg(views[:64])
        while sent and views:
            first = len(views[0])
            if sent >= first:
                sent -= first
                views.pop(0)
            else:
                views[0] = views[0][sent:]
                sent = 0


# =================================================================================================
# The LIDAR's angles
# =================================================================================================
def lidar_to_body(headings, distances, qualities=None, zero=math.pi / 2.0):
    """RPLidar clockwise headings (rad from the device's zero mark) -> body-frame angles
    (rad, counter-clockwise from forward, in [0, 2 pi), ascending) and ranges (m; 0 where the
    device flagged no return: quality 0, or a non-finite or non-positive distance).

        angle = (zero - heading) mod 2 pi

    ``zero`` is the body-frame direction of the device's zero mark (CARS[n]["lidar_zero"]).
    """
    np = _numpy()
    heading = np.asarray(headings, dtype=np.float64).reshape(-1)
    ranges = np.array(distances, dtype=np.float64).reshape(-1)
    n = min(heading.size, ranges.size)
    heading, ranges = heading[:n], ranges[:n]
    bad = ~np.isfinite(ranges) | (ranges <= 0.0) | ~np.isfinite(heading)
    if qualities is not None:
        q = np.asarray(qualities).reshape(-1)[:n]
        bad |= q <= 0
    ranges[bad] = 0.0
    keep = np.isfinite(heading)
    heading, ranges = heading[keep], ranges[keep]
    angles = np.mod(zero - heading, 2.0 * math.pi)
    angles[angles >= 2.0 * math.pi] = 0.0  # -1e-17 mod 2 pi rounds up to 2 pi
    order = np.argsort(angles, kind="mergesort")
    return angles[order], ranges[order]


def _numpy():
    try:
        import numpy
    except ImportError:
        raise CarError("NumPy is not installed for this Python ({}); the car's own NumPy is needed for the "
                       "hardware (it ships with the QCar's Python)".format(sys.executable))
    return numpy


# =================================================================================================
# Cars: the dry run (no hardware) and the Quanser board
# =================================================================================================
class Readout(object):
    __slots__ = ("t", "encoder", "tach", "current", "battery", "gyro", "accel")

    def __init__(self, t, encoder, tach, current, battery, gyro, accel):
        self.t, self.encoder, self.tach, self.current, self.battery = t, encoder, tach, current, battery
        self.gyro, self.accel = gyro, accel


def _clean_lamps(leds):
    return tuple(float(v) for v in leds)


class DryRunCar(object):
    """No hardware opened: a stationary car, for checking the link before the car is powered.

    Everything it reports is synthetic: commands are applied to nothing and echoed back; the
    readout is a car standing still on a charged battery (encoder 0, tach 0, current 0, battery
    12.0 V, gyro 0, accelerometer (0, 0, 9.81)); the LIDAR sees a 4 m x 3 m box room around the
    car (walls 2 m ahead and behind, 1.5 m to each side); the cameras are mid-grey, depth has no
    data (0). The identity says ``dry run`` so no result is mistaken for a measurement."""

    backend = "dry-run"

    def __init__(self, car_type=1):
        self.car_type = car_type
        self.info = CARS[car_type]
        self.t0 = time.monotonic()
        self.hardware_watchdog = False
        self.missing = {}
        self.capabilities = ["drive", "lamps", "encoder", "imu", "battery", "lidar", "rgbd", "csi"]
        self.fault = None
        self.applied = (0.0, 0.0, ALL_OFF)
        n = 720
        angles, ranges = [], []
        for i in range(n):
            a = 2.0 * math.pi * i / n
            c, s = math.cos(a), math.sin(a)
            rx = 2.0 / abs(c) if abs(c) > 1e-12 else float("inf")
            ry = 1.5 / abs(s) if abs(s) > 1e-12 else float("inf")
            angles.append(a)
            ranges.append(min(rx, ry))
        self._lidar = (struct.pack("<%dd" % n, *angles), struct.pack("<%dd" % n, *ranges), n)
        w, h = RGBD_SIZE
        self._color = b"\x80" * (w * h * 3)
        self._depth = bytes(w * h * 4)
        cw, ch = CSI_SIZE
        self._csi = b"\x80" * (cw * ch * 3)

    def name(self):
        return "{} (dry run: no hardware opened)".format(self.info["name"])

    @property
    def time(self):
        return time.monotonic() - self.t0

    def write(self, throttle, steering, leds):
        if self.fault:
            raise CarFault(self.fault)
        self.applied = (throttle, steering, tuple(leds))

    def stop_outputs(self, leds):
        self.write(0.0, 0.0, leds)

    def reopen(self):
        self.fault = None

    def read(self):
        return Readout(self.time, 0, 0.0, 0.0, DRY_RUN_BATTERY, (0.0, 0.0, 0.0), (0.0, 0.0, DRY_RUN_GRAVITY))

    def kick(self):
        return True

    def read_lidar(self):
        a, r, n = self._lidar
        return self.time, [array_part(5, (n,), a), array_part(5, (n,), r)]

    def read_rgbd(self):
        w, h = RGBD_SIZE
        return self.time, [array_part(1, (h, w, 3), self._color), array_part(4, (h, w), self._depth)]

    def read_csi(self):
        w, h = CSI_SIZE
        return self.time, [array_part(1, (h, w, 3), self._csi) for _ in range(4)]

    def extra(self):
        return {"car_type": self.car_type, "dry_run": True, "on_stand": None, "hardware_watchdog": False,
                "depth_aligned": None, "sensors_missing": {}}

    def close(self):
        pass


def _error_text(exc):
    get = getattr(exc, "get_error_message", None)
    try:
        text = get() if callable(get) else str(exc)
    except Exception:
        text = str(exc)
    code = getattr(exc, "error_code", None)
    text = str(text).strip() or type(exc).__name__
    return "{} ({})".format(text, code) if code is not None and str(code) not in text else text


def _error_code(exc):
    code = getattr(exc, "error_code", None)
    if code is None:
        try:
            code = int(str(exc).strip())
        except ValueError:
            return None
    try:
        return int(code)
    except (TypeError, ValueError):
        return None


def import_quanser(name):
    """``quanser.hardware`` / ``quanser.devices`` / ``quanser.multimedia``, or one clear CarError."""
    import importlib
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        raise CarError(
            "Quanser's Python API ({}) cannot be imported here ({}): run this on the QCar, where it ships; "
            "on a QCar 1 keep its PYTHONPATH under sudo: sudo PYTHONPATH=$PYTHONPATH python3 {} ...; "
            "or try the link with --dry-run".format(name, exc, os.path.basename(sys.argv[0] or "qcarlab_car_server.py")))


class QuanserCar(object):
    """A QCar 1 or QCar 2 through Quanser's HIL and device classes.

    Opening does what Quanser's ``QCar`` class does at start-up (``[qcar.py] QCar._set_options``):
    on a QCar 1 PWM 0 in duty-cycle mode at 60e6/4096 Hz and the motor coast pin (digital 40) to
    0; on both the board options ``steer_bias=0;motor_limit=L;``, encoder 0 in 4x quadrature with
    its filter at 60 MHz and its count to 0. Then it writes a stop, and starts the board's own
    watchdog where the board accepts expiration states (throttle and steering to 0 if this process
    stops reloading it); where it does not, a killed process leaves the motor at its last PWM, and
    the server says so at start-up. A failed start always closes the board.

    Every board call holds ``lock`` for that one call only. A write that fails is escalated: the
    car is stopped through another path (``write_pwm`` / ``write_other`` on the drive channels
    alone), the board is closed, and every drive call then raises :class:`CarFault` until
    :meth:`reopen` (a STOP from the controller) opens it afresh, as an over-current latch on a
    QCar 1 needs ([hw1] p.10).
    """

    backend = "quanser"

    def __init__(self, car_type="auto", throttle_limit=0.3, watchdog=0.25, lidar=True, rgbd=True, csi=True,
                 modules=None):
        self.np = _numpy()
        mods = modules or {}
        self.hw = mods.get("quanser.hardware") or import_quanser("quanser.hardware")
        self._modules = mods
        self.HILError = getattr(self.hw, "HILError", Exception)
        self.throttle_limit = float(throttle_limit)
        self.watchdog_s = float(watchdog)
        self.lock = threading.Lock()
        self.t0 = time.monotonic()
        self.fault = None
        self.card = None
        self.hardware_watchdog = False
        self.watchdog_note = "not tried"
        self._last_reload = 0.0
        self.missing = {}
        self.sensors = {}
        self.car_type = None
        self.applied = (0.0, 0.0, ALL_OFF)
        self._open_board(car_type)
        self.info = CARS[self.car_type]
        self.capabilities = ["drive", "lamps", "encoder", "imu", "battery"]
        for name, wanted, opener in (("lidar", lidar, self._open_lidar), ("rgbd", rgbd, self._open_rgbd),
                                     ("csi", csi, self._open_csi)):
            if not wanted:
                self.missing[name] = "disabled (--no-{})".format(name)
                continue
            try:
                self.sensors[name] = opener()
                self.capabilities.append(name)
            except Exception as exc:  # CarError (API missing), DeviceError, MediaError, ...
                self.missing[name] = _error_text(exc)
                _log(logging.WARNING, "%s not available (%s); serving without it", name, _error_text(exc))

    # --- the board ------------------------------------------------------------------------------
    def _u32(self, values):
        return self.np.array(list(values), dtype=self.np.uint32)

    def _tables(self):
        info = CARS[self.car_type]
        np = self.np
        kind_t, ch_t, sign_t = info["throttle"]
        kind_s, ch_s, sign_s = info["steering"]
        self.pwm_ch = self._u32([ch_t] if kind_t == "pwm" else [])
        other = [ch_s] + ([ch_t] if kind_t == "other" else [])
        self.lamp_other = [(i, lamp[1]) for i, lamp in enumerate(info["lamps"]) if lamp and lamp[0] == "other"]
        other += [ch for _, ch in self.lamp_other]
        self.other_ch = self._u32(other)
        self.digital_map = []  # (lamp index, digital channels)
        digital = []
        for i, lamp in enumerate(info["lamps"]):
            if lamp and lamp[0] == "digital":
                self.digital_map.append((i, len(digital), len(lamp[1])))
                digital += list(lamp[1])
        self.digital_ch = self._u32(digital)
        self.drive_other_ch = self._u32([ch_s] + ([ch_t] if kind_t == "other" else []))
        self.pwm_buf = np.zeros(self.pwm_ch.size, dtype=np.float64)
        self.other_buf = np.zeros(self.other_ch.size, dtype=np.float64)
        self.digital_buf = np.zeros(self.digital_ch.size, dtype=np.int8)
        self.analog_ch = self._u32(info["analog"])
        self.encoder_ch = self._u32([info["encoder"]])
        self.other_read_ch = self._u32(info["other_read"])
        self.analog_buf = np.zeros(self.analog_ch.size, dtype=np.float64)
        self.encoder_buf = np.zeros(1, dtype=np.int32)
        self.other_read_buf = np.zeros(self.other_read_ch.size, dtype=np.float64)
        self.signs = (sign_t, sign_s)
        self.throttle_kind = kind_t

    def _open_board(self, car_type):
        types = (1, 2) if car_type == "auto" else (int(car_type),)
        errors = []
        for t in types:  # as [qcar_config.py] check_car_type: "qcar" first, then "qcar2"
            card = self.hw.HIL()
            try:
                card.open(CARS[t]["board"], "0")
            except self.HILError as exc:
                errors.append("'{}': {}".format(CARS[t]["board"], _error_text(exc)))
                _quietly(card.close)
                continue
            self.card, self.car_type = card, t
            break
        if self.card is None:
            raise CarError("cannot open the QCar's HIL board ({})".format("; ".join(errors)))
        try:
            self._tables()
            self._configure()
            self._write(0.0, 0.0, STOP_LAMPS)
        except BaseException as exc:
            card, self.card = self.card, None
            _quietly(card.close)  # a failed start always closes the board
            if isinstance(exc, self.HILError):
                raise CarError("the {} board opened but could not be set up: {}; it was closed".format(
                    CARS[self.car_type]["name"], _error_text(exc)))
            raise
        self._start_watchdog()

    def _configure(self):
        np, card, hw = self.np, self.card, self.hw
        info = CARS[self.car_type]
        if info["pwm_setup"]:
            mode = getattr(getattr(hw, "PWMMode", None), "DUTY_CYCLE", PWM_MODE_DUTY_CYCLE)
            card.set_pwm_mode(self.pwm_ch, self.pwm_ch.size, np.array([int(mode)], dtype=np.int32))
            card.set_pwm_frequency(self.pwm_ch, self.pwm_ch.size, np.array([PWM_FREQUENCY_HZ], dtype=np.float64))
        if info["coast_pin"] is not None:
            card.write_digital(self._u32([info["coast_pin"]]), 1, np.zeros(1, dtype=np.int8))
        options = "steer_bias=0;motor_limit={:.4g};".format(self.throttle_limit)
        card.set_card_specific_options(options, int(getattr(hw, "MAX_STRING_LENGTH", 2048)))
        card.set_encoder_quadrature_mode(self.encoder_ch, 1, np.array([QUADRATURE_4X], dtype=np.uint32))
        card.set_encoder_filter_frequency(self.encoder_ch, 1, np.array([ENCODER_FILTER_HZ], dtype=np.float64))
        card.set_encoder_counts(self.encoder_ch, 1, np.zeros(1, dtype=np.int32))

    def _start_watchdog(self):
        """The board's own watchdog: throttle and steering to 0 if nothing reloads it for
        about the server's watchdog time (a killed or frozen process)."""
        np, card = self.np, self.card
        try:
            _quietly(card.watchdog_stop)
            _quietly(card.watchdog_clear)
            if self.pwm_ch.size:
                card.watchdog_set_pwm_expiration_state(self.pwm_ch, self.pwm_ch.size, np.zeros(self.pwm_ch.size))
            card.watchdog_set_other_expiration_state(self.drive_other_ch, self.drive_other_ch.size,
                                                     np.zeros(self.drive_other_ch.size))
            card.watchdog_start(float(self.watchdog_s))
            self.hardware_watchdog = True
            self.watchdog_note = "the board stops the motor if this process stops for {:g} s".format(self.watchdog_s)
        except Exception as exc:  # HILError: this board cannot set expiration states; AttributeError: old API
            _quietly(card.watchdog_stop)
            self.hardware_watchdog = False
            self.watchdog_note = "unavailable ({})".format(_error_text(exc))
            _log(logging.WARNING, "the board's watchdog is unavailable (%s): if this process is killed (kill -9, power "
                        "loss of the computer) the motor keeps its last PWM; signals (Ctrl-C, SIGTERM, SIGHUP, "
                        "SIGQUIT) still stop it", _error_text(exc))

    def kick(self, force=False):
        """Reload the board's watchdog (at most every watchdog/5 s unless ``force``). Returns False
        when it had expired (the board stopped the motor by itself); it is then cleared and restarted."""
        if not self.hardware_watchdog or self.card is None:
            return True
        now = time.monotonic()
        if not force and now - self._last_reload < self.watchdog_s / 5.0:
            return True
        self._last_reload = now
        with self.lock:
            if self.card is None:
                return True
            try:
                reloaded = self.card.watchdog_reload()
            except self.HILError as exc:
                _log(logging.ERROR, "reloading the board's watchdog failed: %s", _error_text(exc))
                return True
            if reloaded is None or reloaded:
                return True
            try:
                self.card.watchdog_clear()
                self.card.watchdog_start(float(self.watchdog_s))
            except self.HILError as exc:
                self.hardware_watchdog = False
                _log(logging.ERROR, "the board's watchdog expired and could not be restarted: %s", _error_text(exc))
        return False

    def _write(self, throttle, steering, leds):
        sign_t, sign_s = self.signs
        other = self.other_buf
        other[0] = sign_s * steering
        k = 1
        if self.throttle_kind == "pwm":
            self.pwm_buf[0] = sign_t * throttle
        else:
            other[1] = sign_t * throttle
            k = 2
        for j, (i, _ch) in enumerate(self.lamp_other):
            other[k + j] = leds[i]
        for i, start, n in self.digital_map:
            self.digital_buf[start:start + n] = 1 if leds[i] > 0.0 else 0
        self.card.write(
            None, 0,
            self.pwm_ch if self.pwm_ch.size else None, self.pwm_ch.size,
            self.digital_ch if self.digital_ch.size else None, self.digital_ch.size,
            self.other_ch, self.other_ch.size,
            None,
            self.pwm_buf if self.pwm_ch.size else None,
            self.digital_buf if self.digital_ch.size else None,
            self.other_buf,
        )
        self.applied = (throttle, steering, tuple(leds))

    def write(self, throttle, steering, leds):
        with self.lock:
            if self.fault:
                raise CarFault(self.fault)
            try:
                self._write(throttle, steering, leds)
            except self.HILError as exc:
                self._escalate("write failed: " + _error_text(exc))
                raise CarFault(self.fault)

    def stop_outputs(self, leds):
        self.write(0.0, 0.0, leds)

    def _escalate(self, why):
        """Called with the lock held: stop the motor through another path, close, remember."""
        np, card = self.np, self.card
        stopped = []
        if card is not None:
            if self.pwm_ch.size:
                try:
                    card.write_pwm(self.pwm_ch, self.pwm_ch.size, np.zeros(self.pwm_ch.size))
                    stopped.append("PWM 0 set to 0")
                except Exception as exc:
                    stopped.append("write_pwm failed too ({})".format(_error_text(exc)))
            try:
                card.write_other(self.drive_other_ch, self.drive_other_ch.size, np.zeros(self.drive_other_ch.size))
                stopped.append("drive channels set to 0")
            except Exception as exc:
                stopped.append("write_other failed too ({})".format(_error_text(exc)))
            _quietly(card.watchdog_stop)
            _quietly(card.close)
            self.card = None
        self.applied = (0.0, 0.0, ALL_OFF)
        self.fault = ("the {} board {}; {}; the board was closed (send STOP to reopen it)".format(
            self.info["name"] if hasattr(self, "info") else "QCar", why, ", ".join(stopped) or "nothing to stop"))
        _log(logging.ERROR, "%s", self.fault)

    def reopen(self):
        """After a fault: open and set up the board afresh (it starts stopped)."""
        with self.lock:
            if self.card is not None:
                return
            card_type = self.car_type
            self.card = None
            self.fault = None
        try:
            self._open_board(card_type)
        except CarError as exc:
            with self.lock:
                self.fault = "reopening the board failed: {}".format(exc)
            raise CarFault(self.fault)
        _log(logging.WARNING, "the board was reopened; the car is stopped")

    def read(self):
        with self.lock:
            if self.card is None:
                raise CarFault(self.fault or "the board is closed")
            try:
                self.card.read(
                    self.analog_ch, self.analog_ch.size, self.encoder_ch, 1, None, 0,
                    self.other_read_ch, self.other_read_ch.size,
                    self.analog_buf, self.encoder_buf, None, self.other_read_buf,
                )
            except self.HILError as exc:
                raise CarError("HIL read failed: " + _error_text(exc))
            a, o = self.analog_buf, self.other_read_buf
            return Readout(self.time, int(self.encoder_buf[0]), float(o[6]), float(a[0]), float(a[1]),
                           (float(o[0]), float(o[1]), float(o[2])), (float(o[3]), float(o[4]), float(o[5])))

    @property
    def time(self):
        return time.monotonic() - self.t0

    def name(self):
        return "{} ({})".format(self.info["name"], socket.gethostname())

    def extra(self):
        return {"car_type": self.car_type, "board": self.info["board"], "dry_run": False, "on_stand": None,
                "hardware_watchdog": self.hardware_watchdog, "depth_aligned": False,
                "sensors_missing": dict(self.missing)}

    # --- sensors ------------------------------------------------------------------------------
    def _module(self, name):
        return self._modules.get(name) or import_quanser(name)

    def _open_lidar(self):
        dev = self._module("quanser.devices")
        lidar = dev.RPLIDAR()
        lidar.open(self.info["lidar_url"], dev.RangingDistance.LONG)
        return {"dev": dev, "lidar": lidar, "meas": dev.RangingMeasurements(LIDAR_POINTS), "last": None,
                "DeviceError": getattr(dev, "DeviceError", Exception)}

    def _open_rgbd(self):
        mm = self._module("quanser.multimedia")
        w, h = RGBD_SIZE
        video = mm.Video3D("0")
        try:
            color = video.stream_open(mm.Video3DStreamType.COLOR, 0, CAMERA_FPS, w, h,
                                      mm.ImageFormat.ROW_MAJOR_INTERLEAVED_BGR, mm.ImageDataType.UINT8)
            depth = video.stream_open(mm.Video3DStreamType.DEPTH, 0, CAMERA_FPS, w, h,
                                      mm.ImageFormat.ROW_MAJOR_GREYSCALE, mm.ImageDataType.UINT8)
            video.start_streaming()
        except Exception:
            _quietly(video.close)
            raise
        np = self.np
        return {"video": video, "color_stream": color, "depth_stream": depth,
                "color": np.zeros((h, w, 3), dtype=np.uint8), "depth": np.zeros((h, w, 1), dtype=np.float32),
                "t_color": None, "t_depth": None}

    def _open_csi(self):
        mm = self._module("quanser.multimedia")
        w, h = CSI_SIZE
        caps = {}
        try:
            for view, cam in self.info["csi"].items():
                cap = mm.VideoCapture("video://localhost:{}".format(cam), CAMERA_FPS, w, h,
                                      mm.ImageFormat.ROW_MAJOR_INTERLEAVED_BGR, mm.ImageDataType.UINT8, None, 0)
                cap.start()
                caps[view] = cap
        except Exception:
            for cap in caps.values():
                _quietly(cap.stop)
                _quietly(cap.close)
            raise
        np = self.np
        return {"caps": caps, "bufs": {v: np.zeros((h, w, 3), dtype=np.uint8) for v in caps}, "t": {v: None for v in caps}}

    def read_lidar(self):
        t, angles, ranges = self.lidar_arrays()
        return t, [numpy_part(angles), numpy_part(ranges)]

    def read_rgbd(self):
        t, color, depth = self.rgbd_arrays()
        return t, [numpy_part(color), numpy_part(depth)]

    def read_csi(self):
        t, views = self.csi_arrays()
        return t, [numpy_part(v) for v in views]

    def lidar_arrays(self):
        """(t, angles, ranges): the latest turn; a read with no new data (0, or error -34) keeps
        the previous turn and its time."""
        s = self.sensors["lidar"]
        np = self.np
        try:
            n = s["lidar"].read(s["dev"].RangingMeasurementMode.NORMAL, 0.0, 0.0, s["meas"])
        except s["DeviceError"] as exc:
            if _error_code(exc) != WOULD_BLOCK:
                raise CarError("LIDAR read failed: " + _error_text(exc))
            n = 0
        if n and n > 0:
            m = s["meas"]
            quality = getattr(m, "quality", None)
            angles, ranges = lidar_to_body(
                np.asarray(m.heading)[:n], np.asarray(m.distance)[:n],
                None if quality is None else np.asarray(quality)[:n], self.info["lidar_zero"])
            s["last"] = (self.time, angles, ranges)
        elif s["last"] is None:  # no turn yet (the RPLidar spins up for a second or two)
            s["last"] = (0.0, np.zeros(0), np.zeros(0))
        return s["last"]

    def rgbd_arrays(self):
        """(t, color, depth): the latest colour and depth (depth is NOT aligned to colour: the D435 streams them from
        two cameras; Quanser's examples crop it; see docs/how-to/real-car.md)."""
        s = self.sensors["rgbd"]
        try:
            for key, stream, getter in (("color", s["color_stream"], "get_data"), ("depth", s["depth_stream"], "get_meters")):
                frame = stream.get_frame()
                if frame:
                    getattr(frame, getter)(s[key])
                    frame.release()
                    s["t_" + key] = self.time
        except Exception as exc:
            if _error_code(exc) != WOULD_BLOCK:
                raise CarError("RGBD read failed: " + _error_text(exc))
        t = min(s["t_color"] or 0.0, s["t_depth"] or 0.0)  # the older image's time; 0 before both came
        return t, s["color"], s["depth"][:, :, 0]

    def csi_arrays(self):
        """(t, [right, rear, left, front]): the four views; a camera whose read reports no new frame keeps its old frame, and the
        frame's time is the oldest of the four."""
        s = self.sensors["csi"]
        try:
            for view, cap in s["caps"].items():
                if cap.read(s["bufs"][view]):
                    s["t"][view] = self.time
        except Exception as exc:
            raise CarError("CSI read failed: " + _error_text(exc))
        t = min(v or 0.0 for v in s["t"].values())  # the oldest view's time; 0 until all four came
        return t, [s["bufs"][v] for v in ("right", "rear", "left", "front")]

    def close(self):
        self.kick(force=True)  # an expired board watchdog (nobody reloaded it during shutdown) is cleared first
        with self.lock:
            if self.card is not None:
                try:
                    self._write(0.0, 0.0, ALL_OFF)
                except Exception as exc:
                    self._escalate("final stop failed: " + _error_text(exc))
                if self.card is not None:
                    _quietly(self.card.watchdog_stop)
                    _quietly(self.card.close)
                    self.card = None
        lidar = self.sensors.pop("lidar", None)
        if lidar is not None:
            _quietly(lidar["lidar"].close)
        rgbd = self.sensors.pop("rgbd", None)
        if rgbd is not None:
            _quietly(rgbd["video"].stop_streaming)
            _quietly(rgbd["color_stream"].close)
            _quietly(rgbd["depth_stream"].close)
            _quietly(rgbd["video"].close)
        csi = self.sensors.pop("csi", None)
        if csi is not None:
            for cap in csi["caps"].values():
                _quietly(cap.stop)
                _quietly(cap.close)


def _quietly(fn, *args):
    try:
        fn(*args)
    except Exception:
        pass


# =================================================================================================
# The server (docs/protocol.md sections 3, 5 and 6: what a server must do)
# =================================================================================================
MIN_TOKEN, MAX_TOKEN = 16, 256
FREE_FAILURES, PENALTY_BASE_S, PENALTY_MAX_S, FORGET_S = 3, 0.5, 30.0, 600.0
MAX_ADDRESSES, GLOBAL_BURST, GLOBAL_PER_S, TRUSTED_S, MAX_TRUSTED = 4096, 30, 0.1, 86400.0, 256


def check_token(token):
    """None, or the token if it is 16-256 printable characters (else InputError)."""
    if token is None or not token.strip():
        return None
    if not token.isprintable() or token != token.strip() or not MIN_TOKEN <= len(token) <= MAX_TOKEN:
        raise InputError("the token must be {}-{} printable characters without leading or trailing spaces (got {}); "
                         "make one with --new-token".format(MIN_TOKEN, MAX_TOKEN, len(token)))
    return token


def token_matches(given, secret):
    """Constant-time comparison of digests (neither the value nor the length leaks through timing)."""
    if not isinstance(given, str):
        return False
    a = hashlib.sha256(given.encode("utf-8", "surrogatepass")).digest()
    return hmac.compare_digest(a, hashlib.sha256(secret.encode("utf-8")).digest())


def penalty_s(failures):
    """Seconds an address waits after its ``failures``-th wrong token in a row: 3 free, then 0.5,
    1, 2, ... at most 30 s."""
    if failures <= FREE_FAILURES:
        return 0.0
    return min(PENALTY_BASE_S * 2.0 ** (failures - FREE_FAILURES - 1), PENALTY_MAX_S)


class TokenGuard(object):
    """Wrong tokens per client address (the wait before a token from it is compared again), and one
    budget for every address that has not shown the right token lately (qcarlab/net/guard.py: the
    same rules and numbers): rotating addresses does not multiply the guesses, and churning
    addresses cannot make the table forget a penalised one."""

    def __init__(self, clock=time.monotonic):
        self.clock = clock
        self.lock = threading.Lock()
        self.seen = {}  # address -> (failures in a row, wait until, last failure)
        self.trusted = {}  # address -> when it last showed the right token
        self.budget = float(GLOBAL_BURST)
        self.budget_at = clock()
        self.compared = 0

    def _own_wait(self, addr, now):
        entry = self.seen.get(addr)
        if entry is None:
            return 0.0
        if now - entry[2] > FORGET_S:
            del self.seen[addr]
            return 0.0
        return max(0.0, entry[1] - now)

    def _is_trusted(self, addr, now):
        when = self.trusted.get(addr)
        if when is None:
            return False
        if now - when > TRUSTED_S:
            del self.trusted[addr]
            return False
        return True

    def _global_wait(self, now):
        self.budget = min(float(GLOBAL_BURST), self.budget + (now - self.budget_at) * GLOBAL_PER_S)
        self.budget_at = now
        return 0.0 if self.budget >= 1.0 else (1.0 - self.budget) / GLOBAL_PER_S

    def wait_s(self, addr):
        now = self.clock()
        with self.lock:
            own = self._own_wait(addr, now)
            if own > 0.0 or self._is_trusted(addr, now):
                return own
            return self._global_wait(now)

    def admit(self, addr):
        """(seconds to wait, whether it is the global budget's); a 0 takes one unit of the budget."""
        now = self.clock()
        with self.lock:
            own = self._own_wait(addr, now)
            if own > 0.0:
                return own, False
            if self._is_trusted(addr, now):
                return 0.0, False
            wait = self._global_wait(now)
            if wait == 0.0:
                self.budget -= 1.0
                self.compared += 1
            return wait, wait > 0.0

    def failed(self, addr):
        now = self.clock()
        with self.lock:
            failures, _, last = self.seen.pop(addr, (0, 0.0, now))
            if now - last > FORGET_S:
                failures = 0
            failures += 1
            wait = penalty_s(failures)
            self.seen[addr] = (failures, now + wait, now)
            if len(self.seen) > MAX_ADDRESSES:  # the oldest whose wait is over; a penalised one last
                done = [a for a, e in self.seen.items() if e[1] <= now or now - e[2] > FORGET_S]
                pool = done or list(self.seen)
                del self.seen[min(pool, key=lambda a: self.seen[a][2])]
            return wait

    def succeeded(self, addr):
        now = self.clock()
        with self.lock:
            self.seen.pop(addr, None)
            if not self._is_trusted(addr, now):
                self._global_wait(now)
                self.budget = min(float(GLOBAL_BURST), self.budget + 1.0)
            self.trusted[addr] = now
            if len(self.trusted) > MAX_TRUSTED:
                del self.trusted[min(self.trusted, key=self.trusted.get)]

    def failures(self, addr):
        with self.lock:
            return self.seen.get(addr, (0, 0.0, 0.0))[0]


def is_loopback_address(addr):
    try:
        return ipaddress.ip_address(addr.split("%")[0]).is_loopback
    except ValueError:
        return False


def _peer_name(addr):
    if isinstance(addr, tuple) and len(addr) >= 2:
        host = str(addr[0])
        return "[{}]:{}".format(host, addr[1]) if ":" in host else "{}:{}".format(host, addr[1])
    return str(addr)


def _one_line(text, limit=200):
    text = "".join(ch if ch.isprintable() else " " for ch in str(text))
    return text if len(text) <= limit else text[:limit - 3] + "..."


class _End(Exception):
    def __init__(self, reason, bye=False):
        Exception.__init__(self, reason)
        self.reason = reason
        self.bye = bye


class RefusalLog(object):
    """Refusals (connections that never became clients) at a bounded rate: the first of each kind
    in an interval gets its own line, the rest are counted and summed up in one line when the
    interval ends."""

    def __init__(self, interval=10.0):
        self.interval = interval
        self.lock = threading.Lock()
        self.start = time.monotonic()
        self.logged = set()
        self.counts = {}
        self.last_peer = ""
        self.total = 0

    def refused(self, code, peer, detail=""):
        self.flush()
        with self.lock:
            self.total += 1
            first = code not in self.logged
            if first:
                self.logged.add(code)
            else:
                self.counts[code] = self.counts.get(code, 0) + 1
                self.last_peer = peer
        if first:
            _log(logging.WARNING, "%s refused: %s%s", peer, code, ": " + detail if detail else "")

    def flush(self, force=False):
        now = time.monotonic()
        with self.lock:
            if not force and now - self.start < self.interval:
                return
            counts, last, span = self.counts, self.last_peer, now - self.start
            self.start, self.logged, self.counts = now, set(), {}
        if counts:
            n = sum(counts.values())
            kinds = ", ".join("{} {:,}".format(c, k) for c, k in sorted(counts.items(), key=lambda kv: -kv[1]))
            _log(logging.WARNING, "refused %s more connection%s in the last %.0f s (%s); the last from %s",
                 "{:,}".format(n), "" if n == 1 else "s", span, kinds, last)


def _log(level, msg, *args):
    try:
        log.log(level, msg, *args)
    except Exception:  # a failing handler (the terminal is gone) must not end a server thread
        pass


try:
    import fcntl
    import termios

    _OUTQ = termios.TIOCOUTQ
except (ImportError, AttributeError):  # not Linux/Unix: the rule below has nothing to measure
    fcntl, _OUTQ = None, None
_TCP_INFO = getattr(socket, "TCP_INFO", 11 if sys.platform.startswith("linux") else None)
_BYTES_ACKED = struct.Struct("=Q")  # tcp_info's tcpi_bytes_acked, at offset 120 (Linux 4.1 and later)


def send_progress(sock):
    """(bytes sent that the peer has not acknowledged, bytes it acknowledged in all), or None where
    the system does not say. A peer that does not read fills its receive buffer and then
    acknowledges nothing more, however large our own send buffer lets the replies pile up."""
    if fcntl is None or _TCP_INFO is None:
        return None
    raw = getattr(sock, "_s", sock)  # a TLS wrapper's socket
    try:
        info = raw.getsockopt(socket.IPPROTO_TCP, _TCP_INFO, 136)
        if len(info) < 128:
            return None
        outq = struct.unpack("i", fcntl.ioctl(raw.fileno(), _OUTQ, b"\0\0\0\0"))[0]
        return outq, _BYTES_ACKED.unpack_from(info, 120)[0]
    except (OSError, ValueError, struct.error):
        return None


class ProgressWatch(object):
    """docs/protocol.md's "no reply stalled for 5 s": True from :meth:`stalled` once replies have
    waited for the client for ``limit`` s without any of them being taken (sampled now and then)."""

    def __init__(self, limit):
        self.limit = limit
        self.acked = None
        self.since = None

    def stalled(self, sock, now):
        got = send_progress(sock)
        if got is None:
            return False
        outq, acked = got
        if outq <= 0 or acked != self.acked or self.since is None:
            self.acked, self.since = acked, now
            return False
        return now - self.since >= self.limit


class SourceLog(object):
    """Log lines about clients at a bounded rate per client address: at most ``per_source`` lines
    an address in ``interval`` s, the rest counted and said in one line per address when the
    interval ends ("127.0.0.9: 1,234 more lines not logged in the last 10 s"). ``emit(level, msg,
    *args)`` writes a line. Lines about a failed stop of the car are never held back."""

    def __init__(self, emit, interval=10.0, per_source=20, max_sources=4096, clock=time.monotonic):
        self.emit, self.interval, self.per_source, self.max_sources, self.clock = (
            emit, interval, per_source, max_sources, clock)
        self.lock = threading.Lock()
        self.start = clock()
        self.counts = {}  # address -> lines in this interval
        self.suppressed = 0

    def line(self, source, level, msg, *args):
        now = self.clock()
        self.flush(now)
        with self.lock:
            key = source if source in self.counts or len(self.counts) < self.max_sources else "(other addresses)"
            n = self.counts.get(key, 0) + 1
            self.counts[key] = n
            ok = n <= self.per_source or "FAILED" in msg or any("FAILED" in str(a) for a in args)
            if not ok:
                self.suppressed += 1
        if ok:
            self.emit(level, msg, *args)

    def flush(self, now=None, force=False):
        now = self.clock() if now is None else now
        with self.lock:
            if not force and now - self.start < self.interval:
                return
            over = [(a, n - self.per_source) for a, n in self.counts.items() if n > self.per_source]
            span = now - self.start
            self.start, self.counts = now, {}
        for addr, n in sorted(over, key=lambda kv: -kv[1])[:20]:
            self.emit(logging.WARNING, "%s: %s more line%s about its connections not logged in the last %.0f s",
                      addr, "{:,}".format(n), "" if n == 1 else "s", span)


class _Waiting(object):
    """A connection that has not been handed to a thread: accepted, maybe readable."""

    __slots__ = ("sock", "addr", "peer", "source", "accepted", "ready_at")

    def __init__(self, sock, addr, now):
        self.sock, self.addr, self.accepted, self.ready_at = sock, addr, now, None
        self.peer = _peer_name(addr)
        self.source = str(addr[0]) if isinstance(addr, tuple) and addr else self.peer


class Admission(object):
    """Connections before their hello, kept so that a flood cannot use them against a real client
    (docs/protocol.md, section 3; ``qcarlab serve`` uses this same class):

    - a connection is held **without a thread** until its first bytes come (a HELLO's, a TLS
      ClientHello's, anything): ``max_silent`` (256) such connections cost a file descriptor each;
      one that says nothing within ``hello_timeout`` of its accept is closed (``timeout``);
    - when they are all taken, the one that makes room is the **oldest silent** connection of the
      **source address with the most** of them; a connection whose bytes have come is never dropped
      for a new silent one (when nothing silent is left, the new one is refused);
    - a connection whose bytes came gets a thread (``start``); at most ``max_started`` of those are
      reading their hello at once; a waiting one goes first from the source with the fewest started
      (fairness), and when every slot is taken the oldest started one of the source with the most
      makes room (it is told ``too_many_clients``), so stalled half-hellos cannot lock a client out;
    - the hello deadline counts the client's own time: from the accept, plus nothing for the time
      its bytes waited here for a thread (time the server spent, not the client).

    ``start(sock, addr, deadline)`` runs on the accepting thread and returns a handle with
    ``evict()``; the server calls :meth:`done` with it once that connection said hello or ended.
    ``refused(code, peer, detail)`` counts the connections dropped here (for a rate-limited log).
    Runs its loop in :meth:`run` until ``stopping()``; :meth:`wake` from any thread."""

    def __init__(self, listener, start, refused, hello_timeout=2.0, max_started=16, max_silent=256,
                 plain=True):
        self.listener = listener
        self.start = start
        self.refused = refused
        self.hello_timeout = float(hello_timeout)
        self.max_started = int(max_started)
        self.max_silent = int(max_silent)
        self.plain = plain  # False: TLS, nothing can be said to a connection before its handshake
        self.lock = threading.Lock()
        self.silent = {}  # fd -> _Waiting, no bytes yet (in the selector)
        self.ready = []  # _Waiting whose bytes came, waiting for a thread (oldest first)
        self.started = {}  # handle -> (source, when started), oldest first (dicts keep order from 3.6 on)
        self.evicted = 0  # started connections dropped to make room
        self.dropped = 0  # silent connections dropped to make room, or new ones refused
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        import selectors

        self.selector = selectors.DefaultSelector()
        self._events = selectors.EVENT_READ

    # --- other threads -----------------------------------------------------------------------------
    def done(self, handle):
        """The started connection ``handle`` said hello or ended: its slot is free."""
        with self.lock:
            gone = self.started.pop(handle, None) is not None
        if gone:
            self.wake()

    def wake(self):
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass

    @property
    def pending(self):
        return len(self.silent) + len(self.ready) + len(self.started)

    # --- the accepting thread ------------------------------------------------------------------------
    def run(self, stopping, tick=None, every=0.25):
        """Accept and hold connections until ``stopping()``; ``tick(now)`` is called about every
        ``every`` s (the server's periodic checks)."""
        next_tick = 0.0
        self.listener.setblocking(False)
        self.selector.register(self.listener, self._events, None)
        self.selector.register(self._wake_r, self._events, None)
        try:
            while not stopping():
                now = time.monotonic()
                wait = 1.0 if tick is None else max(0.0, min(1.0, next_tick - now))
                if tick is not None and now >= next_tick:
                    next_tick = now + every
                    try:
                        tick(now)
                    except Exception as exc:  # a check must not end the accepting thread
                        _log(logging.WARNING, "periodic check failed: %s", _one_line(str(exc)))
                if self.silent:
                    first = min(w.accepted for w in self.silent.values()) + self.hello_timeout
                    wait = max(0.0, min(wait, first - now))
                try:
                    events = self.selector.select(wait)
                except (OSError, ValueError):
                    if stopping():
                        break
                    continue
                if stopping():
                    break
                for key, _ in events:
                    obj = key.fileobj
                    if obj is self.listener:
                        self._accept_some()
                    elif obj is self._wake_r:
                        try:
                            while self._wake_r.recv(4096):
                                pass
                        except OSError:
                            pass
                    else:
                        self._readable(key.data)
                self._expire(time.monotonic())
                self._promote()
        finally:
            self.close()

    def _accept_some(self):
        for _ in range(64):  # a burst is taken in one go; the rest next time round
            try:
                sock, addr = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            now = time.monotonic()
            try:
                sock.setblocking(False)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
            except OSError:
                pass
            new = _Waiting(sock, addr, now)
            if len(self.silent) + len(self.ready) >= self.max_silent:
                victim = self._silent_victim()
                if victim is None:  # everything held has begun its hello: the newcomer waits outside
                    self.dropped += 1
                    self._close(new, "full", "every waiting connection has begun its hello; refused at once")
                    continue
                self.dropped += 1
                self._forget(victim)
                self._close(victim, "evicted", "dropped to make room (its source held the most silent connections)",
                            "too_many_clients", "more than {} connections were waiting for their hello; this one, "
                            "silent and from the busiest address, was dropped".format(self.max_silent))
            try:
                self.selector.register(sock, self._events, new)
            except (OSError, ValueError):
                self._close(new, "no_hello", "could not be watched")
                continue
            self.silent[sock.fileno()] = new

    def _silent_victim(self):
        counts = {}
        for w in self.silent.values():
            counts[w.source] = counts.get(w.source, 0) + 1
        if not counts:
            return None
        most = max(counts.values())
        busiest = [w for w in self.silent.values() if counts[w.source] == most]
        return min(busiest, key=lambda w: w.accepted)

    def _forget(self, w):
        self.silent.pop(w.sock.fileno(), None)
        try:
            self.selector.unregister(w.sock)
        except (KeyError, ValueError, OSError):
            pass

    def _readable(self, w):
        if w is None:
            return
        self._forget(w)
        try:
            data = w.sock.recv(1, socket.MSG_PEEK)
        except (BlockingIOError, InterruptedError):
            self.silent[w.sock.fileno()] = w  # spurious: watch it again
            self.selector.register(w.sock, self._events, w)
            return
        except OSError as exc:
            self._close(w, "no_hello", "connection error: {}".format(exc.strerror or exc), error=False)
            return
        if not data:
            self._close(w, "no_hello", "closed without a hello", error=False)
            return
        w.ready_at = time.monotonic()
        self.ready.append(w)

    def _expire(self, now):
        late = [w for w in self.silent.values() if now - w.accepted >= self.hello_timeout]
        for w in late:
            self._forget(w)
            self._close(w, "no_hello", "no hello within {:g} s of connecting".format(self.hello_timeout),
                        "timeout", "no hello within {:g} s of connecting".format(self.hello_timeout))

    def _promote(self):
        while self.ready:
            with self.lock:
                counts = {}
                for source, _ in self.started.values():
                    counts[source] = counts.get(source, 0) + 1
                pick = min(self.ready, key=lambda w: (counts.get(w.source, 0), w.ready_at))
                victim = None
                if len(self.started) >= self.max_started:
                    most = max(counts.values())
                    victim = next(h for h, (source, _) in self.started.items() if counts[source] == most)
                    del self.started[victim]
                    self.evicted += 1
            if victim is not None:
                try:
                    victim.evict()
                except Exception:
                    pass
            self.ready.remove(pick)
            now = time.monotonic()
            deadline = pick.accepted + self.hello_timeout + (now - pick.ready_at)  # its wait for a thread is not its own
            with self.lock:  # held while its thread starts: its done() comes after it is counted
                try:
                    handle = self.start(pick.sock, pick.addr, deadline)
                except Exception as exc:  # no thread to be had: this one is dropped
                    handle = exc
                else:
                    self.started[handle] = (pick.source, now)
            if isinstance(handle, Exception):
                self._close(pick, "no_hello", "could not be served: {}".format(handle), error=False)

    def _close(self, w, code, detail, err_code=None, err_message=None, error=True):
        if error and err_code and self.plain:
            body = json.dumps({"code": err_code, "message": err_message, "fatal": True}).encode("utf-8")
            try:
                w.sock.send(HEADER.pack(MAGIC, PROTOCOL, ERROR, 1, 0, len(body)) + body)
            except OSError:
                pass
        _quietly(w.sock.close)
        try:
            self.refused(code, w.peer, detail)
        except Exception:
            pass

    def close(self):
        for w in list(self.silent.values()) + list(self.ready):
            _quietly(w.sock.close)
        self.silent, self.ready = {}, []
        _quietly(self.selector.close)
        _quietly(self._wake_r.close)
        _quietly(self._wake_w.close)


_POLL_GONE = (getattr(select, "POLLRDHUP", 0) | select.POLLHUP | select.POLLERR) if hasattr(select, "poll") else 0


class CarServer(object):
    """Serve ``car`` (a :class:`DryRunCar` or :class:`QuanserCar`) on ``host:port``."""

    def __init__(self, car, host="127.0.0.1", port=DEFAULT_PORT, token=None, watchdog=0.25,
                 controller_timeout=None, throttle_limit=0.3, max_clients=24, max_pending=16,
                 monitor_rate=10.0, hello_timeout=2.0, frame_timeout=5.0, send_timeout=5.0, max_silent=256):
        if not (isinstance(port, int) and 0 <= port < 65536):
            raise InputError("--port must be in 0-65535, got {!r}".format(port))
        if not (math.isfinite(watchdog) and 0.01 <= watchdog <= 60.0):
            raise InputError("--watchdog must be between 0.01 and 60 s, got {}".format(watchdog))
        if controller_timeout is None:
            controller_timeout = 4.0 * watchdog
        if not (math.isfinite(controller_timeout) and 0.01 <= controller_timeout <= 3600.0):
            raise InputError("--controller-timeout must be between 0.01 and 3600 s, got {}".format(controller_timeout))
        if not (math.isfinite(throttle_limit) and 0.0 < throttle_limit <= 1.0):
            raise InputError("--throttle-limit must be in (0, 1], got {}".format(throttle_limit))
        if not 2 <= max_clients <= 1024:
            raise InputError("--max-clients must be in 2-1024 (one slot is kept for a controller), got {}".format(max_clients))
        if not (math.isfinite(monitor_rate) and 0.1 <= monitor_rate <= 1000.0):
            raise InputError("--monitor-rate must be between 0.1 and 1000 Hz, got {}".format(monitor_rate))
        self.car = car
        self.host, self.port = host, port
        self.token = check_token(token)
        self.watchdog = float(watchdog)
        self.controller_timeout = float(controller_timeout)
        self.throttle_limit = float(throttle_limit)
        self.steering_limit = MAX_STEERING
        self.max_clients = max_clients
        self.max_pending = max_pending  # connections reading their hello on a thread at once
        self.max_silent = max_silent  # connections waiting for their first bytes (no thread)
        self.admission = None  # the Admission that holds connections before their hello, once started
        self.monitor_rate = float(monitor_rate)
        self.hello_timeout = hello_timeout
        self.frame_timeout = frame_timeout
        self.send_timeout = send_timeout

        self.drive_lock = threading.RLock()  # controller identity + feeding + drive writes (one HIL call)
        self.control_free = threading.Condition(self.drive_lock)  # notified when the controller leaves
        self.state_lock = threading.Lock()  # the session sets
        self.controller = None
        self.sessions = set()
        self.monitors = set()
        self.last_feed = time.monotonic()
        self.tripped = False
        self.trips = 0
        self.takeovers = 0
        self.stopping = False
        self.refusals = RefusalLog()
        self.clientlog = SourceLog(_log)
        self.tokens = TokenGuard()
        self.sensor_cache = {}  # reply type -> (monotonic time read, payload parts)
        self.sensor_locks = {LIDAR: threading.Lock(), RGBD: threading.Lock(), CSI: threading.Lock()}
        self._stop_evt = threading.Event()
        self._stop_requested = False  # set by request_stop (a signal handler): a plain flag
        self._watchdog_off = threading.Event()  # set last, when every client is gone
        self._kick = threading.Event()  # wakes the watchdog to recompute its deadline
        self._listener = None
        self._threads = []
        self.bound = None

    # --- identity -------------------------------------------------------------------------------
    def welcome(self, role):
        car = self.car
        params = dict(CAR_PARAMS[car.car_type], throttle_limit=self.throttle_limit)
        return {
            "protocol": PROTOCOL, "server": SERVER_VERSION, "role": role,
            "identity": {"name": car.name(), "backend": car.backend, "capabilities": list(car.capabilities),
                         "extra": car.extra()},
            "lockstep": False, "watchdog_s": self.watchdog, "controller_timeout_s": self.controller_timeout,
            "throttle_limit": self.throttle_limit, "steering_limit": self.steering_limit,
            "max_request": MAX_REQUEST, "max_clients": self.max_clients, "monitor_rate_hz": self.monitor_rate,
            "hello_timeout_s": self.hello_timeout, "frame_timeout_s": self.frame_timeout, "params": params,
        }

    # --- lifecycle ------------------------------------------------------------------------------
    @property
    def uri(self):
        host, port = self.bound
        return "tcp://{}:{}".format("[" + host + "]" if ":" in host else host, port)

    def bind(self):
        """Listen; refuses a non-loopback bound address without a token (decided by the address
        the socket is bound to, not by the host's name)."""
        if self._listener is not None:
            return self
        listener = self._bind()
        addr = listener.getsockname()
        if not is_loopback_address(addr[0]) and not self.token:
            listener.close()
            raise InputError(
                "refusing to serve on {} without a token: anyone on that network could drive the car; pass "
                "--token-file FILE (or set QCARLAB_TOKEN; make one with --new-token), or bind to 127.0.0.1".format(
                    addr[0]))
        self._listener = listener
        self.bound = (addr[0], addr[1])
        return self

    def start(self):
        self.bind()
        self.admission = Admission(self._listener, self._start_session, self.refusals.refused, self.hello_timeout,
                                   self.max_pending, self.max_silent)
        for target, name in ((self._accept_loop, "accept"), (self._watchdog_loop, "watchdog")):
            t = threading.Thread(target=target, name="qcarlab-" + name)
            t.daemon = True
            t.start()
            self._threads.append(t)
        return self

    def _bind(self):
        where = "{}:{}".format(self.host or "*", self.port)
        try:
            infos = socket.getaddrinfo(self.host or None, self.port, 0, socket.SOCK_STREAM, 0, socket.AI_PASSIVE)
        except socket.gaierror:
            raise InputError("--host {!r}: unknown host name".format(self.host))
        family, _, _, _, sockaddr = infos[0]
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(sockaddr)
            sock.listen(64)
        except OSError as exc:
            sock.close()
            if exc.errno == errno.EADDRINUSE:
                raise CarError("cannot listen on {}: the port is in use (another server?); pick another --port".format(where))
            if exc.errno in (errno.EACCES, errno.EPERM):
                raise CarError("cannot listen on {}: permission denied".format(where))
            if exc.errno == errno.EADDRNOTAVAIL:
                raise InputError("--host {!r}: this machine has no such address".format(self.host))
            raise CarError("cannot listen on {}: {}".format(where, exc.strerror or exc))
        return sock

    def wait(self, timeout=None):
        """Block until :meth:`request_stop` or :meth:`stop` (True) or ``timeout`` (False); sees a
        request within 0.1 s."""
        end = None if timeout is None else time.monotonic() + timeout
        while not self._stop_requested:
            step = 0.1 if end is None else min(0.1, end - time.monotonic())
            if step <= 0.0:
                return False
            if self._stop_evt.wait(step):
                return True
        return True

    def request_stop(self):
        """Make :meth:`wait` return; safe from a signal handler: it only sets a flag (Event.set
        takes a lock that the interrupted main thread may be holding, inside Event.wait)."""
        self._stop_requested = True

    def stop(self, why="server stopping"):
        """Stop the car first, then tell every client bye and disconnect them."""
        if self.stopping:
            return
        self.stopping = True
        self._stop_evt.set()
        self.safe_stop(why)
        if self.admission is not None:
            self.admission.wake()
        with self.drive_lock:
            self.control_free.notify_all()
        with self.state_lock:
            sessions = list(self.sessions)
        for s in sessions:
            s.interrupt()
        for s in sessions:
            if s.thread is not None:
                s.thread.join(3.0)
        self.safe_stop(why)
        self._watchdog_off.set()
        self._kick.set()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(3.0)
        if self._listener is not None:
            _quietly(self._listener.close)
        self.refusals.flush(force=True)
        self.clientlog.flush(force=True)

    # --- the car --------------------------------------------------------------------------------
    def safe_stop(self, why):
        """Stop the car (throttle 0, wheels straight, brake lamp); never raises."""
        if self.car is None:
            return True
        try:
            with self.drive_lock:
                self.car.stop_outputs(STOP_LAMPS)
            return True
        except CarFault:
            return True  # the board was closed after stopping the car by another path
        except Exception as exc:
            _log(logging.ERROR, "could not stop the car (%s): %s", why, exc)
            return False

    def feed(self):
        self.last_feed = time.monotonic()
        self.tripped = False
        self._kick.set()

    def status(self):
        bits = 0
        if self.tripped:
            bits |= STATUS_WATCHDOG
        if self.controller is not None:
            bits |= STATUS_CONTROLLED
        return bits

    def controller_stale(self, ctl, now):
        """The controller lost its claim: the watchdog stopped the car and it sent nothing for
        ``controller_timeout`` s (the next control hello takes over)."""
        return self.tripped and now - ctl.last_rx >= self.controller_timeout

    def _watchdog_loop(self):
        """Its own thread: waits for the watchdog's deadline itself, trips it, reloads the board's
        watchdog. The only lock it takes is the drive lock, held for one HIL call at a time."""
        while not self._watchdog_off.is_set():
            now = time.monotonic()
            wait = 0.005  # the board's watchdog is reloaded every watchdog/5 s at most; 5 ms is plenty
            if self.controller is not None and not self.tripped:
                wait = min(wait, max(0.0, self.last_feed + self.watchdog - now))
            self._kick.wait(wait)
            self._kick.clear()
            try:
                self._watchdog_tick()
            except Exception as exc:  # never let the watchdog die
                _log(logging.ERROR, "watchdog: %s: %s", type(exc).__name__, exc)

    def _watchdog_tick(self):
        if not self.car.kick():
            with self.drive_lock:
                self._trip(self.controller, "the board's own watchdog expired (this server stalled for more than "
                                            "{:g} s): the board stopped the motor".format(self.watchdog))
        ctl = self.controller
        if ctl is None or self.tripped:
            return
        silent = time.monotonic() - self.last_feed
        if silent > self.watchdog:
            with self.drive_lock:  # re-check under the lock: a command may have just arrived
                silent = time.monotonic() - self.last_feed
                if self.controller is ctl and not self.tripped and silent > self.watchdog:
                    self._trip(ctl, "no command from {} for {:g} s (stopped {:.1f} ms after the last)".format(
                        ctl.peer, self.watchdog, silent * 1e3))

    def _trip(self, ctl, why):
        """With the drive lock held: stop the car with hazard lamps, set status bit 0."""
        try:
            self.car.stop_outputs(WATCHDOG_LAMPS)
        except CarFault:
            pass  # stopped through another path, board closed, logged
        except Exception as exc:
            _log(logging.ERROR, "watchdog could not stop the car: %s", exc)
        if ctl is not None:
            self.tripped = True
            self.trips += 1
        _log(logging.WARNING, "watchdog: %s; car stopped (throttle 0, hazard lamps)", why)

    def claim_control(self, session):
        """Make ``session`` the controller; None, or the refusal's message (``busy``). A controller
        that is leaving is waited for (1 s at most); a stale one is taken over (``control_lost``)."""
        wait_until = time.monotonic() + 1.0
        revoke = None
        with self.control_free:
            while True:
                holder = self.controller
                now = time.monotonic()
                if holder is None or holder is session:
                    break
                if self.controller_stale(holder, now):
                    revoke = holder
                    break
                if (holder.ending or holder.peer_gone()) and now < wait_until and not self.stopping:
                    self.control_free.wait(min(0.05, wait_until - now))  # it is leaving: wait for it to be gone
                    continue
                return ("the car is controlled by {} (last heard {:.2g} s ago; control passes on once the watchdog "
                        "has stopped the car and it has been silent for {:g} s); connect as a monitor to watch".format(
                            holder.peer, now - holder.last_rx, self.controller_timeout))
            self.controller = session
            self.feed()
            if revoke is not None:
                self.takeovers += 1
        if revoke is not None:
            quiet = time.monotonic() - revoke.last_rx
            revoke.revoke("control passed to {}: nothing was heard from this connection for {:.2g} s after the "
                          "watchdog stopped the car".format(session.peer, quiet))
            _log(logging.WARNING, "%s (control) was silent for %.2g s after the watchdog stopped the car; control "
                 "passed to %s", revoke.peer, quiet, session.peer)
        return None

    def release(self, session):
        """``session`` leaves: True if it was the controller (the car is then stopped)."""
        with self.state_lock:
            self.sessions.discard(session)
            self.monitors.discard(session)
        if self.admission is not None:
            self.admission.done(session)
        with self.drive_lock:
            was = self.controller is session
        if not was:
            return None
        ok = self.safe_stop("{} left".format(session.peer))
        with self.control_free:
            if self.controller is session:
                self.controller = None
                self.tripped = False
            self.control_free.notify_all()
        return ok

    # --- connections ----------------------------------------------------------------------------
    def _accept_loop(self):
        self.admission.run(lambda: self.stopping, self._periodic)

    def _periodic(self, now):
        """Every quarter second, on the accepting thread: clients that leave their replies unread
        for ``send_timeout`` s are dropped (a controller's car is stopped); the log's counts."""
        with self.state_lock:
            clients = [s for s in self.sessions if s.role is not None and not s.stalled]
        for s in clients:
            if s.progress.stalled(s.sock, now):
                s.cut("not reading its replies: none of them taken for {:g} s".format(self.send_timeout))
        self.clientlog.flush(now)

    @property
    def evicted(self):
        return 0 if self.admission is None else self.admission.evicted + self.admission.dropped

    def _start_session(self, sock, addr, deadline):
        """A connection whose first bytes came (Admission): its own thread reads the hello by ``deadline``."""
        sock.setblocking(True)
        peer = _peer_name(addr)
        host = str(addr[0]) if isinstance(addr, tuple) else peer
        session = _Session(self, sock, peer, host)
        session.hello_deadline = deadline
        with self.state_lock:
            self.sessions.add(session)
        t = threading.Thread(target=session.run, name="qcarlab-client-" + peer)
        t.daemon = True
        session.thread = t
        try:
            t.start()
        except RuntimeError:
            with self.state_lock:
                self.sessions.discard(session)
            raise
        return session


class _Session(object):
    """One client connection, served by its own thread."""

    def __init__(self, server, sock, peer, host):
        self.server = server
        self.car = server.car
        self.sock = sock
        self.peer = peer
        self.host = host
        self.role = None
        self.client = "?"
        self.rx_seq = 0
        self.tx_seq = 0
        self.errors = 0
        self.thread = None
        self.buf = bytearray()
        self.first_byte_t = None
        self.accepted = time.monotonic()
        self.hello_deadline = self.accepted + server.hello_timeout  # set by the server from the accept
        self.last_rx = self.accepted
        self.send_lock = threading.Lock()
        self.revoked = None
        self.evicted = False
        self.stalled = None  # why another thread ended this connection (not reading its replies)
        self.progress = ProgressWatch(server.send_timeout)
        self.ending = False
        self.bye_ref = None
        self.refusal = None  # (code, detail) when this connection never became a client
        self.next_frame = {}  # a monitor's next sensor slots: reply type -> monotonic time
        self.tokens = MONITOR_BURST  # a monitor's request budget (token bucket)
        self.tokens_at = self.accepted

    # --- sending --------------------------------------------------------------------------------
    def send(self, mtype, ref, *parts):
        with self.send_lock:
            self.tx_seq += 1
            self.sock.settimeout(self.server.send_timeout)
            send_frame(self.sock, mtype, self.tx_seq, ref, list(parts))

    def error(self, code, message, ref):
        try:
            self.send(ERROR, ref, error_payload(code, message))
        except OSError:
            pass
        if code in FATAL_CODES or code in ("unsupported", "not_lockstep"):
            return
        self.errors += 1
        if self.errors <= 5:
            self.say(logging.WARNING, "%s (%s): %s: %s", self.peer, self.role or "no hello", code, _one_line(message))
            if self.errors == 5:
                self.say(logging.WARNING, "%s: further errors from this client are counted, not logged", self.peer)

    def fatal(self, code, message, ref=0, extra=None):
        body = {"code": code, "message": message, "fatal": True}
        body.update(extra or {})
        try:
            self.send(ERROR, ref, json.dumps(body, separators=(",", ":")).encode("utf-8"))
        except OSError:
            pass
        if self.role is None:
            self.refusal = (code, message)
        return _End("{}: {}".format(code, message))

    def say(self, level, msg, *args):
        """A log line about this client: at a bounded rate per client address (SourceLog)."""
        self.server.clientlog.line(self.host, level, msg, *args)

    def cut(self, reason):
        """End this connection from another thread (it broke a rule the server checks now and then)."""
        self.stalled = reason
        self.interrupt()

    def evict(self):
        """Admission dropped this connection (still in its hello) to make room for another."""
        self.evicted = True
        self.interrupt()

    def interrupt(self):
        try:
            self.sock.shutdown(socket.SHUT_RD)
        except OSError:
            pass

    def revoke(self, why):
        """Another client took control from this stale one: tell it and end the connection."""
        self.revoked = why
        self.interrupt()

    def peer_gone(self):
        """The client has closed its end (seen without reading: this thread may be about to)."""
        if not _POLL_GONE:
            return False
        try:
            poller = select.poll()
            poller.register(self.sock.fileno(), _POLL_GONE)
            return bool(poller.poll(0))
        except (OSError, ValueError):
            return True

    # --- the connection's life -------------------------------------------------------------------
    def run(self):
        reason = "closed"
        try:
            reason = self._loop()
        except _End as end:
            reason = end.reason
            if end.bye:
                try:
                    self.send(BYE, 0, json.dumps({"reason": end.reason}).encode("utf-8"))
                except OSError:
                    pass
        except socket.timeout:
            reason = "not reading its replies: one could not be sent within {:g} s".format(self.server.send_timeout)
        except OSError as exc:
            reason = "connection error: {}".format(exc.strerror or exc)
        except Exception as exc:  # never let one client take the server down
            reason = "internal error: {}: {}".format(type(exc).__name__, exc)
        finally:
            self.ending = True
            self._finish(reason)

    def _finish(self, reason):
        server = self.server
        was_controller = server.release(self)
        stopped = ""
        if was_controller is not None:
            stopped = "; car stopped" if was_controller else "; STOPPING THE CAR FAILED"
        if self.errors > 5:
            reason += "; {} error frames in all".format(self.errors)
        if self.bye_ref is not None:
            try:
                self.send(BYE, self.bye_ref)
            except OSError:
                pass
        _quietly(self.sock.close)
        if self.role is None:
            code, detail = self.refusal or ("no_hello", _one_line(reason, 120))
            server.refusals.refused(code, self.peer, _one_line(detail, 160))
            return
        line = "%s (%s) disconnected: %s%s"
        args = (self.peer, self.role, _one_line(reason), stopped)
        level = logging.INFO
        if reason.startswith(("internal", "connection error", "not reading", "control_lost")) or "FAILED" in stopped:
            level = logging.WARNING
        self.say(level, line, *args)

    def _recv_more(self, deadline):
        """Receive more bytes (False at end of stream, None at the deadline); ``deadline`` or None."""
        while True:
            if self.revoked:
                raise self.fatal("control_lost", self.revoked)
            if self.server.stopping:
                raise _End("server stopping", bye=self.role is not None)
            if self.stalled:
                raise _End(self.stalled)
            if self.evicted:
                raise self.fatal("too_many_clients", "more than {} connections were reading their hello at once; this "
                                 "one, the oldest of the busiest address, was dropped to make room".format(
                                     self.server.max_pending))
            wait = 0.25
            if deadline is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                wait = min(wait, left)
            self.sock.settimeout(wait)
            try:
                data = self.sock.recv(65536)
            except socket.timeout:
                continue
            if not data:
                if self.revoked or self.server.stopping or self.evicted or self.stalled:
                    continue  # woken by shutdown(): say why
                return False
            if not self.buf:
                self.first_byte_t = time.monotonic()
            self.buf += data
            return True

    def _read_frame(self):
        """The next frame (type, seq, ref, payload), None at a clean end of stream."""
        server = self.server
        while True:
            buf = self.buf
            n = len(buf)
            if n >= 2 and bytes(buf[:2]) != MAGIC:
                if self.rx_seq == 0 and looks_like_http(buf):
                    self.refusal = ("http", "spoke HTTP; answered 400")
                    raise _End(self._http())
                raise self.fatal("bad_magic", "not a qcarlab frame (bad magic)")
            if n >= HEADER_SIZE:
                _, version, mtype, seq, ref, length = HEADER.unpack_from(buf, 0)
                if version != PROTOCOL:
                    raise self.fatal("bad_version", "protocol version {} is not supported (this side speaks version {})".format(
                        version, PROTOCOL), seq)
                if length > MAX_REQUEST:
                    raise self.fatal("oversized", "payload of {} bytes exceeds the limit of {}".format(length, MAX_REQUEST), seq)
                total = HEADER_SIZE + length
                if n >= total:
                    payload = bytes(buf[HEADER_SIZE:total])
                    del buf[:total]
                    self.first_byte_t = time.monotonic() if buf else None
                    self.last_rx = time.monotonic()
                    return mtype, seq, ref, payload
            if self.role is None:
                deadline = self.hello_deadline
            elif buf:
                deadline = self.first_byte_t + server.frame_timeout
            else:
                deadline = None
            got = self._recv_more(deadline)
            if got is None:  # a deadline passed
                if self.role is None:
                    if looks_like_http(self.buf):
                        self.refusal = ("http", "spoke HTTP; answered 400")
                        raise _End(self._http())
                    what = "no hello" if not self.buf else "the hello was not complete"
                    raise self.fatal("timeout", "{} within {:g} s".format(what, server.hello_timeout))
                raise self.fatal("timeout", "incomplete frame: its bytes must arrive within {:g} s of the first".format(
                    server.frame_timeout))
            if got is False:
                if self.buf:
                    raise _End("closed in the middle of a frame")
                return None

    def _http(self):
        try:
            self.sock.settimeout(1.0)
            self.sock.sendall(HTTP_REPLY)
        except OSError:
            pass
        return "spoke HTTP; answered 400 and closed"

    def _loop(self):
        while True:
            frame = self._read_frame()
            if self.stalled:
                return self.stalled
            if frame is None:
                return "closed by the client"
            mtype, seq, ref, payload = frame
            expected = self.rx_seq + 1
            if seq != expected:
                raise self.fatal("sequence", "frame seq {} out of order (expected {})".format(seq, expected), seq)
            self.rx_seq = seq
            if self.role is None:
                self._hello(mtype, seq, payload)
                continue
            if mtype == BYE:
                self.bye_ref = seq
                return "said bye"
            if self.role == "monitor":
                self._throttle()
            self._dispatch(mtype, seq, payload)

    def _throttle(self):
        """A monitor's requests are served at most MONITOR_REQUESTS_PER_S, in bursts of MONITOR_BURST:
        one over the budget waits for it (a slower reply, never an error), so no monitor can take the
        car computer's CPU from the controller and the watchdog."""
        now = time.monotonic()
        self.tokens = min(MONITOR_BURST, self.tokens + (now - self.tokens_at) * MONITOR_REQUESTS_PER_S)
        self.tokens_at = now
        if self.tokens < 1.0:
            self.server._stop_evt.wait((1.0 - self.tokens) / MONITOR_REQUESTS_PER_S)
            now = time.monotonic()
            self.tokens = min(MONITOR_BURST, self.tokens + (now - self.tokens_at) * MONITOR_REQUESTS_PER_S)
            self.tokens_at = now
        self.tokens = max(0.0, self.tokens - 1.0)

    # --- hello ----------------------------------------------------------------------------------
    def _hello(self, mtype, seq, payload):
        server = self.server
        if mtype != HELLO:
            raise self.fatal("bad_hello", "the first frame must be HELLO, got {}".format(
                MSG_NAMES.get(mtype, "0x{:02x}".format(mtype))), seq)
        try:
            msg = json.loads(payload.decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError):
            raise self.fatal("bad_hello", "hello: payload is not valid UTF-8 JSON", seq)
        if not isinstance(msg, dict):
            raise self.fatal("bad_hello", "hello: payload must be a JSON object", seq)
        proto = msg.get("protocol")
        if proto != PROTOCOL or isinstance(proto, bool):
            raise self.fatal("bad_version", "client speaks protocol {!r}; this server speaks version {}".format(
                proto, PROTOCOL), seq)
        role = msg.get("role", "control")
        if role not in ("control", "monitor"):
            raise self.fatal("bad_hello", "role must be 'control' or 'monitor', got {!r}".format(role), seq)
        client = msg.get("client")
        if isinstance(client, str):
            self.client = "".join(ch if ch.isprintable() else "?" for ch in client[:64])
        if server.token is not None:
            wait, everyone = server.tokens.admit(self.host)
            if wait > 0:
                whose = "from addresses without a right token lately" if everyone else "from " + self.host
                raise self.fatal("bad_token", "too many wrong tokens {}; try again in {:.1f} s".format(
                    whose, wait), seq, {"retry_after_s": round(wait, 3)})
            if not token_matches(msg.get("token"), server.token):
                wait = server.tokens.failed(self.host)
                raise self.fatal("bad_token", "wrong or missing token", seq,
                                 {"retry_after_s": round(wait, 3)} if wait > 0 else None)
            server.tokens.succeeded(self.host)
        with server.state_lock:
            if self.evicted or server.stopping:
                raise self.fatal("too_many_clients", "the server is busy with other connections; try again", seq)
            full = role == "monitor" and len(server.monitors) >= server.max_clients - 1
            if not full:
                if role == "monitor":
                    server.monitors.add(self)
        server.admission.done(self)  # said hello: no longer one of the connections before theirs
        if full:
            raise self.fatal("too_many_clients", "the server already has {} monitors (one more slot is kept for a "
                             "controller); try again later".format(server.max_clients - 1), seq)
        if role == "control":
            refusal = server.claim_control(self)
            if refusal is not None:
                raise self.fatal("busy", refusal, seq)
        self.role = role
        self.say(logging.INFO, "%s connected as %s (%s)", self.peer, role, self.client)
        self.send(WELCOME, seq, json.dumps(server.welcome(role), separators=(",", ":")).encode("utf-8"))

    # --- requests -------------------------------------------------------------------------------
    def _dispatch(self, mtype, seq, payload):
        server = self.server
        name = MSG_NAMES.get(mtype, "0x{:02x}".format(mtype))
        handler = {COMMAND: self._command, STOP: self._stop, READ: self._read, GET_TRUTH: self._truth,
                   GET_TIME: self._time, ADVANCE: self._advance, GET_LIDAR: self._sensor,
                   GET_RGBD: self._sensor, GET_CSI: self._sensor, PING: self._ping}.get(mtype)
        if handler is None:
            if mtype == HELLO:
                self.error("bad_payload", "HELLO was already received on this connection", seq)
            else:
                self.error("unknown_type", "unknown or unexpected message type {}".format(name), seq)
            return
        if mtype in (COMMAND, STOP, ADVANCE) and server.controller is not self:
            self.error("read_only", "{} needs the control role; this connection is a monitor".format(name), seq)
            return
        try:
            handler(mtype, seq, payload)
        except ProtocolError as exc:
            if mtype == COMMAND:
                server.safe_stop("bad command")
            self.error(exc.code, exc.message, seq)
        except CarError as exc:
            if mtype == COMMAND:
                server.safe_stop("command failed")
            self.error("car_error", str(exc), seq)
        except OSError:
            raise
        except Exception as exc:
            if mtype == COMMAND:
                server.safe_stop("command failed")
            self.error("car_error", "{}: {}".format(type(exc).__name__, exc), seq)

    def _empty(self, mtype, payload):
        if payload:
            raise ProtocolError("bad_payload", "{} takes no payload, got {} bytes".format(MSG_NAMES[mtype], len(payload)))

    def _command(self, mtype, seq, payload):
        server = self.server
        if len(payload) != COMMAND_ST.size:
            raise ProtocolError("bad_payload", "command: payload must be {} bytes, got {}".format(COMMAND_ST.size, len(payload)))
        values = COMMAND_ST.unpack(payload)
        throttle, steering, leds, flags = values[0], values[1], values[2:14], values[14]
        if not math.isfinite(throttle):
            raise ProtocolError("bad_value", "throttle must be a finite number, got {!r}".format(throttle))
        if not math.isfinite(steering):
            raise ProtocolError("bad_value", "steering must be a finite number, got {!r}".format(steering))
        for i, v in enumerate(leds):
            if not (math.isfinite(v) and 0.0 <= v <= 1.0):
                raise ProtocolError("bad_value", "lamp {} ({}) must be in [0, 1], got {!r}".format(i, LAMP_NAMES[i], v))
        if flags & ~FLAG_READ_BACK:
            raise ProtocolError("bad_value", "command flags 0x{:x}: only bit 0 is defined; the others must be 0".format(flags))
        throttle = max(-server.throttle_limit, min(server.throttle_limit, throttle))
        steering = max(-server.steering_limit, min(server.steering_limit, steering))
        leds = _clean_lamps(leds)
        with server.drive_lock:
            controller = server.controller is self
            if controller:
                server.feed()
                self.car.write(throttle, steering, leds)
        if not controller:  # taken over a moment ago: not this car's command any more
            self.error("read_only", "this connection lost the control role", seq)
            return
        if flags & FLAG_READ_BACK:
            self.send(READOUT, seq, self._pack_readout(self.car.read(), (throttle, steering, leds)))
        else:
            self.send(APPLIED, seq, APPLIED_ST.pack(throttle, steering, *leds))

    def _pack_readout(self, r, cmd=None):
        throttle, steering, leds = self.car.applied if cmd is None else cmd
        return READOUT_ST.pack(r.t, int(r.encoder), r.tach, r.current, r.battery, r.gyro[0], r.gyro[1], r.gyro[2],
                               r.accel[0], r.accel[1], r.accel[2], steering, throttle, *(tuple(leds) + (self.server.status(),)))

    def _stop(self, mtype, seq, payload):
        server = self.server
        self._empty(mtype, payload)
        if self.car.fault:
            self.car.reopen()  # raises CarFault (car_error) when the board will not open
        with server.drive_lock:
            controller = server.controller is self
            if controller:
                server.feed()
                self.car.stop_outputs(STOP_LAMPS)
        if not controller:
            self.error("read_only", "this connection lost the control role", seq)
            return
        self.send(OK, seq)

    def _read(self, mtype, seq, payload):
        self._empty(mtype, payload)
        self.send(READOUT, seq, self._pack_readout(self.car.read()))

    def _truth(self, mtype, seq, payload):
        self._empty(mtype, payload)
        self.error("unsupported", "this car has no ground truth (only simulated cars do)", seq)

    def _time(self, mtype, seq, payload):
        self._empty(mtype, payload)
        self.send(TIME, seq, SCALAR_ST.pack(self.car.time))

    def _advance(self, mtype, seq, payload):
        if len(payload) != SCALAR_ST.size:
            raise ProtocolError("bad_payload", "advance: payload must be 8 bytes, got {}".format(len(payload)))
        self.error("not_lockstep", "ADVANCE needs a lock-step server (qcarlab serve --lockstep); time runs by "
                   "itself on a real car", seq)

    def _sensor(self, mtype, seq, payload):
        """A sensor frame. Monitors are paced to ``monitor_rate`` frames/s per sensor (a request
        early for its slot waits, then gets the newest frame; frames in between are dropped, never
        queued); a frame younger than 1/rate is resent rather than a new one read. The controller
        is never paced and always gets a fresh reading."""
        server = self.server
        self._empty(mtype, payload)
        reply, cap, method = {GET_LIDAR: (LIDAR, "lidar", "read_lidar"), GET_RGBD: (RGBD, "rgbd", "read_rgbd"),
                              GET_CSI: (CSI, "csi", "read_csi")}[mtype]
        if cap not in self.car.capabilities:
            why = getattr(self.car, "missing", {}).get(cap, "not fitted")
            self.error("unsupported", "this car has no {} sensor ({})".format(cap, why), seq)
            return
        period = 1.0 / server.monitor_rate
        controller = server.controller is self
        if not controller:
            slot = self.next_frame.get(reply, 0.0)
            delay = slot - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            self.next_frame[reply] = max(slot, time.monotonic() - period) + period
        with server.sensor_locks[reply]:  # one reader per sensor; never the drive lock
            cached = server.sensor_cache.get(reply)
            if not controller and cached is not None and time.monotonic() - cached[0] < period:
                parts = cached[1]
            else:
                t, arrays = getattr(self.car, method)()
                parts = pack_arrays(t, arrays)
                server.sensor_cache[reply] = (time.monotonic(), parts)
        self.send(reply, seq, *parts)

    def _ping(self, mtype, seq, payload):
        if len(payload) > MAX_PING:
            raise ProtocolError("bad_payload", "ping payload is at most {} bytes, got {}".format(MAX_PING, len(payload)))
        self.send(PONG, seq, payload)


# =================================================================================================
# Command line
# =================================================================================================
class _Parser(argparse.ArgumentParser):
    def error(self, message):
        sys.stderr.write("qcarlab car server: error: {} (see --help)\n".format(message))
        sys.exit(2)


def build_parser():
    p = _Parser(prog=os.path.basename(sys.argv[0]) or "qcarlab_car_server.py",
                description="Serve a Quanser QCar 1 or QCar 2 over the qcarlab protocol v1 (docs/protocol.md).")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: every interface; needs a token)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="TCP port (0 picks a free one)")
    p.add_argument("--car-type", default="auto", choices=["auto", "1", "2"],
                   help="auto: try the QCar 1 board ('qcar'), then the QCar 2's ('qcar2')")
    p.add_argument("--dry-run", action="store_true", help="open no hardware: serve a stationary car to check the link")
    p.add_argument("--token-file", help="file holding the shared token (preferred: other users can read a command line)")
    p.add_argument("--token", help="the shared token (or set QCARLAB_TOKEN); 16+ characters")
    p.add_argument("--new-token", action="store_true", help="print a fresh random token and exit")
    p.add_argument("--watchdog", type=float, default=0.25, help="stop the car after this many s without a command")
    p.add_argument("--controller-timeout", type=float, default=None,
                   help="a controller silent this long after the watchdog stopped the car loses control (default 4 x watchdog)")
    p.add_argument("--throttle-limit", type=float, default=0.3, help="largest |throttle| (duty fraction) applied")
    p.add_argument("--max-clients", type=int, default=24, help="connections after hello (one slot kept for a controller)")
    p.add_argument("--monitor-rate", type=float, default=10.0, help="sensor frames per second per monitor and sensor")
    p.add_argument("--no-lidar", action="store_true", help="do not open the LIDAR")
    p.add_argument("--no-rgbd", action="store_true", help="do not open the RealSense camera")
    p.add_argument("--no-csi", action="store_true", help="do not open the CSI cameras")
    p.add_argument("--log-file", help="also write the log here (useful when the ssh session that started it ends)")
    p.add_argument("--version", action="version", version=SERVER_VERSION)
    return p


def _token_from(args):
    if args.token_file:
        try:
            with open(os.path.expanduser(args.token_file), "r") as fh:
                text = fh.read().strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError("--token-file {}: cannot read it ({})".format(args.token_file, getattr(exc, "strerror", None) or exc))
        if not text:
            raise InputError("--token-file {}: the file is empty".format(args.token_file))
        return text
    if args.token:
        return args.token
    return os.environ.get("QCARLAB_TOKEN") or None


def main(argv=None):
    args = build_parser().parse_args(argv)
    # hand the interpreter lock over every 1 ms (not 5): the watchdog thread waits less behind
    # threads busy serving camera frames
    sys.setswitchinterval(0.001)
    if args.new_token:
        import secrets
        print(secrets.token_urlsafe(24))
        return 0
    # the log goes through a queue to its own thread: a terminal or file that blocks never holds
    # up the watchdog (which logs each stop)
    import logging.handlers
    import queue

    fmt = logging.Formatter("%(asctime)s %(levelname)s: %(message)s")
    outputs = [logging.StreamHandler(sys.stderr)]
    log_queue = queue.Queue()
    listener = logging.handlers.QueueListener(log_queue, *outputs)
    root = logging.getLogger()
    root.addHandler(logging.handlers.QueueHandler(log_queue))
    root.setLevel(logging.INFO)
    car = None
    server = None
    listening = False
    try:
        token = check_token(_token_from(args))
        if args.log_file:
            try:
                outputs.append(logging.FileHandler(os.path.expanduser(args.log_file)))
            except OSError as exc:
                raise InputError("--log-file {}: {}".format(args.log_file, exc.strerror or exc))
        for h in outputs:
            h.setFormatter(fmt)
        listener.handlers = tuple(outputs)
        listener.start()
        listening = True
        car_type = args.car_type if args.car_type == "auto" else int(args.car_type)
        # options and the port first, then the hardware
        server = CarServer(None, args.host, args.port, token=token, watchdog=args.watchdog,
                           controller_timeout=args.controller_timeout, throttle_limit=args.throttle_limit,
                           max_clients=args.max_clients, monitor_rate=args.monitor_rate).bind()
        if args.dry_run:
            car = DryRunCar(1 if car_type == "auto" else car_type)
        else:
            car = QuanserCar(car_type, throttle_limit=args.throttle_limit, watchdog=args.watchdog,
                             lidar=not args.no_lidar, rgbd=not args.no_rgbd, csi=not args.no_csi)
        server.car = car
        caught = []

        def on_signal(signum, _frame):
            caught.append(signum)
            server.request_stop()

        for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT"):
            if not hasattr(signal, name):
                continue
            if name == "SIGHUP" and signal.getsignal(signal.SIGHUP) == signal.SIG_IGN:
                continue  # started under nohup: the user asked to outlive the terminal
            signal.signal(getattr(signal, name), on_signal)
        server.start()
        missing = "; ".join("{}: {}".format(k, v) for k, v in sorted(car.missing.items()))
        _say("serving {} on {} (protocol v{}, watchdog {:g} s, throttle limit {:g}{}; board watchdog: {}){}; "
             "Ctrl-C to stop".format(car.name(), server.uri, PROTOCOL, server.watchdog, server.throttle_limit,
                                     ", token required" if token else "",
                                     "yes" if car.hardware_watchdog else "no" + (" (dry run)" if args.dry_run else ""),
                                     "; without " + missing if missing else ""))
        while not server.wait(0.5):
            pass
        why = signal.Signals(caught[0]).name if caught else "stopped"
        server.stop("server stopping ({})".format(why))
        car.close()
        car = None
        _say("stopped serving ({}); the car is stopped".format(why))
        return 0
    except InputError as exc:
        sys.stderr.write("qcarlab car server: error: {}\n".format(exc))
        return 2
    except CarError as exc:
        sys.stderr.write("qcarlab car server: error: {}\n".format(exc))
        return 1
    finally:
        if server is not None and not server.stopping:
            server.stop()
        if car is not None:
            car.close()
        if listening:
            listener.stop()


def _say(text):
    try:
        print(text, flush=True)
    except (OSError, ValueError):  # the terminal that started us is gone (ssh closed)
        pass


if __name__ == "__main__":
    sys.exit(main())
