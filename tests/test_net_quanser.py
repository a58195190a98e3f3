"""The on-car driver against a fake of Quanser's Python API (quanser.hardware / devices / multimedia)
injected through sys.modules: signs, channels, LIDAR angles, optional sensors, serving it."""

from __future__ import annotations

import math
import sys
import time
import types

import numpy as np
import pytest

from qcarlab.car.lamps import HIL_CHANNELS
from qcarlab.car.tcp import TcpCar
from qcarlab.errors import CarError, NotBuiltError
from qcarlab.net.server import CarServer


def cli_error_lines(err: str) -> int:
    """Lines the CLI itself printed (an in-process test server may log lines of its own)."""
    return len([line for line in err.splitlines() if not line.startswith(("info:", "warning:"))])


class HILError(Exception):
    def get_error_message(self):
        return f"-{self.args[0]}: board error"


class FakeHIL:
    last: FakeHIL | None = None

    def __init__(self):
        FakeHIL.last = self
        self.opened = None
        self.options = ""
        self.closed = False
        self.writes: list[dict] = []
        self.fail_open = False
        self.analog = [1.25, 11.8]  # analog 5 (current), analog 6 (battery)
        self.encoder = [-4242]
        self.other = [0.01, -0.02, 0.5, 0.3, -0.1, 9.79, 1234.5]  # gyro xyz, accel xyz, tach

    def open(self, card_type, card_id):
        if FAIL_OPEN:
            raise HILError(1077)
        self.opened = (card_type, card_id)

    def set_card_specific_options(self, options, max_length):
        self.options = options

    def set_pwm_mode(self, channels, n, modes):
        pass

    def set_pwm_frequency(self, channels, n, freqs):
        pass

    def set_encoder_quadrature_mode(self, channels, n, modes):
        pass

    def set_encoder_counts(self, channels, n, counts):
        pass

    def write(self, a_ch, n_a, pwm_ch, n_p, d_ch, n_d, o_ch, n_o, a_buf, pwm_buf, d_buf, o_buf):
        assert a_ch is None and d_ch is None and n_p == len(pwm_ch) and n_o == len(o_ch)
        self.writes.append({"pwm": dict(zip(map(int, pwm_ch), map(float, pwm_buf))),
                            "other": dict(zip(map(int, o_ch), map(float, o_buf)))})

    def read(self, a_ch, n_a, e_ch, n_e, d_ch, n_d, o_ch, n_o, a_buf, e_buf, d_buf, o_buf):
        assert list(a_ch) == [5, 6] and list(e_ch) == [0] and list(o_ch) == [3000, 3001, 3002, 4000, 4001, 4002, 14000]
        a_buf[:] = self.analog
        e_buf[:] = self.encoder
        o_buf[:] = self.other

    def close(self):
        self.closed = True


FAIL_OPEN = False
HEADINGS = np.array([0.0, math.pi / 2, math.pi, 3 * math.pi / 2])  # clockwise, from the device's zero
DISTANCES = np.array([1.0, 2.0, 3.0, 4.0])


class RangingMeasurements:
    def __init__(self, n):
        self.heading = np.zeros(n)
        self.distance = np.zeros(n)


class RPLIDAR:
    delay = 0.0  # s a read takes (the device waits for a full turn)

    def open(self, url, mode):
        self.url = url

    def read(self, mode, max_distance, max_angle, measurements):
        if RPLIDAR.delay:
            time.sleep(RPLIDAR.delay)
        n = HEADINGS.size
        measurements.heading[:n] = HEADINGS
        measurements.distance[:n] = DISTANCES
        return n

    def close(self):
        pass


class MediaError(Exception):
    pass


class FakeFrame:
    def __init__(self, kind):
        self.kind = kind

    def get_data(self, buf):
        buf[...] = 7

    def get_meters(self, buf):
        buf[...] = 1.5

    def release(self):
        pass


class FakeStream:
    def __init__(self, kind):
        self.kind = kind

    def get_frame(self):
        return FakeFrame(self.kind)

    def close(self):
        pass


class Video3D:
    fail = False

    def __init__(self, device):
        if Video3D.fail:
            raise MediaError("no RealSense found")

    def stream_open(self, kind, index, fps, w, h, fmt, dtype):
        assert (w, h) == (640, 480)
        return FakeStream(kind)

    def start_streaming(self):
        pass

    def stop_streaming(self):
        pass

    def close(self):
        pass


class VideoCapture:
    def __init__(self, url, fps, w, h, fmt, dtype, attributes, n_attributes):
        self.cam = int(url.rsplit(":", 1)[1])

    def start(self):
        pass

    def read(self, buf):
        buf[...] = self.cam
        return True

    def stop(self):
        pass

    def close(self):
        pass


