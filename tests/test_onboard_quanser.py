"""The car-side server's hardware driver against the strict fake of Quanser's API, for both cars:
channel tables, signs, start-up as Quanser does it, LIDAR angles at the device's marks, cameras,
faults (failed start, failed write, over-current latch), the board's own watchdog."""

from __future__ import annotations

import logging
import math
import sys
import time

import numpy as np
import pytest
from onboard_support import fake_quanser  # noqa: F401  (fixture)

from qcarlab.car.lamps import parse_lamps
from qcarlab.onboard import car_server as cs

ALL_ON = (1.0,) * 12


def outputs(fake, kind):
    return {ch: v for (k, ch), v in fake.STATE.outputs.items() if k == kind}


def events(fake, *kinds):
    return [e for e in fake.STATE.events if not kinds or e["event"] in kinds]


# --- the fake is strict ---------------------------------------------------------------------------
def test_the_fake_refuses_what_a_real_card_would(fake_quanser):
    from quanser.hardware import HIL, HILError

    fake_quanser.reset(car=2)
    card = HIL()
    with pytest.raises(HILError) as exc:
        card.open("qcar", "0")  # a QCar 2's board is "qcar2"
    assert str(exc.value) == "-986"
    card.open("qcar2", "0")
    u32 = lambda *c: np.array(c, dtype=np.uint32)  # noqa: E731
    with pytest.raises(HILError, match="-1001"):  # no PWM channels on a QCar 2
        card.set_pwm_mode(u32(0), 1, np.zeros(1, dtype=np.int32))
    with pytest.raises(HILError, match="-1001"):  # 11001-11011 are not a QCar 2's
        card.write_other(u32(11000, 11001), 2, np.zeros(2))
    with pytest.raises(HILError, match="-1002"):  # a buffer of the wrong size
        card.write_other(u32(1000, 11000), 2, np.zeros(3))
    with pytest.raises(HILError, match="-1002"):  # of the wrong type
        card.write_digital(u32(11), 1, np.zeros(1))
    with pytest.raises(HILError, match="-4"):  # channels as a list
        card.write_other([1000], 1, np.zeros(1))
    card.close()
    with pytest.raises(HILError, match="-1003"):
        card.write_other(u32(1000), 1, np.zeros(1))


# --- both cars through their channel tables --------------------------------------------------------
@pytest.mark.parametrize("car", [1, 2])
def test_detects_the_car_and_opens_its_board(fake_quanser, car):
    fake_quanser.reset(car=car)
    qcar = cs.QuanserCar("auto")
    try:
        assert qcar.car_type == car and qcar.info["board"] == ("qcar" if car == 1 else "qcar2")
        tried = [e.get("board") for e in events(fake_quanser, "open", "open_refused")]
        assert tried == (["qcar"] if car == 1 else ["qcar", "qcar2"])  # Quanser's order: "qcar", then "qcar2"
        assert {"lidar", "rgbd", "csi"} <= set(qcar.capabilities)
    finally:
        qcar.close()
    assert fake_quanser.STATE.open_handles == 0


def test_a_forced_car_type_that_is_not_there_is_one_clear_error(fake_quanser):
    fake_quanser.reset(car=2)
    with pytest.raises(cs.CarError) as exc:
        cs.QuanserCar(1)
    assert "'qcar'" in str(exc.value) and "\n" not in str(exc.value)
    assert fake_quanser.STATE.open_handles == 0


def test_qcar1_throttle_and_steering_are_negated_and_lamps_are_other_channels(fake_quanser):
    qcar = cs.QuanserCar(1)
    try:
        lamps = parse_lamps(["brake", "hazard", "user2"])
        qcar.write(0.2, 0.3, lamps)
        assert outputs(fake_quanser, "pwm") == {0: -0.2}  # [qcar.py] QCar.write: -clip(throttle)
        other = outputs(fake_quanser, "other")
        assert other[1000] == pytest.approx(-0.3)
        assert {ch for ch, v in other.items() if ch >= 11000 and v > 0} == {11000, 11006, 11008, 11009, 11010, 11011}
    finally:
        qcar.close()
    assert outputs(fake_quanser, "pwm") == {0: 0.0} and outputs(fake_quanser, "other")[1000] == 0.0


