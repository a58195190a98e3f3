"""The student's lab (issue 9): every lab a diagram of named blocks a student replaces with their own.

Each test runs the lab as a student would: a template, their file, the command line (or the
Python API), and checks what *their* code made the car do.
"""

from __future__ import annotations

import json
import re
import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

import qcarlab
from qcarlab import paths
from qcarlab.car.sim import SimCar
from qcarlab.experiments.avoid import AvoidConfig, avoid
from qcarlab.experiments.labs import LABS
from qcarlab.experiments.loop import Step, run_loop
from qcarlab.experiments.path_follow import FollowConfig, follow_path
from qcarlab.car.base import Command


def write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(textwrap.dedent(text))
    return path


# --------------------------------------------------------------------------------------------
# templates
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("lab", [lab.command for lab in LABS])
def test_template_writes_a_workspace_and_unfilled_blocks_exit_2(cli, tmp_path, lab):
    code, out, err = cli("template", lab, "--out", tmp_path / "ws")
    assert code == 0, err
    info = next(x for x in LABS if x.command == lab)
    for name in ["params.yaml", "answers.md", "README.md"] + [f"{b.name}.py" for b in info.to_fill]:
        assert (tmp_path / "ws" / name).is_file(), name
    answers = (tmp_path / "ws" / "answers.md").read_text()
    assert all(q[:30] in answers for q in info.questions)
    for spec in info.to_fill:
        text = (tmp_path / "ws" / f"{spec.name}.py").read_text()
        assert spec.signature in text and spec.section in text and "NotImplementedError" in text
        args = ("line",) if lab == "path-follow" else ()
        code, out, err = cli(lab, *args, "--use", tmp_path / "ws" / f"{spec.name}.py")
        assert code == 2
        line = err.strip().splitlines()[-1]
        assert f"{spec.name}.py" in line and spec.name in line and spec.section in line and "not filled in" in line
    # a second template into the same folder does not overwrite the student's work
    code, out, err = cli("template", lab, "--out", tmp_path / "ws")
    assert code == 2 and "would overwrite" in err


def test_params_file_from_the_template_is_accepted_and_the_command_line_wins(cli, tmp_path):
    assert cli("template", "stop-sign", "--out", tmp_path)[0] == 0
    params = tmp_path / "params.yaml"
    text = re.sub(r"  hsv_min: .*", "  hsv_min: [170, 100, 100]", params.read_text())  # the student's choices
    text = re.sub(r"  hsv_max: .*", "  hsv_max: [10, 255, 255]", text)
    params.write_text(text.replace("speed: 0.3", "speed: 0.5").replace("far: 0.4", "far: 0.6"))
    code, out, err = cli("stop-sign", "--params", params, "--json")
    assert code == 0, err
    m = json.loads(out)
    assert m["config"]["speed"] == 0.5 and m["config"]["far"] == 0.6
    code, out, err = cli("stop-sign", "--params", params, "--speed", "0.3", "--json")
    m = json.loads(out)
    assert m["config"]["speed"] == 0.3 and m["config"]["far"] == 0.6  # typed on the command line: it wins
    write(tmp_path, "bad.yaml", "lab:\n  lookahed: 0.3\n")
    code, out, err = cli("stop-sign", "--params", tmp_path / "bad.yaml")
    assert code == 2 and "unknown tunable 'lookahed'" in err


# --------------------------------------------------------------------------------------------
# stop-sign: the student's window, not the reference's
# --------------------------------------------------------------------------------------------
def test_stop_sign_with_the_students_window_stops_where_the_student_said(cli, tmp_path):
    assert cli("template", "stop-sign", "--out", tmp_path / "mylab")[0] == 0
    write(tmp_path / "mylab", "stop_sign.py", """
        def stop_sign(distance_to_sign, desired_speed):
            if 0.5 < distance_to_sign < 1.0:   # a wrong window: stops far too early
                return 0.0
            return desired_speed
    """)
    code, out, err = cli("stop-sign", "--use", tmp_path / "mylab" / "stop_sign.py", "--json")
    assert code == 0, err
    mine = json.loads(out)
    assert "your blocks: stop_sign" in err and mine["student_blocks"]["stop_sign"]["calls"] > 100
    ref = json.loads(cli("stop-sign", "--json")[1])
    assert 0.05 <= ref["stop_distance_m"] <= 0.40
    # the camera reads 2.25 cm more than the bumper distance; the car stops inside the student's window
    assert 0.45 <= mine["stop_distance_m"] <= 1.0 and mine["stop_distance_m"] > ref["stop_distance_m"] + 0.3


