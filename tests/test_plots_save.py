"""plots._save draws a figure once and crops it to its ink (the tight box without measuring every
artist first), and writes the PNG at a low zlib level: the image must show what matplotlib's own
``savefig(bbox_inches="tight")`` of the same figure shows (one built twice: neither save sees the
other's draw), and a figure that reaches beyond its canvas must be saved exactly as savefig does."""

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
    return cv2.cvtColor(img, cv2.COLOR_BGR2BGRA) if img.shape[2] == 3 else img  # (ours are RGB: opaque)


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


def _ink(img: np.ndarray) -> np.ndarray:
    """The image cropped to its pixels that are not white (the figures' face)."""
    ink = np.any(img[:, :, :3] != 255, axis=2)
    rows, cols = np.flatnonzero(ink.any(axis=1)), np.flatnonzero(ink.any(axis=0))
    return img[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]


def _draws(monkeypatch) -> list:
    from matplotlib.figure import Figure

    calls: list = []
    draw = Figure.draw
    monkeypatch.setattr(Figure, "draw", lambda self, renderer: calls.append(1) or draw(self, renderer))
    return calls


@pytest.mark.parametrize("make", [_camera, _speed, _path, _drive, _depth, _polar],
                         ids=["camera", "speed", "path", "drive", "depth", "polar"])
def test_a_saved_png_shows_what_savefig_bbox_inches_tight_shows_in_one_draw(make, monkeypatch, tmp_path):
    reference = io.BytesIO()
    _built(make, monkeypatch).savefig(reference, format="png", bbox_inches="tight")
    fig = _built(make, monkeypatch)
    draws = _draws(monkeypatch)
    out = plots.save_figure(fig, tmp_path / "fig.png")
    assert len(draws) == 1  # every lab figure lies inside its canvas: no measuring pass, no second draw
    mine, theirs = _decoded(out.read_bytes()), _decoded(reference.getvalue())
    # the same ink (drawn at a sub-pixel offset of its own in savefig's box: edges may differ a little) ...
    a, b = _ink(mine), _ink(theirs)
    h, w = min(a.shape[0], b.shape[0]), min(a.shape[1], b.shape[1])
    assert abs(a.shape[0] - b.shape[0]) <= 5 and abs(a.shape[1] - b.shape[1]) <= 5  # (savefig's box moves a
    assert np.mean(np.abs(a[:h, :w].astype(int) - b[:h, :w].astype(int))) < 6.0  # figure legend 3 px: matplotlib's)
    # ... padded by savefig.pad_inches (0.1 in) where the tight box has the artists' blank margins too
    pad = [mine.shape[k] - a.shape[k] for k in (0, 1)]
    assert all(18 <= p <= 22 for p in pad), pad
    assert all(abs(theirs.shape[k] - mine.shape[k]) <= 10 for k in (0, 1)), (mine.shape, theirs.shape)
    assert out.stat().st_size <= 1.5 * len(reference.getvalue())


def test_a_figure_reaching_beyond_its_canvas_saves_as_savefig_would(tmp_path):
    """A legend outside the axes with no room kept for it: the tight box, measured, holds all of it."""
    def make():
        fig = plots._figure(4.0, 3.0)
        ax = fig.add_subplot(1, 1, 1)
        ax.plot([0, 1], [0, 1], label="a legend entry far wider than the room on the right")
        ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0))
        return fig

    reference = io.BytesIO()
    make().savefig(reference, format="png", bbox_inches="tight")
    out = plots.save_figure(make(), tmp_path / "wide.png")
    mine, theirs = _decoded(out.read_bytes()), _decoded(reference.getvalue())
    assert mine.shape == theirs.shape and mine.shape[1] > 4.0 * 100  # wider than the canvas: nothing cut off
    assert np.array_equal(mine, theirs)


def test_a_figure_saves_the_same_twice_and_keeps_its_layout_engine(tmp_path):
    fig = _built(_speed, pytest.MonkeyPatch())
    fig.tight_layout()  # (it leaves an inert layout engine behind)
    engine = fig.get_layout_engine()
    first = plots.save_figure(fig, tmp_path / "a.png").read_bytes()
    assert fig.get_layout_engine() is engine
    assert plots.save_figure(fig, tmp_path / "b.png").read_bytes() == first


@pytest.mark.parametrize("opaque", [False, True], ids=["rgba", "opaque"])
def test_both_encoders_write_the_same_pixels_and_resolution(monkeypatch, opaque):
    """OpenCV's encoder when a lab has loaded cv2, else Pillow's: the same image either way (RGB
    for a figure over an opaque face, else RGBA)."""
    import sys

    from PIL import Image

    rgba = np.dstack([np.random.default_rng(2).integers(0, 256, (37, 53, 3), dtype=np.uint8),
                      np.full((37, 53), 255, np.uint8)])
    rgba[0, 0, 3] = 255 if opaque else 128
    with_cv2 = plots._png(rgba, 100.0, opaque)
    monkeypatch.delitem(sys.modules, "cv2")
    with_pillow = plots._png(rgba, 100.0, opaque)
    for png in (with_cv2, with_pillow):
        im = Image.open(io.BytesIO(png))
        assert im.mode == ("RGB" if opaque else "RGBA") and im.info["dpi"] == pytest.approx((100.0, 100.0), abs=0.01)
        assert np.array_equal(np.asarray(im), rgba[:, :, :3] if opaque else rgba)


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