def test_qcar2_throttle_is_other_11000_not_negated_and_lamps_are_digital_11_to_26(fake_quanser):
    fake_quanser.reset(car=2)
    qcar = cs.QuanserCar(2)
    try:
        qcar.write(0.2, 0.3, ALL_ON)
        other = outputs(fake_quanser, "other")
        assert other == {1000: pytest.approx(0.3), 11000: pytest.approx(0.2)}  # [qcar.py] QCar.write, car type 2
        assert outputs(fake_quanser, "pwm") == {}
        assert all(outputs(fake_quanser, "digital")[ch] == 1.0 for ch in range(11, 27))
        # stopping with the brake lamp on must not touch the throttle (11000 is the throttle on a QCar 2)
        qcar.stop_outputs(cs.STOP_LAMPS)
        other, digital = outputs(fake_quanser, "other"), outputs(fake_quanser, "digital")
        assert other[11000] == 0.0 and other[1000] == 0.0
        assert {ch for ch, v in digital.items() if v} == {11, 12, 13, 14}  # the brake lamps
        qcar.write(0.0, 0.0, parse_lamps(["indicator_rear_left", "headlamp_right", "reverse"]))
        assert {ch for ch, v in outputs(fake_quanser, "digital").items() if v} == {17, 22, 23, 24, 15, 16}
    finally:
        qcar.close()


@pytest.mark.parametrize("car,current,battery", [(1, 1.25, 11.8), (2, 2.5, 15.2)])
def test_readout_comes_from_each_cars_channels(fake_quanser, car, current, battery):
    fake_quanser.reset(car=car)
    qcar = cs.QuanserCar(car)
    try:
        r = qcar.read()
        board = fake_quanser.BOARDS[car]
        assert (r.current, r.battery) == (current, battery)  # analog [5, 6] on a QCar 1, [4, 2] on a QCar 2
        assert r.encoder == board["encoder_in"][0] and r.tach == board["other_in"][14000]
        assert r.gyro == tuple(board["other_in"][c] for c in (3000, 3001, 3002))
        assert r.accel == tuple(board["other_in"][c] for c in (4000, 4001, 4002))
    finally:
        qcar.close()


def test_start_up_is_quansers(fake_quanser):
    qcar = cs.QuanserCar(1, throttle_limit=0.25)
    qcar.close()
    kinds = [e["event"] for e in events(fake_quanser)]
    start = kinds[: kinds.index("write")]
    assert start == ["open", "pwm_mode", "pwm_frequency", "write_digital", "options", "quadrature",
                     "encoder_filter", "encoder_counts"]
    by = {e["event"]: e for e in events(fake_quanser)}
    assert by["pwm_mode"]["modes"] == [0] and by["pwm_frequency"]["hz"] == [pytest.approx(60e6 / 4096)]
    assert by["write_digital"]["digital"] == {"40": 0.0} or by["write_digital"]["digital"] == {40: 0.0}  # motor coast
    assert by["options"]["options"] == {"steer_bias": 0.0, "motor_limit": 0.25}
    assert by["quadrature"]["modes"] == [4] and by["encoder_filter"]["hz"] == [60e6]
    assert by["encoder_counts"]["counts"] == [0]
    first = events(fake_quanser, "write")[0]
    assert first["pwm"] == {0: 0.0} and first["other"][1000] == 0.0  # stopped before anything else

    fake_quanser.reset(car=2)
    cs.QuanserCar(2).close()
    kinds = [e["event"] for e in events(fake_quanser)]
    assert "pwm_mode" not in kinds and "write_digital" not in kinds  # a QCar 2 has neither
    assert kinds[kinds.index("open") + 1: kinds.index("write")] == ["options", "quadrature", "encoder_filter",
                                                                    "encoder_counts"]


@pytest.mark.parametrize("what", ["configuration", "first write"])
def test_a_failed_start_closes_the_card(fake_quanser, monkeypatch, what):
    from quanser.hardware import HIL, HILError

    def broken(self, *args):
        raise HILError(-1004, "encoder filter")

    if what == "configuration":
        monkeypatch.setattr(HIL, "set_encoder_filter_frequency", broken)
    else:
        fake_quanser.reset(car=1, fail_write_after=0)  # the very first write (the start-up stop) fails
    with pytest.raises(cs.CarError, match="could not be set up.*it was closed"):
        cs.QuanserCar(1)
    assert fake_quanser.STATE.open_handles == 0 and events(fake_quanser, "close")


