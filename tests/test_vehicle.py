"""The simulated QCar against the lab sheet's models (sheet 4.1.1) and the car's facts."""

from __future__ import annotations

import math

import numpy as np
import pytest

import qcarlab
from qcarlab.constants import DEFAULT_PARAMS
from qcarlab.control.speed import basic_speed_estimation
from qcarlab.sim.vehicle import Vehicle, cell_voltage, turning_radius


def drive(vehicle: Vehicle, seconds: float, dt: float = 0.01) -> list[tuple[float, float, float]]:
    poses = []
    for _ in range(round(seconds / dt)):
        vehicle.step(dt)
        s = vehicle.state
        poses.append((s.x, s.y, s.yaw))
    return poses


def test_straight_run_covers_v_times_t():
    veh = Vehicle(on_stand=False)
    veh.command(0.1, 0.0)
    drive(veh, 15.0)  # reach steady speed
    v = veh.state.v
    d0, y0 = veh.state.distance, veh.state.y
    drive(veh, 2.0)
    assert veh.state.distance - d0 == pytest.approx(v * 2.0, rel=0.01)
    # the start pose heads -Y: the car drives straight down the Y axis
    assert veh.state.y - y0 == pytest.approx(-v * 2.0, rel=0.01)
    assert abs(veh.state.x) < 1e-9


def test_throttle_point_one_gives_about_one_metre_per_second():
    veh = Vehicle(on_stand=False)
    veh.command(0.1, 0.0)
    drive(veh, 20.0)
    assert 0.8 < veh.state.v < 1.3


@pytest.mark.parametrize("delta", [0.1, 0.3, -0.5])
def test_constant_steering_gives_the_bicycle_turning_radius(delta):
    veh = Vehicle(on_stand=False)
    veh.command(0.08, delta)
    drive(veh, 8.0)  # servo settled, speed near steady
    pts = np.array(drive(veh, 6.0))[:, :2]
    # least-squares circle fit (Kasa): x^2 + y^2 = 2 a x + 2 b y + c
    A = np.c_[2 * pts[:, 0], 2 * pts[:, 1], np.ones(len(pts))]
    a, b, c = np.linalg.lstsq(A, (pts**2).sum(axis=1), rcond=None)[0]
    radius = math.sqrt(c + a * a + b * b)
    expected = turning_radius(delta)
    assert radius == pytest.approx(expected, rel=0.01)
    # exact bicycle: R = sqrt((L/2)^2 + (L/tan delta)^2); the sheet's small-angle form is L/delta
    L = DEFAULT_PARAMS.wheelbase
    assert expected == pytest.approx(math.hypot(L / 2, L / math.tan(abs(delta))))
    # positive steering turns left: yaw increases while driving forward
    yaw0 = veh.state.yaw
    drive(veh, 0.1)
    assert math.copysign(1, (veh.state.yaw - yaw0 + math.pi) % (2 * math.pi) - math.pi) == math.copysign(1, delta)


def test_steering_servo_lags_and_limits():
    veh = Vehicle()
    veh.command(0.0, 2.0)  # beyond the limit
    veh.step(0.16)  # one time constant
    assert veh.state.delta == pytest.approx(DEFAULT_PARAMS.max_steering * (1 - math.exp(-1)), rel=0.01)
    veh.step(2.0)
    assert veh.state.delta == pytest.approx(DEFAULT_PARAMS.max_steering, rel=1e-4)


def test_encoder_speed_chain_round_trips():
    with qcarlab.open_car("sim", seed=3) as car:
        car.write(0.15, 0.0)
        car.advance(3.0)
        r0, t0 = car.read(), car.truth()
        # tach (counts/s) -> m/s through the four scaling terms
        assert basic_speed_estimation(r0.tach) == pytest.approx(t0.wheel_speed, rel=0.01)
        car.advance(1.0)
        r1, t1 = car.read(), car.truth()
        counts = r1.encoder_counts - r0.encoder_counts
        assert counts * DEFAULT_PARAMS.speed_per_count == pytest.approx(t1.distance - t0.distance, rel=0.01)
    # the design's single constant: 1 count/s = 6.866e-6 m/s
    assert basic_speed_estimation(1.0) == pytest.approx(6.866e-6, rel=1e-3)
    assert np.allclose(basic_speed_estimation(np.array([0.0, 2880.0])), [0.0, 0.09537 * 2 * math.pi * 0.033], rtol=1e-3)


def test_on_the_stand_the_wheels_turn_but_the_car_stays_put():
    with qcarlab.open_car("sim", on_stand=True) as car:
        car.write(0.2, 0.3)
        car.advance(2.0)
        r, t = car.read(), car.truth()
        assert r.encoder_counts > 100_000
        assert t.wheel_speed > 1.0
        assert (t.x, t.y) == (0.0, 0.0) and t.distance == 0.0 and t.speed == 0.0
        assert abs(r.gyro[2]) < 0.02  # not turning, only noise and bias


