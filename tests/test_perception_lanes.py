"""Lane perception on synthetic images: line-shaped blobs, both lane lines at any resolution,
"no line" on a plain floor, HSV defaults that keep paint but not brown boxes or dry grass."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from qcarlab.errors import InputError
from qcarlab.perception.components import group_collinear, line_components
from qcarlab.perception.lane import (
    YELLOW_HSV_MAX,
    YELLOW_HSV_MIN,
    color_thresholding_hsv,
    detect_lane,
    image_selector,
    linear_poly_fit,
    white_line_mask,
)
from qcarlab.perception.lane_lines import detect_lane_lines

ROAD = (60, 58, 62)  # BGR: dark asphalt
YELLOW = (30, 190, 230)  # road paint: H ~23, S ~200
WHITE = (235, 235, 235)
BROWN = (58, 96, 140)  # a brown box as the simulator draws it: H 14, S 150
GRASS = (116, 144, 165)  # dry grass as the road photos show it: H 17, S 75 (paint: S 100..200)


def road(w: int = 960, h: int = 540, dashed_right: bool = True) -> tuple[np.ndarray, dict]:
    """A straight road in perspective: a solid yellow line on the left and a (dashed) white line
    on the right meeting at the vanishing point (w/2, 0.55 h). Returns the image and the lines
    as (slope, intercept) of u = slope v + intercept."""
    img = np.full((h, w, 3), ROAD, np.uint8)
    img[: int(0.55 * h)] = (200, 170, 120)  # sky
    vx, vy = w / 2.0, 0.55 * h
    lines = {"left": (0.15 * w, "yellow"), "right": (0.88 * w, "white")}
    out = {}
    for side, (u_bottom, paint) in lines.items():
        slope = (u_bottom - vx) / (h - 1 - vy)
        b = vx - slope * vy
        out[side] = (slope, b)
        color = YELLOW if paint == "yellow" else WHITE
        thick = max(3, w // 60)
        v_top = int(0.58 * h)
        if side == "right" and dashed_right:
            for k in range(7):
                v0 = v_top + k * (h - v_top) // 7
                v1 = v0 + (h - v_top) // 14
                cv2.line(img, (round(slope * v0 + b), v0), (round(slope * v1 + b), v1), color, thick)
        else:
            cv2.line(img, (round(slope * v_top + b), v_top), (round(slope * (h - 1) + b), h - 1), color, thick)
    return img, out


def at(line, v):
    return line[0] * v + line[1]


# ---------------------------------------------------------------------------------- blobs
def test_line_components_keep_lines_and_drop_blobs_and_flat_strips():
    mask = np.zeros((200, 400), np.uint8)
    cv2.line(mask, (50, 190), (150, 20), 255, 8)  # a lane line
    cv2.circle(mask, (300, 100), 30, 255, -1)  # a round blob (a patch of grass)
    mask[150:165, 200:390] = 255  # a flat strip (a box's lower edge, a stop line)
    blobs = line_components(mask, 20)
    assert len(blobs) == 1
    (b,) = blobs
    assert b.slope == pytest.approx((150 - 50) / (20 - 190), abs=0.05)  # du/dv along the axis
    assert b.elongation > 20 and 6 < b.thickness < 11


def test_dashes_of_one_line_are_one_group():
    mask = np.zeros((300, 300), np.uint8)
    for k in range(5):  # dashes along u = 0.5 v + 40
        v0, v1 = 40 + 50 * k, 65 + 50 * k
        cv2.line(mask, (round(0.5 * v0 + 40), v0), (round(0.5 * v1 + 40), v1), 255, 5)
    cv2.line(mask, (250, 290), (280, 150), 255, 5)  # another line
    groups = group_collinear(line_components(mask, 10), 10.0)
    assert len(groups) == 2
    dashes = max(groups, key=lambda g: len(g.labels))
    assert len(dashes.labels) == 5
    assert dashes.column_at(250) == pytest.approx(0.5 * 250 + 40, abs=2)


# ---------------------------------------------------------------------------------- both lines
@pytest.mark.parametrize("w, h", [(960, 540), (640, 480), (1280, 720), (320, 240)])
def test_detect_lane_lines_finds_both_lines_at_any_resolution(w, h):
    img, truth = road(w, h)
    lines = detect_lane_lines(img)
    assert lines.left is not None and lines.right is not None
    assert lines.left.source == "yellow" and lines.right.source == "white"
    for side in ("left", "right"):
        found = getattr(lines, side)
        for v in (h - 1, 0.6 * h):  # 2 % of the width on both rows: a wrong slope fails
            assert abs(found.column_at(v) - at(truth[side], v)) < 0.02 * w, (side, v)
    assert lines.confidence > 0.6
    d = lines.as_dict()
    assert list(d) == ["width", "height", "left", "right", "confidence"]
    (x0, y0), (x1, y1) = d["left"]
    assert y0 == h - 1 and y1 < y0 and abs(x0 - at(truth["left"], h - 1)) < 0.02 * w


def test_detect_lane_lines_says_no_line_on_a_plain_floor_and_on_a_pole():
    floor = np.full((480, 640, 3), (175, 180, 182), np.uint8)  # a light grey floor, no paint
    floor[:200] = (120, 110, 100)
    assert detect_lane_lines(floor).left is None and detect_lane_lines(floor).right is None
    pole = floor.copy()
    pole[150:470, 300:330] = 250  # a white pole standing upright in front of the car
    lines = detect_lane_lines(pole)
    assert lines.left is None and lines.right is None and lines.confidence == 0.0


def test_detect_lane_lines_input_errors():
    with pytest.raises(InputError):
        detect_lane_lines(np.zeros((480, 640), np.uint8))
    with pytest.raises(InputError):
        detect_lane_lines(np.zeros((480, 640, 3), np.uint8), roi_top=1.5)


# ---------------------------------------------------------------------------------- the lab's chain
def test_image_selector_rows_are_a_fraction_of_the_height():
    for h in (480, 540, 720):
        img = np.full((h, 640), 255, np.uint8)
        kept = np.nonzero(image_selector(img, "right").any(axis=1))[0]
        assert kept[0] == round(2 * h / 3)
    img = np.full((540, 640), 255, np.uint8)
    assert np.nonzero(image_selector(img, "right", 320).any(axis=1))[0][0] == 320  # an int: a pixel row
    assert np.nonzero(image_selector(img, "right", 0.5).any(axis=1))[0][0] == 270  # a float: a fraction


def test_hsv_defaults_keep_paint_not_brown_boxes_or_dry_grass():
    swatch = np.array([[YELLOW, BROWN, GRASS, WHITE, ROAD]], np.uint8)
    kept = color_thresholding_hsv(swatch, YELLOW_HSV_MIN, YELLOW_HSV_MAX)[0]
    assert kept.tolist() == [255, 0, 0, 0, 0]


def test_detect_lane_fits_the_line_not_the_grass_beside_it():
    img, truth = road(960, 540)
    # dry-grass-coloured patches and a brown box on the left verge, inside the yellow line's region
    rng = np.random.default_rng(0)
    for _ in range(12):
        x, y = int(rng.integers(0, 150)), int(rng.integers(380, 530))
        cv2.ellipse(img, (x, y), (25, 12), 0, 0, 360, GRASS, -1)
    cv2.rectangle(img, (20, 390), (110, 470), BROWN, -1)
    det = detect_lane(img, "right")
    assert det.source == "yellow"
    for v in (539, 400):
        assert abs(det.fit.column_at(v) - at(truth["left"], v)) < 10


def test_white_backup_answers_no_line_on_a_plain_floor():
    floor = np.full((480, 640, 3), (175, 180, 182), np.uint8)
    floor[:240] = (110, 100, 95)
    det = detect_lane(floor, "right")
    assert det.fit is None and det.source is None
    # a real white edge line on the right is found
    img = floor.copy()
    img[320:] = ROAD
    cv2.line(img, (420, 330), (620, 479), WHITE, 10)
    det = detect_lane(img, "right")
    assert det.source == "white"
    assert det.fit.column_at(479) == pytest.approx(620, abs=6)
    assert det.fit.slope == pytest.approx(200 / 149, abs=0.08)


def test_linear_poly_fit_block_fits_the_line_not_the_blob_beside_it():
    mask = np.zeros((480, 640), np.uint8)
    cv2.line(mask, (100, 479), (300, 300), 255, 6)
    cv2.circle(mask, (450, 420), 40, 255, -1)  # a round blob of the same colour (a patch of grass)
    fit = linear_poly_fit(mask)
    assert fit.slope == pytest.approx(-200 / 179, abs=0.02) and fit.column_at(479) == pytest.approx(100, abs=2)
    every = linear_poly_fit(mask, whole_mask=True)  # the sheet's block as it was: the blob drags it
    assert abs(every.column_at(420) - fit.column_at(420)) > 40
    white = white_line_mask(np.dstack([mask] * 3))
    assert white.shape == mask.shape and white[400].any()
    assert math.isfinite(fit.intercept)


def test_white_mask_is_grey_pixels_at_or_above_the_adaptive_level():
    """white_from_hsv = inRange(hsv, (0, 0, level), (179, s_max, 255)) with level from
    white_level: the definition, checked on random HSV images (dim, bright, saturated)."""
    from qcarlab.perception.lane import WHITE_S_MAX, WHITE_V_MIN, white_from_hsv, white_level

    rng = np.random.default_rng(7)
    for k in range(20):
        hsv = np.dstack([rng.integers(0, 180, (60, 90)), rng.integers(0, 256, (60, 90)),
                         rng.integers(40 + 5 * k, 256, (60, 90))]).astype(np.uint8)
        grey = cv2.inRange(hsv, (0, 0, 0), (179, WHITE_S_MAX, 255))
        level = white_level(hsv, grey, WHITE_V_MIN)
        want = (cv2.inRange(hsv, (0, 0, level), (179, WHITE_S_MAX, 255)) if level <= 255
                else np.zeros(hsv.shape[:2], np.uint8))
        assert np.array_equal(white_from_hsv(hsv), want)