# --- the LIDAR --------------------------------------------------------------------------------------
@pytest.mark.parametrize("car,expected", [
    # device marks 0, 90, 180, 270 deg (clockwise) at 1, 2, 3, 4 m; body angle = (zero - heading) mod 360
    (1, {90.0: 1.0, 0.0: 2.0, 270.0: 3.0, 180.0: 4.0}),  # zero mark to the car's left
    (2, {180.0: 1.0, 90.0: 2.0, 0.0: 3.0, 270.0: 4.0}),  # zero mark to the rear
])
def test_lidar_returns_at_the_devices_marks_land_in_the_body_frame(fake_quanser, car, expected):
    fake_quanser.reset(car=car, lidar_script=["scan"])
    qcar = cs.QuanserCar(car, rgbd=False, csi=False)
    try:
        t, angles, ranges = qcar.lidar_arrays()
    finally:
        qcar.close()
    deg = np.degrees(angles)
    got = {round(float(a), 6): float(r) for a, r in zip(deg, ranges) if r > 0}
    assert got == pytest.approx(expected)
    assert np.all(np.diff(angles) > 0) and angles.min() >= 0 and angles.max() < 2 * math.pi
    no_return = 45.0 if car == 1 else 135.0  # the quality-0 beam at the device's 45 deg mark
    assert ranges[np.isclose(deg, no_return)] == 0.0


def test_no_new_scan_keeps_the_last_turn_and_its_time(fake_quanser):
    fake_quanser.reset(car=1, lidar_script=["block", "scan", "none", "block", "scan"])
    qcar = cs.QuanserCar(1, rgbd=False, csi=False)
    try:
        t0, a0, _ = qcar.lidar_arrays()  # -34 before the first turn: an empty scan, not an error
        assert a0.size == 0 and t0 == 0.0
        t1, a1, r1 = qcar.lidar_arrays()
        assert a1.size == 5 and t1 > 0
        time.sleep(0.01)
        for _ in range(2):  # 0 (nothing new), then -34 again: the same turn, the same time
            t, a, r = qcar.lidar_arrays()
            assert t == t1 and np.array_equal(a, a1) and np.array_equal(r, r1)
        assert qcar.lidar_arrays()[0] > t1
    finally:
        qcar.close()


def test_the_lidar_url_is_each_cars(fake_quanser):
    for car, port, baud in ((1, "2", "115200"), (2, "1", "256000")):
        fake_quanser.reset(car=car)
        qcar = cs.QuanserCar(car, rgbd=False, csi=False)
        qcar.close()
        (opened,) = events(fake_quanser, "lidar_open")
        assert f"localhost:{port}?baud='{baud}'" in opened["uri"]


# --- cameras ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("car,ids", [(1, {"right": 0, "rear": 1, "left": 2, "front": 3}),
                                     (2, {"right": 0, "rear": 1, "front": 2, "left": 3})])
def test_csi_views_come_from_each_cars_camera_ids(fake_quanser, car, ids):
    fake_quanser.reset(car=car)
    qcar = cs.QuanserCar(car, lidar=False, rgbd=False)
    try:
        t, views = qcar.csi_arrays()
        for view, img in zip(("right", "rear", "left", "front"), views):
            assert img.shape == (410, 820, 3) and int(img[0, 0, 0]) == 10 + 40 * ids[view]
    finally:
        qcar.close()


def test_a_camera_read_without_a_new_frame_keeps_its_time(fake_quanser):
    fake_quanser.reset(car=1, camera_script=[True, True, True, True, False, False, False, False])
    qcar = cs.QuanserCar(1, lidar=False, rgbd=False)
    try:
        t1, _ = qcar.csi_arrays()
        time.sleep(0.01)
        t2, _ = qcar.csi_arrays()  # every capture said "no new frame": the old frames, the old time
        assert t1 > 0 and t2 == t1
    finally:
        qcar.close()


def test_rgbd_frames_are_timed_by_arrival_and_depth_is_not_aligned(fake_quanser):
    qcar = cs.QuanserCar(1, lidar=False, csi=False)
    try:
        t0, color, depth = qcar.rgbd_arrays()  # the first poll has no frame yet
        assert t0 == 0.0 and color.shape == (480, 640, 3) and depth.shape == (480, 640)
        t1, color, depth = qcar.rgbd_arrays()
        assert t1 > 0 and color.max() == 7 and depth.dtype == np.float32 and depth[0, 0] == 1.5
        assert qcar.extra()["depth_aligned"] is False
    finally:
        qcar.close()


