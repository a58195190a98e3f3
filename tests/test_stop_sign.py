"""Stop sign (sheet 5.1-5.2): HSV threshold, find objects, distance, the stopSign block, the CLI."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from qcarlab.constants import DEFAULT_PARAMS
from qcarlab.control.stop_sign import StopSignBehaviour, stop_sign
from qcarlab.errors import InputError
from qcarlab.perception.stop_sign import (
    calculate_distance,
    color_thresholding_hsv,
    detect_stop_sign,
    detection_image,
    find_objects,
)


def octagon_image(centre=(400.0, 180.0), radius=40.0, bgr=(16, 16, 200), size=(480, 640)):
    """A grey scene with a filled octagon of colour ``bgr``; its exact centroid is ``centre``."""
    img = np.full(size + (3,), (120, 125, 130), np.uint8)
    ang = math.pi / 8 + np.arange(8) * math.pi / 4
    pts = np.column_stack((centre[0] + radius * np.cos(ang), centre[1] + radius * np.sin(ang)))
    cv2.fillPoly(img, [np.round(pts * 16).astype(np.int32)], bgr, cv2.LINE_8, 4)
    return img


# --- perception ---------------------------------------------------------------------------------
def test_octagon_centroid_bbox_area():
    img = octagon_image((400.0, 180.0), 40.0)
    mask = color_thresholding_hsv(img, (170, 100, 100), (10, 255, 255))
    assert mask.dtype == np.uint8 and set(np.unique(mask)) == {0, 255}
    obj = find_objects(mask, min_area=100)
    assert obj is not None
    assert abs(obj.centroid[0] - 400.0) < 2 and abs(obj.centroid[1] - 180.0) < 2
    x, y, w, h = obj.bbox
    assert abs(x + w / 2 - 400.5) < 2 and abs(y + h / 2 - 180.5) < 2
    area = 2 * math.sqrt(2) * 40.0**2  # regular octagon of circumradius 40
    assert abs(obj.area - area) / area < 0.05


def test_red_hue_wraps_around_zero():
    # OpenCV hue 175 (purplish red, 350 deg) and hue 3 (orange-red): both red, on either side of 0
    hsv = np.array([[[175, 220, 200]], [[3, 220, 200]], [[60, 220, 200]]], np.uint8)
    bgr = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR).reshape(1, 3, 3)
    wrapped = color_thresholding_hsv(bgr, (170, 100, 100), (10, 255, 255))
    assert wrapped.tolist() == [[255, 255, 0]]
    # without wrapping only one side is kept
    assert color_thresholding_hsv(bgr, (0, 100, 100), (10, 255, 255)).tolist() == [[0, 255, 0]]
    # low saturation (pink-grey) is not red
    grey_red = cv2.cvtColor(np.array([[[0, 60, 200]]], np.uint8), cv2.COLOR_HSV2BGR)
    assert color_thresholding_hsv(grey_red, (170, 100, 100), (10, 255, 255)).item() == 0


def test_find_objects_largest_and_min_area():
    mask = np.zeros((100, 100), np.uint8)
    mask[10:20, 10:20] = 255  # 100 px
    mask[50:80, 40:60] = 255  # 600 px
    obj = find_objects(mask, min_area=50)
    assert obj.area == 600 and obj.bbox == (40, 50, 20, 30)
    assert obj.centroid == pytest.approx((49.5, 64.5))
    assert find_objects(mask, min_area=601) is None
    assert find_objects(np.zeros((10, 10), np.uint8)) is None


def test_calculate_distance_median_ignores_zeros():
    depth = np.zeros((50, 60), np.float32)
    depth[20:31, 25:36] = 1.25
    depth[25, 30] = 9.0  # one outlier
    assert calculate_distance(depth, (30, 25)) == pytest.approx(1.25)
    assert calculate_distance(depth, (25, 20, 11, 11)) == pytest.approx(1.25)  # a bbox: its centre
    assert calculate_distance(depth, (5, 5)) == 0.0  # no valid depth there
    assert calculate_distance(depth, (59, 49)) == 0.0  # the window is clipped at the corner
    with pytest.raises(InputError):
        calculate_distance(depth, (1, 2, 3))


def test_detect_stop_sign_and_figure():
    img = octagon_image((300.0, 200.0), 50.0)
    depth = np.full((480, 640), 2.0, np.float32)
    depth[150:250, 250:350] = 0.8
    det = detect_stop_sign(img, depth)
    assert det.found and det.distance == pytest.approx(0.8)
    assert abs(det.centre[0] - 300) < 2 and abs(det.centre[1] - 200) < 2
    fig = detection_image(img, det, depth)
    assert fig.ndim == 3 and fig.shape[1] > 3 * 640 and fig.dtype == np.uint8
    none = detect_stop_sign(np.full((480, 640, 3), 128, np.uint8), depth)
    assert not none.found and none.distance == 0.0 and none.centre is None


@pytest.mark.parametrize("bad", [(180, 0, 0), (0, 256, 0), (0, 0), (1.5, 0, 0), ("a", 0, 0)])
def test_bad_hsv_triples(bad):
    with pytest.raises(InputError):
        color_thresholding_hsv(np.zeros((4, 4, 3), np.uint8), bad, (10, 255, 255))


# --- control ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "d, expected",
    [(0.0, 0.3), (0.05, 0.3), (0.0501, 0.0), (0.2, 0.0), (0.3999, 0.0), (0.40, 0.3), (1.0, 0.3)],
)
def test_stop_sign_block_boundaries(d, expected):
    assert stop_sign(d, 0.3) == expected


def test_behaviour_slows_stops_holds_and_ignores_the_sign():
    beh = StopSignBehaviour(0.5, hold=3.0)
    assert beh.step(0.0, 0.5, 2.0) == 0.5 and beh.state == "drive"
    v = beh.step(0.1, 0.5, 0.5)
    assert beh.state == "approach" and 0.0 < v < 0.5
    # the sign leaves the view: the distance is dead-reckoned, not forgotten
    v2 = beh.step(0.2, 0.3, 0.0)
    assert beh.state == "approach" and beh.estimate == pytest.approx(0.5 - 0.03)
    assert beh.step(0.3, 0.3, 0.29) == 0.0 and beh.state == "stopping"
    assert beh.step(0.5, 0.0, None) == 0.0 and beh.state == "holding"
    assert beh.step(3.4, 0.0, 0.29) == 0.0
    assert beh.step(3.5, 0.0, 0.29) == 0.5 and beh.state == "leaving"
    assert beh.step(3.6, 0.1, 0.25) == 0.5  # still in view: ignored
    assert beh.step(4.0, 0.5, 0.0) == 0.5 and beh.state == "leaving"
    assert beh.step(5.2, 0.5, 0.0) == 0.5 and beh.state == "drive"  # out of view for 1 s: re-armed
    assert beh.stops == 1
    beh.reset()
    assert beh.state == "drive" and beh.stops == 0 and v2 > 0


# --- the command, end to end --------------------------------------------------------------------
def _run(cli, *args):
    code, out, err = cli("stop-sign", *args, "--json")
    assert code == 0, err
    return json.loads(out)


@pytest.mark.parametrize("speed", ["0.3", "0.5"])
def test_sheet_mode_stops_before_the_sign(cli, speed):
    m = _run(cli, "--speed", speed)
    assert m["stopped"] is True
    assert 0.05 < m["stop_distance_m"] < 0.40
    assert 0.05 < m["measured_distance_m"] < 0.40
    # the camera (rgbd_x = 8.22 cm ahead of the centre) is 13.03 cm behind the bumper (length / 2):
    # the reading agrees with the truth to within 2 cm
    behind = DEFAULT_PARAMS.length / 2 - DEFAULT_PARAMS.rgbd_x
    assert abs(m["measured_distance_m"] - (m["stop_distance_m"] + behind)) < 0.02
    assert m["detected_at_m"] > 2.0 and m["min_distance_m"] > 0.05


def test_hold_mode_stops_waits_and_drives_on(cli):
    m = _run(cli, "--behaviour", "hold", "--hold", "3", "--speed", "0.5")
    assert m["stopped"] is True and 0.05 < m["stop_distance_m"] < 0.40
    assert 2.9 <= m["hold_s"] <= 3.3
    assert m["passed_sign"] is True and m["stops"] == 1


def test_same_seed_same_json(cli):
    a = cli("stop-sign", "--speed", "0.5", "--seed", "7", "--json")
    b = cli("stop-sign", "--speed", "0.5", "--seed", "7", "--json")
    assert a[0] == 0 and a[1] == b[1]


def test_out_writes_log_and_figures(cli, tmp_path):
    code, _out, err = cli("stop-sign", "--start", "0,-1.77,-1.5708", "--out", tmp_path, "--frames")
    assert code == 0, err
    for name in ("results.json", "log.csv", "detection.png", "speed.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert len(list((tmp_path / "frames").glob("*.jpg"))) >= 3
    fig = cv2.imread(str(tmp_path / "detection.png"))
    assert fig.shape[1] > 3 * 640
    header = (tmp_path / "log.csv").read_text().splitlines()[0].split(",")
    assert {"t", "v_ref", "v_meas", "sign_distance", "true_distance", "throttle"} <= set(header)


@pytest.mark.parametrize(
    "args, words",
    [
        (["--behaviour", "brake"], "--behaviour"),
        (["--speed", "0"], "--speed"),
        (["--speed", "-0.3"], "--speed"),
        (["--hsv-min", "170,100"], "--hsv-min"),
        (["--hsv-max", "10,300,255"], "--hsv-max"),
        (["--hsv-min", "x,1,2"], "--hsv-min"),
        (["--hold", "-1", "--behaviour", "hold"], "--hold"),
    ],
)
def test_bad_input_one_line_exit_2(cli, args, words):
    code, _out, err = cli("stop-sign", *args)
    assert code == 2
    assert words in err and len(err.strip().splitlines()) == 1