@pytest.fixture
def fake_quanser(monkeypatch):
    global FAIL_OPEN
    FAIL_OPEN = False
    Video3D.fail = False
    RPLIDAR.delay = 0.0
    pkg = types.ModuleType("quanser")
    hw = types.ModuleType("quanser.hardware")
    hw.HIL, hw.HILError, hw.MAX_STRING_LENGTH = FakeHIL, HILError, 2048
    hw.PWMMode = types.SimpleNamespace(DUTY_CYCLE=1)
    dev = types.ModuleType("quanser.devices")
    dev.RPLIDAR, dev.RangingMeasurements = RPLIDAR, RangingMeasurements
    dev.RangingMeasurementMode = types.SimpleNamespace(NORMAL=0)
    dev.RangingDistance = types.SimpleNamespace(LONG=2)
    mm = types.ModuleType("quanser.multimedia")
    mm.Video3D, mm.VideoCapture, mm.MediaError = Video3D, VideoCapture, MediaError
    mm.Video3DStreamType = types.SimpleNamespace(COLOR=1, DEPTH=2)
    mm.ImageFormat = types.SimpleNamespace(ROW_MAJOR_INTERLEAVED_BGR=1, ROW_MAJOR_GREYSCALE=2)
    mm.ImageDataType = types.SimpleNamespace(UINT8=1, UINT16=2)
    pkg.hardware, pkg.devices, pkg.multimedia = hw, dev, mm
    for name, mod in (("quanser", pkg), ("quanser.hardware", hw), ("quanser.devices", dev), ("quanser.multimedia", mm)):
        monkeypatch.setitem(sys.modules, name, mod)
    return pkg


@pytest.fixture
def qcar(fake_quanser):
    from qcarlab.car.quanser import QuanserCar

    car = QuanserCar()
    yield car
    car.close()


def test_without_quansers_api_one_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "quanser", None)  # import quanser.* now fails
    from qcarlab.car.quanser import QuanserCar

    with pytest.raises(CarError) as exc:
        QuanserCar()
    assert "not installed" in str(exc.value) and "\n" not in str(exc.value)


def test_serve_backend_quanser_without_the_api_exits_1(cli, monkeypatch):
    monkeypatch.setitem(sys.modules, "quanser", None)
    code, out, err = cli("serve", "--backend", "quanser", "--port", "0")
    assert code == 1 and "not installed" in err and cli_error_lines(err) == 1


@pytest.mark.parametrize("args", [("--lockstep",), ("--world", "studio"), ("--backend", "carla")])
def test_serve_refuses_option_mixups(cli, args):
    base = ("serve", "--port", "0") if "--backend" in args else ("serve", "--backend", "quanser", "--port", "0")
    code, out, err = cli(*base, *args)
    assert code == 2 and cli_error_lines(err) == 1


def test_board_open_failure_is_one_line(fake_quanser):
    global FAIL_OPEN
    FAIL_OPEN = True
    from qcarlab.car.quanser import QuanserCar

    with pytest.raises(CarError, match="cannot open the QCar's HIL board .*board error"):
        QuanserCar()
    assert FakeHIL.last.closed


def test_throttle_and_steering_are_negated_at_the_board_only(qcar):
    hil = FakeHIL.last
    assert hil.opened == ("qcar", "0") and "motor_limit=0.3" in hil.options
    applied = qcar.write(0.2, 0.3, ["brake", "hazard"])
    assert (applied.throttle, applied.steering) == (0.2, 0.3)  # the user never sees the sign flip
    sent = hil.writes[-1]
    assert sent["pwm"] == {0: -0.2}
    assert sent["other"][1000] == pytest.approx(-0.3)
    on = {ch for ch, v in sent["other"].items() if ch >= 11000 and v > 0}
    assert on == {HIL_CHANNELS[n] for n in ("brake", "indicator_rear_left", "indicator_rear_right",
                                             "indicator_front_left", "indicator_front_right")}
    qcar.write(-0.9, -1.0)  # clamped first, then negated
    assert hil.writes[-1]["pwm"] == {0: 0.3} and hil.writes[-1]["other"][1000] == pytest.approx(0.5236)


def test_readout_comes_from_the_sheets_channels(qcar):
    qcar.write(0.1, -0.2, ["headlamps"])
    r = qcar.read()
    assert (r.motor_current, r.battery_voltage, r.encoder_counts, r.tach) == (1.25, 11.8, -4242, 1234.5)
    assert np.allclose(r.gyro, [0.01, -0.02, 0.5]) and np.allclose(r.accel, [0.3, -0.1, 9.79])
    assert (r.throttle, r.steering) == (0.1, -0.2) and r.leds[2] == r.leds[3] == 1.0
    assert qcar.time > 0 and not qcar.stepped


