"""The plots among the outputs are matplotlib figures with axes in metres, a title and a legend
naming every line and dot; the camera panels carry a legend of their overlays (issue 29)."""

from __future__ import annotations

import math

import numpy as np

from qcarlab import plots
from qcarlab.experiments.worlds import figure_map
from qcarlab.sim.world import load_world


def _labels(ax) -> list[str]:
    legend = ax.get_legend() or ax.figure.legends[0]
    return [t.get_text() for t in legend.get_texts()]


def _one_axes(fig):
    (ax,) = fig.axes
    assert ax.get_xlabel() == "X (m)" and ax.get_ylabel() == "Y (m)" and ax.get_title()
    return ax


def test_lane_png_is_a_map_in_metres_with_a_legend(tmp_path):
    from qcarlab.experiments.lane_follow import lane_figure

    world = load_world("track")
    a = np.linspace(0, math.pi / 2, 50)
    poses = np.column_stack((np.cos(a), np.sin(a), a + math.pi / 2))
    centre = poses[:, :2] * 1.02
    fig = lane_figure(world, poses, centre, {"rms_lateral_deviation_m": 0.02, "max_lateral_deviation_m": 0.05,
                                             "time_out_of_lane_s": 0.0})
    ax = _one_axes(fig)
    assert _labels(ax) == ["lane centre (reference)", "driven path (truth)", "car at the start", "car at the end"]
    assert "RMS lateral deviation 2.0 cm" in ax.get_title()
    xmin, xmax = ax.get_xlim()
    assert xmin < world.bounds[0] and xmax > world.bounds[2]  # the whole world, in metres
    out = plots.save_figure(fig, tmp_path / "lane.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_drive_png_explains_the_dots_and_the_collision():
    world = load_world("obstacles")
    bg, extent = figure_map(world, show_start=False)
    poses = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [1.0, 0.1, 0.2]])
    scans = [np.array([[1.5, 0.0], [1.6, 0.2]]), np.array([[1.4, 0.0]])]
    metrics = {"strategy": "stop", "duration_s": 3.0, "distance_m": 1.0, "collisions": 1, "min_clearance_m": 0.0,
               "collision": {"x": 1.0, "y": 0.1, "t": 2.9}}
    ax = _one_axes(plots.drive_figure(bg, extent, poses, scans, metrics))
    assert _labels(ax) == ["LIDAR returns (every 2nd scan)", "LIDAR returns, last scan", "driven path (truth)",
                           "car at the start", "car at the end", "collision"]
    assert "1 collision(s)" in ax.get_title() and "0.0 cm" in ax.get_title()


def test_trials_png_legend_names_each_kind_once():
    world = load_world("obstacles")
    bg, extent = figure_map(world, show_start=False)
    run = {"success": True, "path": [[0, 0], [0.5, 0.1]], "start": [0, 0, 0], "collision": None,
           "moved": [{"to": [1.0, 1.0]}], "balls": []}
    bad = {**run, "success": False, "collision": {"x": 0.5, "y": 0.1},
           "balls": [{"start": [2.0, 0.0], "rolls_m": 1.0, "direction_rad": math.pi}]}
    metrics = {"experiment": "avoid", "successes": 2, "trials": 3, "success_rate": 2 / 3, "collisions": 1,
               "runs": [run, run, bad]}
    ax = _one_axes(plots.trials_figure(bg, extent, metrics))
    assert _labels(ax) == ["a ball's roll", "trial succeeded", "trial failed", "an obstacle moved here",
                           "start of a trial", "collision"]
    assert ax.get_title().startswith("avoid: 2 of 3 trials succeeded (67 %)")


def test_camera_panels_have_titles_and_a_legend_of_the_overlays():
    from qcarlab.experiments.lane_follow import frame_figure
    from qcarlab.experiments.stop_sign import detection_figure
    from qcarlab.perception.lane import LaneDetection
    from qcarlab.perception.stop_sign import StopSignDetection

    color = np.zeros((480, 640, 3), np.uint8)
    fig = frame_figure(color, LaneDetection(None, None, 0, 0, None, None), (260, 200, 380, 280))
    assert [ax.get_title() for ax in fig.axes] == ["no line found"]
    assert _labels(fig.axes[0]) == ["the tracked line's pixels (HSV mask)", "the line fitted to them",
                                    "the obstacle window (depth averaged in it)"]
    det = StopSignDetection(True, (320.0, 240.0), (300, 220, 40, 40), 1600, 0.35,
                            mask=np.zeros((480, 640), np.uint8))
    fig = detection_figure(color, det, np.full((480, 640), 1.0, np.float32))
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[0] == "colour: stop sign 0.35 m" and titles[2].startswith("depth: black 0 m to white 3 m")
    assert _labels(fig.axes[0]) == ["the detected sign's box", "its centre (the distance is read there)"]


def test_the_hsv_tuners_figure_says_what_its_pixels_are():
    from qcarlab.experiments.lane_follow import hsv_tune_figure

    img = np.zeros((48, 64, 3), np.uint8)
    fig = hsv_tune_figure([[(img, "colour"), (img[:, :, 0], "HSV mask"), (img, "lane mask")]] * 2, "HSV range")
    texts = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    assert any(t.startswith("white: the pixels the HSV range keeps") for t in texts)
    assert any(t.startswith("red: the kept pixels in the lane's region") for t in texts)
    assert [ax.get_title() for ax in fig.axes][:3] == ["colour", "HSV mask", "lane mask"] and len(fig.axes) == 6
