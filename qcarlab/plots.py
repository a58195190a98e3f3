"""PNG figures (matplotlib, Agg, imported lazily so that ``import qcarlab`` stays fast).

Figures are drawn with matplotlib's object API on an Agg canvas (no pyplot, no global state, no
display needed). Every ``plot_*`` takes the output ``file`` and returns it; every ``*_figure``
returns the matplotlib Figure (to check or change) and :func:`save_figure` writes it.
"""

from __future__ import annotations

import io
import struct
import sys
import zlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["camera_figure", "drive_figure", "lane_figure", "plot_cloud", "plot_depth", "plot_follow", "plot_path",
           "plot_polar_scan", "plot_speed", "plot_step_response", "plot_sweep", "save_figure", "trials_figure"]


def _figure(width: float = 7.6, height: float = 6.0, legend_room: float = 0.0) -> Any:
    """A Figure on an Agg canvas, ``width`` x ``height`` inches; ``legend_room`` inches more on the
    right for a legend outside the axes (the axes keep the place they would have had without it),
    so that everything lies inside the canvas and :func:`_save` crops it in one draw."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width + legend_room, height), dpi=100)
    FigureCanvasAgg(fig)
    if legend_room:
        sp = fig.subplotpars
        scale = width / (width + legend_room)
        fig.subplots_adjust(left=sp.left * scale, right=sp.right * scale)
    return fig


LEGEND_ROOM = 2.6  #: in: the room on the right of a figure whose legend is outside its axes


PNG_COMPRESS_LEVEL = 1  # zlib level of the PNGs: 2-4x faster to write than matplotlib's 6, some 1.1-1.25x the bytes


def _save(fig: Any, file: str | Path) -> Path:
    """Write ``fig`` to a PNG cropped as ``savefig(bbox_inches="tight")`` crops it, drawn once.

    ``bbox_inches="tight"`` measures every artist's extent first (``fig.get_tightbbox``: the tick
    labels laid out twice, some 40 % of a draw; with a finished ``fig.tight_layout()``'s inert
    engine, a whole second draw). Here the figure is drawn once on its own canvas and cropped to
    its ink (the pixels not of the face colour) padded by ``savefig.pad_inches``: the same box as
    the artists' up to their blank margins. A figure whose ink reaches the canvas's edge (a legend
    outside it, say) may reach beyond it and is saved as before: the tight box measured, the
    figure drawn in it. The RGBA buffer is encoded by :func:`_png` (tests/test_plots_save.py).
    """
    import matplotlib as mpl
    from matplotlib.layout_engine import PlaceHolderLayoutEngine

    out = Path(file)
    out.parent.mkdir(parents=True, exist_ok=True)
    engine = fig.get_layout_engine()
    inert = isinstance(engine, PlaceHolderLayoutEngine) and not (
        mpl.rcParams["figure.autolayout"] or mpl.rcParams["figure.constrained_layout.use"])
    pad, dpi = mpl.rcParams["savefig.pad_inches"], mpl.rcParams["savefig.dpi"]
    agg = hasattr(fig.canvas, "get_renderer") and hasattr(fig.canvas, "buffer_rgba")  # (a bare Figure() has none)
    plain = not mpl.rcParams["savefig.transparent"] and all(
        mpl.rcParams[f"savefig.{k}"] == "auto" for k in ("facecolor", "edgecolor"))  # the canvas's own colours
    if not agg or not plain or (engine is not None and not inert) or not isinstance(pad, float) \
            or dpi not in ("figure", fig.dpi):
        # a live layout engine lays out in savefig's first pass; a savefig dpi of its own measures there
        fig.savefig(out, format="png", bbox_inches="tight", pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL})
        return out
    if inert:
        fig.set_layout_engine(None)  # its execute() does nothing; without it savefig skips the layout pass
    try:
        fig.canvas.draw()
        rgba = np.asarray(fig.canvas.buffer_rgba())
        box = _ink_box(rgba, fig.get_facecolor()) if _drawn_as_saved(fig) else None
        if box is not None:  # everything drawn lies inside the canvas: crop it to the ink, padded
            out.write_bytes(_png(_padded(rgba, box, int(round(pad * fig.dpi))), fig.dpi))
            return out
        bbox = fig.get_tightbbox(fig.canvas.get_renderer()).padded(pad)
        raw = io.BytesIO()
        fig.savefig(raw, format="rgba", bbox_inches=bbox)
    finally:
        if inert:
            fig.set_layout_engine(engine)
    shape = np.asarray(fig.canvas.buffer_rgba()).shape  # the canvas savefig drew last: (H, W, 4)
    rgba = np.frombuffer(raw.getbuffer(), np.uint8).reshape(shape)
    out.write_bytes(_png(rgba, fig.dpi))
    return out


def _drawn_as_saved(fig: Any) -> bool:
    """Whether ``fig``'s canvas, drawn, is what savefig draws, all of it inside the canvas: no
    animated artist (savefig draws them, a canvas's draw leaves them out), no screen's
    device-pixel ratio (a doubled dpi), and no legend or text (of the figure or its axes, where
    things are put outside the axes) beyond the canvas's edge: one wholly outside leaves no ink
    at the edge to tell."""
    if getattr(fig, "_original_dpi", fig.dpi) != fig.dpi or fig.findobj(lambda a: a.get_animated(), include_self=False):
        return False
    renderer = fig.canvas.get_renderer()
    w, h = fig.bbox.width, fig.bbox.height
    # (a legend placed in its own axes or figure is inside it, or its ink reaches the edge: only one
    # anchored elsewhere is measured, measuring loc="best" again costs some 4 ms)
    outside = [leg for leg in fig.legends if leg.get_bbox_to_anchor() is not fig.bbox] + list(fig.texts)
    for ax in fig.axes:
        leg = ax.get_legend()
        outside += [*ax.texts, *([leg] if leg is not None and leg.get_bbox_to_anchor() is not ax.bbox else [])]
    for artist in outside:
        if artist.get_visible():
            b = artist.get_window_extent(renderer)
            if b.x0 < 0 or b.y0 < 0 or b.x1 > w or b.y1 > h:
                return False
    return True


def _ink_box(rgba: np.ndarray, face: Sequence[float]) -> tuple[int, int, int, int] | None:
    """The rows ``y0..y1`` and columns ``x0..x1`` (ends exclusive) of the pixels of an (H, W, 4)
    RGBA canvas that differ from the figure's face colour (as Agg rounds it: half up); None when
    some of them lie on the canvas's edge (something may reach beyond it) or the canvas is not
    the face colour where it is empty (its corners: a hidden face, say)."""
    face_px = np.array([int(255 * min(max(float(c), 0.0), 1.0) + 0.5) for c in face], np.uint8)
    words = rgba.view(np.uint32).reshape(rgba.shape[:2])
    bg = face_px.view(np.uint32)[0]
    if words[0, 0] != bg or words[-1, -1] != bg:
        return None
    ink = words != bg
    rows, cols = np.flatnonzero(ink.any(axis=1)), np.flatnonzero(ink.any(axis=0))
    if not len(rows):
        return None
    y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    if y0 == 0 or x0 == 0 or y1 == words.shape[0] or x1 == words.shape[1]:
        return None
    return y0, y1, x0, x1


def _padded(rgba: np.ndarray, box: tuple[int, int, int, int], margin: int) -> np.ndarray:
    """The canvas ``rgba`` cut to ``box`` (y0, y1, x0, x1) and ``margin`` pixels around it; where
    the canvas ends first, the margin is the face colour (its corner pixel)."""
    y0, y1, x0, x1 = box
    H, W = rgba.shape[:2]
    if y0 >= margin and x0 >= margin and y1 + margin <= H and x1 + margin <= W:
        return rgba[y0 - margin:y1 + margin, x0 - margin:x1 + margin]  # (a view: the encoder reads it as it is)
    out = np.empty((y1 - y0 + 2 * margin, x1 - x0 + 2 * margin, 4), np.uint8)
    out[:] = rgba[0, 0]
    a, b, c, d = max(y0 - margin, 0), min(y1 + margin, H), max(x0 - margin, 0), min(x1 + margin, W)
    out[a - (y0 - margin):b - (y0 - margin), c - (x0 - margin):d - (x0 - margin)] = rgba[a:b, c:d]
    return out


def _png(rgba: np.ndarray, dpi: float) -> bytes:
    """An (H, W, 4) uint8 RGBA image as PNG bytes at :data:`PNG_COMPRESS_LEVEL`, with the
    resolution (``dpi``, a pHYs chunk) matplotlib's PNGs carry: RGB when it is opaque (alpha 255
    everywhere, as a figure drawn over an opaque face), else RGBA, 8 bits. OpenCV's encoder when a
    camera lab has loaded it (the Up filter on every row: 2x faster than the encoder's own choice
    for a figure, for as many bytes; RGB a further 1.2-1.5x), else Pillow's, which matplotlib has
    loaded (importing OpenCV would cost more than it saves)."""
    opaque = bool(rgba[:, :, 3].min() == 255)
    cv2 = sys.modules.get("cv2")
    if cv2 is None:
        from PIL import Image

        buf = io.BytesIO()
        im = Image.frombuffer("RGBA", (rgba.shape[1], rgba.shape[0]), np.ascontiguousarray(rgba), "raw", "RGBA", 0, 1)
        (im.convert("RGB") if opaque else im).save(buf, format="png", compress_level=PNG_COMPRESS_LEVEL,
                                                   dpi=(dpi, dpi))
        return buf.getvalue()
    params = [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESS_LEVEL]
    if hasattr(cv2, "IMWRITE_PNG_FILTER"):  # (OpenCV >= 4.11) the Up filter on every row: half the
        # time of the encoder's own choice for a figure, as many bytes (a camera frame does better without)
        params += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP]
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGR if opaque else cv2.COLOR_RGBA2BGRA), params)
    if not ok:
        raise OSError("cannot encode the figure as PNG")
    data = buf.tobytes()
    ppm = int(dpi / 0.0254 + 0.5)  # pixels per metre, as Pillow rounds it
    phys = struct.pack(">IIB", ppm, ppm, 1)
    chunk = struct.pack(">I", len(phys)) + b"pHYs" + phys + struct.pack(">I", zlib.crc32(b"pHYs" + phys))
    return data[:33] + chunk + data[33:]  # after the signature (8 bytes) and the IHDR chunk (25)


def plot_path(
    path: np.ndarray,
    file: str | Path,
    title: str = "Reference path",
    tight_spots: Sequence[Mapping[str, Any]] | None = None,
) -> Path:
    """Plot a path (``(N, 2)``, m) to a PNG: equal axes in metres, grid, start and direction.

    The start is a green dot with an arrow along the first segment; the end a red square.
    ``tight_spots`` (``paths.summary(path)["tight_spots"]``: dicts with ``x``, ``y``,
    ``radius_m``) are circled in red and labelled with their radius.
    """
    p = np.asarray(path, dtype=float).reshape(-1, 2)
    fig = _figure(legend_room=LEGEND_ROOM)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(p[:, 0], p[:, 1], "-", color="tab:blue", lw=1.5, label="path")
    if len(p):
        ax.plot(p[0, 0], p[0, 1], "o", color="tab:green", ms=8, label="start", zorder=3)
        ax.plot(p[-1, 0], p[-1, 1], "s", color="tab:red", ms=6, label="end", zorder=3)
        steps = np.diff(p, axis=0)
        moving = np.flatnonzero(np.hypot(steps[:, 0], steps[:, 1]) > 0)
        if len(moving):
            span = max(float(np.ptp(p[:, 0])), float(np.ptp(p[:, 1])), 1e-9)
            d = steps[moving[0]] / np.hypot(*steps[moving[0]])
            ax.annotate(
                "",
                xy=(p[0, 0] + 0.12 * span * d[0], p[0, 1] + 0.12 * span * d[1]),
                xytext=(p[0, 0], p[0, 1]),
                arrowprops={"arrowstyle": "->", "color": "tab:green", "lw": 2},
                zorder=4,
            )
    for i, spot in enumerate(tight_spots or []):
        x, y, r = float(spot["x"]), float(spot["y"]), float(spot["radius_m"])
        ax.plot(x, y, "o", ms=18, mfc="none", mec="tab:red", mew=1.5,
                label="tighter than the car can turn" if i == 0 else None, zorder=3)
        ax.annotate(f"r = {r:.2f} m", (x, y), xytext=(10, 10), textcoords="offset points",
                    color="tab:red", fontsize=9)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.4)
    ax.set_xlabel("X (m)")
    ax.set_ylabel("Y (m)")
    ax.set_title(title)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, borderaxespad=0.0)
    return _save(fig, file)


def estimate_label(pose: str, short: bool = False) -> str:
    """What the logged pose estimate of a path-follow run is: the ``--pose`` source, except under
    ``--pose truth``, where the controller had the simulator's truth and the bicycle model's estimate
    ran beside it, unused (it is not the truth)."""
    if pose == "truth":
        return "bicycle, unused" if short else "bicycle, unused: --pose truth"
    return pose


def plot_follow(path: np.ndarray, log: Mapping[str, Any], metrics: Mapping[str, Any], file: str | Path) -> Path:
    """Reference path against the driven path (true pose on a simulator, else the estimate),
    the dead-reckoning estimate dashed, and the worst cross-track error marked."""
    p = np.asarray(path, dtype=float)
    fig = _figure()
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(p[:, 0], p[:, 1], "-", color="0.6", lw=3, label="reference")
    if "true_x" in log:
        ax.plot(log["true_x"], log["true_y"], "-", color="tab:blue", lw=1.3, label="driven (truth)")
        ax.plot(log["est_x"], log["est_y"], "--", color="tab:orange", lw=1, label=f"estimate ({estimate_label(metrics['config']['pose'])})")
    else:
        ax.plot(log["est_x"], log["est_y"], "-", color="tab:blue", lw=1.3, label="driven (estimate)")
    wx, wy = metrics["worst_point"]
    ax.plot(wx, wy, "x", color="tab:red", ms=10, mew=2,
            label=f"worst error {metrics['max_cross_track_m'] * 100:.1f} cm")
    ax.plot(p[0, 0], p[0, 1], "o", color="tab:green", ms=8, label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.4)
    ax.set_xlabel("X (m)")
    ax.set_ylabel("Y (m)")
    ax.set_title(f"{metrics.get('path', 'path')}: RMS cross-track {metrics['rms_cross_track_m'] * 100:.1f} cm, "
                 f"completion {metrics['completion'] * 100:.0f} %")
    ax.legend(loc="best", fontsize=8)
    return _save(fig, file)


def plot_speed(log: Mapping[str, Any], file: str | Path) -> Path:
    """Desired against measured speed over time (the sheet's scope, Figure 44), and the throttle."""
    fig = _figure(7.0, 4.5)
    ax = fig.add_subplot(2, 1, 1)
    ax.plot(log["t"], log["v_ref"], "-", color="tab:orange", label="desired")
    ax.plot(log["t"], log["v_meas"], "-", color="tab:blue", lw=1, label="measured (encoder)")
    ax.set_ylabel("speed (m/s)")
    ax.grid(True, alpha=0.4)
    ax.legend(loc="best", fontsize=8)
    ax2 = fig.add_subplot(2, 1, 2, sharex=ax)
    ax2.plot(log["t"], log["throttle"], "-", color="tab:green")
    ax2.set_ylabel("throttle (duty)")
    ax2.set_xlabel("time (s)")
    ax2.grid(True, alpha=0.4)
    # margins in inches, room for the labels (what tight_layout would measure, at twice the cost of the draw;
    # _save crops the rest)
    fig.subplots_adjust(left=0.85 / 7.0, right=1 - 0.15 / 7.0, bottom=0.55 / 4.5, top=1 - 0.12 / 4.5,
                        hspace=0.28)
    return _save(fig, file)


def plot_sweep(path: np.ndarray, runs: Sequence[tuple[float, Mapping[str, Any], Mapping[str, Any]]],
               file: str | Path) -> Path:
    """Overlay of the driven paths of a look-ahead sweep, ``runs`` = (look-ahead, log, metrics)."""
    p = np.asarray(path, dtype=float)
    fig = _figure()
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(p[:, 0], p[:, 1], "-", color="0.6", lw=3, label="reference")
    for lookahead, log, metrics in runs:
        x, y = (log["true_x"], log["true_y"]) if "true_x" in log else (log["est_x"], log["est_y"])
        ax.plot(x, y, "-", lw=1, label=f"l_d = {lookahead:g} m: RMS {metrics['rms_cross_track_m'] * 100:.1f} cm")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.4)
    ax.set_xlabel("X (m)")
    ax.set_ylabel("Y (m)")
    ax.set_title("look-ahead sweep")
    ax.legend(loc="best", fontsize=8)
    return _save(fig, file)


