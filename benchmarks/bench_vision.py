"""Vision benchmark: the lane chain and the stop-sign detectors on real camera images, against
plain OpenCV baselines written here; accuracy on hand-made labels and frames per second.

    python benchmarks/bench_vision.py                 # the tables (needs ../shared/data)
    python benchmarks/bench_vision.py --repeat 7      # more timing batches (medians)
    python benchmarks/bench_vision.py --json          # the figures as JSON

Lanes (labels: tests/data/labels/lanes.yaml, two points per line, by looking): a line is right when
the detected line lies within 5 % of the image width of the label on the bottom row *and* on the
row at 60 % of the height; a frame is right when all its labelled lines are (and nothing is found
where the label says there is no line). Compared:

- ``qcarlab``: :func:`qcarlab.perception.lane_lines.detect_lane_lines` (``qcarlab detect lanes``);
- ``canny+hough``: the classic pipeline (grey, 5x5 Gaussian blur, Canny 50/150, a trapezoid
  region from 60 % of the height, probabilistic Hough, segments split by the sign of their slope,
  a length-weighted line through each side's segment end points); resolution-independent here.

Stop signs (labels: tests/data/labels/signs.yaml, a box per sign): a hit is a detection with
IoU >= 0.5 against a labelled box; every other detection is a false positive. Compared: the
sheet's red threshold with the largest blob (``sheet``: no shape check, S and V from 100, as the
lab model), ``qcarlab detect stop-sign --method hsv`` and ``--method hough``.

Speed (one core, medians of alternating batches): at 640 x 480, on the simulator's track frames
and on the real photos resized to 640 x 480, ``detect_lane`` (the yellow line, the white backup;
the region cropped before one HSV conversion), the lab model's blocks called one by one on full
frames (``image_selector`` -> ``color_thresholding_hsv`` -> ``linear_poly_fit``, the white edge
line when that finds nothing) and ``detect_lane_lines`` (both lines) against the plain OpenCV
chain (whole-frame HSV, ``inRange``, rows below 2/3 of the height, ``findNonZero`` +
``fitLine``) and that chain cropped first.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from qcarlab.perception.lane import YELLOW_HSV_MAX, YELLOW_HSV_MIN, detect_lane  # noqa: E402
from qcarlab.perception.lane_lines import detect_lane_lines  # noqa: E402
from qcarlab.perception.stop_sign import color_thresholding_hsv, find_objects  # noqa: E402
from qcarlab.perception.stop_signs import detect_stop_signs  # noqa: E402

SHARED = REPO.parent / "shared" / "data"
LABELS = REPO / "tests" / "data" / "labels"
TOL = 0.05  # of the width
FRAC = 0.6  # the second row checked, fraction of the height


# ------------------------------------------------------------------------------------ data
def load_set(name: str) -> dict[str, list[dict]]:
    """``{set name: [frame, ...]}`` of a labels file; each frame gets ``image`` (BGR, cropped)."""
    doc = yaml.safe_load((LABELS / f"{name}.yaml").read_text())
    out = {}
    for set_name, frames in doc["sets"].items():
        for f in frames:
            img = cv2.imread(str(SHARED / f["file"]), cv2.IMREAD_COLOR)
            if img is None:
                raise SystemExit(f"cannot read {SHARED / f['file']}")
            x, y, w, h = f.get("crop") or (0, 0, img.shape[1], img.shape[0])
            f["image"] = np.ascontiguousarray(img[y:y + h, x:x + w])
            f["offset"] = (x, y)
        out[set_name] = frames
    return out


def label_line(pts, offset) -> tuple[float, float] | None:
    """(slope, intercept) of a labelled line u = slope v + intercept in the cropped view."""
    (x0, y0), (x1, y1) = pts
    ox, oy = offset
    x0, x1, y0, y1 = x0 - ox, x1 - ox, y0 - oy, y1 - oy
    slope = (x1 - x0) / (y1 - y0)
    return slope, x0 - slope * y0


# ------------------------------------------------------------------------------------ baseline
def canny_hough(img: np.ndarray) -> dict[str, tuple[float, float] | None]:
    """The classic Canny + Hough lane finder; lines as (slope, intercept) of u = slope v + b."""
    h, w = img.shape[:2]
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    edges = cv2.Canny(cv2.GaussianBlur(grey, (5, 5), 0), 50, 150)
    region = np.zeros_like(edges)
    top = int(FRAC * h)
    poly = np.array([[(0, h - 1), (int(0.45 * w), top), (int(0.55 * w), top), (w - 1, h - 1)]], np.int32)
    cv2.fillPoly(region, poly, 255)
    edges = cv2.bitwise_and(edges, region)
    scale = w / 960.0
    segs = cv2.HoughLinesP(edges, 1, np.pi / 180, max(10, int(20 * scale)), minLineLength=max(8, int(20 * scale)),
                           maxLineGap=max(10, int(40 * scale)))
    out: dict[str, tuple[float, float] | None] = {"left": None, "right": None}
    if segs is None:
        return out
    sides: dict[str, list] = {"left": [], "right": []}
    for x1, y1, x2, y2 in np.asarray(segs).reshape(-1, 4).astype(float):
        if x2 == x1:
            continue
        m = (y2 - y1) / (x2 - x1)  # dy/dx: negative = the left line (image rows grow downwards)
        if abs(m) < 0.3:  # nearly flat: not a lane line
            continue
        side = "left" if m < 0 else "right"
        length = math.hypot(x2 - x1, y2 - y1)
        sides[side] += [(x1, y1, length), (x2, y2, length)]
    for side, pts in sides.items():
        if len(pts) < 2:
            continue
        a = np.array(pts, float)
        if np.ptp(a[:, 1]) < 2:
            continue
        slope, b = np.polyfit(a[:, 1], a[:, 0], 1, w=a[:, 2])  # u = slope v + b, length-weighted
        out[side] = (float(slope), float(b))
    return out


def qcarlab_lanes(img: np.ndarray, **kw) -> dict[str, tuple[float, float] | None]:
    ll = detect_lane_lines(img, **kw)
    return {s: ((ln.slope, ln.intercept) if ln is not None else None) for s, ln in (("left", ll.left), ("right", ll.right))}


def sheet_sign(img: np.ndarray) -> list[tuple[int, int, int, int]]:
    """The sheet's chain as the lab model has it: red 170..10, S and V from 100, largest blob."""
    obj = find_objects(color_thresholding_hsv(img, (170, 100, 100), (10, 255, 255)), 150)
    return [obj.bbox] if obj is not None else []


