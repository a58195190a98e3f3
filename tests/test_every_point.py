"""Issue 27: every point depends on the student, and the sheet's lessons show on the defaults.

- Every shipped sheet passes its self-check when read (no scenario task runs only qcarlab's code)
  and, graded, the untouched template earns 0 points while the reference earns every one.
- The student's choices (params.yaml) are theirs: the template leaves them empty, a run refuses
  them empty, the grader fails the tasks that grade them.
- 5.3: the HSV range decides what is followed (a wrong range loses the line and the run says so).
- 4.2.2: the look-ahead sweep ranks by the error the controller sees and marks missed goals.
- 5.2 Task 4: the hold behaviour is the student's stop_sign_hold block.
"""

from __future__ import annotations

import json
import textwrap

import numpy as np
import pytest

from qcarlab.experiments.labs import LABS, find_lab, write_template
from qcarlab.grading.sheet import load_sheet, shipped_sheets
from qcarlab.grading.selfcheck import static_problems
from tests.grading_submissions import correct_submission, write_block


@pytest.mark.parametrize("path", shipped_sheets(), ids=lambda p: p.stem)
def test_every_shipped_sheet_grades_only_the_students_work(path):
    assert static_problems(load_sheet(path)) == []


def test_a_sheet_whose_task_runs_only_qcarlabs_code_fails_its_self_check(tmp_path, cli):
    sheet = tmp_path / "free-points.yaml"
    sheet.write_text(textwrap.dedent("""
        title: Free points
        lab: stop-sign
        tasks:
          - id: free
            command: qcarlab stop-sign
            criteria: {stopped: {min: 1}}
    """), encoding="utf-8")
    assert static_problems(load_sheet(sheet)) == [
        "free: uses none of the student's blocks or choices: an untouched template earns its points "
        "(add uses: [BLOCK or TUNABLE])"]
    code, out, _ = cli("labs", "check", str(sheet))
    assert code == 1
    assert "FAIL" in out and "the untouched template earns free: stopped >= 1" in out.replace("\n", " ")


def test_labs_check_grades_the_template_at_zero_and_the_reference_at_full_marks(cli):
    code, out, err = cli("labs", "check", "stop-sign", "basic-io", "--json")
    assert code == 0, out + err
    sheets = {s["sheet"]: s for s in json.loads(out)["sheets"]}
    for name, total in (("stop-sign", 21), ("basic-io", 9)):
        s = sheets[name]
        assert s["ok"], s
        assert (s["template"]["points"], s["template"]["max_points"]) == (0, total)
        assert (s["reference"]["points"], s["reference"]["max_points"]) == (total, total)


@pytest.mark.slow
def test_labs_check_passes_for_every_shipped_sheet(cli):
    code, out, err = cli("labs", "check", "--jobs", "2")
    assert code == 0, out + err


@pytest.mark.parametrize("lab", [lab for lab in LABS if lab.choose], ids=lambda lab: lab.command)
def test_the_template_leaves_the_students_choices_empty_and_a_run_refuses_them(lab, tmp_path, cli, monkeypatch):
    write_template(lab, tmp_path)
    text = (tmp_path / "params.yaml").read_text()
    for choice in lab.choose:
        assert f"\n  {choice.name}:   # empty until you fill it in" in text
    monkeypatch.chdir(tmp_path)
    first = lab.choose[0].name
    code, _, err = cli(lab.command, *(["circle"] if lab.command == "path-follow" else []), "--params", "params.yaml")
    assert code == 2
    assert f"params.yaml: lab: {first} is empty: it is yours to choose" in err
    assert "Traceback" not in err


def test_the_grader_fails_a_task_whose_choice_is_left_empty(tmp_path, cli):
    root = correct_submission(tmp_path, ("stop-sign",)) / "stop-sign"
    params = root / "params.yaml"
    params.write_text(params.read_text().replace("  hsv_min: [170, 100, 100]\n", "  hsv_min:\n"))
    code, out, _ = cli("grade", "stop-sign", "--submission", str(root), "--task", "5.1-detect", "--task",
                       "5.2-task1-stopsign", "--json")
    rows = {r["id"]: r for r in json.loads(out)["tasks"]}
    assert code == 1
    assert rows["5.1-detect"]["problem"] == ("params.yaml: lab: hsv_min is empty: the task grades your choice of it "
                                             "(fill it in)")
    assert rows["5.2-task1-stopsign"]["passed"]  # a task that does not grade the choice runs with qcarlab's


