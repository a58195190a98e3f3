"""The lab's speed blocks and the control loop."""

from __future__ import annotations

import math

import pytest

import qcarlab
from qcarlab.car.base import Command
from qcarlab.control.speed import SpeedController, turn_speed_handling
from qcarlab.experiments.loop import STOP, run_loop


def test_speed_controller_equation():
    pi = SpeedController(kp=0.3, ki=1.0, kff=0.1)
    # first step: Kff v_ref + Kp e + Ki e dt
    assert pi(1.0, 0.5, 0.01) == pytest.approx(0.1 * 1.0 + 0.3 * 0.5 + 1.0 * 0.5 * 0.01)
    assert pi.integral == pytest.approx(0.005)


def test_speed_controller_clamps_integral_and_output_and_resets_when_disarmed():
    pi = SpeedController(kp=0.0, ki=10.0, kff=0.0, throttle_limit=0.3)
    for _ in range(1000):
        u = pi(2.0, 0.0, 0.01)
    assert pi.integral == pytest.approx(0.4)  # anti-windup clamp
    assert u == pytest.approx(0.3)  # throttle limit
    assert pi(2.0, 0.0, 0.01, armed=False) == 0.0 and pi.integral == 0.0


def test_turn_speed_handling():
    assert turn_speed_handling(1.0, 0.0) == 1.0
    assert turn_speed_handling(1.0, 0.2) == pytest.approx(math.cos(0.2) ** 8)
    assert turn_speed_handling(1.0, 0.5236) == 0.5  # clipped at half speed
    assert turn_speed_handling(1.0, 0.5236, enable=False) == 1.0


def test_pi_controller_holds_the_desired_speed_on_the_simulator():
    pi = SpeedController()
    from qcarlab.control.speed import basic_speed_estimation

    with qcarlab.open_car("sim", seed=1) as car:
        log = run_loop(car, lambda t, r: Command(pi(0.8, basic_speed_estimation(r.tach), 0.01), 0.0), 6.0)
    speed = log.arrays()["true_speed"]
    assert abs(speed[-100:].mean() - 0.8) < 0.02


def test_loop_stops_the_car_on_error_and_on_stop():
    with qcarlab.open_car("sim") as car:

        def boom(t, r):
            if t > 0.1:
                raise RuntimeError("controller crashed")
            return Command(0.2, 0.1)

        with pytest.raises(RuntimeError):
            run_loop(car, boom, 1.0)
        assert car.read().throttle == 0.0
        log = run_loop(car, lambda t, r: STOP if t >= 0.05 else Command(0.1, 0.0), 1.0)
        assert log.stopped_early and log.ticks == 5
        assert car.read().throttle == 0.0


def test_speed_controller_holds_a_car_at_rest():
    pi = SpeedController()
    for _ in range(50):  # braking from 0.5 m/s winds the integral negative
        pi(0.0, 0.5, 0.01)
    assert pi.integral < 0
    assert pi(0.0, 0.005, 0.01) == 0.0 and pi.integral == 0.0  # at rest: no creeping backwards
    assert pi(0.0, 0.2, 0.01) < 0.0  # still moving: it brakes