# ------------------------------------------------------------------------------------ scoring
def line_ok(found, label, h: int, w: int) -> bool:
    if label is None:
        return found is None
    if found is None:
        return False
    for v in (h - 1, FRAC * h):
        if abs((found[0] * v + found[1]) - (label[0] * v + label[1])) > TOL * w:
            return False
    return True


def score_lanes(sets, detector) -> dict[str, dict]:
    out = {}
    for name, frames in sets.items():
        lines_ok = lines = frames_ok = 0
        for f in frames:
            img = f["image"]
            h, w = img.shape[:2]
            found = detector(img)
            all_ok = True
            for side in ("left", "right"):
                if side not in f:
                    continue
                label = label_line(f[side], f["offset"]) if f[side] is not None else None
                ok = line_ok(found[side], label, h, w)
                lines += 1
                lines_ok += ok
                all_ok &= ok
            frames_ok += all_ok
        out[name] = {"frames": len(frames), "frames_ok": frames_ok, "lines": lines, "lines_ok": lines_ok}
    return out


def iou(a, b) -> float:
    ax, ay, aw, ah = a
    bx, by, bw, bh = b
    ix = max(0, min(ax + aw, bx + bw) - max(ax, bx))
    iy = max(0, min(ay + ah, by + bh) - max(ay, by))
    inter = ix * iy
    return inter / float(aw * ah + bw * bh - inter) if inter else 0.0


def score_signs(sets, detector) -> dict[str, dict]:
    out = {}
    for name, frames in sets.items():
        hits = signs = fps = fp_frames = 0
        for f in frames:
            ox, oy = f["offset"]
            labels = [(x - ox, y - oy, w, h) for x, y, w, h in f["signs"]]
            boxes = detector(f["image"])
            used = set()
            for lab in labels:
                signs += 1
                best = max(range(len(boxes)), key=lambda i: iou(boxes[i], lab), default=None)
                if best is not None and best not in used and iou(boxes[best], lab) >= 0.5:
                    hits += 1
                    used.add(best)
            extra = len(boxes) - len(used)
            fps += extra
            fp_frames += extra > 0
        out[name] = {"frames": len(frames), "signs": signs, "hits": hits, "false_positives": fps,
                     "frames_with_false_positive": fp_frames}
    return out