@pytest.mark.parametrize("body, words", [
    ("return 1 / (distance_to_sign - distance_to_sign)", ["ZeroDivisionError", "stop_sign.py:3"]),
    ("return float('nan')", ["returned nan"]),
    ("return (desired_speed, 0.0)", ["returned (0.3, 0.0)", "expected a number"]),
    ("return 'go'", ["returned 'go'"]),
    ("return 50.0", ["out of range"]),
    ("import sys; sys.exit(3)", ["sys.exit"]),
])
def test_a_failing_student_block_stops_the_run_with_one_clear_error(cli, tmp_path, body, words):
    path = write(tmp_path, "stop_sign.py", f"""
        def stop_sign(distance_to_sign, desired_speed):
            {body}
    """)
    code, out, err = cli("stop-sign", "--use", path)
    assert code == 1, err
    assert "block stop_sign" in err and "the car was stopped" in err
    for w in words:
        assert w in err
    assert "qcarlab/" not in err and "Traceback (most recent" not in err  # the student's frames only


@pytest.mark.parametrize("lab, block, body, words", [
    ("lane-follow", "image_selector(image)", "return image[::2]",
     ["block image_selector returned an array of shape (240, 640, 3)", "shape (480, 640, 3), like its input"]),
    ("lane-follow", "color_thresholding_hsv(image_bgr)", "return image_bgr[:, :, 0] > 100",
     ["dtype bool", "a uint8 mask (0/255) of shape (480, 640)"]),
    ("stop-sign", "color_thresholding_hsv(image_bgr)", "return None",
     ["block color_thresholding_hsv returned None", "a uint8 mask"]),
])
def test_an_image_block_with_the_wrong_shape_or_type_names_the_block(cli, tmp_path, lab, block, body, words):
    # (it used to surface later, inside the lab, as an "internal error" about boolean indices)
    path = write(tmp_path, "blocks.py", f"""
        def {block}:
            {body}
    """)
    code, out, err = cli(lab, "--use", path, *(["--duration", "2"] if lab == "lane-follow" else []))
    assert code == 1, err
    assert "internal error" not in err and "the car was stopped" in err
    for w in words:
        assert w in err


def test_a_failing_block_leaves_the_car_stopped():
    def bad(distance_to_sign, desired_speed):
        raise RuntimeError("boom")

    from qcarlab.blocks import StudentBlockError
    from qcarlab.experiments.stop_sign import StopSignConfig, run_stop_sign

    with qcarlab.open_car("sim", world="stop-sign") as car:
        car.write(0.2, 0.1)
        with pytest.raises(StudentBlockError, match="boom"):
            run_stop_sign(car, StopSignConfig(), blocks={"stop_sign": bad})
        r = car.read()
        assert r.throttle == 0.0 and r.steering == 0.0


# --------------------------------------------------------------------------------------------
# avoid: the student's lidar_stop, lidar_steer and lidar_avoid
# --------------------------------------------------------------------------------------------
def test_avoid_with_the_students_lidar_stop_stops_at_their_distance(cli, tmp_path):
    path = write(tmp_path, "lidar.py", """
        import numpy as np

        def lidar_stop(distances, headings, desired_speed):
            ahead = (distances > 0) & (np.abs(headings) < 0.2)
            return 0.0 if ahead.any() and distances[ahead].min() < 0.9 else desired_speed
    """)
    code, out, err = cli("avoid", "--strategy", "stop", "--use", path, "--duration", "8", "--json")
    assert code == 0, err
    mine = json.loads(out)
    ref = json.loads(cli("avoid", "--strategy", "stop", "--duration", "8", "--json")[1])
    assert mine["collisions"] == 0 and ref["collisions"] == 0
    assert ref["stopped_before_obstacle"] < 0.45
    assert 0.75 < mine["stopped_before_obstacle"] < 0.95  # from the LIDAR, as the student measured it