# ------------------------------------------------------------------------------------ 5.3 HSV
def test_a_wrong_hsv_range_loses_the_lane_and_says_so(cli):
    code, out, err = cli("lane-follow", "--duration", "20", "--hsv-min", "100,100,100", "--hsv-max", "130,255,255",
                         "--json")
    m = json.loads(out)
    assert code == 1
    assert m["line_lost"] and m["frames_yellow"] == 0 and m["frames_white_backup"] == 0
    assert m["failure"].startswith("never found the yellow line in ")
    assert "[100, 100, 100]..[130, 255, 255]" in m["failure"] and "--hsv-tune" in m["failure"]


def test_the_white_backup_only_bridges_the_curves_of_a_yellow_line_seen(cli_json):
    m = cli_json("lane-follow", "--duration", "20")
    assert m["goal_reached"] and not m["line_lost"]
    assert m["frames_yellow"] > 150 and m["frames_white_backup"] > 0  # the curves: the yellow line out of view


def test_a_wrong_hsv_range_loses_the_lane_tasks_points(tmp_path, cli):
    root = correct_submission(tmp_path, ("lane-following",)) / "lane-following"
    params = root / "params.yaml"
    text = params.read_text().replace("hsv_min: [17, 85, 70]", "hsv_min: [100, 100, 100]")
    params.write_text(text.replace("hsv_max: [38, 255, 255]", "hsv_max: [130, 255, 255]"))
    code, out, _ = cli("grade", "lane-following", "--submission", str(root), "--json")
    student = json.loads(out)
    assert code == 1
    assert student["points"] == 0


# ------------------------------------------------------------------------------------ 4.2.2 look-ahead
def test_the_lookahead_sweep_ranks_by_the_tracking_error_and_marks_missed_goals(cli):
    code, out, err = cli("path-follow", "butterfly", "--size", "2", "--lookahead", "0.05,0.5,1.2", "--json")
    m = json.loads(out)
    ranked = [r["lookahead"] for r in m["runs"]]
    assert code == 0, err
    assert ranked[0] == 0.5  # the middle: 0.05 m weaves (and misses its goal), 1.2 m cuts the corners
    assert ranked[-1] == 0.05 and not m["runs"][-1]["goal_reached"]
    by = {r["lookahead"]: r for r in m["runs"]}
    assert by[1.2]["rms_cross_track_estimate_m"] > 2 * by[0.5]["rms_cross_track_estimate_m"]
    assert by[0.05]["rms_cross_track_estimate_m"] > 2 * by[0.5]["rms_cross_track_estimate_m"]
    code, out, _ = cli("path-follow", "butterfly", "--size", "2", "--lookahead", "0.05,0.5")
    assert "MISSED" in out and "look-ahead 0.05 m missed its goal" in out


# ------------------------------------------------------------------------------------ 5.2 Task 4
def test_the_hold_behaviour_is_the_students_stop_sign_hold(tmp_path, cli):
    root = correct_submission(tmp_path, ("stop-sign",)) / "stop-sign"
    code, out, err = cli("grade", "stop-sign", "--submission", str(root), "--task", "5.2-task4-improve", "--json")
    assert code == 0, out + err
    write_block(root, "stop_sign_hold.py", """
        class stop_sign_hold:
            def reset(self):
                pass

            def __call__(self, t, distance_to_sign, new_frame, speed, desired_speed):
                return 0.0 if 0.05 < distance_to_sign < 0.40 else desired_speed   # the sheet's block again
    """)
    code, out, _ = cli("grade", "stop-sign", "--submission", str(root), "--task", "5.2-task4-improve", "--json")
    row = json.loads(out)["tasks"][0]
    assert code == 1
    assert row["uses"] == ["stop_sign_hold"] and row["earned"] < row["points"]


def test_the_template_has_every_block_the_stop_sign_sheet_grades(tmp_path):
    write_template(find_lab("stop-sign"), tmp_path)
    text = (tmp_path / "stop_sign_hold.py").read_text()
    assert "class stop_sign_hold:" in text
    assert "def __call__(self, t, distance_to_sign, new_frame, speed, desired_speed):" in text


