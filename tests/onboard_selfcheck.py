"""The car-side server's own checks, runnable on the car's Pythons (3.6, 3.8) without pytest:

    python3.6 tests/onboard_selfcheck.py [path/to/car_server.py]

Drives the server's hardware driver against the strict fake of Quanser's API for both cars
(channels, signs, start-up, LIDAR angles at the device's marks, faults, the board's watchdog),
then serves a fake QCar 2 over TCP and speaks the protocol to it with a raw client. Prints one
line per check; exit 0 when all pass. tests/test_onboard_compat.py runs it under 3.6 and 3.8.
"""

import json
import math
import os
import socket
import struct
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "fake_quanser"))
SERVER_PATH = sys.argv[1] if len(sys.argv) > 1 else os.path.join(HERE, "..", "qcarlab", "onboard", "car_server.py")

import importlib.util  # noqa: E402

spec = importlib.util.spec_from_file_location("car_server", SERVER_PATH)
cs = importlib.util.module_from_spec(spec)
spec.loader.exec_module(cs)

import numpy as np  # noqa: E402
from quanser import _fake  # noqa: E402

CHECKS = []


def check(fn):
    CHECKS.append(fn)
    return fn


def approx(a, b, tol=1e-9):
    return abs(a - b) <= tol


@check
def channel_tables_and_signs():
    for car in (1, 2):
        st = _fake.reset(car=car, sensors=[], journal="")
        qcar = cs.QuanserCar("auto")
        assert qcar.car_type == car, qcar.car_type
        qcar.write(0.2, 0.3, cs.STOP_LAMPS)
        out = st.outputs
        if car == 1:
            assert out[("pwm", 0)] == -0.2 and approx(out[("other", 1000)], -0.3) and out[("other", 11000)] == 1.0
        else:
            assert out[("other", 11000)] == 0.2 and approx(out[("other", 1000)], 0.3)
            assert [out[("digital", c)] for c in (11, 12, 13, 14)] == [1.0] * 4
        r = qcar.read()
        assert (r.current, r.battery) == ((1.25, 11.8) if car == 1 else (2.5, 15.2))
        qcar.close()
        assert st.open_handles == 0


@check
def start_up_like_quanser():
    st = _fake.reset(car=1, sensors=[], journal="")
    cs.QuanserCar(1).close()
    kinds = [e["event"] for e in st.events]
    assert kinds[:9] == ["open", "pwm_mode", "pwm_frequency", "write_digital", "options", "quadrature",
                         "encoder_filter", "encoder_counts", "write"], kinds[:9]


@check
def lidar_marks_in_the_body_frame():
    for car, want in ((1, {90: 1.0, 0: 2.0, 270: 3.0, 180: 4.0}), (2, {180: 1.0, 90: 2.0, 0: 3.0, 270: 4.0})):
        _fake.reset(car=car, sensors=["lidar"], lidar_script=["scan"], journal="")
        qcar = cs.QuanserCar(car)
        t, angles, ranges = qcar.lidar_arrays()
        qcar.close()
        got = dict((int(round(math.degrees(a))), float(r)) for a, r in zip(angles, ranges) if r > 0)
        assert got == want, (car, got)


@check
def a_failed_write_escalates():
    st = _fake.reset(car=2, sensors=[], fail_write_after=2, journal="")
    qcar = cs.QuanserCar(2)
    qcar.write(0.1, 0.0, cs.ALL_OFF)
    try:
        qcar.write(0.1, 0.0, cs.ALL_OFF)
        raise AssertionError("the failing write was not reported")
    except cs.CarFault:
        pass
    assert st.outputs[("other", 11000)] == 0.0 and st.open_handles == 0
    qcar.reopen()
    qcar.write(0.1, 0.0, cs.ALL_OFF)
    assert st.outputs[("other", 11000)] == 0.1
    qcar.close()


@check
def the_boards_watchdog():
    st = _fake.reset(car=1, sensors=[], journal="")
    qcar = cs.QuanserCar(1, watchdog=0.05)
    assert qcar.hardware_watchdog
    qcar.write(0.2, 0.0, cs.ALL_OFF)
    time.sleep(0.12)
    st.expire_watchdog_if_due()
    assert st.outputs[("pwm", 0)] == 0.0
    assert qcar.kick() is False
    qcar.close()


class Raw(object):
    def __init__(self, port):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=3)
        self.seq = 0

    def request(self, mtype, payload=b""):
        self.seq += 1
        self.sock.sendall(cs.HEADER.pack(cs.MAGIC, 1, mtype, self.seq, 0, len(payload)) + payload)
        head = self._recv(16)
        _, version, rtype, seq, ref, length = cs.HEADER.unpack(head)
        return rtype, ref, self._recv(length)

    def _recv(self, n):
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            assert chunk, "closed"
            data += chunk
        return data


@check
def serving_a_fake_qcar2_over_tcp():
    st = _fake.reset(car=2, sensors=["lidar"], lidar_script=["scan"], journal="")
    car = cs.QuanserCar("auto", watchdog=0.25)
    server = cs.CarServer(car, "127.0.0.1", 0, watchdog=0.25).start()
    try:
        raw = Raw(server.bound[1])
        rtype, ref, body = raw.request(cs.HELLO, json.dumps({"protocol": 1, "role": "control"}).encode())
        welcome = json.loads(body.decode())
        assert rtype == cs.WELCOME and welcome["identity"]["extra"]["car_type"] == 2
        assert welcome["params"]["motor_kt"] == 0.0047 and welcome["steering_limit"] == 0.5
        rtype, ref, body = raw.request(cs.COMMAND, cs.COMMAND_ST.pack(0.9, -2.0, *([0.0] * 12 + [0])))
        thr, ste = struct.unpack_from("<2d", body)
        assert rtype == cs.APPLIED and (thr, ste) == (0.3, -0.5) and st.outputs[("other", 11000)] == 0.3
        rtype, ref, body = raw.request(cs.READ)
        assert rtype == cs.READOUT and len(body) == 204 and struct.unpack_from("<d", body, 32)[0] == 15.2
        rtype, ref, body = raw.request(cs.GET_LIDAR)
        assert rtype == cs.LIDAR and struct.unpack_from("<I", body, 8)[0] == 2
        time.sleep(0.6)  # silent: the watchdog stops the car with hazard lamps
        assert st.outputs[("other", 11000)] == 0.0
        assert [st.outputs[("digital", c)] for c in (17, 18, 25, 26)] == [1.0] * 4
        raw.sock.close()
    finally:
        server.stop()
        car.close()


def main():
    failed = 0
    for fn in CHECKS:
        try:
            fn()
            print("ok   " + fn.__name__)
        except Exception as exc:  # report every check, then fail
            failed += 1
            print("FAIL {}: {}: {}".format(fn.__name__, type(exc).__name__, exc))
    print("selfcheck on Python {}: {} of {} checks passed".format(
        ".".join(map(str, sys.version_info[:3])), len(CHECKS) - failed, len(CHECKS)))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