def test_lidar_clockwise_headings_become_ccw_body_angles(qcar):
    scan = qcar.read_lidar()
    # device: 0 ahead (1 m), 90 deg clockwise = right (2 m), 180 behind (3 m), 270 cw = left (4 m)
    # body frame as the simulator gives it: CCW from forward, in [0, 2 pi), ascending
    assert np.allclose(scan.angles, [0.0, math.pi / 2, math.pi, 3 * math.pi / 2])
    assert np.allclose(scan.ranges, [1.0, 4.0, 3.0, 2.0])
    right = scan.ranges[np.isclose(scan.angles, 3 * math.pi / 2)][0]
    left = scan.ranges[np.isclose(scan.angles, math.pi / 2)][0]
    assert (right, left) == (2.0, 4.0)  # body frame: +y is left
    assert np.all(np.diff(scan.angles) > 0) and scan.angles.min() >= 0 and scan.angles.max() < 2 * math.pi


def test_lidar_conversion_wraps_small_negative_angles():
    from qcarlab.car.quanser import lidar_to_body

    angles, ranges = lidar_to_body([1e-17, 2 * math.pi - 0.1, 0.1], [1.0, 2.0, 3.0])
    assert np.all((angles >= 0) & (angles < 2 * math.pi))
    assert np.allclose(angles, [0.0, 0.1, 2 * math.pi - 0.1]) and list(ranges) == [1.0, 2.0, 3.0]


def test_cameras_and_capabilities(qcar):
    assert {"lidar", "rgbd", "csi"} <= set(qcar.identity().capabilities)
    assert qcar.identity().backend == "quanser"
    rgbd = qcar.read_rgbd()
    assert rgbd.color.shape == (480, 640, 3) and rgbd.color.dtype == np.uint8 and rgbd.color.max() == 7
    assert rgbd.depth.shape == (480, 640) and rgbd.depth.dtype == np.float32 and rgbd.depth[0, 0] == 1.5
    csi = qcar.read_csi()
    assert [int(getattr(csi, k)[0, 0, 0]) for k in ("right", "rear", "left", "front")] == [0, 1, 2, 3]
    assert csi.front.shape == (410, 820, 3)


def test_a_camera_that_fails_to_open_is_left_out(fake_quanser, caplog):
    from qcarlab.car.quanser import QuanserCar

    Video3D.fail = True
    with QuanserCar() as car:
        assert "rgbd" not in car.identity().capabilities and "lidar" in car.identity().capabilities
        with pytest.raises(NotBuiltError, match="no RealSense"):
            car.read_rgbd()


def test_close_stops_and_releases_the_board(fake_quanser):
    from qcarlab.car.quanser import QuanserCar

    car = QuanserCar()
    car.write(0.2, 0.1)
    car.close()
    hil = FakeHIL.last
    assert hil.writes[-1]["pwm"] == {0: 0.0} and hil.writes[-1]["other"][1000] == 0.0 and hil.closed


def test_the_physical_car_served_over_tcp(qcar):
    hil = FakeHIL.last
    with CarServer(qcar, "127.0.0.1", 0) as server, TcpCar(*server.address) as remote:
        assert not remote.stepped and remote.identity().extra["remote_backend"] == "quanser"
        remote.write(0.15, 0.25)
        assert hil.writes[-1]["pwm"] == {0: -0.15} and hil.writes[-1]["other"][1000] == pytest.approx(-0.25)
        assert remote.read().battery_voltage == 11.8
        assert np.allclose(remote.read_lidar().angles, [0.0, math.pi / 2, math.pi, 3 * math.pi / 2])
        assert remote.truth() is None  # a real car has no ground truth
    assert hil.writes[-1]["pwm"] == {0: 0.0}  # the controller left: stopped


def test_a_slow_lidar_holds_up_neither_commands_nor_the_watchdog(qcar):
    """Was: the LIDAR and cameras were read under the lock the HIL board's writes need."""
    from qcarlab.net.protocol import MsgType as M
    from qcarlab.net.testing import RawClient

    hil = FakeHIL.last
    RPLIDAR.delay = 1.0
    with CarServer(qcar, "127.0.0.1", 0, watchdog=0.1) as server, TcpCar(*server.address) as ctl, \
            RawClient(server.address, timeout=5.0) as mon:
        mon.hello("monitor")
        ctl.write(0.2, 0.0)
        mon.send(M.GET_LIDAR)  # a 1 s reading starts
        time.sleep(0.02)
        t0 = time.monotonic()
        ctl.write(0.15, 0.0)
        assert time.monotonic() - t0 < 0.5 and hil.writes[-1]["pwm"] == {0: -0.15}
        sent = time.monotonic()
        while hil.writes[-1]["pwm"] != {0: 0.0} and time.monotonic() - sent < 1.0:
            time.sleep(0.002)
        assert hil.writes[-1]["pwm"] == {0: 0.0} and time.monotonic() - sent < 0.1 + 0.2  # the watchdog
        assert mon.recv().type == M.LIDAR