# ------------------------------------------------------------------------------------ 6.1 headings
def test_a_lidar_block_gets_headings_ahead_0_left_positive_right_negative(tmp_path, cli):
    """A student's 'h < 0 is right' works: the headings come in (-pi, pi], as the template says."""
    seen = tmp_path / "seen.txt"
    block = write_block(tmp_path, "lidar_steer.py", f"""
        import numpy as np

        def lidar_steer(distances, headings, desired_speed):
            with open({str(seen)!r}, "a") as f:
                f.write(f"{{headings.min()}} {{headings.max()}}\\n")
            near = (distances > 0) & (distances < 1.0) & (np.abs(headings) < 0.6)
            if not near.any():
                return 0.0
            return -0.5 if np.mean(headings[near]) > 0 else 0.5   # obstacle left: steer right
    """)
    code, out, err = cli("avoid", "--strategy", "steer", "--duration", "3", "--block",
                         f"lidar_steer={block}:lidar_steer", "--json")
    assert code == 0, err
    lo, hi = (float(x) for x in seen.read_text().split("\n")[0].split())
    assert -np.pi < lo < -3.0 and 3.0 < hi <= np.pi  # right negative, left positive
    write_template(find_lab("avoid"), tmp_path / "tpl")
    assert "0 straight ahead, + to the left, - to the right, in (-pi, pi]" in (tmp_path / "tpl" / "lidar_steer.py").read_text()


# ------------------------------------------------------------------------------------ the report's stop sign
def test_the_race_car_reports_stop_sign_drives_with_the_students_blocks(tmp_path, cli):
    root = correct_submission(tmp_path, ("stop-sign",)) / "stop-sign"
    code, out, err = cli("grade", "stop-sign", "--submission", str(root), "--task", "report-hough-stop", "--json")
    row = json.loads(out)["tasks"][0]
    assert code == 0, out + err
    assert row["uses"] == ["red_share", "stop_sign_hold"] and row["earned"] == row["points"] == 4
    write_block(root, "red_share.py", """
        def red_share(image_bgr, circle):
            return 0.0   # sees no red: the car never stops
    """)
    code, out, _ = cli("grade", "stop-sign", "--submission", str(root), "--task", "report-hough-stop", "--json")
    row = json.loads(out)["tasks"][0]
    assert code == 1 and row["earned"] == 0


def test_stop_sign_detector_hough_stops_and_drives_on_at_every_speed(cli_json):
    for speed in ("0.3", "1.0"):
        m = cli_json("stop-sign", "--detector", "hough", "--behaviour", "hold", "--speed", speed)
        assert m["detector"] == "hough" and m["goal_reached"]
        assert 0.05 <= m["stop_distance_m"] <= 0.40 and 2.9 <= m["hold_s"] <= 3.3 and m["passed_sign"]
        assert 1.9 <= m["detected_at_m"] < 2.0  # the report counts a sign under 2 m


@pytest.mark.parametrize("lab", LABS, ids=lambda lab: lab.command)
def test_the_template_has_a_file_for_every_block_of_the_lab(lab, tmp_path):
    write_template(lab, tmp_path)
    for spec in lab.blocks:
        path = tmp_path / (f"{spec.name}.py" if spec.fill else f"other-blocks/{spec.name}.py")
        text = path.read_text()
        assert spec.signature in text and f"units: {spec.units}" in text
        assert f'raise NotImplementedError("{spec.name} is not filled in yet' in text


# ------------------------------------------------------------------------------------ 4.2.3 PI tuning
def step(cli_json, kp, ki, realism="lab"):
    return cli_json("path-follow", "line", "--step-response", "--speed", "0.5", "--kp", kp, "--ki", ki,
                    "--realism", realism)


def test_pi_tuning_is_a_trade_off_on_the_lab_car(cli_json):
    """The lab car's ESC (30 ms late, 2 % dead-band): huge gains ring and chatter, tiny ones never
    settle, the middle is best; the ideal drive train has no such penalty."""
    huge, middle, tiny = step(cli_json, "20", "200"), step(cli_json, "5", "20"), step(cli_json, "0.05", "0.2")
    assert huge["throttle_chatter"] > 0.05 and huge["throttle_saturated_s"] > 3.0
    assert huge["settling_time_s"] is None or huge["settling_time_s"] > 4.0
    assert middle["settling_time_s"] < 1.5 and middle["throttle_chatter"] < 0.01
    assert tiny["settling_time_s"] is None and abs(tiny["steady_state_error_mps"]) > 0.02
    ideal = step(cli_json, "20", "200", "ideal")
    assert ideal["settling_time_s"] < 0.5 and ideal["throttle_chatter"] < 0.01