def test_avoid_with_the_students_lidar_steer_and_lidar_avoid_class(tmp_path):
    calls = []

    def lidar_steer(distances, headings, desired_speed):
        calls.append(desired_speed)
        return 0.25

    with qcarlab.open_car("sim", world="obstacles", seed=1) as car:
        steer = avoid(car, AvoidConfig(strategy="steer", duration=2.0), blocks={"lidar_steer": lidar_steer})
    assert calls and set(calls) == {0.3}
    assert np.allclose(steer.logs["log.csv"]["steering"][20:], 0.25)
    assert steer.metrics["student_blocks"]["lidar_steer"]["calls"] == len(calls)

    path = write(tmp_path, "avoid.py", """
        class lidar_avoid:
            def reset(self):
                self.state = "cruise"
                self.scans = 0

            def __call__(self, distances, headings, desired_speed):
                self.scans += 1
                near = ((distances > 0) & (abs(headings) < 0.4) & (distances < 0.8)).any()
                self.state = "stop" if near else "cruise"
                return (0.0, 0.0) if near else (desired_speed, 0.0)
    """)
    from qcarlab.blocks import resolve_student_blocks
    from qcarlab.experiments.avoid import AvoidLab

    mine = resolve_student_blocks(AvoidLab.specs(), "avoid", [path])
    with qcarlab.open_car("sim", world="obstacles", seed=1) as car:
        res = avoid(car, AvoidConfig(strategy="student", duration=6.0), blocks=mine)
    m = res.metrics
    assert m["collisions"] == 0 and m["stopped_before_obstacle"] is not None
    assert set(m["time_in_state_s"]) <= {"cruise", "stop", ""} and m["time_in_state_s"]["stop"] > 1.0


def test_strategy_student_needs_the_students_lidar_avoid(cli):
    code, out, err = cli("avoid", "--strategy", "student")
    assert code == 2 and "lidar_avoid" in err and "--use" in err


# --------------------------------------------------------------------------------------------
# path-follow: the student's pure_pursuit and speed_controller
# --------------------------------------------------------------------------------------------
def test_path_follow_with_the_students_pure_pursuit_and_speed_controller(cli, tmp_path):
    assert cli("template", "path-follow", "--out", tmp_path)[0] == 0
    write(tmp_path, "pure_pursuit.py", """
        import math

        def pure_pursuit(pose, target, lookahead, wheelbase):
            x, y, yaw = pose
            alpha = math.atan2(target[1] - y, target[0] - x) - yaw
            return math.atan2(2 * wheelbase * math.sin(alpha), lookahead)
    """)
    write(tmp_path, "speed_controller.py", """
        class speed_controller:
            def reset(self):
                self.integral = 0.0

            def __call__(self, v_ref, v_measured, dt):
                if v_ref == 0 and abs(v_measured) < 0.01:
                    return 0.0
                e = v_ref - v_measured
                self.integral += 2.0 * e * dt
                return max(-0.3, min(0.3, 0.1 * v_ref + 0.5 * e + self.integral))
    """)
    code, out, err = cli("path-follow", "circle", "--use", tmp_path, "--json")
    assert code == 0, err
    m = json.loads(out)
    assert set(m["student_blocks"]) == {"pure_pursuit", "speed_controller"}
    # the lab car's dead reckoning drifts: it stops where its own estimate puts the end
    assert m["rms_cross_track_estimate_m"] < 0.03 and m["rms_cross_track_m"] < 0.04 and m["reached_by_estimate"]
    # a student's steering that never turns: the car leaves the circle and the run says so (exit 1)
    write(tmp_path, "pure_pursuit.py", """
        def pure_pursuit(pose, target, lookahead, wheelbase):
            return 0.0
    """)
    code, out, err = cli("path-follow", "circle", "--use", tmp_path / "pure_pursuit.py", "--max-time", "30", "--json")
    assert code == 1 and "goal missed" in err
    m = json.loads(out)
    assert m["goal_reached"] is False and (m.get("collision") or m.get("left_world")) and m["completion"] < 0.5


def test_the_python_api_takes_the_same_mapping():
    seen = []

    def my_pp(pose, target, lookahead, wheelbase):
        seen.append((pose, tuple(target), lookahead, wheelbase))
        from qcarlab.control.steering import pure_pursuit

        return pure_pursuit(pose, target, lookahead, wheelbase)

    path = paths.line(3.0)
    with qcarlab.open_car("sim") as car:
        res = follow_path(car, path, FollowConfig(), blocks={"pure_pursuit": my_pp})
    assert res.metrics["stopped_at_goal"] and len(seen) > 100
    pose, target, la, L = seen[50]
    assert la == 0.3 and L == pytest.approx(0.256)
    # the pose is the rear axle's: L/2 behind the centre, heading -Y from (0, 0)
    assert pose[1] == pytest.approx(res.logs["log.csv"]["est_y"][50] + L / 2, abs=1e-9)


