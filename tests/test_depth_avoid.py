"""``avoid --strategy depth`` (issue 11, item 3): the race-car report's left/middle/right depth
windows and its state machine (Stop, Straight, Straight Left/Right, Turn Left/Right, Back)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from qcarlab.control.depth_avoid import DepthAvoid
from qcarlab.experiments.avoid import AvoidLab
from qcarlab.perception.depth_windows import depth_windows, window_boxes


def image(left: float, middle: float, right: float, shape=(480, 640)) -> np.ndarray:
    """A depth image whose left, middle and right thirds (40 % in the middle) read the given depths."""
    d = np.zeros(shape, np.float32)
    w = shape[1]
    d[:, : int(0.3 * w)], d[:, int(0.3 * w): int(0.7 * w)], d[:, int(0.7 * w):] = left, middle, right
    return d


def test_the_three_windows_read_the_mean_depth_of_their_part_of_the_image():
    assert depth_windows(image(1.5, 4.0, 0.8)) == pytest.approx((1.5, 4.0, 0.8))
    d = image(1.0, 3.0, 2.0)
    (x0, y0, x1, y1) = window_boxes(d.shape)[0]
    d[y0:y1, x0:(x0 + x1) // 2] = 2.0  # half the left window at 2 m
    assert depth_windows(d)[0] == pytest.approx(1.5, abs=0.02)


def test_no_data_reads_zero_and_a_small_ball_in_the_middle_shows_in_the_added_window():
    d = image(1.5, 4.0, 1.5)
    d[:, :200] = 0.0  # the D435's "no data"
    assert depth_windows(d)[0] == 0.0
    ball = image(1.5, 5.0, 1.5)
    x0, y0, x1, y1 = window_boxes(ball.shape)[3]  # the added detection area at the middle
    ball[y0:y1, x0:x1] = 2.0  # a ball 2 m ahead: a tenth of the middle window
    left, middle, right = depth_windows(ball)
    assert middle == pytest.approx(2.0)  # the middle window's mean alone would read about 4.7 m


def test_the_state_machine_goes_straight_balances_turns_to_the_open_side_and_backs_up():
    sm = DepthAvoid()
    assert sm(1.4, 5.0, 1.4, 0.3) == (0.3, 0.0) and sm.state == "straight"
    v, delta = sm(2.5, 5.0, 0.9, 0.3)  # the right wall is near: a small left turn
    assert sm.state == "straight-left" and delta == pytest.approx(0.15) and v == 0.3
    sm(1.4, 5.0, 1.3, 0.3)
    assert sm.state == "straight"  # balanced again
    sm.reset()
    v, delta = sm(2.0, 0.8, 3.0, 0.3)  # a wall ahead, more room on the right
    assert sm.state == "turn-right" and delta == pytest.approx(-0.5) and 0 < v < 0.3
    sm(2.0, 1.2, 3.0, 0.3)
    assert sm.state == "turn-right"  # until the front is clear
    sm(2.5, 2.0, 2.5, 0.3)
    assert sm.state == "straight"
    v, delta = sm(0.3, 0.2, 0.25, 0.3)  # every window near: the report's collision -> Back
    assert sm.state == "back" and v < 0 and delta == 0.0 and sm.backups == 1
    sm(0.5, 0.6, 0.5, 0.3)
    assert sm.state == "back"  # until the middle is clear again
    sm(1.0, 1.5, 1.0, 0.3)
    assert sm.state != "back"
    assert sm(0.0, 0.0, 0.0, 0.3) == (0.0, 0.0) and sm.state == "stop"  # no data: Stop


def test_something_rolling_at_the_car_makes_it_turn_earlier():
    still, rolling = DepthAvoid(), DepthAvoid()
    for k in range(8):
        still(1.5, 2.0 - 0.01 * k, 1.5, 0.3)  # the car closes on a wall at 0.3 m/s
        rolling(1.5, 2.6 - 0.045 * k, 1.5, 0.3)  # a ball closes at 1.35 m/s
    assert still.state == "straight" and rolling.state.startswith("turn")
    assert rolling.turn_at > 2.0 > still.turn_at


def test_avoid_strategy_depth_drives_the_hallway_corridor_and_takes_the_corner(cli_json):
    m = cli_json("avoid", "--strategy", "depth", "--world", "hallway", "--duration", "19")
    assert m["collisions"] == 0 and m["distance_m"] > 5.0 and m["depth_frames"] >= 19 * 30 - 2
    assert m["time_in_state_s"].get("turn-left", 0) > 1.0  # the left turn into the bottom corridor
    assert m["min_clearance_m"] > 0.1


def test_the_depth_blocks_are_the_labs_and_a_students_depth_avoid_replaces_the_reference(cli, tmp_path):
    names = [b.name for b in AvoidLab.BLOCKS]
    assert "depth_windows" in names and "depth_avoid" in names
    code, out, err = cli("blocks", "avoid")
    assert code == 0 and "depth_avoid" in out and "depth_windows" in out
    mine = tmp_path / "mine.py"
    mine.write_text("class depth_avoid:\n    def __call__(self, left, middle, right, desired_speed):\n"
                    "        return 0.0, 0.0\n")
    code, out, err = cli("avoid", "--strategy", "depth", "--use", mine, "--duration", "1", "--json")
    m = json.loads(out)
    assert code == 0 and "depth_avoid" in m["student_blocks"] and m["distance_m"] < 0.01
