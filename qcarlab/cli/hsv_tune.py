"""The sheet's HSV tuner in a terminal (``qcarlab lane-follow --hsv-tune``, ``qcarlab detect lanes
PHOTO --hsv-tune``): the six sliders (mean and window for H, S and V), a live preview of the mask
in half-block characters (in colour where the terminal has it) with the pixel count and the
line fit, keys to move them, and a profile YAML that ``--hsv FILE`` reads.

    profile = run_hsv_tuner(frames, HsvProfile(), Path("hsv.yaml"), stdout)

Without a terminal (stdin or stdout not a TTY: a pipe, CI, a script) it runs the automatic tuner
(:func:`qcarlab.perception.tuner.auto_tune`) over the frames and saves its result.

Keys: up/down (or k/j) pick a slider, left/right (h/l) move it by 1, ``[``/``]`` by 10, tab/n
and p change the frame, ``a`` runs the automatic tuner from where the sliders are, ``r`` resets
them to the defaults, ``s`` or enter saves and closes, ``q``/escape/ctrl-c closes without saving.
Works in tmux and screen (plain ANSI; no mouse).
"""

from __future__ import annotations

import os
import select
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from rich.console import Console, Group
from rich.live import Live
from rich.panel import Panel
from rich.style import Style
from rich.text import Text

from qcarlab.hsv_profile import save_hsv_profile
from qcarlab.perception.hsv_range import HsvProfile
from qcarlab.perception.lane import lane_mask
from qcarlab.perception.tuner import NAMES, SLIDERS, TOP, TuneFrames, TunerState, apply_key, auto_tune

__all__ = ["render", "run_hsv_tuner", "tuned_metrics"]

_BAR = 24  # characters of a slider's bar


def _interactive() -> bool:
    try:
        return sys.stdin.isatty() and sys.stdout.isatty()
    except (AttributeError, ValueError):
        return False


def _bar(value: float, top: float, width: int = _BAR) -> str:
    pos = int(round(value / top * (width - 1))) if top > 0 else 0
    return "━" * pos + "●" + "━" * (width - 1 - pos)