def test_battery_sags_under_load_and_drains():
    idle = Vehicle()
    idle.step(0.3)
    loaded = Vehicle(on_stand=False)
    loaded.command(0.3, 0.0)
    loaded.step(0.3)  # high current while accelerating
    assert loaded.state.battery_voltage < idle.state.battery_voltage - 0.05
    assert loaded.state.soc < idle.state.soc
    assert cell_voltage(1.0) * 3 == pytest.approx(12.6)
    assert cell_voltage(0.0) * 3 < DEFAULT_PARAMS.battery_shutdown_v


def test_motor_current_follows_the_motor_model():
    veh = Vehicle(on_stand=True)
    veh.command(0.2, 0.0)
    veh.step(0.01)
    s, p = veh.state, DEFAULT_PARAMS
    # i = (d V_batt - K_b w) / R
    assert s.current == pytest.approx((0.2 * s.battery_voltage - p.motor_kb * s.omega) / p.motor_resistance, rel=0.02)


def test_same_seed_same_noise_other_seed_other_noise():
    def readings(seed):
        with qcarlab.open_car("sim", seed=seed) as car:
            car.write(0.1, 0.1)
            car.advance(0.5)
            r = car.read()
            return np.r_[r.gyro, r.accel, r.motor_current, r.battery_voltage]

    assert np.array_equal(readings(7), readings(7))
    assert not np.array_equal(readings(7), readings(8))


def test_noise_drawn_in_blocks_is_the_per_read_noise():
    """SimCar draws the IMU noise for many reads at once; across block boundaries the readings
    are exactly those of one draw per read from the seed's IMU stream (the car at rest)."""
    from qcarlab.car.sim import NOISE_BLOCK

    p = DEFAULT_PARAMS
    imu_seq = np.random.SeedSequence(5).spawn(5)[0]
    ref = np.random.default_rng(imu_seq)
    bias = ref.normal(0.0, p.gyro_bias_sd, 3)
    with qcarlab.open_car("sim", seed=5, on_stand=True) as car:
        for _ in range(2 * NOISE_BLOCK + 7):
            r = car.read()
            n = ref.normal(0.0, 1.0, 6)
            assert np.array_equal(r.gyro, bias + p.gyro_noise * n[:3])
            assert np.array_equal(r.accel, p.accel_noise * n[3:] + np.array([0.0, 0.0, p.gravity]))


@pytest.mark.skipif(not __import__("qcarlab.sim._kernels", fromlist=["HAVE_NUMBA"]).HAVE_NUMBA,
                    reason="numba not installed: there is only the Python path")
@pytest.mark.parametrize("realism", ["ideal", "lab"])
def test_compiled_and_python_physics_agree_to_the_last_bit(monkeypatch, realism):
    """The sub-steps run as plain Python or compiled (vehicle.COMPILED): the same numbers, also
    with the lab car's servo play and delay and its tyres."""
    from qcarlab.sim import vehicle as V
    from qcarlab.sim.realism import load_realism

    def run() -> list[float]:
        veh = Vehicle(on_stand=False, realism=load_realism(realism))
        for k in range(400):
            veh.command(0.3 * math.sin(k / 30.0), 0.5 * math.sin(k / 17.0))
            veh.step(0.01 if k % 3 else 0.013)
        return veh.state.values()

    monkeypatch.setattr(V, "COMPILED", False)
    python = run()
    monkeypatch.setattr(V, "COMPILED", True)
    compiled = run()
    assert V._compiled() is not None
    assert compiled == python


def test_time_set_from_outside_is_where_the_next_step_counts_from():
    """The step keeps its time in whole nanoseconds beside the state's t: a t set from outside
    is recounted, and 100 steps of 10 ms still make exactly one second from there."""
    veh = Vehicle()
    veh.step(0.01)
    veh.state.t = 5.0
    for _ in range(100):
        veh.step(0.01)
    assert veh.state.t == 6.0


def test_pose_at_interpolates_the_true_pose_between_steps():
    """A sensor frame due between two steps is taken from the pose interpolated there."""
    with qcarlab.open_car("sim", seed=0) as car:
        car.write(0.2, 0.3)
        truths = []
        for _ in range(30):
            car.advance(0.01)
            truths.append(car.truth())
        a, b = truths[-2], truths[-1]
        x, y, yaw = car.pose_at(0.5 * (a.t + b.t))
        assert (x, y, yaw) == pytest.approx((0.5 * (a.x + b.x), 0.5 * (a.y + b.y), 0.5 * (a.yaw + b.yaw)), abs=1e-12)
        assert car.pose_at(b.t + 1.0) == (b.x, b.y, b.yaw)  # the latest: the present pose
        assert car.pose_at(a.t) == pytest.approx((a.x, a.y, a.yaw), abs=1e-15)