def plot_step_response(log: Mapping[str, Any], metrics: Mapping[str, Any], file: str | Path) -> Path:
    """A speed step: desired and measured speed, with the 2 % band and the figures in the title."""
    fig = _figure(7.0, 4.0)
    ax = fig.add_subplot(1, 1, 1)
    step = metrics["speed_step_mps"]
    ax.axhspan(0.98 * step, 1.02 * step, color="tab:orange", alpha=0.15, label="2 % band")
    ax.plot(log["t"], log["v_ref"], "-", color="tab:orange", label="desired")
    ax.plot(log["t"], log["v_meas"], "-", color="tab:blue", label="measured")
    rise = metrics["rise_time_s"]
    who = metrics.get("controller", "")
    gains = "your speed_controller" if who.startswith("your") else f"Kp {metrics['kp']}, Ki {metrics['ki']}"
    ax.set_title(f"{gains}: rise {rise if rise is None else round(rise, 2)} s, "
                 f"overshoot {metrics['overshoot_pct']:.1f} %")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("speed (m/s)")
    ax.grid(True, alpha=0.4)
    ax.legend(loc="best", fontsize=8)
    return _save(fig, file)


def plot_polar_scan(angles: np.ndarray, ranges: np.ndarray, file: str | Path, title: str = "LIDAR scan") -> Path:
    """The sheet's body-frame polar plot (Figure 24): forward up, angles counter-clockwise."""
    fig = _figure(6.0, 6.0)
    ax = fig.add_subplot(1, 1, 1, projection="polar")
    ok = ranges > 0
    ax.scatter(angles[ok], ranges[ok], s=2, color="tab:red")
    ax.set_theta_zero_location("N")  # forward (body x) up
    ax.set_theta_direction(1)  # counter-clockwise, REP-103
    ax.set_title(f"{title} ({int(ok.sum())} returns; range in m)")
    return _save(fig, file)