def _preview(frames: TuneFrames, i: int, profile: HsvProfile, cols: int, rows: int, color: bool) -> tuple[Text, dict]:
    """The frame with the kept pixels in red and the fitted line in green, ``cols`` x ``rows``
    cells of half blocks (two pixel rows per cell); and the fit's numbers."""
    img = frames.frames[i]
    h, w = img.shape[:2]
    hsv, r0, c0, need, width = frames.crops[i]
    k = w // width if width else 1
    q = frames.quality(i, profile)
    small = frames.mask(i, profile)
    full = np.zeros((h, w), np.uint8)
    part = cv2.resize(small, (small.shape[1] * k, small.shape[0] * k), interpolation=cv2.INTER_NEAREST)
    full[r0 * k:r0 * k + part.shape[0], c0 * k:c0 * k + part.shape[1]] = part[: h - r0 * k, : w - c0 * k]
    shown = lane_mask(img, full)
    if q.slope is not None:  # fit in tuning pixels -> image pixels
        v0, v1 = q.rows
        p0 = (int(round((q.slope * v0 + q.intercept) * k)), v0 * k)
        p1 = (int(round((q.slope * v1 + q.intercept) * k)), v1 * k)
        cv2.line(shown, p0, p1, (0, 255, 0), max(2, w // 100))
    cv2.line(shown, (0, r0 * k), (w - 1, r0 * k), (255, 255, 255), max(1, w // 320))
    cells = cv2.resize(shown, (cols, rows * 2), interpolation=cv2.INTER_AREA)
    kept = cv2.resize(full, (cols, rows * 2), interpolation=cv2.INTER_AREA) > 64
    text = Text(no_wrap=True, overflow="crop")
    for r in range(rows):
        top, bot = cells[2 * r], cells[2 * r + 1]
        if color:
            for c in range(cols):
                b1, g1, r1 = (int(x) for x in top[c])
                b2, g2, r2 = (int(x) for x in bot[c])
                text.append("▀", Style(color=f"rgb({r1},{g1},{b1})", bgcolor=f"rgb({r2},{g2},{b2})"))
        else:
            kt, kb = kept[2 * r], kept[2 * r + 1]
            text.append("".join("█" if a and b else "▀" if a else "▄" if b else " " for a, b in zip(kt, kb)))
        if r < rows - 1:
            text.append("\n")
    info = {"pixels": q.pixels * k * k, "line_pixels": q.line_pixels * k * k, "quality": q.quality,
            "slope": q.slope, "rows": None if q.rows is None else (q.rows[0] * k, q.rows[1] * k)}
    return text, info


def render(state: TunerState, frames: TuneFrames, width: int, height: int, color: bool, message: str = "") -> Panel:
    """The tuner's screen for a ``width`` x ``height`` terminal."""
    img = frames.frames[state.frame]
    h, w = img.shape[:2]
    cols = max(20, min(width - 4, 120))
    rows = max(6, min(height - 15, int(round(cols * h / w / 2.0))))
    cols = max(20, min(cols, int(round(rows * 2.0 * w / h))))
    preview, info = _preview(frames, state.frame, state.profile, cols, rows, color)
    lines = Text(no_wrap=True, overflow="ellipsis")
    lo, hi = state.profile.hsv_min, state.profile.hsv_max
    for k, (ch, part) in enumerate(SLIDERS):
        value = state.slider_value(k)
        mark = "▶" if k == state.selected else " "
        label = f"{mark} {NAMES[ch]} {part:<6s} {value:6.1f} "
        style = "bold reverse" if k == state.selected else ""
        lines.append(label, style=style)
        lines.append(_bar(value, TOP[ch]))
        lines.append(f"   {NAMES[ch]} {lo[ch]:3d}..{hi[ch]:3d}\n" if part == "window" else "\n")
    fit = "no line" if info["slope"] is None else \
        f"line: slope {info['slope']:+.2f} (u = m v + b), rows {info['rows'][0]}..{info['rows'][1]}"
    lines.append(f"kept: {info['pixels']} px in the region, {info['line_pixels']} on the line; {fit}\n")
    lines.append(f"quality {info['quality']:.2f} (share of kept pixels on the line x rows covered); "
                 f"mean over {len(frames)} frame(s) {frames.mean_quality(state.profile):.2f}\n")
    lines.append("↑↓ slider  ←→ ±1  [ ] ±10  tab frame  a auto  r reset  s save  q quit", style="dim")
    if message:
        lines.append(f"\n{message}", style="bold")
    title = f"HSV tuner · {frames.names[state.frame]} ({state.frame + 1}/{len(frames)}) · {w}x{h}"
    return Panel(Group(preview, lines), title=title, title_align="left", expand=False)


def _read_keys(fd: int, decoder, now: float) -> list[str] | None:
    from qcarlab.experiments.keyboard_drive import read_keys

    return read_keys(fd, decoder, now)


def run_hsv_tuner(
    frames: Sequence[np.ndarray],
    profile: HsvProfile | None = None,
    out_file: Path | None = None,
    console: Console | None = None,
    lane: str | None = None,
    names: Sequence[str] | None = None,
    interactive: bool | None = None,
    start: tuple[Sequence[int], Sequence[int]] | None = None,
) -> HsvProfile:
    """Tune the yellow range on ``frames`` (BGR images) from ``profile``; return the tuned
    profile and save it to ``out_file`` (in the interactive tuner: on ``s``; without a terminal:
    the automatic tuner's result; ``out_file`` None: ``hsv.yaml`` here after ``s``, nothing
    written by the automatic tuner). ``lane`` ("right"/"left") judges the lab's region, None the
    whole width from 60 % of the height (a photo). ``console`` prints one line on what was
    saved (None: quiet). Closing with ``q`` returns ``profile`` unchanged. ``start``
    (``hsv_min``, ``hsv_max``) stands for ``profile`` when that is None."""
    profile = profile or (HsvProfile(tuple(start[0]), tuple(start[1])) if start is not None else HsvProfile())
    tf = TuneFrames(frames, lane, names=names)
    if interactive is None:
        interactive = _interactive()
    if not interactive:
        tuned = auto_tune(tf, profile)
        if out_file is not None:
            save_hsv_profile(tuned, out_file)
        if console is not None:
            where = f"saved to {out_file}" if out_file is not None else "not saved (give --out to keep it)"
            console.print(f"automatic HSV tuner (no terminal): H,S,V {','.join(map(str, tuned.hsv_min))} .. "
                          f"{','.join(map(str, tuned.hsv_max))}, quality {tuned.score:.2f}; {where}",
                          markup=False, highlight=False)
        return tuned
    return _interactive_tuner(tf, profile, out_file, console or Console())


def tuned_metrics(profile: HsvProfile, path: Path | None) -> dict:
    """What a command reports of a tuned profile: the range, its quality, where it was saved."""
    return {"hsv_min": list(profile.hsv_min), "hsv_max": list(profile.hsv_max), "quality": profile.score,
            "file": str(path) if path is not None and Path(path).is_file() else None}


def _interactive_tuner(tf: TuneFrames, profile: HsvProfile, out_file: Path | None, console: Console) -> HsvProfile:
    from qcarlab.experiments.keyboard_drive import KeyDecoder, cbreak_terminal

    fd = sys.stdin.fileno()
    color = console.color_system is not None
    state = TunerState(profile, frames=len(tf))
    decoder = KeyDecoder()
    message = ""

    def screen() -> Panel:
        size = console.size
        return render(state, tf, size.width, size.height, color, message)

    with cbreak_terminal(fd):
        with Live(screen(), console=console, auto_refresh=False, transient=True) as live:
            while state.done not in ("save", "quit"):
                select.select([fd], [], [], 0.1)
                keys = _read_keys(fd, decoder, time.monotonic())
                if keys is None:  # the terminal went away
                    state = replace(state, done="quit")
                    break
                if not keys:
                    continue
                for key in keys:
                    state = apply_key(state, key)
                    if state.done == "auto":
                        tuned = auto_tune(tf, state.profile)
                        state = replace(state, profile=replace(tuned, tuned_on=()), done=None)
                        message = f"automatic tuner: quality {tuned.score:.2f}"
                    elif state.done in ("save", "quit"):
                        break
                    else:
                        message = ""
                live.update(screen(), refresh=True)
    if state.done == "save":
        target = out_file if out_file is not None else Path("hsv.yaml")
        saved = replace(state.profile, tuned_on=tuple(tf.names), score=round(tf.mean_quality(state.profile), 3))
        save_hsv_profile(saved, target)
        console.print(f"HSV profile saved to {target}: H,S,V {','.join(map(str, saved.hsv_min))} .. "
                      f"{','.join(map(str, saved.hsv_max))}", markup=False, highlight=False)
        return saved
    console.print("HSV tuner closed without saving", markup=False, highlight=False)
    return profile


if os.name != "posix":  # pragma: no cover - the interactive tuner needs termios
    _interactive = lambda: False  # noqa: E731
