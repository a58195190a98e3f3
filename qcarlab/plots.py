"""PNG figures (matplotlib, Agg, imported lazily so that ``import qcarlab`` stays fast).

Figures are drawn with matplotlib's object API on an Agg canvas (no pyplot, no global state, no
display needed). Every plot takes the output ``file`` and returns it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["plot_cloud", "plot_depth", "plot_follow", "plot_path", "plot_polar_scan", "plot_speed",
           "plot_step_response", "plot_sweep"]


def _figure(width: float = 7.6, height: float = 6.0) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, file: str | Path) -> Path:
    out = Path(file)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, format="png", bbox_inches="tight")
    return out


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
    fig = _figure()
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
    fig.tight_layout()
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