def plot_cloud(cloud: np.ndarray, poses: Sequence[Sequence[float]], file: str | Path,
               background: np.ndarray | None = None, extent: Sequence[float] | None = None) -> Path:
    """Scan points accumulated in the world frame (the sheet's point-cloud map, Figure 25),
    over an optional top-down render of the world (``extent`` = [xmin, xmax, ymin, ymax])."""
    fig = _figure()
    ax = fig.add_subplot(1, 1, 1)
    if background is not None and extent is not None:
        ax.imshow(background[:, :, ::-1], extent=extent, origin="upper", alpha=0.5)
    ax.scatter(cloud[:, 0], cloud[:, 1], s=1, color="tab:red", label="LIDAR returns")
    if poses:
        p = np.asarray(poses)
        ax.plot(p[:, 0], p[:, 1], "-", color="tab:blue", lw=1)
        ax.quiver(p[-1, 0], p[-1, 1], np.cos(p[-1, 2]), np.sin(p[-1, 2]), color="tab:blue", scale=15,
                  label="LIDAR pose")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.4)
    ax.set_xlabel("X (m)")
    ax.set_ylabel("Y (m)")
    ax.set_title("point cloud in the world frame")
    ax.legend(loc="upper right", fontsize=8)
    return _save(fig, file)


