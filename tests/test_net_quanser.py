"""``qcarlab serve --backend quanser``: the Car adapter over the car-side server's driver, against the
strict fake of Quanser's API (tests/fake_quanser), for both cars, served over TCP."""

from __future__ import annotations

import math
import sys
import time

import numpy as np
import pytest
from onboard_support import fake_quanser  # noqa: F401  (fixture)

from qcarlab.car.lamps import HIL_CHANNELS
from qcarlab.car.tcp import TcpCar
from qcarlab.constants import QCAR1_PARAMS, QCAR2_PARAMS
from qcarlab.errors import CarError, NotBuiltError
from qcarlab.net.server import CarServer


def cli_error_lines(err: str) -> int:
    """Lines the CLI itself printed (an in-process test server may log lines of its own)."""
    return len([line for line in err.splitlines() if not line.startswith(("info:", "warning:"))])


def test_without_quansers_api_one_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "quanser", None)  # import quanser.* now fails
    from qcarlab.car.quanser import QuanserCar

    with pytest.raises(CarError) as exc:
        QuanserCar()
    assert "cannot be imported" in str(exc.value) and "\n" not in str(exc.value)


def test_serve_backend_quanser_without_the_api_exits_1(cli, monkeypatch):
    monkeypatch.setitem(sys.modules, "quanser", None)
    code, out, err = cli("serve", "--backend", "quanser", "--port", "0")
    assert code == 1 and "cannot be imported" in err and cli_error_lines(err) == 1


@pytest.mark.parametrize("args", [("--lockstep",), ("--world", "studio"), ("--backend", "carla")])
def test_serve_refuses_option_mixups(cli, args):
    base = ("serve", "--port", "0") if "--backend" in args else ("serve", "--backend", "quanser", "--port", "0")
    code, out, err = cli(*base, *args)
    assert code == 2 and cli_error_lines(err) == 1


def test_board_open_failure_is_one_line(fake_quanser):
    from qcarlab.car.quanser import QuanserCar

    fake_quanser.reset(car=2)
    with pytest.raises(CarError, match="cannot open the QCar's HIL board .*'qcar'.*not found") as exc:
        QuanserCar(car_type=1)
    assert "\n" not in str(exc.value) and fake_quanser.STATE.open_handles == 0


@pytest.mark.parametrize("car,params", [(1, QCAR1_PARAMS), (2, QCAR2_PARAMS)])
def test_the_car_brings_its_own_parameters(fake_quanser, car, params):
    from qcarlab.car.quanser import QuanserCar

    fake_quanser.reset(car=car)
    with QuanserCar() as qcar:
        assert qcar.car_type == car and qcar.params == params
        assert qcar.steering_limit == 0.5 and qcar.identity().extra["car_type"] == car


def test_qcar1_signs_are_hidden_from_the_user(fake_quanser):
    from qcarlab.car.quanser import QuanserCar

    with QuanserCar() as qcar:
        applied = qcar.write(0.2, 0.3, ["brake", "hazard"])
        assert (applied.throttle, applied.steering) == (0.2, 0.3)  # the user never sees the sign flip
        out = fake_quanser.STATE.outputs
        assert out[("pwm", 0)] == -0.2 and out[("other", 1000)] == pytest.approx(-0.3)
        on = {ch for (kind, ch), v in out.items() if kind == "other" and ch >= 11000 and v > 0}
        assert on == {HIL_CHANNELS[n] for n in ("brake", "indicator_rear_left", "indicator_rear_right",
                                                 "indicator_front_left", "indicator_front_right")}
        qcar.write(-0.9, -1.0)  # clamped first (0.3, 0.5 rad), then negated
        assert out[("pwm", 0)] == 0.3 and out[("other", 1000)] == pytest.approx(0.5)


def test_readout_and_sensors_through_the_adapter(fake_quanser):
    from qcarlab.car.quanser import QuanserCar

    fake_quanser.reset(car=2, lidar_script=["scan"])
    with QuanserCar() as qcar:
        qcar.write(0.1, -0.2, ["headlamps"])
        r = qcar.read()
        assert (r.motor_current, r.battery_voltage, r.encoder_counts, r.tach) == (2.5, 15.2, 777, -321.0)
        assert np.allclose(r.gyro, [-0.04, 0.03, -0.6]) and (r.throttle, r.steering) == (0.1, -0.2)
        assert r.leds[2] == r.leds[3] == 1.0 and qcar.time > 0 and not qcar.stepped
        scan = qcar.read_lidar()
        assert np.isclose(scan.ranges[np.isclose(scan.angles, 0.0)], 3.0)  # the QCar 2's 180 deg mark is ahead
        assert qcar.read_csi().front[0, 0, 0] == 10 + 40 * 2  # the QCar 2's front camera is id 2


