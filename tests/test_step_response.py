"""The PI tuning step (sheet 4.2.3) runs the lab's speed loop: the student's blocks, the params' gains."""

from __future__ import annotations

import json

import pytest

from tests.grading_submissions import correct_submission, write_block

P_ONLY = """
    def speed_controller(v_ref, v_measured, dt):
        return 0.3 * (v_ref - v_measured)          # no feed-forward, no integral: a lasting error
"""
TUNED = """
    from qcarlab.control.speed import SpeedController

    class speed_controller:
        def __init__(self):
            self.reset()

        def reset(self):
            self._pi = SpeedController(0.5, 2.0, 0.1)

        def __call__(self, v_ref, v_measured, dt):
            return self._pi(v_ref, v_measured, dt)
"""
STEP = ("path-follow", "line", "--step-response", "--speed", "0.5")


def results(cli, *args):
    code, out, err = cli(*STEP, *args, "--json")
    return code, json.loads(out), err


def test_the_students_speed_controller_drives_the_step(cli, tmp_path):
    mine = write_block(tmp_path, "speed_controller.py", P_ONLY)
    code, m, err = results(cli, "--use", mine)
    assert code == 1 and "never reached 90 % of the 0.5 m/s step" in err
    assert m["steady_state_error_mps"] > 0.1 and m["rise_time_s"] is None  # P only: it never gets there
    assert m["student_blocks"]["speed_controller"]["calls"] == 600 and m["controller"].startswith("your")
    tuned = write_block(tmp_path, "tuned.py", TUNED)
    code, m, err = results(cli, "--block", f"speed_controller={tuned}:speed_controller")
    assert code == 0, err
    assert abs(m["steady_state_error_mps"]) < 0.01 and m["rise_time_s"] < 0.3  # faster than the defaults
    assert m["student_blocks"]["speed_controller"]["calls"] == 600


def test_the_speed_is_measured_by_qcarlab_not_by_the_students_estimate(cli, tmp_path):
    mine = write_block(tmp_path, "basic_speed_estimation.py", """
        _reference = __import__("importlib").import_module("qcarlab.control.speed").basic_speed_estimation

        def basic_speed_estimation(counts_per_s):
            return 2.0 * _reference(counts_per_s)      # twice the true speed
    """)
    code, m, err = results(cli, "--use", mine, "--max-time", "8")
    assert code == 1 and "never reached 90 %" in err  # the controller holds the estimate at 0.5: the car at 0.25
    assert m["steady_state_error_mps"] == pytest.approx(0.25, abs=0.02)
    assert m["student_blocks"]["basic_speed_estimation"]["calls"] == 800


def test_the_params_gains_tune_the_reference_controller_and_options_win(cli, tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text("lab:\n  kp: 0.05\n  ki: 0.1\n  lookahead: 0.5\n")
    _, default, _ = results(cli)
    _, sluggish, _ = results(cli, "--params", params)
    assert (sluggish["kp"], sluggish["ki"]) == (0.05, 0.1)
    assert sluggish["rise_time_s"] > 2 * default["rise_time_s"]
    _, typed, _ = results(cli, "--params", params, "--kp", "0.3", "--ki", "1")
    assert (typed["kp"], typed["ki"]) == (0.3, 1.0)
    assert typed["rise_time_s"] == pytest.approx(default["rise_time_s"])


def test_a_raising_controller_stops_the_car_with_one_line(cli, tmp_path):
    mine = write_block(tmp_path, "speed_controller.py", """
        def speed_controller(v_ref, v_measured, dt):
            return v_ref / (v_measured * 0)
    """)
    code, _, err = cli(*STEP, "--use", mine)
    assert code == 1 and "block speed_controller" in err and "ZeroDivisionError" in err


def test_a_step_into_the_wall_is_a_goal_missed(cli):
    code, m, err = results(cli, "--speed", "2.5")
    assert code == 1 and "collision at" in err and m["collision"]["t"] < 6.0


def test_the_step_starts_at_the_back_of_the_room():
    from qcarlab.constants import DEFAULT_PARAMS
    from qcarlab.experiments.step_response import step_start
    from qcarlab.experiments.worlds import load_world

    x, y, yaw = step_start(load_world("studio", DEFAULT_PARAMS), DEFAULT_PARAMS)  # centre, heading -Y
    assert (x, yaw) == (0.0, -1.5707963267948966) and 4.3 <= y <= 4.5  # 0.3 m from the wall at +5 m


def test_the_readmes_step_has_room(cli):
    code, _, err = cli(*STEP[:3], "--speed", "0.8", "--kp", "0.5", "--ki", "2", "--json")
    assert code == 0, err  # from the room's centre it would reach the wall before the 6 s are up


def test_the_pi_task_grades_the_students_speed_controller(cli, tmp_path):
    sub = correct_submission(tmp_path / "me", ("path-following",))
    grade = ("grade", "path-following", "--submission", sub, "--task", "pi-tuning", "--json")
    code, out, _ = cli(*grade)
    task = json.loads(out)["tasks"][0]
    assert code == 0 and task["passed"], task
    assert "--block speed_controller=speed_controller.py:speed_controller" in task["command"]
    write_block(sub / "path-following", "speed_controller.py", P_ONLY)
    code, out, _ = cli(*grade)
    task = json.loads(out)["tasks"][0]
    assert code == 1 and not task["passed"]
    reasons = [c["reason"] for c in task["criteria"] if not c["passed"]]
    assert any(r.startswith("steady_state_error_mps = 0.15") for r in reasons), reasons
    assert task["run_failure"].startswith("the speed never reached 90 %")