def plot_depth(depth: np.ndarray, file: str | Path) -> Path:
    """A depth image with a colour scale bar in metres; pixels with no data (0) in black.
    Answers the sheet's question "darker = closer?" by looking at the bar."""
    fig = _figure(7.2, 5.0)
    ax = fig.add_subplot(1, 1, 1)
    shown = np.ma.masked_equal(depth, 0.0)
    from matplotlib import colormaps

    cmap = colormaps["viridis"].with_extremes(bad="black")
    im = ax.imshow(shown, cmap=cmap)
    bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    bar.set_label("depth (m): dark = near, bright = far; black = no data")
    ax.set_title("RGBD depth")
    ax.set_axis_off()
    return _save(fig, file)


# ------------------------------------------------------------------ top-down maps (world frame, m)
CAR_SIZE = (0.425, 0.192)  # m, length x width (DESIGN.md section 3): the outline drawn at a pose


def save_figure(fig: Any, file: str | Path) -> Path:
    """Write a Figure made by one of the ``*_figure`` functions to a PNG; returns the path."""
    return _save(fig, file)


def _map_axes(fig: Any, background: np.ndarray | None, extent: Sequence[float] | None, title: str) -> Any:
    """One equal-aspect axes in metres over the world seen from above (a BGR render and its
    ``[xmin, xmax, ymin, ymax]``, as :func:`qcarlab.experiments.worlds.topdown_map` gives them)."""
    ax = fig.add_subplot(1, 1, 1)
    if background is not None and extent is not None:
        ax.imshow(background[:, :, ::-1], extent=list(extent), origin="upper", interpolation="antialiased",
                  zorder=0)
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal")
    ax.grid(True, alpha=0.3)
    ax.set_xlabel("X (m)")
    ax.set_ylabel("Y (m)")
    ax.set_title(title, fontsize=10)
    return ax