def test_a_path_behind_the_car_hits_the_wall_and_exits_1(cli, tmp_path):
    path = write(tmp_path, "behind.csv", "x,y\n0,0\n0,2\n0,4\n0,6\n")
    code, out, err = cli("path-follow", path, "--json")
    assert code == 1 and "collision" in err
    assert json.loads(out)["collision"]["y"] < -4.0  # it drove forward (-Y) into the studio's wall


# --------------------------------------------------------------------------------------------
# over TCP: the student's code runs on the client
# --------------------------------------------------------------------------------------------
def test_student_blocks_over_tcp_give_the_same_run(cli, tmp_path):
    from qcarlab.net.server import CarServer
    from qcarlab.sim.world import load_world

    path = write(tmp_path, "stop_sign.py", """
        def stop_sign(distance_to_sign, desired_speed):
            return 0.0 if 0.5 < distance_to_sign < 1.0 else desired_speed
    """)
    server = CarServer(SimCar(seed=0, world=load_world("stop-sign")), "127.0.0.1", 0, watchdog=5.0).start()
    try:
        code, out, err = cli("stop-sign", "--use", path, "--car", server.uri, "--json")
    finally:
        server.stop()
    assert code == 0, err
    remote = json.loads(out)
    local = json.loads(cli("stop-sign", "--use", path, "--realism", "ideal", "--json")[1])  # the server's
    assert remote["stop_distance_m"] is None  # no truth over TCP; the camera's reading is the measure
    assert remote["measured_distance_m"] == pytest.approx(local["measured_distance_m"], abs=1e-9)
    assert 0.5 < remote["measured_distance_m"] < 1.0


# --------------------------------------------------------------------------------------------
# blocks, the loop
# --------------------------------------------------------------------------------------------
def test_blocks_lists_each_labs_blocks_with_signature_units_and_section(cli):
    code, out, err = cli("blocks", "avoid", "--json")
    assert code == 0
    rows = {r["name"]: r for r in json.loads(out)["blocks"]}
    assert rows["lidar_stop"]["signature"] == "lidar_stop(distances, headings, desired_speed) -> speed_cmd"
    assert rows["lidar_avoid"]["stateful"] and "6.1" in rows["lidar_avoid"]["section"]
    code, out, err = cli("blocks", "5.2")
    assert code == 0 and "stop_sign(distance_to_sign, desired_speed) -> speed_cmd" in out
    code, out, err = cli("blocks", "moon")
    assert code == 2 and "unknown lab" in err


class _PacedCar(SimCar):
    """A simulator paced in real time whose 10th read stalls for 0.2 s (a slow sensor read)."""

    def __init__(self):
        super().__init__(realtime=True)
        self.reads = 0

    def read(self):
        import time

        self.reads += 1
        if self.reads == 10:
            time.sleep(0.2)
        return super().read()


def test_a_late_tick_gives_the_real_dt_and_is_counted():
    dts = []

    class Lab:
        def step(self, t, r, dt):
            dts.append(dt)
            return Step(Command(0.0, 0.0), {"dt": dt})

    car = _PacedCar()
    with car:
        log = run_loop(car, Lab(), duration=0.3, rate=100.0)
    assert log.overruns >= 1 and log.worst_tick_s >= 0.19
    late = max(dts)
    assert late >= 0.19  # the block is told the real time since the last tick ...
    after = np.cumsum(dts[dts.index(late) + 1:])
    # ... and no burst of catch-up ticks follows: about 5 ticks in the next 50 ms, not the 20 missed
    assert np.count_nonzero(after <= 0.05) <= 9
    assert np.asarray(log.arrays()["dt"]).max() == late


def test_control_perception_and_sim_do_not_import_upwards():
    import ast

    root = Path(qcarlab.__file__).parent
    banned = {"control": ("qcarlab.car", "qcarlab.sim", "qcarlab.net", "qcarlab.cli", "qcarlab.experiments"),
              "perception": ("qcarlab.car", "qcarlab.sim", "qcarlab.net", "qcarlab.cli", "qcarlab.experiments"),
              "sim": ("qcarlab.control", "qcarlab.perception", "qcarlab.cli", "qcarlab.experiments",
                      "qcarlab.net")}
    bad = []
    for package, prefixes in banned.items():
        for file in (root / package).rglob("*.py"):
            for node in ast.walk(ast.parse(file.read_text())):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module:
                    names = [node.module]
                bad += [f"{file.relative_to(root)} imports {n}" for n in names if n.startswith(prefixes)]
    assert not bad, bad


