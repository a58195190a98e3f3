"""The lane example's user inputs and lamps (issue 11, item 4) and its obstacle stop (item 5):
speed selector, stopping-distance offset and distance to lane in per cent, start/stop, the lamps in
the log, and automatedDriving bringing v_ref to 0 before an obstacle in the lane."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from qcarlab.car import open_car
from qcarlab.control.lamps import indicator_and_lamps
from qcarlab.control.lane import automated_driving, user_inputs
from qcarlab.experiments.lane_follow import LaneFollowConfig, place_obstacle, run_lane_follow
from qcarlab.sim.world import load_world


def test_the_user_inputs_sliders_in_per_cent():
    assert user_inputs(100, 0, 100) == pytest.approx((0.3, 0.6, 1.0))
    assert user_inputs(50, 100, 0, max_speed=0.8) == pytest.approx((0.4, 1.2, 0.0))  # offset 100 %: 1.2 m
    assert user_inputs(0, 50, 25) == pytest.approx((0.0, 0.9, 0.25))
    with pytest.raises(ValueError):
        user_inputs(120, 0, 100)


def test_automated_driving_reaches_zero_at_the_stop_distance():
    """The old linear ramp never got there: 1 cm before the stop distance it still asked for 5 mm/s."""
    assert automated_driving(0.3, 0.61, stop_distance=0.6) >= 0.05
    assert automated_driving(0.3, 0.60, stop_distance=0.6) == 0.0
    assert automated_driving(0.3, 0.9, stop_distance=0.6) == pytest.approx(0.15)
    assert automated_driving(0.3, 0.0) == 0.3 and automated_driving(0.3, 1.5) == 0.3
    assert automated_driving(0.02, 0.7, stop_distance=0.6) == pytest.approx(0.02)  # never above the desired speed


def test_the_reverse_lamps_light_when_backing_up():
    assert "reverse" in indicator_and_lamps(0.0, -0.2) and "brake" not in indicator_and_lamps(0.0, -0.2)
    assert indicator_and_lamps(0.0, 0.0) == ("brake",)
    assert set(indicator_and_lamps(0.4, 0.3)) == {"left-indicators"}


def _lane(world=None, **cfg):
    world = world or load_world("track")
    with open_car("sim", world=world) as car:
        return run_lane_follow(car, LaneFollowConfig(**cfg), world)


def test_an_obstacle_in_the_lane_stops_the_car_with_the_brake_lamp_on():
    world = load_world("track")
    place_obstacle(world, world.start, 0.8)
    r = _lane(world, duration=8.0)
    m, log = r.metrics, r.logs["log.csv"]
    assert m["stopped_for_obstacle_s"] > 2.0 and m["brake_lamp_s"] >= m["stopped_for_obstacle_s"]
    stopped = np.asarray(log["v_ref"]) == 0.0
    assert all("brake" in str(x).split("+") for x in np.asarray(log["lamps"])[stopped])
    d = np.asarray(log["obstacle_distance"], float)
    assert 0.5 < d[-1] <= 0.6 + 1e-6 and abs(float(log["v_meas"][-1])) < 0.01  # at rest at the stop distance
    assert m["goal_reached"] and not m.get("collision")


def test_the_stopping_distance_offset_stops_the_car_farther_away():
    world = load_world("track")
    place_obstacle(world, world.start, 1.5)
    r = _lane(world, duration=9.0, stop_offset=50.0)
    d = np.asarray(r.logs["log.csv"]["obstacle_distance"], float)
    assert r.metrics["user_inputs"]["stop_distance_m"] == pytest.approx(0.9)
    assert 0.8 < d[-1] <= 0.9 + 1e-6 and r.metrics["stopped_for_obstacle_s"] > 1.0


def test_the_speed_selector_and_the_start_and_stop_switches():
    r = _lane(duration=6.0, speed=0.4, speed_selector=50.0, start_at=1.0, stop_at=4.0)
    log = r.logs["log.csv"]
    t, v, armed = (np.asarray(log[k], float) for k in ("t", "v_meas", "armed"))
    assert np.all(armed[t < 0.99] == 0) and np.all(armed[(t > 1.01) & (t < 3.99)] == 1) and np.all(armed[t > 4.01] == 0)
    assert np.abs(v[t < 1.0]).max() < 1e-3  # the start switch: it stands until 1 s
    assert float(np.median(v[(t > 2.5) & (t < 4.0)])) == pytest.approx(0.2, abs=0.03)  # 50 % of 0.4 m/s
    assert abs(v[-1]) < 0.05 and np.all(np.asarray(log["throttle"], float)[t > 4.01] == 0.0)  # stopped, disarmed
    lamps = np.asarray(log["lamps"])
    assert all("brake" in str(x) for x in lamps[t < 0.99])
    assert r.metrics["stopped_for_obstacle_s"] == 0.0  # standing at the switch is not an obstacle stop


def test_distance_to_lane_moves_the_car_towards_the_line():
    centre = _lane(duration=5.0)
    half = _lane(duration=5.0, distance_to_lane=50.0)
    dev = np.asarray(half.logs["log.csv"]["lateral_deviation"], float)
    assert centre.metrics["rms_lateral_deviation_m"] < 0.04
    assert float(np.median(dev[len(dev) // 2:])) == pytest.approx(0.1, abs=0.03)  # half way to the yellow line
    x, y = (np.asarray(half.logs["log.csv"][k], float) for k in ("true_x", "true_y"))
    assert float(np.median(y[len(y) // 2:])) > -1.7 + 0.07  # towards the yellow line (y = -1.5), not away


def test_lane_follow_options_and_the_lamps_column_from_the_command_line(cli, tmp_path):
    # the camera sits 13 cm behind the bumper (Quanser's mount): the box 0.62 m ahead of the bumper
    # reads 0.75 m, so the car creeps for ~3 s before it is within the 0.6 m stop distance
    code, out, err = cli("lane-follow", "--duration", "6", "--obstacle", "0.62", "--stop-offset", "0",
                         "--speed-selector", "100", "--json", "--out", tmp_path / "o")
    m = json.loads(out)
    assert code == 0 and m["stopped_for_obstacle_s"] > 0.5
    rows = list(csv.DictReader(open(tmp_path / "o" / "log.csv")))
    assert "lamps" in rows[0] and any(r["lamps"] == "brake" for r in rows)
    code, out, err = cli("lane-follow", "--speed-selector", "150", "--duration", "1")
    assert code == 2 and "--speed-selector must be a percentage" in err
    code, out, err = cli("lane-follow", "--start-at", "3", "--stop-at", "2", "--duration", "1")
    assert code == 2 and "--stop-at" in err


def test_lane_follow_drives_with_a_tuned_hsv_profile(cli, cli_json, tmp_path):
    """--hsv-tune writes hsv.yaml; --hsv FILE drives with the range it holds."""
    profile = tmp_path / "mine.yaml"
    profile.write_text("qcarlab: hsv-profile\nversion: 1\nyellow:\n  hsv_min: [18, 90, 75]\n  hsv_max: [37, 255, 255]\n")
    m = cli_json("lane-follow", "--hsv", profile, "--duration", "4", "--out", tmp_path / "run")
    assert m["goal_reached"]
    import json as _json

    saved = _json.loads((tmp_path / "run" / "results.json").read_text())
    assert saved["config"]["hsv_min"] == [18, 90, 75] and saved["config"]["hsv_max"] == [37, 255, 255]
    # the file and an explicit range conflict: one line, exit 2
    code, _, err = cli("lane-follow", "--hsv", profile, "--hsv-min", "1,2,3")
    assert code == 2 and "leave out --hsv-min" in err
    profile.write_text("yellow: {hsv_min: [40, 0, 0], hsv_max: [10, 255, 255]}\n")
    code, _, err = cli("lane-follow", "--hsv", profile)
    assert code == 2 and "Traceback" not in err