def _outline(ax: Any, pose: Sequence[float], color: str, label: str | None, size: Sequence[float] = CAR_SIZE,
             arrow: bool = False) -> None:
    x, y, yaw = (float(v) for v in pose[:3])
    c, s = np.cos(yaw), np.sin(yaw)
    hl, hw = size[0] / 2.0, size[1] / 2.0
    local = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw], [hl, hw]])
    pts = np.column_stack((x + c * local[:, 0] - s * local[:, 1], y + s * local[:, 0] + c * local[:, 1]))
    ax.plot(pts[:, 0], pts[:, 1], "-", color=color, lw=2, label=label, zorder=5)
    if arrow:
        ax.annotate("", xy=(x + 0.35 * c, y + 0.35 * s), xytext=(x, y), zorder=5,
                    arrowprops={"arrowstyle": "->", "color": color, "lw": 2})


def _legend_outside(ax: Any) -> None:
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, borderaxespad=0.0, framealpha=0.95,
              markerscale=2.0)


def lane_figure(background: np.ndarray | None, extent: Sequence[float] | None, poses: np.ndarray,
                centre: np.ndarray | None, metrics: Mapping[str, Any] | None = None) -> Any:
    """``lane.png``: the lane's centre (the reference), the driven path (the simulator's truth),
    the start and the car at the end, over the track seen from above, in metres. Returns the Figure."""
    m = metrics or {}
    rms = m.get("rms_lateral_deviation_m")
    title = "lane following: the driven path in the lane"
    if rms is not None:
        title += (f"\nRMS lateral deviation {rms * 100:.1f} cm, max {m['max_lateral_deviation_m'] * 100:.1f} cm, "
                  f"{m.get('time_out_of_lane_s', 0.0):.2f} s out of the lane")
    fig = _figure(legend_room=LEGEND_ROOM)
    ax = _map_axes(fig, background, extent, title)
    q = np.asarray(poses, dtype=float).reshape(-1, 3)
    if centre is not None and len(centre) >= 2:
        c = np.asarray(centre, dtype=float)
        ax.plot(c[:, 0], c[:, 1], "--", color="tab:purple", lw=1.5, label="lane centre (reference)", zorder=3)
    if len(q):
        ax.plot(q[:, 0], q[:, 1], "-", color="tab:red", lw=1.8, label="driven path (truth)", zorder=4)
        _outline(ax, q[0], "tab:green", "car at the start", arrow=True)
        _outline(ax, q[-1], "tab:red", "car at the end")
    _legend_outside(ax)
    return fig


