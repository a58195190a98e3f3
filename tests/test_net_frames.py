"""Sensor frames over TCP: LIDAR scans, RGBD pairs and CSI frames as raw binary (issue 5)."""

from __future__ import annotations

import numpy as np
import pytest

from qcarlab.car.sim import SimCar
from qcarlab.car.tcp import TcpCar
from qcarlab.errors import CarError, NotBuiltError
from qcarlab.wire import protocol as P
from qcarlab.wire.frames import frame_class
from qcarlab.wire.protocol import MsgType as M
from qcarlab.net.server import CarServer
from qcarlab.net.testing import RawClient, SyntheticCar, error_of


@pytest.fixture
def synthetic():
    car = SyntheticCar(seed=3)
    server = CarServer(car, "127.0.0.1", 0).start()
    yield server, car
    server.stop()


def test_capabilities_list_the_sensors_the_backend_has(synthetic):
    server, _ = synthetic
    with TcpCar(*server.address, role="monitor") as mon:
        assert {"lidar", "rgbd", "csi"} <= set(mon.capabilities)
        assert mon.identity().extra["remote_backend"] == "synthetic"


def test_lidar_rgbd_and_csi_arrive_exactly(synthetic):
    server, car = synthetic
    with TcpCar(*server.address, role="monitor") as mon:
        scan = mon.read_lidar()
        assert isinstance(scan, frame_class(M.LIDAR))
        assert np.array_equal(scan.angles, car.lidar[0]) and np.array_equal(scan.ranges, car.lidar[1])
        rgbd = mon.read_rgbd()
        assert rgbd.color.shape == (480, 640, 3) and rgbd.color.dtype == np.uint8
        assert rgbd.depth.shape == (480, 640) and rgbd.depth.dtype == np.float32
        assert np.array_equal(rgbd.color, car.color) and np.array_equal(rgbd.depth, car.depth)
        csi = mon.read_csi()
        for name, expected in zip(("right", "rear", "left", "front"), car.csi):
            got = getattr(csi, name)
            assert got.shape == (410, 820, 3) and np.array_equal(got, expected)
        assert rgbd.t > 0 and csi.t >= rgbd.t


def test_frames_are_binary_not_base64(synthetic):
    server, car = synthetic
    with RawClient(server.address) as raw:
        raw.hello("monitor")
        frame = raw.request(M.GET_RGBD)
        assert frame.type == M.RGBD
        assert len(frame.payload) == 16 + 2 * 16 + car.color.nbytes + car.depth.nbytes


def test_a_backend_without_sensors_answers_unsupported():
    with CarServer(SyntheticCar(sensors=()), "127.0.0.1", 0) as server:
        with TcpCar(*server.address, role="monitor") as mon:
            assert not {"lidar", "rgbd", "csi"} & set(mon.capabilities)
            for read in (mon.read_lidar, mon.read_rgbd, mon.read_csi):
                with pytest.raises(NotBuiltError):
                    read()
        with RawClient(server.address) as raw:  # a client asking anyway gets an error frame
            raw.hello("monitor")
            for request in (M.GET_LIDAR, M.GET_RGBD, M.GET_CSI):
                err = error_of(raw.request(request))
                assert err["code"] == "unsupported" and not err["fatal"]
            assert raw.request(M.PING, b"").type == M.PONG


def test_the_simulators_sensors_over_lockstep_tcp_match_in_process():
    def drive(car):
        car.write(0.15, 0.2)
        car.advance(0.35)
        return car.read_lidar(), car.read_rgbd()

    with CarServer(SimCar(seed=5), "127.0.0.1", 0) as server, TcpCar(*server.address) as remote:
        assert {"lidar", "rgbd", "csi"} <= set(remote.capabilities)
        scan, rgbd = drive(remote)
    with SimCar(seed=5) as local:
        ref_scan, ref_rgbd = drive(local)
    assert type(scan) is type(ref_scan) and scan.t == ref_scan.t
    assert np.array_equal(scan.angles, ref_scan.angles) and np.array_equal(scan.ranges, ref_scan.ranges)
    assert np.array_equal(rgbd.color, ref_rgbd.color) and np.array_equal(rgbd.depth, ref_rgbd.depth)


def test_a_sensor_that_fails_at_read_time_is_an_error_frame():
    car = SyntheticCar(sensors=("rgbd",))
    with CarServer(car, "127.0.0.1", 0) as server, TcpCar(*server.address, role="monitor") as mon:
        assert mon.read_rgbd().color.shape == (480, 640, 3)
        mon._caps.add("lidar")  # pretend the capability was advertised
        with pytest.raises(NotBuiltError):
            mon.read_lidar()
        assert mon.ping() > 0


def test_lockstep_monitors_get_the_controllers_last_frame():
    car = SyntheticCar(stepped=True)
    with CarServer(car, "127.0.0.1", 0) as server:
        with TcpCar(*server.address) as ctl, TcpCar(*server.address, role="monitor") as mon:
            with pytest.raises(CarError, match="no_data"):
                mon.read_rgbd()
            ctl.advance(0.1)
            first = ctl.read_rgbd()
            ctl.advance(0.1)
            again = mon.read_rgbd()
            assert again.t == first.t == pytest.approx(0.1)  # the cached frame, not a new one
            assert np.array_equal(again.color, first.color)
            ctl.read()
            r = mon.read()
            assert r.t == pytest.approx(0.2) and mon.status & P.STATUS_CACHED
