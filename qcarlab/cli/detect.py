"""``qcarlab detect lanes|stop-sign PATH...``: the lab's perception on your own photos and videos.

    qcarlab detect lanes road.jpg                       # a table: left and right line, confidence
    qcarlab detect lanes photos/ drive.mp4 --every 5 --json --out runs/lanes
    qcarlab detect lanes mat.jpg --hsv-tune --hsv mat.yaml  # tune the yellow range on it, save it
    qcarlab detect stop-sign lab.jpg --method hough --depth lab_depth.npy

PATH is an image, a video or a folder of them. ``--json`` prints one JSON object per frame
(JSON lines); ``--out DIR`` writes an overlay per image (PNG) or video (MP4: H.264 with PyAV, the ``video``
extra; else OpenCV's MPEG-4 Part 2, which browsers may not play) and
``detections.jsonl``. Exit 0 when every input was read, 2 on bad input (one line).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import cv2
import numpy as np
import typer
from rich.console import Console

from qcarlab.cli.app import app
from qcarlab.cli.common import DebugOpt, Table, check_out, parse_hsv, stdout
from qcarlab.cli.helpfmt import Typer
from qcarlab.errors import InputError
from qcarlab.hsv_profile import load_hsv_profile
from qcarlab.media import Source, VideoOut, expand_paths, frames_of, read_depth, video_fps
from qcarlab.perception.hsv_range import HsvProfile
from qcarlab.perception.lane_lines import ROI_TOP, detect_lane_lines, lane_lines_image
from qcarlab.perception.stop_signs import METHODS, detect_stop_signs, signs_image

detect_app = Typer(
    help="Run the lab's perception on your own photos and videos: lane lines, stop signs.",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="rich",
    context_settings={"help_option_names": ["-h", "--help"]},
)
app.add_typer(detect_app, name="detect")

PathsArg = Annotated[list[Path], typer.Argument(help="Images, videos or folders of them.", show_default=False)]
EveryOpt = Annotated[int, typer.Option("--every", min=1, help="Every N-th frame of a video (1 = all).")]
JsonOpt = Annotated[bool, typer.Option("--json", help="One JSON object per frame on stdout (JSON lines), nothing else.")]
OutOpt = Annotated[Path | None, typer.Option("--out", help="Folder for the overlays (PNG / MP4) and detections.jsonl.",
                                             callback=check_out)]
TUNE_FRAMES = 8  # frames the tuner sees at most


class _Outputs:
    """Where a run's overlays and JSON lines go."""

    def __init__(self, out: Path | None, json_out: bool):
        self.out, self.json_out = out, json_out
        self.rows: list[dict] = []
        self.written: list[Path] = []
        self.notes: list[str] = []
        self._names: set[str] = set()
        self._jsonl = None
        if out is not None:
            try:
                out.mkdir(parents=True, exist_ok=True)
                self._jsonl = (out / "detections.jsonl").open("w", encoding="utf-8")
            except OSError as exc:
                raise InputError(f"{out}: cannot write here ({exc.strerror or exc})") from None

    def name(self, src: Source, ext: str) -> Path:
        stem = src.path.stem
        name, n = f"{stem}{ext}", 2
        while name in self._names:
            name, n = f"{stem}-{n}{ext}", n + 1
        self._names.add(name)
        return self.out / name

    def emit(self, row: dict) -> None:
        line = json.dumps(row)
        if self.json_out:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()
        if self._jsonl is not None:
            self._jsonl.write(line + "\n")
        self.rows.append(row)

    def image(self, src: Source, img: np.ndarray) -> None:
        path = self.name(src, ".png")
        if not cv2.imwrite(str(path), img):
            raise InputError(f"{path}: cannot write the overlay")
        self.written.append(path)

    def close(self) -> None:
        if self._jsonl is not None:
            self._jsonl.close()
            self.written.append(self.out / "detections.jsonl")


def _run(sources: list[Source], every: int, outputs: _Outputs, detect, overlay) -> None:
    """Detect on every frame; overlays per image / per video."""
    for src in sources:
        video = None
        if outputs.out is not None and src.kind == "video":
            video = VideoOut(outputs.name(src, ".mp4"), max(1.0, video_fps(src.path) / every))
        try:
            for index, frame in frames_of(src, every):
                row, found = detect(frame)
                outputs.emit({"file": str(src.path), "frame": index, **row})
                if outputs.out is not None:
                    img = overlay(frame, found)
                    if video is not None:
                        video.write(img)
                    else:
                        outputs.image(src, img)
        finally:
            if video is not None:
                video.close()
                outputs.written.append(video.path)
                if video.note and video.note not in outputs.notes:
                    outputs.notes.append(video.note)  # once per run: the video may not play in a browser
                    _console(outputs.json_out).print(f"note: {video.note}", markup=False, soft_wrap=True)