def drive_figure(background: np.ndarray | None, extent: Sequence[float] | None, poses: np.ndarray | None,
                 scans: Sequence[np.ndarray], metrics: Mapping[str, Any]) -> Any:
    """``drive.png`` (``qcarlab avoid``): the driven path, LIDAR returns in the world frame (``scans``:
    world-frame (N, 2) arrays, the last one the final scan), the car at the start and at the end and a
    collision, over the world seen from above, in metres. Returns the Figure."""
    m = metrics
    clear = "n/a" if m.get("min_clearance_m") is None else f"{m['min_clearance_m'] * 100:.1f} cm"
    title = (f"avoid ({m.get('strategy', '')}): {m.get('duration_s', 0.0):.1f} s, {m.get('distance_m', 0.0):.2f} m "
             f"driven, {m.get('collisions', 0)} collision(s), min clearance {clear}")
    fig = _figure(8.4, 6.0, LEGEND_ROOM)
    ax = _map_axes(fig, background, extent, title)
    scans = [np.asarray(s, dtype=float).reshape(-1, 2) for s in scans]
    if len(scans) > 1:
        older = np.concatenate(scans[:-1])
        ax.scatter(older[:, 0], older[:, 1], s=1.5, color="tab:blue", alpha=0.5, linewidths=0,
                   label="LIDAR returns (every 2nd scan)", zorder=2)
    if scans:
        ax.scatter(scans[-1][:, 0], scans[-1][:, 1], s=6, color="tab:orange", linewidths=0,
                   label="LIDAR returns, last scan", zorder=3)
    if poses is not None and len(poses):
        q = np.asarray(poses, dtype=float).reshape(-1, 3)
        ax.plot(q[:, 0], q[:, 1], "-", color="tab:red", lw=1.8, label="driven path (truth)", zorder=4)
        _outline(ax, q[0], "tab:green", "car at the start", arrow=True)
        _outline(ax, q[-1], "tab:red", "car at the end")
    hit = m.get("collision")
    if hit:
        ax.plot(hit["x"], hit["y"], "X", color="red", mec="black", ms=12, label="collision", zorder=6)
    _legend_outside(ax)
    return fig


