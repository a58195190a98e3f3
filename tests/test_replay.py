"""--car replay:FILE: a recording as a car; an unchanged lab reproduces the recorded commands exactly."""

from __future__ import annotations

import csv
import json

import pytest

pytest.importorskip("foxglove")
pytest.importorskip("mcap")
pytest.importorskip("rosbags")

from record_helpers import COLOR, DEPTH, ODOM, SCAN, TOPICS, make_bag  # noqa: E402


def run_json(cli, *args):
    code, out, err = cli(*args, "--json")
    assert code == 0, err
    return json.loads(out)


NEAR_SIGN = ["--start", "0,-1.3,-1.5708"]  # 1.3 m on from the world's start: a stop in 3.4 s
EXACT = {  # lab -> (its arguments, record options): camera labs need --record-exact for an exact replay
    "stop-sign": (["stop-sign", *NEAR_SIGN], ["--record-exact"]),
    "lane-follow": (["lane-follow", "--duration", "2"], ["--record-exact"]),
    "avoid": (["avoid", "--duration", "3"], []),
    "lidar-scan": (["lidar-scan", "--scans", "4", "--drive", "--world", "obstacles"], []),
}


@pytest.mark.parametrize("lab", sorted(EXACT))
def test_replay_of_an_unchanged_lab_reproduces_every_command(lab, cli, tmp_path):
    args, rec = EXACT[lab]
    f = tmp_path / f"{lab}.mcap"
    original = run_json(cli, *args, "--record", f, *rec)
    replay = run_json(cli, *args, "--car", f"replay:{f}")
    r = replay["replay"]
    assert r["recorded_ticks"] > 0
    assert r["identical"] and r["ticks_compared"] == r["recorded_ticks"] == r["replayed_ticks"]
    assert r["max_throttle_difference"] == 0.0 and r["max_steering_difference_rad"] == 0.0
    # the lab's own results come out the same from the recorded sensors (and the recorded world)
    # invocation: --car differs; realism: the simulator's profile, which a recording's car does not have
    skip = {"car", "replay", "recording", "sensor_pose", "config", "invocation", "realism"}
    assert {k: v for k, v in replay.items() if k not in skip} == {k: v for k, v in original.items() if k not in skip}


def test_a_changed_lab_shows_where_its_decisions_differ(cli, tmp_path):
    f = tmp_path / "s.mcap"
    run_json(cli, "stop-sign", *NEAR_SIGN, "--record", f, "--record-exact")  # exact frames: only the speed differs
    out = tmp_path / "out"
    code, text, err = cli("stop-sign", "--speed", "0.4", "--car", f"replay:{f}", "--out", out, "--json")
    assert code == 1 and "the replay differs from the recording" in err and "Traceback" not in err  # like diff
    replay = json.loads(text)
    r = replay["replay"]
    assert not r["identical"] and r["ticks_differing"] > 0
    assert not r["within_tolerance"] and r["ticks_beyond_tolerance"] > 0
    first = r["first_differences"][0]
    assert first["t"] == 0.0 and first["recorded"]["throttle"] != first["replayed"]["throttle"]
    rows = list(csv.DictReader((out / "replay.csv").open()))
    assert len(rows) >= r["recorded_ticks"] and {"t", "recorded_throttle", "replayed_throttle", "same"} <= set(rows[0])
    assert any(row["same"] == "0" for row in rows)
    code, text, _ = cli("stop-sign", "--speed", "0.4", "--car", f"replay:{f}")
    assert code == 1 and "NO:" in text and "tick(s) differ" in text
    code, _, err = cli("stop-sign", *NEAR_SIGN, "--replay-tolerance", "1")
    assert code == 2 and "--replay-tolerance is for a replay" in err


def test_compact_camera_recording_replays_with_a_note(cli, tmp_path):
    f = tmp_path / "l.mcap"
    run_json(cli, "lane-follow", "--duration", "1", "--record", f)
    code, out, _ = cli("lane-follow", "--duration", "1", "--car", f"replay:{f}")
    assert code == 0 and "--record-exact for an exact replay" in out


