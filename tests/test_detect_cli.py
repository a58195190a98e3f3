"""qcarlab detect lanes|stop-sign end to end: photos, folders, videos, the JSON, overlays, bad input."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from test_perception_lanes import road


def octagon_sign(img: np.ndarray, centre, radius) -> None:
    ang = math.pi / 8 + np.arange(8) * math.pi / 4
    pts = np.column_stack((centre[0] + radius * np.cos(ang), centre[1] + radius * np.sin(ang)))
    cv2.fillPoly(img, [np.round(pts).astype(np.int32)], (30, 30, 200))
    cv2.putText(img, "STOP", (int(centre[0] - 0.8 * radius), int(centre[1] + 0.25 * radius)),
                cv2.FONT_HERSHEY_SIMPLEX, radius / 40.0, (255, 255, 255), max(1, int(radius / 12)))


def json_lines(out: str) -> list[dict]:
    return [json.loads(line) for line in out.strip().splitlines()]


@pytest.fixture
def photo(tmp_path):
    img, truth = road(960, 540)
    path = tmp_path / "road.jpg"
    cv2.imwrite(str(path), img)
    return path, truth


def test_lanes_json_is_exactly_as_specified(cli, photo):
    path, truth = photo
    code, out, err = cli("detect", "lanes", str(path), "--json")
    assert code == 0, err
    (row,) = json_lines(out)
    assert list(row) == ["file", "frame", "width", "height", "left", "right", "confidence"]
    assert row["file"] == str(path) and row["frame"] == 0 and (row["width"], row["height"]) == (960, 540)
    for side in ("left", "right"):
        (x0, y0), (x1, y1) = row[side]
        assert y0 == 539 and y1 < y0  # (x0, y0) nearest the bottom
        slope, b = truth[side]
        assert abs(x0 - (slope * y0 + b)) < 15 and abs(x1 - (slope * y1 + b)) < 15
    assert 0.5 < row["confidence"] <= 1.0


def test_lanes_human_table_and_overlay(cli, photo, tmp_path):
    path, _ = photo
    code, out, _ = cli("detect", "lanes", str(path), "--out", str(tmp_path / "o"))
    assert code == 0 and "road.jpg" in out and "left line" in out
    overlay = cv2.imread(str(tmp_path / "o" / "road.png"))
    assert overlay is not None and overlay.shape[1] == 960 and overlay.shape[0] > 540
    assert json_lines((tmp_path / "o" / "detections.jsonl").read_text())[0]["left"] is not None


def test_lanes_on_a_video_every_n_frames_with_an_mp4_overlay(cli, tmp_path):
    path = tmp_path / "drive.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (640, 480))
    for k in range(6):
        img, _ = road(640, 480)
        img = np.roll(img, 8 * k, axis=1)  # the car drifts left: the lines move right
        writer.write(img)
    writer.release()
    code, out, err = cli("detect", "lanes", str(path), "--every", "2", "--json", "--out", str(tmp_path / "v"))
    assert code == 0, err
    rows = json_lines(out)
    assert [r["frame"] for r in rows] == [0, 2, 4]
    lefts = [r["left"][0][0] for r in rows]
    assert lefts[0] < lefts[1] < lefts[2] and lefts[2] - lefts[0] == pytest.approx(32, abs=6)
    cap = cv2.VideoCapture(str(tmp_path / "v" / "drive.mp4"))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 3


def test_a_folder_of_photos(cli, tmp_path):
    for name, w, h in (("a.png", 640, 480), ("b.jpg", 1280, 720)):
        cv2.imwrite(str(tmp_path / name), road(w, h)[0])
    (tmp_path / "notes.txt").write_text("not an image")
    code, out, _ = cli("detect", "lanes", str(tmp_path), "--json")
    rows = json_lines(out)
    assert code == 0 and [r["file"].split("/")[-1] for r in rows] == ["a.png", "b.jpg"]
    assert all(r["left"] and r["right"] for r in rows)


def test_real_road_photos(cli, shared_data):
    code, out, _ = cli("detect", "lanes", str(shared_data / "real-lanes"), "--json")
    rows = json_lines(out)
    assert code == 0 and len(rows) == 4
    assert all(r["left"] is not None and r["right"] is not None for r in rows)


def test_hsv_profile_is_used_and_a_bad_one_is_one_line(cli, photo, tmp_path):
    path, _ = photo
    blue = tmp_path / "blue.yaml"  # a range that keeps no yellow: the left line is gone
    blue.write_text("qcarlab: hsv-profile\nyellow:\n  hsv_min: [100, 80, 80]\n  hsv_max: [130, 255, 255]\n")
    code, out, _ = cli("detect", "lanes", str(path), "--hsv", str(blue), "--json", "--no-white")
    assert code == 0 and json_lines(out)[0]["left"] is None
    bad = tmp_path / "bad.yaml"
    bad.write_text("yellow:\n  hsv_min: [200, 0, 0]\n  hsv_max: [30, 255, 255]\n")
    code, _, err = cli("detect", "lanes", str(path), "--hsv", str(bad))
    assert code == 2 and "bad.yaml" in err and "hue 200" in err and len(err.strip().splitlines()) == 1


def test_hsv_tune_without_a_terminal_saves_the_automatic_tuning(cli, photo, tmp_path):
    path, _ = photo
    prof = tmp_path / "tuned.yaml"
    start = tmp_path / "start.yaml"  # start from a range that misses the line
    code, out, err = cli("detect", "lanes", str(path), "--hsv-tune", "--hsv", str(prof), "--json")
    assert code == 0, err
    assert prof.is_file() and "automatic HSV tuner" in err
    assert json_lines(out)[0]["left"] is not None
    start.write_text("yellow:\n  hsv_min: [100, 80, 80]\n  hsv_max: [130, 255, 255]\n")
    code, out, err = cli("detect", "lanes", str(path), "--hsv-tune", "--hsv", str(start), "--json")
    assert code == 0
    from qcarlab.hsv_profile import load_hsv_profile

    tuned = load_hsv_profile(start)
    assert tuned.hsv_min[0] <= 24 <= tuned.hsv_max[0] and tuned.score > 0.8  # the paint's hue is 24
    assert json_lines(out)[0]["left"] is not None


def test_stop_sign_json_methods_and_depth(cli, tmp_path):
    img = np.full((480, 640, 3), (120, 125, 130), np.uint8)
    octagon_sign(img, (400, 180), 40)
    path = tmp_path / "sign.png"
    cv2.imwrite(str(path), img)
    depth = np.full((480, 640), 3.0, np.float32)
    depth[140:220, 360:440] = 0.8
    np.save(tmp_path / "depth.npy", depth)
    for method in ("hsv", "hough"):
        code, out, err = cli("detect", "stop-sign", str(path), "--method", method, "--json")
        assert code == 0, err
        (row,) = json_lines(out)
        assert list(row) == ["file", "frame", "signs"] and len(row["signs"]) == 1
        (sign,) = row["signs"]
        assert list(sign) == ["box", "score"]
        x, y, w, h = sign["box"]
        assert abs(x + w / 2 - 400) < 4 and abs(y + h / 2 - 180) < 4 and 70 < w < 90
    code, out, _ = cli("detect", "stop-sign", str(path), "--depth", str(tmp_path / "depth.npy"), "--json",
                       "--out", str(tmp_path / "o"))
    assert json_lines(out)[0]["signs"][0]["distance"] == pytest.approx(0.8)
    overlay = cv2.imread(str(tmp_path / "o" / "sign.png"))
    assert overlay is not None and overlay.shape[0] > 480 and (tmp_path / "o" / "detections.jsonl").is_file()
    mm = (depth * 1000).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "depth.png"), mm)
    code, out, _ = cli("detect", "stop-sign", str(path), "--depth", str(tmp_path / "depth.png"), "--json")
    assert json_lines(out)[0]["signs"][0]["distance"] == pytest.approx(0.8)


def test_stop_sign_not_on_a_red_car_or_a_tail_light(cli, tmp_path):
    img = np.full((480, 640, 3), (120, 125, 130), np.uint8)
    cv2.rectangle(img, (50, 250), (330, 400), (30, 30, 190), -1)  # a red car's back
    cv2.ellipse(img, (480, 300), (40, 12), 0, 0, 360, (40, 40, 230), -1)  # a tail light
    cv2.circle(img, (560, 120), 30, (20, 20, 40), -1)  # a red traffic light: a solid red disc ...
    cv2.circle(img, (560, 120), 24, (30, 30, 230), -1)  # ... in its dark housing
    cv2.imwrite(str(tmp_path / "street.png"), img)
    for method in ("hsv", "hough"):
        code, out, _ = cli("detect", "stop-sign", str(tmp_path / "street.png"), "--method", method, "--json")
        assert code == 0 and json_lines(out)[0]["signs"] == [], method


@pytest.mark.parametrize("args, words", [
    (("lanes", "nowhere.jpg"), "no such file"),
    (("lanes", "{tmp}/notes.txt"), "not an image"),
    (("lanes", "{tmp}/broken.jpg"), "cannot read this image"),
    (("lanes", "{tmp}/texts"), "no images"),
    (("lanes", "{tmp}/ok.png", "--every", "0"), "--every"),
    (("lanes", "{tmp}/ok.png", "--roi-top", "1.2"), "--roi-top"),
    (("stop-sign", "{tmp}/ok.png", "--method", "yolo"), "--method"),
    (("stop-sign", "{tmp}/ok.png", "{tmp}/ok.png", "--depth", "{tmp}/d.npy"), "exactly one image"),
    (("stop-sign", "{tmp}/ok.png", "--depth", "{tmp}/small.npy"), "aligned"),
    (("stop-sign", "{tmp}/ok.png", "--hsv-min", "1,2"), "--hsv-min"),
])
def test_bad_input_is_one_line_exit_2(cli, tmp_path, args, words):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("x")
    (empty / "texts").mkdir()
    (empty / "texts" / "readme.md").write_text("x")
    (empty / "broken.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    cv2.imwrite(str(tmp_path / "ok.png"), np.zeros((48, 64, 3), np.uint8))
    np.save(tmp_path / "d.npy", np.zeros((48, 64), np.float32))
    np.save(tmp_path / "small.npy", np.zeros((10, 10), np.float32))
    argv = [a.replace("{tmp}/ok.png", str(tmp_path / "ok.png")).replace("{tmp}/d.npy", str(tmp_path / "d.npy"))
            .replace("{tmp}/small.npy", str(tmp_path / "small.npy")).replace("{tmp}", str(empty)) for a in args]
    code, _, err = cli("detect", *argv)
    assert code == 2, err
    assert words in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