def trials_figure(background: np.ndarray | None, extent: Sequence[float] | None, metrics: Mapping[str, Any]) -> Any:
    """``trials.png`` (``qcarlab trials``): every trial's path, green when it succeeded and red when
    it failed, its start, its collision, the balls' rolls and where obstacles were moved to, over
    the world seen from above, in metres. Returns the Figure."""
    m = metrics
    title = (f"{m['experiment']}: {m['successes']} of {m['trials']} trials succeeded "
             f"({100.0 * m['success_rate']:.0f} %), {m['collisions']} collision(s)")
    fig = _figure(8.4, 6.0, LEGEND_ROOM)
    ax = _map_axes(fig, background, extent, title)
    runs = m.get("runs", [])
    labelled: set[str] = set()

    def once(label: str) -> str | None:
        if label in labelled:
            return None
        labelled.add(label)
        return label

    for r in runs:
        for b in r.get("balls", []):
            a = b["start"]
            e = (a[0] + b["rolls_m"] * np.cos(b["direction_rad"]), a[1] + b["rolls_m"] * np.sin(b["direction_rad"]))
            ax.plot([a[0], e[0]], [a[1], e[1]], "--", color="tab:orange", lw=1, label=once("a ball's roll"), zorder=2)
    for ok_pass in (True, False):  # failures drawn last, on top
        for r in runs:
            if r["success"] != ok_pass or len(r["path"]) < 2:
                continue
            p = np.asarray(r["path"], dtype=float)
            ax.plot(p[:, 0], p[:, 1], "-", color="tab:green" if ok_pass else "tab:red", lw=1.5, zorder=3,
                    label=once("trial succeeded" if ok_pass else "trial failed"))
    for r in runs:
        for mv in r.get("moved", []):
            ax.plot(mv["to"][0], mv["to"][1], "o", color="saddlebrown", ms=3,
                    label=once("an obstacle moved here"), zorder=4)
    for r in runs:
        ax.plot(r["start"][0], r["start"][1], "o", color="black", ms=4, label=once("start of a trial"), zorder=5)
        hit = r.get("collision")
        if hit:
            ax.plot(hit["x"], hit["y"], "X", color="red", mec="black", ms=10, label=once("collision"), zorder=6)
    _legend_outside(ax)
    return fig


