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


def _raw(png: bytes) -> np.ndarray:
    """The PNG's pixels as stored: BGR (ours, opaque) or BGRA."""
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
    return img


def _bgra(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_BGR2BGRA) if img.shape[2] == 3 else img


def _decoded(png: bytes) -> np.ndarray:
    """The PNG's pixels as BGRA, whichever it stored."""
    return _bgra(_raw(png))


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
    when every pixel is opaque, else RGBA)."""
    import sys

    from PIL import Image

    rgba = np.dstack([np.random.default_rng(2).integers(0, 256, (37, 53, 3), dtype=np.uint8),
                      np.full((37, 53), 255, np.uint8)])
    rgba[0, 0, 3] = 255 if opaque else 128
    big = np.zeros((41, 60, 4), np.uint8)
    big[2:39, 3:56] = rgba
    rgba = big[2:39, 3:56]  # a view into a canvas, as a cropped figure is
    with_cv2 = plots._png(rgba, 100.0)
    monkeypatch.delitem(sys.modules, "cv2")
    with_pillow = plots._png(rgba, 100.0)
    for png in (with_cv2, with_pillow):
        im = Image.open(io.BytesIO(png))
        assert im.mode == ("RGB" if opaque else "RGBA") and im.info["dpi"] == pytest.approx((100.0, 100.0), abs=0.01)
        assert np.array_equal(np.asarray(im), rgba[:, :, :3] if opaque else rgba)


def _small(face="white"):
    fig = plots._figure(4.0, 3.0)
    fig.set_facecolor(face)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot([0, 1], [0, 1], label="a line")
    ax.legend()
    return fig


def _saved_like_savefig(make, tmp_path, draws_expected=None, monkeypatch=None):
    reference = io.BytesIO()
    make().savefig(reference, format="png", bbox_inches="tight")
    draws = _draws(monkeypatch) if monkeypatch else None
    out = plots.save_figure(make(), tmp_path / "f.png")
    if draws is not None:
        assert len(draws) == draws_expected
    return _raw(out.read_bytes()), _raw(reference.getvalue())


def test_a_grey_face_is_cropped_in_one_draw(tmp_path, monkeypatch):
    """The face as Agg rounds it (0.7 grey: 178.5 -> 179, half up): found, and no second draw."""
    mine, theirs = _saved_like_savefig(lambda: _small("0.7"), tmp_path, 1, monkeypatch)
    assert mine.shape[2] == 3 and tuple(mine[0, 0]) == (179, 179, 179)
    assert abs(mine.shape[0] - theirs.shape[0]) <= 10 and abs(mine.shape[1] - theirs.shape[1]) <= 10


def test_a_hidden_face_keeps_its_transparency(tmp_path):
    """No face drawn: the canvas is transparent where nothing is, and the PNG keeps its alpha, as savefig's."""
    def make():
        fig = _small()
        fig.patch.set_visible(False)
        return fig

    mine, theirs = _saved_like_savefig(make, tmp_path)
    assert mine.shape == theirs.shape and mine.shape[2] == 4
    assert np.array_equal(mine, theirs)
    assert (mine[:, :, 3] == 0).mean() > 0.2


@pytest.mark.parametrize("where", ["text", "animated"])
def test_what_a_canvas_draw_would_miss_is_saved_as_savefig_saves_it(tmp_path, where):
    """A text wholly beyond the canvas's edge (no ink at the edge tells), an animated artist (a
    canvas's draw leaves it out): saved exactly as savefig(bbox_inches="tight") saves them."""
    def make():
        fig = _small()
        if where == "text":
            fig.text(1.05, 0.5, "beyond the right edge")
        else:
            fig.axes[0].plot([0, 1], [1, 0], lw=6, color="red", animated=True)
        return fig

    mine, theirs = (_bgra(a) for a in _saved_like_savefig(make, tmp_path))
    assert mine.shape == theirs.shape and np.array_equal(mine, theirs)
    if where == "text":
        assert mine.shape[1] > 4.0 * 100


def test_a_mask_panel_shows_as_the_grey_map_shows_it_and_a_narrow_figure_widens_to_its_legend(tmp_path, monkeypatch):
    mask = np.zeros((120, 160), np.uint8)
    mask[40:80, 50:110] = 255
    legend = [("the pixels the HSV range keeps, a long label", "white", "pixels"),
              ("the line fitted to them, another long label", "lime", "line")]

    def grid(m):
        return plots.camera_grid([[(m, "mask")]], legend, "one narrow panel")

    draws = _draws(monkeypatch)
    a = _decoded(plots.save_figure(grid(mask), tmp_path / "a.png").read_bytes())
    assert len(draws) == 1  # the legend, wider than one panel, fits: no second draw
    monkeypatch.undo()
    fig = grid(mask)
    fig.axes[0].images[0].remove()
    fig.axes[0].imshow(mask, cmap="gray", interpolation="nearest")  # what the grey map shows
    b = _decoded(plots.save_figure(fig, tmp_path / "b.png").read_bytes())
    assert a.shape == b.shape and np.array_equal(a, b)
    assert a.shape[1] > 0.5 * fig.get_figwidth() * 100


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