def test_no_package_cycles_car_net_and_sim_world_raster():
    import ast

    root = Path(qcarlab.__file__).parent

    def imports(file):
        out = []
        for node in ast.walk(ast.parse(file.read_text())):
            if isinstance(node, ast.Import):
                out += [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                out.append(node.module)
        return out

    bad = [f"car/{f.name} imports {n}" for f in (root / "car").glob("*.py") for n in imports(f)
           if n.startswith("qcarlab.net")]
    bad += [f"wire/{f.name} imports {n}" for f in (root / "wire").glob("*.py") for n in imports(f)
            if n.startswith(("qcarlab.net", "qcarlab.car"))]
    bad += [f"sim/world.py imports {n}" for n in imports(root / "sim" / "world.py")
            if n.startswith(("qcarlab.sim.raster", "qcarlab.sim.render", "qcarlab.sim.camera", "qcarlab.sim.lidar"))]
    assert not bad, bad


def test_cli_does_not_import_the_simulator():
    import ast

    root = Path(qcarlab.__file__).parent / "cli"
    bad = []
    for file in root.glob("*.py"):
        for node in ast.walk(ast.parse(file.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("qcarlab.sim"):
                bad.append(f"{file.name} imports {node.module}")
    assert not bad, bad


def test_run_without_student_blocks_is_unchanged_by_the_redesign(cli_json):
    # the figures the README states for the reference blocks
    m = cli_json("stop-sign")
    assert m["student_blocks"] == {} and m["goal_reached"] and 0.15 <= m["stop_distance_m"] <= 0.25
    assert math.isclose(m["stop_distance_m"], 0.204, abs_tol=0.01)  # the camera 13 cm behind the bumper


def test_a_block_slower_than_the_tick_on_a_real_time_car_is_reported(cli, tmp_path):
    path = write(tmp_path, "slow.py", """
        import time

        def basic_speed_estimation(counts_per_s):
            time.sleep(0.015)          # longer than the 10 ms tick at 100 Hz
            return counts_per_s * 6.866e-6
    """)
    code, out, err = cli("io-test", "--use", path, "--realtime", "--duration", "0.3", "--json")
    assert code == 0, err
    timing = json.loads(out)["student_blocks"]["basic_speed_estimation"]
    assert timing["over_budget"] >= 10 and timing["worst_s"] >= 0.015 and timing["budget_s"] == 0.01
    assert "your basic_speed_estimation took longer than the 10.0 ms tick" in err
    # on the stepped simulator (as fast as it can) there is no tick budget to miss
    code, out, err = cli("io-test", "--use", path, "--duration", "0.1", "--json")
    assert code == 0 and json.loads(out)["student_blocks"]["basic_speed_estimation"]["over_budget"] == 0


def test_a_workspace_runs_with_the_filled_block_while_a_block_the_run_does_not_call_is_unfilled(cli, tmp_path):
    """Sheet 5.2 Task 1 with the template's folder: stop_sign filled, red_share (the report's
    --detector hough) still a stub: the sheet's run drives with the student's stop_sign; the hough
    run, which calls red_share, stops with the template's one line (exit 2)."""
    assert cli("template", "stop-sign", "--out", tmp_path)[0] == 0
    params = tmp_path / "params.yaml"
    text = re.sub(r"  hsv_min: .*", "  hsv_min: [170, 100, 100]", params.read_text())
    params.write_text(re.sub(r"  hsv_max: .*", "  hsv_max: [10, 255, 255]", text))
    write(tmp_path, "stop_sign.py", """\
        def stop_sign(distance_to_sign, desired_speed):
            return 0.0 if 0.6 < distance_to_sign < 1.0 else desired_speed  # stops early, on purpose
        """)
    code, out, err = cli("stop-sign", "--use", tmp_path, "--params", params, "--json")
    assert code == 0, err
    assert 0.6 < json.loads(out)["stop_distance_m"] < 1.0  # the student's window, not the reference's
    code, out, err = cli("stop-sign", "--use", tmp_path, "--params", params, "--detector", "hough")
    assert code == 2 and "red_share.py: red_share is not filled in yet" in err.strip().splitlines()[-1]
