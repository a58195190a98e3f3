"""The bugs a student meets and the failures that were silent (issue 27, items 4 and 5): each test
fails on the code before its fix."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


# --- a folder named like a shipped world does not shadow it ----------------------------------
def test_a_folder_named_like_a_shipped_world_does_not_break_the_lab(cli, tmp_path, monkeypatch):
    """`qcarlab template stop-sign --out stop-sign` makes stop-sign/; every run from the folder
    above then said '--world stop-sign: is a folder', even without --world."""
    (tmp_path / "studio").mkdir()  # lidar-scan's default world
    (tmp_path / "studio" / "stop_sign.py").write_text("# a student's work\n")
    monkeypatch.chdir(tmp_path)
    code, out, err = cli("lidar-scan", "--json")  # no --world: the default 'studio'
    assert code == 0, err
    assert json.loads(out)["world"] == "studio"
    code, out, err = cli("lidar-scan", "--world", "studio", "--json")  # the name: the shipped world
    assert code == 0, err
    code, out, err = cli("lidar-scan", "--world", "./studio")  # a path: the folder, refused in one line
    assert code == 2 and "is a folder" in err and len(err.strip().splitlines()) == 1


def test_a_path_like_world_argument_is_a_file(tmp_path, monkeypatch):
    from qcarlab.errors import InputError
    from qcarlab.experiments.worlds import load_world, looks_like_path

    for text in ("./studio", "studio/", "maps/studio", "studio.yaml", "STUDIO.YML", "~/studio", ".studio"):
        assert looks_like_path(text), text
    assert not looks_like_path("studio") and not looks_like_path("stop-sign")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "track").write_text("not a world")  # a file named like a shipped world: the name wins
    assert load_world("track").name == "track"
    with pytest.raises(InputError, match="no such world file"):
        load_world("./nowhere.yaml")


# --- sheet names, command names and sections --------------------------------------------------
@pytest.mark.parametrize("name, sheet", [("avoid", "obstacle-avoidance"), ("io-test", "basic-io"),
                                         ("path-follow", "path-following"), ("lane-follow", "lane-following"),
                                         ("5.1", "stop-sign"), ("6.1", "obstacle-avoidance"),
                                         ("ping", "connectivity"), ("lidar-scan", "lidar"),
                                         ("obstacle-avoidance", "obstacle-avoidance")])
def test_a_sheet_is_found_by_its_commands_name_and_section(name, sheet):
    """`qcarlab grade avoid` said: unknown lab sheet 'avoid'."""
    from qcarlab.grading.sheet import find_sheet

    assert find_sheet(name).stem == sheet


def test_a_command_two_sheets_run_is_one_clear_line(cli):
    code, out, err = cli("labs", "camera")
    assert code == 2 and "csi-cameras" in err and "rgbd-camera" in err and len(err.strip().splitlines()) == 1
    code, out, err = cli("labs", "avoid", "--json")
    assert code == 0, err
    assert "obstacle-avoidance" in out


def test_the_template_readme_says_how_to_grade_yourself(tmp_path):
    from qcarlab.experiments.labs import find_lab, write_template

    for command in ("stop-sign", "avoid", "io-test"):
        lab = find_lab(command)
        write_template(lab, tmp_path / command)
        text = (tmp_path / command / "README.md").read_text()
        assert f"qcarlab grade {lab.sheet} --submission ." in text


# --- --pose truth: the estimate is not labelled the truth ------------------------------------
def test_pose_truth_does_not_label_the_bicycle_estimate_truth(cli, tmp_path, monkeypatch):
    """Under --pose truth the bicycle model's estimate (still logged, unused) was labelled
    'estimate (truth)' in the figure and 'pose estimate drift (truth)' in the summary."""
    from qcarlab import plots

    labels = []
    save = plots._save

    def keep(fig, file):
        if Path(file).name == "path.png":
            labels.extend(fig.axes[0].get_legend_handles_labels()[1])
        return save(fig, file)

    monkeypatch.setattr(plots, "_save", keep)
    code, out, err = cli("path-follow", "line", "--length", "1", "--pose", "truth", "--out", tmp_path / "run")
    assert code == 0, err
    text = " ".join(out.split())
    assert "drift (truth)" not in text and "unused" in text
    estimate = [lb for lb in labels if lb.startswith("estimate")]
    assert estimate and all("(truth)" not in lb and "unused" in lb for lb in estimate), labels
    assert "driven (truth)" in labels


# --- lidar-scan --target: the box is measured, out to the sheet's 12 m ------------------------
@pytest.mark.parametrize("target", [8.0, 12.0])
def test_lidar_target_beyond_the_studio_is_measured_not_the_wall(cli, target):
    """--target 8 put the box behind the studio's wall (4.9 m ahead) and measured the wall;
    --target 12 (the sheet's range) was refused."""
    code, out, err = cli("lidar-scan", "--target", str(target), "--scans", "3", "--json")
    assert code == 0, err
    m = json.loads(out)
    assert m["target"]["measured_m"] == pytest.approx(target, abs=0.05)
    assert m["nearest_obstacle_m"] == pytest.approx(target, abs=0.1)  # nothing else in the way
    assert m["world"] == "open-hall" and "open hall" in err


def test_lidar_target_in_a_chosen_world_without_room_is_refused(cli):
    code, out, err = cli("lidar-scan", "--target", "8", "--world", "studio")
    assert code == 2 and "4.9" in err and "room" in err and len(err.strip().splitlines()) == 1
    code, out, err = cli("lidar-scan", "--target", "1.5", "--json")  # it fits: the studio, as before
    assert code == 0 and json.loads(out)["world"] == "studio"
    assert json.loads(out)["target"]["measured_m"] == pytest.approx(1.5, abs=0.02)


# --- grades: a value the run measured none of, and the run's own failure sentence -------------
def _failed_step_row():
    from qcarlab.grading.checks import check_metric
    from qcarlab.grading.sheet import MetricCriterion

    results = {"settling_time_s": None, "min_clearance_m": None, "overshoot_pct": 3.0}
    verdicts = [check_metric(results, MetricCriterion("settling_time_s", max=3.0)),
                check_metric(results, MetricCriterion("min_clearance_m", min=0.05)),
                check_metric(results, MetricCriterion("rise_time_s", max=1.0)),
                check_metric(results, MetricCriterion("overshoot_pct", max=10.0))]
    failure = "collision at (0.00, -4.71) m near (0.00, -5.00), t = 5.12 s"
    row = {"sheet": "path-following", "id": "pi-tuning", "kind": "scenario", "command": "qcarlab path-follow",
           "uses": [], "status": "failed", "passed": False, "problem": None,
           "criteria": [v.as_dict() for v in verdicts], "points": 4.0, "earned": 1.0, "seconds": 2.0,
           "run_failure": failure}
    student = {"student": "me", "tasks": [row], "passed": 0, "total": 1, "points": 1.0, "max_points": 4.0,
               "skipped": 0, "errors": 0}
    return row, student, failure


def test_a_value_never_measured_is_said_in_words():
    """'settling_time_s is None, not a number', and a blank for a missing minimum clearance."""
    row, _, _ = _failed_step_row()
    settle, clearance, rise, overshoot = row["criteria"]
    assert settle["reason"] == "settling_time_s: never settled" and settle["missing"] == "never settled"
    assert clearance["reason"] == "min_clearance_m: not measured" and clearance["missing"] == "not measured"
    assert rise["missing"] == "not measured" and "not in the results" in rise["reason"]
    assert overshoot["passed"] and "missing" not in overshoot
    assert all("None" not in (c["reason"] or "") for c in row["criteria"])


def test_the_grade_table_html_and_junit_show_the_words_and_the_runs_failure(tmp_path, capsys):
    from qcarlab.cli.grade import _print
    from qcarlab.grading.report import write_html, write_junit
    from qcarlab.grading.sheet import find_sheet, load_sheet

    row, student, failure = _failed_step_row()
    _print([load_sheet(find_sheet("path-following"))], [student], single=True)
    table = " ".join(capsys.readouterr().out.split())
    assert "never settled" in table and "not measured" in table
    assert "collision at (0.00, -4.71) m" in table
    html = write_html(tmp_path / "report.html", "grades", [student], {}, {}).read_text()
    assert "never settled" in html and "not measured" in html and "collision at (0.00, -4.71) m" in html
    xml = write_junit(tmp_path / "junit.xml", [student], single=True).read_text()
    assert xml.count(failure) >= 3  # in each failed criterion's failure message
    assert "got None" not in xml and "never settled" in xml


# --- keyboard-drive collides like every lab, and keeps --max-throttle --------------------------
def _drive_into_the_wall(max_throttle: float, seconds: float):
    from qcarlab.car import open_car
    from qcarlab.experiments.keyboard_drive import DriveConfig, keyboard_drive

    car = open_car("sim", world="studio", seed=1)  # walls at +-5 m; the car at the centre heading -Y
    frames = []

    def keys(t: float):
        return ["w"] * 20 if not frames else (["q"] if t > seconds else [])

    cfg = DriveConfig(max_throttle=max_throttle, throttle_step=min(0.03, max_throttle), throttle_ramp=3.0)
    summary = keyboard_drive(car, cfg, keys=keys, on_frame=frames.append, rate=100.0)
    return car, summary, frames


def test_keyboard_drive_stops_at_a_wall():
    """It drove on through the walls (x = +4.05 m with the walls at +-3.25 m)."""
    car, summary, frames = _drive_into_the_wall(0.3, 8.0)
    assert summary.reason == "collision" and summary.collision.startswith("collision at"), summary
    assert car.truth().y > -5.0 + 0.2  # it stopped at the wall (at -5 m), not past it
    assert car.read().throttle == 0.0
    assert summary.duration_s < 6.0  # ended by the wall, not by the q at 8 s
    assert max(f.state.throttle for f in frames) <= 0.3


def test_keyboard_drive_keeps_max_throttle():
    _, summary, frames = _drive_into_the_wall(0.05, 2.0)
    assert summary.reason == "quit"
    assert max(f.state.throttle for f in frames) == pytest.approx(0.05)
    assert summary.top_speed_mps < 0.5  # the cap holds the speed down (0.1 holds about 1 m/s)


def test_keyboard_drive_into_a_wall_exits_1_with_one_line():
    from ptyrun import PtyRun

    run = PtyRun("keyboard-drive", "--world", "track", "--max-throttle", "0.3", "--ramp", "3", "--no-map")
    run.wait_for("speed")
    run.send(b"w" * 10)
    rc = run.finish(timeout=60.0)
    text = run.text
    assert rc == 1, text[-2000:]
    assert run.after == run.before
    errors = [ln for ln in text.splitlines() if "collision at" in ln]
    assert len(errors) == 1 and "keyboard-drive" in errors[0] and "the car is stopped" in errors[0], text[-2000:]
    assert "Traceback" not in text


# --- a student's block stuck in a loop: named in one line, the run ended, the car stopped ------
STUCK = '''
def pure_pursuit(pose, target, lookahead, wheelbase):
    """Turn towards the target."""
    steering = 0.0
    while abs(steering) < 10.0:  # never: a bug that loops for ever
        try:
            steering = steering * 1.0
        except Exception:  # swallows what it can; the watchdog's alarm is not an Exception
            pass
    return steering
'''

SLEEPS = '''
import time


def speed_controller(v_ref, v_measured, dt):
    """Wait for the speed to come (a sleep in a block stalls the whole car)."""
    time.sleep(3600)
    return 0.0
'''


def test_a_block_stuck_in_a_loop_ends_the_run_with_the_car_stopped(tmp_path, monkeypatch):
    """It hung the lab for ever, with no message."""
    import time

    from qcarlab.blocks import StudentBlockError, resolve_student_blocks
    from qcarlab.car import open_car
    from qcarlab.experiments.path_follow import FollowConfig, PathFollowingLab, follow_path
    from qcarlab.paths import line

    monkeypatch.setenv("QCARLAB_BLOCK_TIMEOUT_S", "0.5")
    for name, text in (("pure_pursuit", STUCK), ("speed_controller", SLEEPS)):
        (tmp_path / f"{name}.py").write_text(text)
        mine = resolve_student_blocks(PathFollowingLab.specs(), "path-follow", [tmp_path / f"{name}.py"])
        car = open_car("sim", world="studio", seed=0)
        t0 = time.monotonic()
        with pytest.raises(StudentBlockError) as exc:
            follow_path(car, line(2.0, 5), FollowConfig(), blocks=mine)
        assert time.monotonic() - t0 < 10.0
        text = str(exc.value)
        assert len(text.splitlines()) == 1 and f"block {name}" in text and "has not returned after 0.5 s" in text
        assert f"{name}.py:" in text  # where it was stuck: the student's own line
        assert car.read().throttle == 0.0  # the car stopped


def test_a_stuck_block_is_one_line_and_exit_1_from_the_command(cli, tmp_path, monkeypatch):
    monkeypatch.setenv("QCARLAB_BLOCK_TIMEOUT_S", "0.5")
    (tmp_path / "pure_pursuit.py").write_text(STUCK)
    code, out, err = cli("path-follow", "line", "--length", "1", "--use", tmp_path / "pure_pursuit.py")
    assert code == 1
    errors = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(errors) == 1 and "pure_pursuit" in errors[0] and "has not returned" in errors[0], err
    assert "Traceback" not in err


def test_a_stuck_block_is_named_when_graded_in_its_own_process(cli, tmp_path, monkeypatch):
    """Graded, the block runs in the student's process: the trusted side stops waiting and ends it."""
    from qcarlab.experiments.labs import find_lab, write_template

    monkeypatch.setenv("QCARLAB_BLOCK_TIMEOUT_S", "0.5")
    write_template(find_lab("stop-sign"), tmp_path / "me")
    (tmp_path / "me" / "stop_sign.py").write_text('''
def stop_sign(distance_to_sign, desired_speed):
    while distance_to_sign > 0.4:
        pass
    return 0.0
''')
    code, out, err = cli("grade", "stop-sign", "--submission", tmp_path / "me", "--task", "5.2-task1-block", "--json")
    assert code == 1
    reasons = [c["reason"] for c in json.loads(out)["tasks"][0]["criteria"] if not c["passed"]]
    assert any("block stop_sign" in r and "has not returned after 0.5 s" in r for r in reasons), reasons


# --- blocks never called and options a student's block makes meaningless: one warning each -----
CARROT = '''
import math


def follow_the_carrot(pose, target, k_carrot):
    """Steer towards the carrot."""
    return max(-0.5, min(0.5, k_carrot * (math.atan2(target[1] - pose[1], target[0] - pose[0]) - pose[2])))
'''

MY_PI = '''
class speed_controller:
    def __init__(self):
        self.reset()

    def reset(self):
        self.i = 0.0

    def __call__(self, v_ref, v_measured, dt):
        e = v_ref - v_measured
        self.i += e * dt
        return max(-0.3, min(0.3, 0.1 * v_ref + 0.3 * e + 1.0 * self.i))
'''


def _warnings(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if ": warning: " in ln]


def test_a_block_given_but_never_called_is_one_warning(cli, tmp_path):
    """A student's follow_the_carrot with the default controller was listed as 'your blocks' and
    called 0 times, silently."""
    (tmp_path / "carrot.py").write_text(CARROT)
    code, out, err = cli("path-follow", "line", "--length", "1", "--use", tmp_path / "carrot.py", "--json")
    assert code == 0, err
    assert json.loads(out)["student_blocks"]["follow_the_carrot"]["calls"] == 0
    warnings = _warnings(err)
    assert len(warnings) == 1 and "follow_the_carrot" in warnings[0] and "never called" in warnings[0]
    assert "--controller carrot" in warnings[0]
    code, out, err = cli("path-follow", "line", "--length", "1", "--use", tmp_path / "carrot.py",
                         "--controller", "carrot", "--json")
    assert code == 0 and not _warnings(err), err


def test_options_a_students_block_makes_meaningless_are_one_warning_each(cli, tmp_path):
    """--kp 5 --ki 20 were silently ignored with the student's speed_controller."""
    (tmp_path / "pi.py").write_text(MY_PI)
    step = ("path-follow", "line", "--step-response", "--speed", "0.5", "--use", tmp_path / "pi.py", "--json")
    code, out, err = cli(*step, "--kp", "5", "--ki", "20")
    assert code == 0, err
    warnings = _warnings(err)
    assert len(warnings) == 2, err
    assert "--kp is not used" in warnings[0] and "--ki is not used" in warnings[1]
    assert all("speed_controller" in w for w in warnings)
    code, out, err = cli(*step)  # the defaults, not typed: nothing to warn of
    assert code == 0 and not _warnings(err), err
    code, out, err = cli("path-follow", "line", "--step-response", "--speed", "0.5", "--kp", "0.5", "--json")
    assert code == 0 and not _warnings(err), err  # qcarlab's controller: --kp is used


# --- io-test reports what the run's block made of the encoder --------------------------------
DOUBLE = '''
def basic_speed_estimation(counts_per_s):
    """Twice the speed (a wrong gear ratio)."""
    return 2.0 * counts_per_s * 6.866e-6
'''


def test_io_test_distance_and_live_speed_come_from_the_students_block(cli, tmp_path):
    """io-test's distance_m was the package's counts x metres-per-count, whatever the block said."""
    (tmp_path / "bse.py").write_text(DOUBLE)
    base = ("io-test", "--on-floor", "--throttle", "0.1", "--duration", "1", "--json")
    code, out, err = cli(*base)
    assert code == 0, err
    ours = json.loads(out)
    code, out, err = cli(*base, "--use", tmp_path / "bse.py")
    assert code == 0, err
    mine = json.loads(out)
    assert mine["encoder_counts"] == ours["encoder_counts"]  # the same drive
    assert mine["mean_speed_mps"] == pytest.approx(2.0 * ours["mean_speed_mps"], rel=1e-3)
    assert mine["distance_m"] == pytest.approx(2.0 * ours["distance_m"], rel=1e-3)
    assert ours["distance_m"] == pytest.approx(ours["truth"]["wheel_distance_m"], rel=0.02)

    from qcarlab.car import open_car
    from qcarlab.experiments.io_test import io_test

    seen = []
    with open_car("sim", seed=0) as car:
        io_test(car, 0.1, 0.0, (), 0.5, on_tick=lambda t, r, cmd, v: seen.append((r.tach, v)),
                blocks={"basic_speed_estimation": lambda c: 2.0 * c * 6.866e-6})
    assert seen and all(v == pytest.approx(2.0 * tach * 6.866e-6) for tach, v in seen)