def test_a_replay_stops_when_the_recording_runs_out(cli, tmp_path):
    f = tmp_path / "a.mcap"
    run_json(cli, "avoid", "--duration", "1", "--record", f)
    replay = run_json(cli, "avoid", "--duration", "5", "--car", f"replay:{f}")
    assert replay["replay"]["identical"] and replay["replay"]["replayed_ticks"] == 100
    assert replay["duration_s"] == pytest.approx(1.0)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_rosbag2_replays_into_lidar_scan_and_stop_sign(storage, cli, tmp_path):
    bag = make_bag(tmp_path / "bag", seconds=4.5, throttle=0.12, storage=storage)
    scan = run_json(cli, "lidar-scan", "--scans", "3", "--car", f"replay:{bag}", "--topics", f"scan={SCAN}")
    assert scan["beams"] == 800 and scan["points_with_return"] > 700 and scan["nearest_obstacle_m"] > 0.5
    stop = run_json(cli, "stop-sign", "--max-time", "8", "--car", f"replay:{bag}", "--topics", TOPICS)
    assert stop["frames_with_sign"] > 50 and 2.0 < stop["detected_at_m"] < 2.6
    r = stop["replay"]
    assert r["recorded_ticks"] == 0 and r["replayed_ticks"] > 300
    # the lab decides to stop when the sign comes within 0.40 m (the car in the bag drove on)
    assert any(c["lamps"] == "brake" for c in r["replayed_lamp_changes"])
    code, out, err = cli("replay", "info", bag, "--json")
    assert code == 0, err
    info = json.loads(out)
    assert info["format"] == "rosbag2" and info["topics"][SCAN]["schema"] == "sensor_msgs/msg/LaserScan"
    assert info["topics"][COLOR]["count"] == 135 and info["topics"][ODOM]["count"] == 225


@pytest.mark.parametrize("topics, message", [
    ("nose=/scan", "unknown sensor 'nose'"),
    ("scan=/nothere", "the bag has no topic /nothere"),
    (f"scan={COLOR}", "is not a sensor_msgs/msg/LaserScan"),
    ("scan", "expected SENSOR=/topic"),
])
def test_bad_topic_maps_are_refused(topics, message, cli, tmp_path):
    bag = make_bag(tmp_path / "bag", seconds=0.3)
    code, _, err = cli("lidar-scan", "--car", f"replay:{bag}", "--topics", topics)
    assert code == 2 and message in err and "Traceback" not in err


def test_python_api_replay(tmp_path):
    """open_car("replay:...") in a script: the recorded readouts in order, commands kept for comparison."""
    from qcarlab.car import open_car
    from qcarlab.recording.car import RecordingCar
    from qcarlab.recording.writer import Recorder

    f = tmp_path / "p.mcap"
    with RecordingCar(open_car("sim", seed=2), Recorder(f)) as car:
        rec = []
        for _ in range(20):
            rec.append(car.read())
            car.write(0.1, 0.0)
            car.advance(0.01)
    with open_car(f"replay:{f}") as car:
        assert car.stepped and car.identity().backend == "replay"
        got = []
        while not car.ended:
            got.append(car.read())
            car.write(0.1, 0.0)
            car.advance(0.01)
    assert [r.to_dict() for r in got] == [r.to_dict() for r in rec]
    assert car.comparison()["summary"]["identical"]
    assert DEPTH  # (the helper's topics are importable)


def test_a_compact_recordings_replay_says_its_frames_were_compressed_instead_of_failing(cli, tmp_path):
    """The default (compact) recording keeps JPEG colour and 2 Hz depth: an unchanged camera lab may
    decide a few ticks apart on them; that is a note (exit 0), and --replay-tolerance makes it a bound."""
    f = tmp_path / "s.mcap"
    run_json(cli, "stop-sign", "--record", f)
    code, text, err = cli("stop-sign", "--car", f"replay:{f}", "--json")
    r = json.loads(text)["replay"]
    assert code == 0, err
    if not r["within_tolerance"]:
        assert r["lossy"] and "the recording keeps the camera's frames compressed" in err and "--record-exact" in err
        code, _, err = cli("stop-sign", "--car", f"replay:{f}", "--replay-tolerance", "0.02", "--json")
        assert code == 1 and "the replay differs from the recording" in err