# ------------------------------------------------------------------------------------ speed
def plain_chain(img: np.ndarray, crop: bool = False):
    """The plain OpenCV lane chain: HSV, inRange yellow, the lower third, findNonZero, fitLine."""
    h = img.shape[0]
    r0 = (2 * h) // 3
    if crop:
        mask = cv2.inRange(cv2.cvtColor(img[r0:], cv2.COLOR_BGR2HSV), YELLOW_HSV_MIN, YELLOW_HSV_MAX)
    else:
        mask = cv2.inRange(cv2.cvtColor(img, cv2.COLOR_BGR2HSV), YELLOW_HSV_MIN, YELLOW_HSV_MAX)
        mask[:r0] = 0
    pts = cv2.findNonZero(mask)
    if pts is None or len(pts) < 150:
        return None
    return cv2.fitLine(pts, cv2.DIST_L2, 0, 0.01, 0.01)


def sim_frames(n: int = 8) -> list[np.ndarray]:
    """640 x 480 frames of the simulator's track at ``n`` spots round the lane."""
    from qcarlab.experiments.lane_follow import lane_centre, tune_spots
    from qcarlab.sim.camera import RGBDCamera
    from qcarlab.sim.world import load_world

    world = load_world("track")
    cam = RGBDCamera(world, rng=np.random.default_rng(0))
    spots = tune_spots(lane_centre(world, world.start), world.start, n)
    return [cam.render(p).color for p in spots]


def fps(fn, frames, batches: int, per_batch: int = 300, clock=time.perf_counter) -> float:
    """Median frames per second of ``batches`` batches (``clock``: wall time, or this process's
    CPU time, which a loaded machine's other processes do not inflate)."""
    rates = []
    for _ in range(batches):
        t0 = clock()
        for i in range(per_batch):
            fn(frames[i % len(frames)])
        rates.append(per_batch / max(1e-9, clock() - t0))
    return statistics.median(rates)


def speed(batches: int) -> dict[str, dict[str, float]]:
    cv2.setNumThreads(1)
    sets = {"simulator track": sim_frames()}
    real = [cv2.imread(str(SHARED / "real-lanes" / n)) for n in sorted(os.listdir(SHARED / "real-lanes"))
            if n.endswith(".jpg")] if SHARED.is_dir() else []
    if real:
        sets["road photos"] = [cv2.resize(im, (640, 480), interpolation=cv2.INTER_AREA) for im in real]
    from qcarlab.experiments.lane_follow import white_edge_mask
    from qcarlab.perception.lane import image_selector, linear_poly_fit

    def block_chain(im):  # the lab model's diagram, block by block (full frames, as a student's would be)
        fit = linear_poly_fit(color_thresholding_hsv(image_selector(im), YELLOW_HSV_MIN, YELLOW_HSV_MAX))
        return fit if fit is not None else linear_poly_fit(white_edge_mask(im, "right"))

    chains = {
        "qcarlab detect_lane (yellow, white backup; crops first)": lambda im: detect_lane(im),
        "the lab model's blocks, one by one (full frames)": block_chain,
        "qcarlab detect_lane_lines (both lines)": lambda im: detect_lane_lines(im),
        "plain OpenCV chain": lambda im: plain_chain(im),
        "plain OpenCV chain, cropped first": lambda im: plain_chain(im, crop=True),
    }
    out: dict[str, dict[str, float]] = {name: {} for name in chains}
    for set_name, frames in sets.items():
        for fn in chains.values():  # warm up
            fn(frames[0])
        for clock_name, clock in (("wall", time.perf_counter), ("cpu", time.process_time)):
            rates: dict[str, list[float]] = {name: [] for name in chains}
            for _ in range(batches):  # alternate the chains batch by batch
                for name, fn in chains.items():
                    rates[name].append(fps(fn, frames, 1, clock=clock))
            for name in chains:
                out[name][f"{set_name} ({clock_name})"] = statistics.median(rates[name])
    return out


