"""The state behind the strict fake of Quanser's Python API (tests only; Python 3.6+, NumPy).

The fake models the boards as Quanser's own code drives them (pal/products/qcar.py,
pal/products/qcar_config.py, quanser.devices' RPLIDAR.read) and refuses what a real card would:
another board's name, a channel the car has not got, a buffer of the wrong size or type, a PWM
call on a QCar 2, a write after the card was closed. It is written from Quanser's code, not from
the server under test: its tables are its own.

Configuration: ``reset(car=1|2, ...)`` in-process, or environment variables for a server run
as a subprocess (``QCARLAB_FAKE_CAR``, ``QCARLAB_FAKE_WATCHDOG`` = 0/1,
``QCARLAB_FAKE_FAIL_WRITE_AFTER`` = N, ``QCARLAB_FAKE_SENSORS`` = comma list of lidar,rgbd,csi,
``QCARLAB_FAKE_LIDAR_SCRIPT`` = comma list of scan/none/block, ``QCARLAB_FAKE_JOURNAL`` = a file
that receives one JSON line per board event).
"""

import json
import math
import os
import threading
import time

# error codes: -986 and -34 are Quanser's (qcar_config.py compares str(e) with '-986'; -34 is
# -QERR_WOULD_BLOCK); the others are this fake's own
BOARD_NOT_FOUND = -986
WOULD_BLOCK = -34
INVALID_ARGUMENT = -4
INVALID_CHANNEL = -1001
INVALID_BUFFER = -1002
NOT_OPEN = -1003
NOT_SUPPORTED = -1004
OVER_CURRENT = -1005
WATCHDOG_EXPIRED = -1006
BUFFER_TOO_SMALL = -1007
SERIAL_PORT = -1008

MESSAGES = {
    BOARD_NOT_FOUND: "The specified board type was not found",
    WOULD_BLOCK: "The operation would block",
    INVALID_ARGUMENT: "Invalid argument",
    INVALID_CHANNEL: "Invalid channel for this board",
    INVALID_BUFFER: "Buffer of the wrong size or type",
    NOT_OPEN: "The card is not open",
    NOT_SUPPORTED: "This board does not support the operation",
    OVER_CURRENT: "Motor over-current: the amplifier latched off",
    WATCHDOG_EXPIRED: "The watchdog has expired",
    BUFFER_TOO_SMALL: "The buffer is too small",
    SERIAL_PORT: "Unable to open the serial port",
}

_QCAR1_URL = "serial-cpu://localhost:2?baud='115200',word='8',parity='none',stop='1',flow='none',dsr='on'"
_QCAR2_URL = "serial-cpu://localhost:1?baud='256000',word='8',parity='none',stop='1',flow='none',dsr='on'"

# what each board has (qcar_config.py / qcar.py, and the lab sheet's other channels 11000-11011)
BOARDS = {
    1: {
        "name": "qcar",
        "analog_in": {5: 1.25, 6: 11.8},  # motor current A, battery V
        "encoder_in": {0: -4242},
        "other_in": {3000: 0.01, 3001: -0.02, 3002: 0.5, 4000: 0.3, 4001: -0.1, 4002: 9.79, 14000: 1234.5},
        "pwm_out": {0},
        "other_out": {1000} | set(range(11000, 11012)),
        "digital_out": {40},
        "lidar_url": _QCAR1_URL,
        "csi_ids": {0, 1, 2, 3},
    },
    2: {
        "name": "qcar2",
        "analog_in": {4: 2.5, 2: 15.2},  # motor current A (4), battery V (2)
        "encoder_in": {0: 777},
        "other_in": {3000: -0.04, 3001: 0.03, 3002: -0.6, 4000: -0.2, 4001: 0.4, 4002: 9.81, 14000: -321.0},
        "pwm_out": set(),
        "other_out": {1000, 11000},
        "digital_out": set(range(11, 27)),
        "lidar_url": _QCAR2_URL,
        "csi_ids": {0, 1, 2, 3},
    },
}


class _State(object):
    def __init__(self):
        self.lock = threading.RLock()
        self.reset()

    def reset(self, car=None, watchdog=None, fail_write_after=None, fail_all_paths=False, sensors=None,
              lidar_script=None, camera_script=None, journal=None):
        env = os.environ
        self.car = int(car if car is not None else env.get("QCARLAB_FAKE_CAR", "1"))
        self.watchdog_supported = bool(int(watchdog if watchdog is not None else env.get("QCARLAB_FAKE_WATCHDOG", "1")))
        fwa = fail_write_after if fail_write_after is not None else env.get("QCARLAB_FAKE_FAIL_WRITE_AFTER")
        self.fail_write_after = None if fwa in (None, "") else int(fwa)
        self.fail_all_paths = fail_all_paths or env.get("QCARLAB_FAKE_FAIL_ALL_PATHS") == "1"
        if sensors is None:
            sensors = env.get("QCARLAB_FAKE_SENSORS", "lidar,rgbd,csi").split(",")
        self.sensors = set(s.strip() for s in sensors if s.strip())
        if lidar_script is None:
            lidar_script = env.get("QCARLAB_FAKE_LIDAR_SCRIPT", "block,scan,none,scan").split(",")
        self.lidar_script = list(lidar_script)
        self.camera_script = list(camera_script) if camera_script is not None else [True]
        self.journal_path = journal if journal is not None else env.get("QCARLAB_FAKE_JOURNAL")
        self.events = []
        self.writes = 0  # card.write calls that reached the outputs
        self.latched = False  # over-current latch: cleared by closing every handle and reopening
        self.outputs = {}  # ("pwm"|"other"|"digital", channel) -> value: what the amplifier and lamps see
        self.open_handles = 0
        self.watchdog = None  # {"timeout", "last", "states": {key: value}, "expired"}
        self.lidar_reads = 0
        self.camera_reads = 0

    @property
    def board(self):
        return BOARDS[self.car]

    def event(self, what, **data):
        data["event"] = what
        data["t"] = time.time()
        with self.lock:
            self.events.append(data)
            if self.journal_path:
                with open(self.journal_path, "a") as fh:
                    fh.write(json.dumps(data, default=_plain) + "\n")

    def expire_watchdog_if_due(self):
        """The board's watchdog: once expired it sets the expiration states and refuses writes."""
        with self.lock:
            wd = self.watchdog
            if wd is None or wd["expired"]:
                return
            if time.monotonic() - wd["last"] > wd["timeout"]:
                wd["expired"] = True
                for key, value in wd["states"].items():
                    self.outputs[key] = value
                self.event("watchdog_expired", outputs=dict((str(k), v) for k, v in self.outputs.items()))


def _plain(obj):
    try:
        return obj.tolist()
    except AttributeError:
        return str(obj)


STATE = _State()


def reset(**kwargs):
    STATE.reset(**kwargs)
    return STATE


def lidar_scan():
    """One turn as an RPLidar reports it: clockwise headings from the device's zero mark (rad,
    ascending), distances (m) and qualities. Returns at the device's 0, 90, 180 and 270 degree
    marks at 1, 2, 3 and 4 m, and one beam at 45 degrees without a return (quality 0)."""
    headings = [0.0, math.pi / 4.0, math.pi / 2.0, math.pi, 3.0 * math.pi / 2.0]
    distances = [1.0, 0.0, 2.0, 3.0, 4.0]
    qualities = [47, 0, 47, 47, 47]
    return headings, distances, qualities