def _console(json_out: bool) -> Console:
    return Console(stderr=True, highlight=False) if json_out else stdout


# ------------------------------------------------------------------------------------------- lanes
def _fmt_line(pts) -> str:
    if pts is None:
        return "-"
    (x0, y0), (x1, y1) = pts
    return f"({x0:.0f}, {y0}) → ({x1:.0f}, {y1})"


def _lanes_summary(rows: list[dict], outputs: _Outputs) -> None:
    table = Table(title="lane lines (pixels; from the bottom row to the top of the paint)", title_justify="left")
    for col in ("file", "frame", "left line", "right line", "confidence"):
        table.add_column(col, justify="right" if col in ("frame", "confidence") else "left")
    by_file: dict[str, list[dict]] = {}
    for r in rows:
        by_file.setdefault(r["file"], []).append(r)
    for name, rs in by_file.items():
        if len(rs) == 1:
            r = rs[0]
            table.add_row(Path(name).name, str(r["frame"]), _fmt_line(r["left"]), _fmt_line(r["right"]),
                          f"{r['confidence']:.2f}")
        else:
            both = sum(r["left"] is not None and r["right"] is not None for r in rs)
            none = sum(r["left"] is None and r["right"] is None for r in rs)
            table.add_row(Path(name).name, f"{len(rs)} frames", f"both lines in {both}", f"neither in {none}",
                          f"{np.mean([r['confidence'] for r in rs]):.2f} mean")
    stdout.print(table)
    if outputs.written:
        stdout.print(f"wrote {len(outputs.written)} file(s) to {outputs.out}: "
                     + ", ".join(p.name for p in outputs.written[:6]) + (" ..." if len(outputs.written) > 6 else ""))


def _tune_frames(sources: list[Source], every: int) -> tuple[list[np.ndarray], list[str]]:
    frames, names = [], []
    for src in sources:
        for index, frame in frames_of(src, every if src.kind == "image" else max(every, 15)):
            frames.append(frame)
            names.append(src.path.name if src.kind == "image" else f"{src.path.name} #{index}")
            if len(frames) >= TUNE_FRAMES:
                return frames, names
    return frames, names


@detect_app.command("lanes")
def lanes_cmd(
    paths: PathsArg,
    every: EveryOpt = 1,
    hsv: Annotated[Path | None, typer.Option("--hsv", help="HSV profile YAML (yellow range; see qcarlab/hsv_profile.py). "
                                             "With --hsv-tune: where the tuned profile goes.", show_default=False)] = None,
    hsv_tune: Annotated[bool, typer.Option("--hsv-tune", help="Tune the yellow range on the frames first (the sheet's "
                                           "sliders; automatic without a terminal), save it, then detect.")] = False,
    roi_top: Annotated[float, typer.Option("--roi-top", help="The region starts this far down the image (fraction of "
                                           "the height; below the horizon).")] = ROI_TOP,
    no_white: Annotated[bool, typer.Option("--no-white", help="Yellow paint only (no white lines).")] = False,
    json_out: JsonOpt = False,
    out: OutOpt = None,
    debug: DebugOpt = False,
) -> None:
    """The ego lane's left and right lines in photos and videos (any resolution).

    JSON per frame: {"file", "frame", "width", "height", "left": [[x0, y0], [x1, y1]] | null,
    "right": ... | null, "confidence"}: pixels, (x0, y0) on the bottom row.
    """
    if not (0.0 <= roi_top < 1.0):
        raise InputError(f"--roi-top must be a fraction of the height in [0, 1), got {roi_top}")
    sources = expand_paths(paths)
    profile = HsvProfile()
    if hsv is not None and (not hsv_tune or hsv.exists()):
        profile = load_hsv_profile(hsv)
    if hsv_tune:
        from qcarlab.cli.hsv_tune import run_hsv_tuner

        target = hsv if hsv is not None else (out / "hsv.yaml" if out is not None else Path("hsv.yaml"))
        frames, names = _tune_frames(sources, every)
        profile = run_hsv_tuner(frames, profile, target, _console(json_out), lane=None, names=names)
    outputs = _Outputs(out, json_out)
    kw = {**profile.lane_kwargs(), "roi_top": roi_top, "white": not no_white}

    def detect(frame):
        lines = detect_lane_lines(frame, **kw)
        return lines.as_dict(), lines

    try:
        _run(sources, every, outputs, detect, lambda frame, lines: lane_lines_image(frame, lines))
    finally:
        outputs.close()
    if not json_out:
        _lanes_summary(outputs.rows, outputs)