# ------------------------------------------------------------------------------------ main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=5, help="timing batches (median)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    results: dict = {"machine": f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}"}
    if SHARED.is_dir():
        lanes = load_set("lanes")
        signs = load_set("signs")
        results["lanes"] = {"qcarlab": score_lanes(lanes, qcarlab_lanes), "canny+hough": score_lanes(lanes, canny_hough)}
        results["signs"] = {
            "sheet (red, largest blob)": score_signs(signs, sheet_sign),
            "qcarlab --method hsv": score_signs(signs, lambda im: [d.bbox for d in detect_stop_signs(im, method="hsv")]),
            "qcarlab --method hough": score_signs(signs, lambda im: [d.bbox for d in detect_stop_signs(im, method="hough")]),
        }
        results["sign_speed_fps"] = sign_speed(signs, args.repeat)
    else:
        print(f"{SHARED} is absent: accuracy skipped, speed on simulator frames only", file=sys.stderr)
    results["lane_speed_fps"] = speed(args.repeat)
    results["machine"] += f" (after: load {os.getloadavg()[0]:.2f})"
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print_tables(results)
    return 0


def sign_speed(signs, batches: int) -> dict[str, float]:
    frames = [f["image"] for fr in signs.values() for f in fr]
    frames = [cv2.resize(im, (640, 480), interpolation=cv2.INTER_AREA) for im in frames]
    chains = {
        "sheet (red, largest blob)": sheet_sign,
        "qcarlab --method hsv": lambda im: detect_stop_signs(im, method="hsv"),
        "qcarlab --method hough": lambda im: detect_stop_signs(im, method="hough"),
    }
    rates: dict[str, list[float]] = {k: [] for k in chains}
    for _ in range(batches):
        for name, fn in chains.items():
            rates[name].append(fps(fn, frames, 1, 100))
    return {k: statistics.median(v) for k, v in rates.items()}


def print_tables(r: dict) -> None:
    print(f"machine: {r['machine']}")
    if "lanes" in r:
        print("\nlane lines: right within 5 % of the width at the bottom row and at 60 % of the height")
        print(f"{'set':16s} {'method':14s} {'frames right':>13s} {'lines right':>12s}")
        for set_name in r["lanes"]["qcarlab"]:
            for method, res in r["lanes"].items():
                s = res[set_name]
                print(f"{set_name:16s} {method:14s} {s['frames_ok']:>6d} of {s['frames']:<4d} {s['lines_ok']:>5d} of {s['lines']:<4d}")
        print("\nstop signs: hit = IoU >= 0.5; false positives = other detections")
        print(f"{'set':14s} {'method':26s} {'hits':>10s} {'false pos.':>10s} {'(frames)':>9s}")
        for set_name in r["signs"]["qcarlab --method hsv"]:
            for method, res in r["signs"].items():
                s = res[set_name]
                print(f"{set_name:14s} {method:26s} {s['hits']:>4d} of {s['signs']:<3d} {s['false_positives']:>10d}"
                      f" {s['frames_with_false_positive']:>4d} of {s['frames']:<3d}")
        print("\nstop-sign frames/s at 640 x 480 (all labelled frames resized):")
        for k, v in r["sign_speed_fps"].items():
            print(f"  {k:28s} {v:8.0f}")
    print("\nlane chain frames/s at 640 x 480 (one core, median of alternating batches; wall time and"
          " this process's CPU time)")
    sets = list(next(iter(r["lane_speed_fps"].values())).keys())
    print(f"  {'chain':56s} " + " ".join(f"{s:>24s}" for s in sets))
    for k, v in r["lane_speed_fps"].items():
        print(f"  {k:56s} " + " ".join(f"{v[s]:24.0f}" for s in sets))
    plain = r["lane_speed_fps"]["plain OpenCV chain"]
    ours = r["lane_speed_fps"]["qcarlab detect_lane (yellow, white backup; crops first)"]
    print("  detect_lane / plain OpenCV chain: " + ", ".join(f"{s} {ours[s] / plain[s]:.2f}x" for s in sets))


if __name__ == "__main__":
    raise SystemExit(main())