# ------------------------------------------------------------- camera frames with their overlays
def _rgba(bgr: np.ndarray) -> np.ndarray:
    """A BGR image as the RGBA matplotlib shows: uint8 with an opaque alpha, which imshow resamples
    in float32 as it is, where an RGB one gets its alpha stacked on in float64 first (the same
    pixels, some 40 % less work per panel)."""
    if bgr.dtype != np.uint8 or bgr.shape[2] != 3:
        return bgr[:, :, ::-1]
    rgba = np.empty(bgr.shape[:2] + (4,), np.uint8)
    rgba[:, :, :3] = bgr[:, :, ::-1]
    rgba[:, :, 3] = 255
    return rgba


def camera_figure(panels: Sequence[tuple[np.ndarray, str]], legend: Sequence[tuple[str, str, str]],
                  title: str = "", px_per_inch: float = 100.0) -> Any:
    """Camera images (BGR or grey, each with its panel title) side by side at about their own
    resolution, with a legend of the overlays: ``legend`` = (what it is, matplotlib colour, kind),
    kind ``"line"``, ``"box"``, ``"pixels"`` or ``"cross"``. Returns the Figure."""
    return camera_grid([list(panels)], legend, title, px_per_inch)


def camera_grid(rows: Sequence[Sequence[tuple[np.ndarray, str]]], legend: Sequence[tuple[str, str, str]],
                title: str = "", px_per_inch: float = 100.0) -> Any:
    """:func:`camera_figure` with several rows of panels (e.g. one row per spot). Returns the Figure."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    n_rows = max(1, len(rows))
    n = max([len(r) for r in rows] + [1])
    first = rows[0][0][0] if rows and rows[0] else None
    h, w = first.shape[:2] if first is not None else (480, 640)
    fig = _figure(1.07 * n * w / px_per_inch + 0.3, n_rows * (h / px_per_inch + 0.35) + 0.75)
    for i, row in enumerate(rows):
        for k, (img, name) in enumerate(row):
            ax = fig.add_subplot(n_rows, n, i * n + k + 1)
            im = np.asarray(img)
            if im.ndim == 2 and im.dtype == np.uint8 and im.min() == 0 and im.max() == 255 \
                    and ((im == 0) | (im == 255)).all():  # a mask: black and white as the grey map shows it, unmapped
                im = np.repeat(im[:, :, None], 3, axis=2)
            ax.imshow(_rgba(im) if im.ndim == 3 else im, cmap=None if im.ndim == 3 else "gray",
                      interpolation="nearest")
            ax.set_title(name, fontsize=10)
            ax.set_xticks([])
            ax.set_yticks([])
    handles = []
    for label, color, kind in legend:
        if kind == "pixels":
            handles.append(Patch(facecolor=color, edgecolor="0.3", label=label))  # (white pixels need an edge)
        elif kind == "box":
            handles.append(Patch(facecolor="none", edgecolor=color, lw=2, label=label))
        elif kind == "cross":
            handles.append(Line2D([], [], ls="none", marker="+", ms=10, mew=2, color=color, label=label))
        else:
            handles.append(Line2D([], [], color=color, lw=2, label=label))
    if handles:
        leg = fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 3), fontsize=9, frameon=False)
        wide = leg.get_window_extent(fig.canvas.get_renderer()).width / fig.dpi + 0.3
        if wide > fig.get_figwidth():  # (one panel, three long entries) the legend inside the canvas
            fig.set_figwidth(wide)
    if title:
        fig.suptitle(title, fontsize=11)
    top_margin, bottom_margin = (0.85 if title else 0.35), (0.45 if handles else 0.1)
    height = fig.get_figheight()
    fig.subplots_adjust(left=0.01, right=0.99, top=1.0 - top_margin / height, bottom=bottom_margin / height,
                        wspace=0.03, hspace=0.2)
    return fig
