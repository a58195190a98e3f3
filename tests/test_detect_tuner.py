"""The HSV tuner as a user meets it: in a terminal (a pseudo-terminal, as tmux gives), and
lane-follow --hsv-tune saving its profile."""

from __future__ import annotations

import cv2
import pytest

from ptyrun import PtyRun
from qcarlab.hsv_profile import load_hsv_profile
from qcarlab.perception.hsv_range import HsvProfile

from test_perception_lanes import road


@pytest.fixture
def photo(tmp_path):
    path = tmp_path / "road.png"
    cv2.imwrite(str(path), road(640, 480)[0])
    return path


def test_tuner_in_a_terminal_moves_sliders_and_saves(photo, tmp_path):
    prof = tmp_path / "mine.yaml"
    run = PtyRun("detect", "lanes", str(photo), "--hsv-tune", "--hsv", str(prof))
    run.wait_for("HSV tuner", 20)
    run.wait_for("quality", 5)
    run.send(b"\x1b[C", 0.3)  # right arrow: H mean +1 -> H 18..39
    run.wait_for("H  18.. 39")
    run.send(b"\x1b[B\x1b[B", 0.2)  # down twice: the S mean
    run.send(b"[", 0.3)  # -10 -> S 75..245
    run.wait_for("S  75..245")
    run.send(b"s")
    run.wait_for("HSV profile saved to")
    assert run.finish(20) == 0
    assert run.before == run.after  # the terminal is restored
    saved = load_hsv_profile(prof)
    assert saved.hsv_min == (18, 75, 70) and saved.hsv_max == (39, 245, 255)
    assert "left line" in run.text  # then the detection ran with it


def test_tuner_quit_keeps_nothing(photo, tmp_path):
    prof = tmp_path / "never.yaml"
    run = PtyRun("detect", "lanes", str(photo), "--hsv-tune", "--hsv", str(prof))
    run.wait_for("HSV tuner", 20)
    run.send(b"\x1b[C\x1b[C", 0.3)
    run.send(b"q")
    run.wait_for("closed without saving")
    assert run.finish(20) == 0 and not prof.exists()
    assert run.before == run.after


def test_lane_follow_hsv_tune_saves_a_profile_lane_follow_can_read(cli_json, tmp_path):
    m = cli_json("lane-follow", "--hsv-tune", "--hsv-min", "100,80,80", "--hsv-max", "130,255,255",
                 "--out", str(tmp_path))
    assert m["spots_with_line"] == 0  # the given range, as before: the student sees it fails
    tuned = m["tuned"]
    assert tuned["file"] == str(tmp_path / "hsv.yaml") and tuned["quality"] > 0.9
    prof = load_hsv_profile(tmp_path / "hsv.yaml")
    assert prof == HsvProfile(tuple(tuned["hsv_min"]), tuple(tuned["hsv_max"]))
    assert prof.hsv_min[0] <= 25 <= prof.hsv_max[0]  # the track's paint
    again = cli_json("lane-follow", "--hsv-tune", "--hsv-min", ",".join(map(str, prof.hsv_min)),
                     "--hsv-max", ",".join(map(str, prof.hsv_max)))
    assert again["spots_with_line"] >= 3
