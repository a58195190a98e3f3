"""``qcarlab lidar-scan`` and ``qcarlab camera`` as a user runs them, and sensor timing on the car."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import qcarlab


def test_target_ahead_reads_its_true_distance(cli_json):
    m = cli_json("lidar-scan", "--target", "1.5")
    assert m["target"]["measured_m"] == pytest.approx(1.5, abs=0.02)
    assert m["nearest_obstacle_m"] == pytest.approx(1.5, abs=0.02)
    # a flat face: 3 deg off its normal is only 2 mm farther, inside the lab car's range noise
    assert abs(m["nearest_bearing_rad"]) < math.radians(6)
    assert len(m["angles_rad"]) == len(m["ranges_m"]) == 800
    assert len(m["sensor_pose"]) == 3


def test_obstacles_world_scan_and_files(cli, tmp_path):
    code, out, err = cli("lidar-scan", "--world", "obstacles", "--scans", "3", "--out", tmp_path)
    assert code == 0, err
    m = json.loads((tmp_path / "results.json").read_text())
    assert m["points_with_return"] > 700 and 0.4 < m["nearest_obstacle_m"] < 1.6
    rows = (tmp_path / "scan.csv").read_text().splitlines()
    assert rows[0] == "angle_rad,range_m" and len(rows) == 801
    assert (tmp_path / "polar.png").stat().st_size > 0 and (tmp_path / "cloud.png").stat().st_size > 0


def test_ros_map_scan(cli_json, shared_data):
    m = cli_json("lidar-scan", "--world", shared_data / "maps" / "berlin.yaml", "--beams", "360")
    assert m["beams"] == 360 and m["points_with_return"] > 300


def test_drive_moves_the_lidar(cli_json):
    still = cli_json("lidar-scan", "--scans", "5")
    moving = cli_json("lidar-scan", "--scans", "5", "--drive")
    assert still["sensor_pose"] != moving["sensor_pose"]


def test_camera_rgbd_and_csi(cli, tmp_path):
    code, _, err = cli("camera", "--rgbd", "--csi", "--out", tmp_path)
    assert code == 0, err
    m = json.loads((tmp_path / "results.json").read_text())
    assert m["rgbd"]["color_size"] == [640, 480] and m["rgbd"]["depth"]["valid_fraction"] > 0.5
    assert m["csi"]["views"]["front"] == [820, 410]
    for name in ("color", "depth", "csi_right", "csi_rear", "csi_left", "csi_front", "panorama"):
        assert (tmp_path / f"{name}.png").stat().st_size > 0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("lidar-scan", "--start", "1,2"), "expected X,Y,YAW"),
        (("lidar-scan", "--target", "-1"), "--target must be"),
        (("lidar-scan", "--world", "moon"), "moon"),
        (("lidar-scan", "--watch"), "interactive terminal"),
        (("camera", "--world", "nowhere.yaml"), "nowhere.yaml"),
    ],
)
def test_bad_input(cli, args, message):
    code, out, err = cli(*args)
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_bad_world_file_names_file_and_field(cli, tmp_path):
    bad = tmp_path / "w.yaml"
    bad.write_text("floor: {size: [4, 4]}\nobstacles:\n  - {circle: [1, 1], radius: -1}\n")
    code, _, err = cli("lidar-scan", "--world", bad)
    assert code == 2 and "w.yaml" in err and "radius" in err


def test_frames_come_at_the_sensor_rate_and_latest_is_returned():
    with qcarlab.open_car("sim", world="obstacles", seed=2) as car:
        car.write(0.1, 0.0)
        car.advance(0.25)
        scan = car.read_lidar()
        assert scan.t == pytest.approx(0.2)  # 10 Hz: the frame taken at 0.2 s
        assert car.read_lidar() is scan  # a read between two frames returns the latest
        car.advance(0.06)
        assert car.read_lidar().t == pytest.approx(0.3)
        frame = car.read_rgbd()
        assert frame.t == pytest.approx(math.floor(0.31 * 30) / 30)


def test_sensor_frames_are_deterministic():
    def grab(seed):
        with qcarlab.open_car("sim", world="obstacles", seed=seed) as car:
            car.advance(0.1)
            return car.read_lidar().ranges.copy(), car.read_rgbd().depth.copy()

    (a1, d1), (a2, d2), (b1, _) = grab(4), grab(4), grab(5)
    assert np.array_equal(a1, a2) and np.array_equal(d1, d2) and not np.array_equal(a1, b1)


def test_watch_shows_sectors_live_on_a_terminal():
    from ptyrun import PtyRun

    run = PtyRun("lidar-scan", "--watch", "--world", "obstacles", "--scans", "5")
    rc = run.finish(timeout=20)
    assert rc == 0, run.text[-2000:]
    text = run.text
    assert "nearest obstacle per sector" in text and "ahead-left" in text
    assert "scan 5" in text and "Traceback" not in text
    assert run.after == run.before
