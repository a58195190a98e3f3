"""The HSV tuner's pure parts: the sheet's sliders, keys, the quality of a range, the automatic
tuner; the profile YAML."""

from __future__ import annotations

import pytest

from qcarlab.errors import InputError
from qcarlab.hsv_profile import load_hsv_profile, profile_yaml, save_hsv_profile
from qcarlab.perception.hsv_range import HsvProfile
from qcarlab.perception.tuner import TuneFrames, TunerState, apply_key, auto_tune, move_slider

from test_perception_lanes import road


def test_sliders_are_the_sheets_mean_and_window():
    p = HsvProfile((17, 85, 70), (38, 255, 255))
    assert p.sliders == ((27.5, 21), (170.0, 170), (162.5, 185))
    assert HsvProfile.from_sliders(p.sliders) == p
    # a window at 100 % of the channel keeps everything; the range is clipped at the channel's ends
    assert HsvProfile.from_sliders([(90, 179), (300, 40), (0, 20)]) == HsvProfile((0, 255, 0), (179, 255, 10))


def test_keys_move_the_selected_slider():
    s = TunerState(HsvProfile((17, 85, 70), (38, 255, 255)), frames=3)
    s = apply_key(s, "right")  # H mean +1: the window moves
    assert (s.profile.hsv_min[0], s.profile.hsv_max[0]) == (18, 39)
    s = apply_key(apply_key(s, "down"), "]")  # H window +10
    assert s.profile.hsv_max[0] - s.profile.hsv_min[0] == 31
    s = apply_key(apply_key(s, "down"), "[")  # S mean -10
    assert s.profile.hsv_min[1] == 75
    assert apply_key(s, "up").selected == 1 and apply_key(apply_key(s, "tab"), "p").frame == 0
    assert apply_key(s, "tab").frame == 1 and apply_key(TunerState(s.profile, frame=2, frames=3), "tab").frame == 0
    assert apply_key(s, "r").profile == HsvProfile()
    assert apply_key(s, "s").done == "save" and apply_key(s, "q").done == "quit" and apply_key(s, "a").done == "auto"
    assert apply_key(s, "x") == s
    assert move_slider(HsvProfile(), 1, -1000).hsv_min[0] == move_slider(HsvProfile(), 1, -1000).hsv_max[0]


def test_quality_is_one_for_the_line_alone_and_zero_without_it():
    img, _ = road(640, 480)
    tf = TuneFrames([img], lane="right")
    q = tf.quality(0, HsvProfile())
    assert q.quality > 0.9 and q.line_pixels == q.pixels and q.slope < 0
    assert tf.quality(0, HsvProfile((100, 80, 80), (130, 255, 255))).quality == 0.0
    # a range that also keeps the grey road: the mask is not only the line
    assert tf.quality(0, HsvProfile((0, 0, 0), (179, 255, 255))).quality < 0.2


def test_auto_tune_finds_the_line_from_a_range_that_misses_it():
    frames = [road(640, 480)[0], road(960, 540)[0]]
    tf = TuneFrames(frames, lane=None, names=["a", "b"])
    tuned = auto_tune(tf, HsvProfile((100, 80, 80), (130, 255, 255)))
    assert tuned.hsv_min[0] <= 24 <= tuned.hsv_max[0]  # the paint's hue
    assert tuned.score > 0.9 and tuned.tuned_on == ("a", "b")
    # from a range that already finds it, it does not wander off
    kept = auto_tune(tf, HsvProfile())
    assert kept.hsv_min == HsvProfile().hsv_min and kept.hsv_max == HsvProfile().hsv_max


def test_profile_yaml_round_trip_and_sliders_only(tmp_path):
    p = HsvProfile((20, 90, 80), (35, 250, 250), white_s_max=70, tuned_on=("x.jpg",), score=0.9)
    path = save_hsv_profile(p, tmp_path / "sub" / "p.yaml")
    assert load_hsv_profile(path) == p and "sliders:" in profile_yaml(p)
    (tmp_path / "s.yaml").write_text(
        "yellow:\n  sliders:\n    hue: {mean: 27.5, window: 21}\n    saturation: {mean: 170, window: 170}\n"
        "    value: {mean: 162.5, window: 185}\n")
    assert load_hsv_profile(tmp_path / "s.yaml") == HsvProfile((17, 85, 70), (38, 255, 255))


@pytest.mark.parametrize("text, words", [
    ("[1, 2]", "a YAML mapping"),
    ("qcarlab: world\nyellow: {}", "not an hsv-profile"),
    ("white: {s_max: 40}", "missing 'yellow'"),
    ("yellow:\n  hsv_min: [1, 2]\n  hsv_max: [3, 4, 5]", "yellow.hsv_min"),
    ("yellow:\n  hsv_min: [40, 0, 0]\n  hsv_max: [30, 255, 255]", "above hsv_max"),
    ("yellow:\n  hsv_min: [10, 0, 0]\n  hsv_max: [30, 255, 255]\nwhite: {s_max: 300}", "white.s_max"),
    ("yellow: [: bad", "line 1"),
])
def test_bad_profiles_are_one_line(tmp_path, text, words):
    path = tmp_path / "p.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as exc:
        load_hsv_profile(path)
    assert words in str(exc.value) and "p.yaml" in str(exc.value) and "\n" not in str(exc.value)
