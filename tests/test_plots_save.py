"""plots._save draws a figure once (the tight box measured without a layout pass) and writes the PNG
at a low zlib level: the image must decode to the same pixels, and size, as matplotlib's own
``savefig(bbox_inches="tight")`` of the same figure (one built twice: neither save sees the other's draw)."""

from __future__ import annotations

import io
import math

import cv2
import numpy as np
import pytest

from qcarlab import plots


def _built(make, monkeypatch):
    """The Figure ``make()`` builds (a ``plot_*`` saves it: its ``_save`` is caught here)."""
    caught = []
    monkeypatch.setattr(plots, "_save", lambda fig, file: caught.append(fig))
    fig = make()
    monkeypatch.undo()
    return caught[0] if caught else fig


def _decoded(png: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
    return img


def _camera():
    rng = np.random.default_rng(1)
    color = cv2.GaussianBlur(rng.integers(0, 256, (480, 640, 3), dtype=np.uint8), (9, 9), 0)
    grey = color[:, :, 1].copy()
    return plots.camera_figure([(color, "colour"), (grey, "mask"), (color[::-1], "depth")],
                               [("box", "lime", "box"), ("centre", "red", "cross"), ("mask", "white", "pixels")],
                               "a title")


def _speed():
    t = np.linspace(0.0, 12.0, 1200)
    return plots.plot_speed({"t": t, "v_ref": np.minimum(t / 4, 0.5), "v_meas": 0.5 * (1 - np.exp(-t)),
                             "throttle": 0.1 * np.sin(t)}, "unused.png")  # tight_layout + a shared x


def _path():
    a = np.linspace(0.0, 2 * math.pi, 400)
    p = np.column_stack((np.sin(a), np.sin(a) * np.cos(a)))
    return plots.plot_path(p, "unused.png", tight_spots=[{"x": 0.0, "y": 0.0, "radius_m": 0.3}])  # legend outside


def _drive():
    from qcarlab.experiments.worlds import figure_map
    from qcarlab.sim.world import load_world

    background, extent = figure_map(load_world("hallway"))
    poses = np.column_stack((np.linspace(0, 2, 50), np.zeros(50), np.zeros(50)))
    scans = [np.column_stack((np.linspace(0, 3, 90), np.full(90, 0.6 + 0.1 * k))) for k in range(3)]
    return plots.drive_figure(background, extent, poses, scans,
                              {"strategy": "steer", "collisions": 1, "collision": {"x": 2.0, "y": 0.0}})


def _depth():
    d = np.tile(np.linspace(0.0, 3.0, 640, dtype=np.float32), (480, 1))
    return plots.plot_depth(d, "unused.png")  # a colour bar


def _polar():
    a = np.linspace(-math.pi, math.pi, 400, endpoint=False)
    return plots.plot_polar_scan(a, 1.0 + 0.3 * np.cos(3 * a), "unused.png")


@pytest.mark.parametrize("make", [_camera, _speed, _path, _drive, _depth, _polar],
                         ids=["camera", "speed", "path", "drive", "depth", "polar"])
def test_a_saved_png_has_the_pixels_of_savefig_bbox_inches_tight(make, monkeypatch, tmp_path):
    reference = io.BytesIO()
    _built(make, monkeypatch).savefig(reference, format="png", bbox_inches="tight")
    out = plots.save_figure(_built(make, monkeypatch), tmp_path / "fig.png")
    mine, theirs = _decoded(out.read_bytes()), _decoded(reference.getvalue())
    assert mine.shape == theirs.shape
    assert np.array_equal(mine, theirs)
    assert out.stat().st_size <= 1.5 * len(reference.getvalue())


def test_a_figure_saves_the_same_twice_and_keeps_its_layout_engine(tmp_path):
    fig = _built(_speed, pytest.MonkeyPatch())
    engine = fig.get_layout_engine()
    first = plots.save_figure(fig, tmp_path / "a.png").read_bytes()
    assert fig.get_layout_engine() is engine
    assert plots.save_figure(fig, tmp_path / "b.png").read_bytes() == first


def test_both_encoders_write_the_same_pixels_and_resolution(monkeypatch):
    """OpenCV's encoder when a lab has loaded cv2, else Pillow's: the same image either way."""
    import sys

    from PIL import Image

    rgba = np.dstack([np.random.default_rng(2).integers(0, 256, (37, 53, 3), dtype=np.uint8),
                      np.full((37, 53), 255, np.uint8)])
    with_cv2 = plots._png(rgba, 100.0)
    monkeypatch.delitem(sys.modules, "cv2")
    with_pillow = plots._png(rgba, 100.0)
    for png in (with_cv2, with_pillow):
        im = Image.open(io.BytesIO(png))
        assert im.mode == "RGBA" and im.info["dpi"] == pytest.approx((100.0, 100.0), abs=0.01)
        assert np.array_equal(np.asarray(im), rgba)


def test_a_figure_without_an_agg_canvas_saves_as_savefig_would(tmp_path):
    """save_figure is public: a bare matplotlib Figure() (no Agg canvas attached) is saved too."""
    from matplotlib.figure import Figure

    def bare():
        fig = Figure(figsize=(3, 2))
        fig.add_subplot().plot([0, 1, 0.5])
        return fig

    reference = io.BytesIO()
    bare().savefig(reference, format="png", bbox_inches="tight")
    out = plots.save_figure(bare(), tmp_path / "bare.png")
    assert np.array_equal(_decoded(out.read_bytes()), _decoded(reference.getvalue()))