# --------------------------------------------------------------------------------------- stop signs
def _signs_summary(rows: list[dict], outputs: _Outputs, method: str) -> None:
    table = Table(title=f"stop signs ({method}; box = x, y, w, h in pixels)", title_justify="left")
    for col in ("file", "frame", "signs"):
        table.add_column(col, justify="right" if col == "frame" else "left")
    by_file: dict[str, list[dict]] = {}
    for r in rows:
        by_file.setdefault(r["file"], []).append(r)
    for name, rs in by_file.items():
        if len(rs) == 1:
            signs = rs[0]["signs"]
            text = "none" if not signs else "; ".join(
                f"[{', '.join(map(str, s['box']))}] score {s['score']:.2f}" + (f", {s['distance']:.2f} m" if "distance" in s else "")
                for s in signs)
            table.add_row(Path(name).name, str(rs[0]["frame"]), text)
        else:
            hits = sum(bool(r["signs"]) for r in rs)
            table.add_row(Path(name).name, f"{len(rs)} frames", f"a sign in {hits}")
    stdout.print(table)
    if outputs.written:
        stdout.print(f"wrote {len(outputs.written)} file(s) to {outputs.out}: "
                     + ", ".join(p.name for p in outputs.written[:6]) + (" ..." if len(outputs.written) > 6 else ""))


@detect_app.command("stop-sign")
def stop_sign_cmd(
    paths: PathsArg,
    method: Annotated[str, typer.Option("--method", help="hsv (the sheet's red threshold + a shape check) or hough "
                                        "(circles + red inside; the race-car report's).")] = "hsv",
    every: EveryOpt = 1,
    depth: Annotated[Path | None, typer.Option("--depth", help="Aligned depth of the one image: .npy in metres or a "
                                               "16-bit .png in millimetres; adds each sign's distance.",
                                               show_default=False)] = None,
    hsv_min: Annotated[str | None, typer.Option("--hsv-min", help="Red range, lower H,S,V (default: the sheet's "
                                                "170,100,100, then a dim pass).", show_default=False)] = None,
    hsv_max: Annotated[str | None, typer.Option("--hsv-max", help="Red range, upper H,S,V (default 10,255,255).",
                                                show_default=False)] = None,
    min_area: Annotated[int | None, typer.Option("--min-area", min=1, help="Smallest sign, red pixels (default 150, "
                                                 "more on large images).", show_default=False)] = None,
    json_out: JsonOpt = False,
    out: OutOpt = None,
    debug: DebugOpt = False,
) -> None:
    """Stop signs in photos and videos: a box and a score each (and the distance with --depth).

    JSON per frame: {"file", "frame", "signs": [{"box": [x, y, w, h], "score"} ...]}; with
    --depth each sign also has "distance" (m, 0 = no depth there).
    """
    if method not in METHODS:
        raise InputError(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
    lo = parse_hsv(hsv_min, "--hsv-min") if hsv_min is not None else None
    hi = parse_hsv(hsv_max, "--hsv-max") if hsv_max is not None else None
    if (lo is None) != (hi is None):
        lo = lo if lo is not None else (170, 100, 100)
        hi = hi if hi is not None else (10, 255, 255)
    sources = expand_paths(paths)
    depth_img = None
    if depth is not None:
        if len(sources) != 1 or sources[0].kind != "image":
            raise InputError("--depth goes with exactly one image (the depth frame aligned to it)")
        first = next(frames_of(sources[0]))[1]
        depth_img = read_depth(depth, first.shape[:2])
    outputs = _Outputs(out, json_out)

    def detect(frame):
        signs = detect_stop_signs(frame, method, lo, hi, min_area, depth_img)
        return {"signs": [s.as_dict() for s in signs]}, signs

    try:
        _run(sources, every, outputs, detect, lambda frame, signs: signs_image(frame, signs, method))
    finally:
        outputs.close()
    if not json_out:
        _signs_summary(outputs.rows, outputs, method)
