"""Vision lane following (lab sheet 5.3, the *Autonomous Driving* / lane example model) on any car.

Each tick (``rate``, 100 Hz by default)::

    v     = basic_speed_estimation(tach)                         # encoder -> m/s
    on each new RGBD frame (30 Hz):
        det   = detect_lane(color, lane, hsv_min, hsv_max)       # imageSelector, colorThresholdingHSV,
                                                                 # linearPolyFit (white edge line as backup)
        delta = steering_calculation(det.fit, line_offset(lane, det.source))
        box   = draw_box(depth.shape, delta); d_obs = calculate_distance(depth, box)
    v_ref = automated_driving(v_desired, d_obs, stop_distance)
    v_ref = turn_speed_handling(v_ref, delta)                    # cos(delta)^8, clipped to 0.5..1
    u     = speed_controller(v_ref, v)                           # feed-forward PI -> throttle

The steering is held between frames (zero-order hold); a frame with no line keeps the last steering
for up to ``hold_lost`` s (a curve goes on), then steers straight.

Scoring (simulator only, duckietown style) uses the true pose and the world's paint: the lane
centre is the yellow centre line offset by half a lane (0.2 m) to the side the car starts on;
``lateral deviation`` is the distance from the car's centre to that polyline, ``out of lane`` when
it exceeds half a lane (the car's centre over a line); ``distance_along_lane_m`` is the arc length
travelled along the lane centre (unwrapped round the loop), ``laps`` that over the loop's length.

:func:`hsv_tune` is the sheet's HSV-tuning step: no driving; frames at a few spots of the track,
each thresholded, so a student sees what the HSV range keeps.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from qcarlab.car.base import Car, Command
from qcarlab.car.lamps import ALL_OFF, parse_lamps
from qcarlab.control.lane import (
    LaneCamera,
    automated_driving,
    line_offset,
    steering_calculation,
)
from qcarlab.control.speed import KFF, KI, KP
from qcarlab.control.speed import (
    SpeedController,
    basic_speed_estimation,
    turn_speed_handling,
)
from qcarlab.control.tracking import Polyline
from qcarlab.errors import InputError
from qcarlab.experiments.loop import STOP, check_rate, run_loop
from qcarlab.experiments.result import Result
from qcarlab.perception.lane import (
    LANES,
    MIN_PIXELS,
    YELLOW_HSV_MAX,
    YELLOW_HSV_MIN,
    LaneDetection,
    calculate_distance,
    color_thresholding_hsv,
    detect_lane,
    draw_box,
    image_selector,
    lane_image,
    lane_mask,
)
from qcarlab.perception.stop_sign import check_hsv

LANE_HALF_WIDTH = 0.2  # m
YELLOW_BGR = (20, 200, 240)  # the world's "yellow" paint, BGR


@dataclass
class LaneFollowConfig:
    """Everything that shapes a run."""

    speed: float = 0.3  # m/s desired
    lane: str = "right"
    duration: float = 30.0  # s
    laps: float | None = None  # stop after this many laps (simulator)
    hsv_min: tuple[int, int, int] = YELLOW_HSV_MIN
    hsv_max: tuple[int, int, int] = YELLOW_HSV_MAX
    min_pixels: int = MIN_PIXELS
    lookahead: float = 0.5  # m ahead of the camera
    white_backup: bool = True
    turn_speed: bool = True
    stop_distance: float = 0.6  # m
    hold_lost: float = 1.0  # s the last steering is kept when the line is lost
    kp: float = KP
    ki: float = KI
    kff: float = KFF
    rate: float = 100.0

    def check(self) -> None:
        if self.lane not in LANES:
            raise InputError(f"--lane must be one of {', '.join(LANES)}, got {self.lane!r}")
        if not (math.isfinite(self.speed) and 0.0 < self.speed <= 3.0):
            raise InputError(f"--speed must be a number of m/s in (0, 3], got {self.speed}")
        if not (math.isfinite(self.duration) and 0.0 < self.duration <= 3600.0):
            raise InputError(f"--duration must be 0..3600 s, got {self.duration}")
        if self.laps is not None and not (math.isfinite(self.laps) and 0.0 < self.laps <= 100.0):
            raise InputError(f"--laps must be a positive number (at most 100), got {self.laps}")
        self.hsv_min = check_hsv(self.hsv_min, "--hsv-min")
        self.hsv_max = check_hsv(self.hsv_max, "--hsv-max")
        if self.hsv_min[1] > self.hsv_max[1] or self.hsv_min[2] > self.hsv_max[2]:
            raise InputError(f"--hsv-min {self.hsv_min} is above --hsv-max {self.hsv_max} in saturation or value")
        if not (math.isfinite(self.lookahead) and 0.3 <= self.lookahead <= 1.5):
            raise InputError(f"--lookahead must be 0.3..1.5 m, got {self.lookahead}")
        if not (math.isfinite(self.stop_distance) and 0.0 <= self.stop_distance <= 1.2):
            raise InputError(f"--stop-distance must be 0..1.2 m, got {self.stop_distance}")
        for name in ("kp", "ki", "kff"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"--{name} must be a non-negative number, got {value}")
        check_rate(self.rate)


# ------------------------------------------------------------------------------- scoring (sim)
def _yellow_line(world) -> np.ndarray | None:
    best = None
    for m in getattr(world, "markings", []) or []:
        if m.filled or m.color != YELLOW_BGR:
            continue
        if best is None or len(m.points) > len(best.points):
            best = m
    if best is None:
        return None
    pts = np.asarray(best.points, float)
    if best.closed or np.allclose(pts[0], pts[-1]):
        pts = np.vstack([pts, pts[:1]]) if not np.allclose(pts[0], pts[-1]) else pts
    return pts


def lane_centre(world, start: tuple[float, float, float], half_width: float = LANE_HALF_WIDTH) -> np.ndarray | None:
    """The centre polyline of the lane the car at ``start`` is in: the world's yellow centre line
    offset by ``half_width`` to the side of ``start``; None when the world has no yellow line."""
    line = _yellow_line(world)
    if line is None:
        return None
    closed = np.allclose(line[0], line[-1])
    pts = line[:-1] if closed else line
    n = len(pts)
    if closed:
        tang = np.roll(pts, -1, axis=0) - np.roll(pts, 1, axis=0)
    else:
        tang = np.gradient(pts, axis=0)
    tang /= np.maximum(np.hypot(tang[:, 0], tang[:, 1]), 1e-12)[:, None]
    normal = np.stack([-tang[:, 1], tang[:, 0]], axis=1)  # left of the polyline's direction
    _, s = Polyline(line).nearest(np.array([start[:2]]))
    k = min(n - 1, int(np.searchsorted(Polyline(line).cum, s[0], side="right")) - 1)
    side = 1.0 if np.dot(np.asarray(start[:2]) - pts[k % n], normal[k % n]) >= 0 else -1.0
    centre = pts + side * half_width * normal
    return np.vstack([centre, centre[:1]]) if closed else centre


def lane_metrics(xy: np.ndarray, centre: np.ndarray, dt: float, half_width: float = LANE_HALF_WIDTH) -> dict:
    """Duckietown-style scores of the driven points ``xy`` (one per tick of ``dt`` s) against the
    lane ``centre`` polyline."""
    poly = Polyline(centre)
    dist, s = poly.nearest(xy)
    ds = np.diff(s)
    L = poly.length
    ds = (ds + L / 2.0) % L - L / 2.0  # unwrap round the loop
    along = float(abs(ds.sum())) if len(ds) else 0.0
    return {
        "rms_lateral_deviation_m": float(np.sqrt(np.mean(dist**2))) if len(dist) else None,
        "max_lateral_deviation_m": float(dist.max()) if len(dist) else None,
        "time_out_of_lane_s": float(np.count_nonzero(dist > half_width) * dt),
        "distance_along_lane_m": along,
        "lane_length_m": L,
        "laps": along / L if L > 0 else None,
    }, dist


# ------------------------------------------------------------------------------- the run
def run_lane_follow(car: Car, cfg: LaneFollowConfig, world=None) -> Result:
    """Follow the lane at ``cfg.speed`` for ``cfg.duration`` s (or ``cfg.laps`` laps)."""
    cfg.check()
    p = car.params
    dt = 1.0 / cfg.rate
    frame_dt = 1.0 / p.rgbd_rate
    cam = LaneCamera.from_params(p)
    pi = SpeedController(cfg.kp, cfg.ki, cfg.kff, throttle_limit=car.throttle_limit)
    truth0 = car.truth()
    centre = lane_centre(world, (truth0.x, truth0.y, truth0.yaw)) if (world is not None and truth0 is not None) else None
    lap_poly = Polyline(centre) if centre is not None else None
    rec: dict[str, list] = {k: [] for k in ("v_ref", "v_meas", "line", "obstacle_distance")}
    st = {"next_frame": 0.0, "delta": 0.0, "det": LaneDetection(None, None), "frame": None, "frames": 0,
          "lost": 0, "white": 0, "last_seen": 0.0, "d_obs": 0.0, "box": None, "along": 0.0, "s": None,
          "shown": None}
    if lap_poly is not None:
        st["s"] = float(lap_poly.nearest(np.array([[truth0.x, truth0.y]]))[1][0])

    def step(t: float, r) -> Command | object:
        v = basic_speed_estimation(r.tach, p)
        if t + 1e-9 >= st["next_frame"]:
            frame = car.read_rgbd()
            st["next_frame"] = (math.floor((t + 1e-9) / frame_dt) + 1) * frame_dt
            det = detect_lane(frame.color, cfg.lane, cfg.hsv_min, cfg.hsv_max, cfg.min_pixels, cfg.white_backup)
            st["frames"] += 1
            if det.fit is not None:
                st["delta"] = steering_calculation(det.fit, line_offset(cfg.lane, det.source), cam, cfg.lookahead)
                st["last_seen"] = t
                if det.source == "white":
                    st["white"] += 1
            else:
                st["lost"] += 1
                if t - st["last_seen"] > cfg.hold_lost:
                    st["delta"] = 0.0
            box = draw_box(frame.depth.shape, st["delta"])
            st["d_obs"], st["box"], st["det"], st["frame"] = calculate_distance(frame.depth, box), box, det, frame
            if st["shown"] is None and det.source == "yellow" and t >= 1.0:
                st["shown"] = (frame, det, box)
        delta = st["delta"]
        v_ref = automated_driving(cfg.speed, st["d_obs"], cfg.stop_distance)
        v_ref = turn_speed_handling(v_ref, delta, cfg.turn_speed)
        throttle = pi(v_ref, v, dt)
        for key, value in (("v_ref", v_ref), ("v_meas", v), ("line", st["det"].source or "none"),
                           ("obstacle_distance", st["d_obs"])):
            rec[key].append(value)
        if cfg.laps is not None and lap_poly is not None:
            tr = car.truth()
            s = float(lap_poly.nearest(np.array([[tr.x, tr.y]]))[1][0])
            L = lap_poly.length
            st["along"] += abs((s - st["s"] + L / 2.0) % L - L / 2.0)
            st["s"] = s
            if st["along"] >= cfg.laps * L:
                return STOP
        return Command(throttle, delta, _lamps(delta, v_ref))

    log = run_loop(car, step, cfg.duration, cfg.rate)
    cols = {k: np.asarray(v) for k, v in log.arrays().items()}
    n = log.ticks
    for key in rec:
        cols[key] = np.asarray(rec[key][:n])
    duration = n * dt
    metrics: dict = {"experiment": "lane-follow", "lane": cfg.lane, "speed_mps": cfg.speed}
    if centre is not None and "true_x" in cols and n:
        xy = np.stack([cols["true_x"], cols["true_y"]], axis=1)
        lm, dist = lane_metrics(xy, centre, dt)
        metrics.update(lm)
        cols["lateral_deviation"] = dist
    else:
        metrics.update({k: None for k in ("rms_lateral_deviation_m", "max_lateral_deviation_m",
                                          "time_out_of_lane_s", "distance_along_lane_m", "lane_length_m", "laps")})
    metrics.update({
        "duration_s": duration,
        "mean_speed_mps": float(np.mean(cols["true_speed"])) if "true_speed" in cols and n
        else (float(np.mean(cols["v_meas"])) if n else 0.0),
        "frames": st["frames"],
        "frames_line_lost": st["lost"],
        "frames_white_backup": st["white"],
        "stopped_for_obstacle_s": float(np.count_nonzero(cols["v_ref"] == 0.0) * dt) if n else 0.0,
    })
    metrics["config"] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()}

    result = Result("lane-follow", metrics, logs={"log.csv": _log_columns(cols)}, figures={})
    shown = st["shown"] or ((st["frame"], st["det"], st["box"]) if st["frame"] is not None else None)
    if shown is not None:
        frame, det, box = shown
        result.data["frame"] = shown
        result.figures["frame.png"] = lambda f: _imwrite(f, lane_image(frame.color, det, box))
    if world is not None and "true_x" in cols and n:
        poses = np.stack([cols["true_x"], cols["true_y"], cols["true_yaw"]], axis=1)
        result.figures["lane.png"] = lambda f: _topdown(f, world, poses, centre)
    return result


_LEFT, _RIGHT = parse_lamps(["left-indicators"]), parse_lamps(["right-indicators"])


def _lamps(delta: float, v_ref: float):
    """indicatorAndLamps: indicators beyond 0.3 rad of steering, brake when stopped."""
    if v_ref == 0.0:
        return parse_lamps(["brake"])
    if delta > 0.3:
        return _LEFT
    if delta < -0.3:
        return _RIGHT
    return ALL_OFF


def _topdown(file, world, poses: np.ndarray, centre) -> None:
    from qcarlab.sim.render import (
        render_topdown,  # experiments may wire the simulator's renderer
    )

    img = render_topdown(world, 100.0, poses=poses[:: max(1, len(poses) // 400)], path=centre)
    _imwrite(file, img)


def _imwrite(file, image: np.ndarray) -> None:
    if not cv2.imwrite(str(file), image):
        raise InputError(f"cannot write {file}")


def _log_columns(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    keep = ["t", "line", "lateral_deviation", "obstacle_distance", "v_ref", "v_meas", "true_speed", "throttle",
            "steering", "true_x", "true_y", "true_yaw"]
    return {k: cols[k] for k in keep if k in cols}


# ------------------------------------------------------------------------------- HSV tuning
def tune_spots(centre: np.ndarray | None, start: tuple[float, float, float], count: int = 4) -> list[tuple]:
    """``count`` poses spread evenly round the lane centre (heading along it, in the direction the
    car at ``start`` faces); without a lane, just ``start``."""
    if centre is None:
        return [tuple(start)]
    poly = Polyline(centre)
    s0 = float(poly.nearest(np.array([start[:2]]))[1][0])
    _p0, j = poly.point_at(s0)
    seg = centre[j + 1] - centre[j]
    forward = 1.0 if math.cos(math.atan2(seg[1], seg[0]) - start[2]) >= 0 else -1.0
    spots = []
    for i in range(count):
        s = (s0 + forward * i * poly.length / count) % poly.length
        p, j = poly.point_at(s)
        seg = centre[j + 1] - centre[j]
        yaw = math.atan2(seg[1], seg[0]) + (0.0 if forward > 0 else math.pi)
        spots.append((float(p[0]), float(p[1]), math.atan2(math.sin(yaw), math.cos(yaw))))
    return spots


def hsv_tune(frames: list, cfg: LaneFollowConfig) -> Result:
    """Threshold each ``(pose, RGBDFrame)`` of ``frames`` with the HSV range: per spot the yellow
    pixel count (in the lane's region of interest and in the whole image) and the figure
    ``hsv_tune.png``: colour | thresholded mask | lane mask (red over the kept pixels), one row
    per spot."""
    cfg.check()
    spots, rows = [], []
    for pose, frame in frames:
        full = color_thresholding_hsv(frame.color, cfg.hsv_min, cfg.hsv_max)
        roi = image_selector(full, cfg.lane)
        det = detect_lane(frame.color, cfg.lane, cfg.hsv_min, cfg.hsv_max, cfg.min_pixels, white_backup=False)
        spots.append({
            "pose": [round(v, 3) for v in pose],
            "pixels_whole_image": int(np.count_nonzero(full)),
            "pixels_in_region": int(np.count_nonzero(roi)),
            "line_found": det.fit is not None,
            "slope": det.fit.slope if det.fit else None,
        })
        rows.append(_tune_row(frame.color, full, roi, spots[-1]))
    metrics = {
        "experiment": "lane-follow",
        "mode": "hsv-tune",
        "lane": cfg.lane,
        "hsv_min": list(cfg.hsv_min),
        "hsv_max": list(cfg.hsv_max),
        "spots": spots,
        "spots_with_line": sum(s["line_found"] for s in spots),
    }
    image = np.vstack(rows) if rows else None
    result = Result("lane-follow", metrics, figures={})
    if image is not None:
        result.data["hsv_tune"] = image
        result.figures["hsv_tune.png"] = lambda f: _imwrite(f, image)
    return result


def _tune_row(color: np.ndarray, full: np.ndarray, roi: np.ndarray, spot: dict) -> np.ndarray:
    h, w = color.shape[:2]
    panels = [color.copy(), cv2.cvtColor(full, cv2.COLOR_GRAY2BGR), lane_mask(color, roi)]
    labels = [f"colour at {spot['pose'][0]:.2f}, {spot['pose'][1]:.2f}",
              f"HSV mask: {spot['pixels_whole_image']} px",
              f"lane mask: {spot['pixels_in_region']} px in region"]
    out = []
    for panel, label in zip(panels, labels):
        bar = np.full((28, w, 3), 255, np.uint8)
        cv2.putText(bar, label, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
        out += [np.vstack([bar, panel]), np.full((h + 28, 6, 3), 255, np.uint8)]
    return np.vstack([np.hstack(out[:-1]), np.full((6, 3 * w + 12, 3), 255, np.uint8)])