def test_a_camera_that_fails_to_open_is_left_out(fake_quanser):
    from qcarlab.car.quanser import QuanserCar

    fake_quanser.reset(car=1, sensors=["lidar", "csi"])
    with QuanserCar() as car:
        assert "rgbd" not in car.identity().capabilities and "lidar" in car.identity().capabilities
        with pytest.raises(NotBuiltError, match="RealSense"):
            car.read_rgbd()


def test_close_stops_and_releases_the_board(fake_quanser):
    from qcarlab.car.quanser import QuanserCar

    car = QuanserCar()
    car.write(0.2, 0.1)
    car.close()
    out = fake_quanser.STATE.outputs
    assert out[("pwm", 0)] == 0.0 and out[("other", 1000)] == 0.0 and fake_quanser.STATE.open_handles == 0


def test_the_adapter_keeps_the_boards_watchdog_reloaded(fake_quanser):
    from qcarlab.car.quanser import QuanserCar

    # watchdog 0.5 s, reloaded every 0.1 s: a reload may come late by 0.4 s on a busy CI machine
    # (with 0.2 s it flaked under load) and the test still sees the board expire if none came
    with QuanserCar(watchdog=0.5) as car:
        car.write(0.2, 0.0)
        time.sleep(1.5)  # three watchdog periods with no command: the adapter's thread reloads it
        fake_quanser.STATE.expire_watchdog_if_due()
        assert not fake_quanser.STATE.watchdog["expired"] and fake_quanser.STATE.outputs[("pwm", 0)] == -0.2


def test_the_physical_car_served_over_tcp(fake_quanser):
    from qcarlab.car.quanser import QuanserCar

    fake_quanser.reset(car=1, lidar_script=["scan"])
    out = fake_quanser.STATE.outputs
    with QuanserCar() as qcar, CarServer(qcar, "127.0.0.1", 0) as server, TcpCar(*server.address) as remote:
        assert not remote.stepped and remote.identity().extra["remote_backend"] == "quanser"
        remote.write(0.15, 0.25)
        assert out[("pwm", 0)] == -0.15 and out[("other", 1000)] == pytest.approx(-0.25)
        assert remote.read().battery_voltage == 11.8
        angles = remote.read_lidar().angles
        assert np.allclose(angles[remote.read_lidar().ranges > 0], [0.0, math.pi / 2, math.pi, 3 * math.pi / 2])
        assert remote.truth() is None  # a real car has no ground truth
    assert out[("pwm", 0)] == 0.0  # the controller left: stopped


def test_a_slow_lidar_holds_up_neither_commands_nor_the_watchdog(fake_quanser, monkeypatch):
    """Was: the LIDAR and cameras were read under the lock the HIL board's writes need."""
    import quanser.devices as devices

    from qcarlab.car.quanser import QuanserCar
    from qcarlab.wire.protocol import MsgType as M
    from qcarlab.net.testing import RawClient

    fake_quanser.reset(car=1, lidar_script=["scan"])
    read = devices.RPLIDAR.read

    def slow_read(self, *args):
        time.sleep(1.0)  # the device waits for a full turn
        return read(self, *args)

    monkeypatch.setattr(devices.RPLIDAR, "read", slow_read)
    out = fake_quanser.STATE.outputs
    with QuanserCar() as qcar, CarServer(qcar, "127.0.0.1", 0, watchdog=0.1) as server, \
            TcpCar(*server.address) as ctl, RawClient(server.address, timeout=5.0) as mon:
        mon.hello("monitor")
        ctl.write(0.2, 0.0)
        mon.send(M.GET_LIDAR)  # a 1 s reading starts
        time.sleep(0.02)
        t0 = time.monotonic()
        ctl.write(0.15, 0.0)
        assert time.monotonic() - t0 < 0.5 and out[("pwm", 0)] == -0.15
        sent = time.monotonic()
        while out[("pwm", 0)] != 0.0 and time.monotonic() - sent < 1.0:
            time.sleep(0.002)
        assert out[("pwm", 0)] == 0.0 and time.monotonic() - sent < 0.1 + 0.2  # the watchdog
        assert mon.recv().type == M.LIDAR