def test_a_sensor_that_fails_to_open_is_left_out(fake_quanser, caplog):
    fake_quanser.reset(car=1, sensors=["lidar"])
    with caplog.at_level(logging.WARNING, logger="qcarlab.car_server"):
        qcar = cs.QuanserCar(1)
    try:
        assert "lidar" in qcar.capabilities and "rgbd" not in qcar.capabilities and "csi" not in qcar.capabilities
        assert "RealSense" in qcar.missing["rgbd"]
    finally:
        qcar.close()


# --- faults -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("car", [1, 2])
def test_a_failed_write_stops_the_car_another_way_closes_the_board_and_stop_reopens_it(fake_quanser, car):
    fake_quanser.reset(car=car, fail_write_after=3)  # the start-up stop + two commands, then over-current
    qcar = cs.QuanserCar(car)
    try:
        qcar.write(0.2, 0.1, cs.ALL_OFF)
        qcar.write(0.2, 0.1, cs.ALL_OFF)
        with pytest.raises(cs.CarFault, match="write failed.*board was closed"):
            qcar.write(0.2, 0.1, cs.ALL_OFF)
        throttle = ("pwm", 0) if car == 1 else ("other", 11000)
        assert fake_quanser.STATE.outputs[throttle] == 0.0 and fake_quanser.STATE.outputs[("other", 1000)] == 0.0
        assert events(fake_quanser, "write_pwm" if car == 1 else "write_other")  # another path than card.write
        assert fake_quanser.STATE.open_handles == 0  # closed: that clears an over-current latch
        with pytest.raises(cs.CarFault):  # no retrying the failing write
            qcar.write(0.1, 0.0, cs.ALL_OFF)
        with pytest.raises(cs.CarFault):
            qcar.read()
        qcar.reopen()
        assert qcar.fault is None and fake_quanser.STATE.open_handles == 1
        qcar.write(0.1, 0.0, cs.ALL_OFF)
        assert fake_quanser.STATE.outputs[throttle] == pytest.approx(0.1 * (-1 if car == 1 else 1))
    finally:
        qcar.close()


@pytest.mark.parametrize("car", [1, 2])
def test_the_boards_watchdog_stops_the_motor_when_nothing_reloads_it(fake_quanser, car):
    fake_quanser.reset(car=car)
    qcar = cs.QuanserCar(car, watchdog=0.2)
    try:
        assert qcar.hardware_watchdog and qcar.extra()["hardware_watchdog"] is True
        started = events(fake_quanser, "watchdog_start")[-1]
        drive = {"('pwm', 0)", "('other', 1000)"} if car == 1 else {"('other', 1000)", "('other', 11000)"}
        assert set(started["states"]) == drive and set(started["states"].values()) == {0.0}
        assert started["timeout"] == 0.2
        qcar.write(0.2, 0.1, cs.ALL_OFF)
        for _ in range(10):  # reloaded in time: the motor keeps running
            time.sleep(0.04)
            assert qcar.kick()
        throttle = ("pwm", 0) if car == 1 else ("other", 11000)
        assert fake_quanser.STATE.outputs[throttle] != 0.0
        time.sleep(0.45)  # a frozen or killed server: nobody reloads it
        fake_quanser.STATE.expire_watchdog_if_due()
        assert fake_quanser.STATE.outputs[throttle] == 0.0 and fake_quanser.STATE.outputs[("other", 1000)] == 0.0
        assert qcar.kick() is False  # noticed, cleared and restarted
        qcar.write(0.1, 0.0, cs.ALL_OFF)
        assert fake_quanser.STATE.outputs[throttle] != 0.0
    finally:
        qcar.close()


def test_without_a_board_watchdog_the_server_says_a_killed_process_leaves_the_motor_running(fake_quanser, caplog):
    fake_quanser.reset(car=1, watchdog=0)
    with caplog.at_level(logging.WARNING, logger="qcarlab.car_server"):
        qcar = cs.QuanserCar(1)
    try:
        assert qcar.hardware_watchdog is False and qcar.extra()["hardware_watchdog"] is False
        assert any("keeps its last PWM" in r.getMessage() for r in caplog.records)
        assert qcar.kick() is True
    finally:
        qcar.close()


def test_without_quansers_api_one_clear_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "quanser", None)
    with pytest.raises(cs.CarError) as exc:
        cs.QuanserCar("auto")
    assert "cannot be imported" in str(exc.value) and "PYTHONPATH" in str(exc.value) and "\n" not in str(exc.value)
