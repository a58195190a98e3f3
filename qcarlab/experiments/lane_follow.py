"""Vision lane following (lab sheet 5.3, the *Autonomous Driving* / lane example model) on any car.

The model, :class:`LaneFollowingLab`, is the lane example's diagram; each tick (100 Hz)::

    at the start: v_max, d_stop, gain = user_inputs(speed_selector %, stop_offset %, distance_to_lane %)
    v     = basic_speed_estimation(tach)                         # encoder -> m/s
    on each new RGBD frame (30 Hz):
        roi   = image_selector(color)                            # the region the line is expected in
        mask  = color_thresholding_hsv(roi)                      # the yellow centre line
        fit   = linear_poly_fit(mask)                            # u = slope v + intercept (or None)
              (no yellow: the white edge line, the same way, as a backup)
        delta = steering_calculation(fit, gain * line_offset(lane, line))
        box   = draw_box(depth.shape, delta); d_obs = calculate_distance(depth, box)
    v_ref = automated_driving(v_max, d_obs)                      # slower, then 0, before an obstacle
    v_ref = turn_speed_handling(v_ref, delta)                    # cos(delta)^8, clipped to 0.5..1
    u     = speed_controller(v_ref, v, dt)                       # feed-forward PI -> throttle
    lamps = indicator_and_lamps(delta, v_ref)                    # logged as "lamps"

Start/stop (the model's arm switch): before ``start_at`` s and from ``stop_at`` s the motor is
disarmed: v_ref = 0, throttle 0, the speed controller's integrator reset, the brake lamp on.

Every block is looked up by its sheet name; ``--use`` replaces any of them.

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
from dataclasses import asdict, dataclass, replace

import cv2
import numpy as np

from collections.abc import Mapping
from functools import partial
from typing import Any

from qcarlab.blocks import BlockSpec
from qcarlab.car.base import Car, Command
from qcarlab.car.lamps import lamps_named
from qcarlab.control.lane import (
    LaneCamera,
    automated_driving,
    line_offset,
    steering_calculation,
    user_inputs,
)
from qcarlab.control.speed import KFF, KI, KP
from qcarlab.control.speed import (
    SpeedController,
    basic_speed_estimation,
    turn_speed_handling,
)
from qcarlab.control.tracking import Polyline
from qcarlab.errors import InputError
from qcarlab.constants import QCarParams
from qcarlab.control.lamps import indicator_and_lamps
from qcarlab.experiments.loop import STOP, Step, check_rate, run_loop
from qcarlab.experiments.model import BASIC_SPEED_ESTIMATION, INDICATOR_AND_LAMPS, SPEED_CONTROLLER, TURN_SPEED_HANDLING, LabModel, finish
from qcarlab.experiments.safety import WorldWatch
from qcarlab.experiments.result import Result, save_figure
from qcarlab.perception.lane import (
    LANES,
    WHITE_S_MAX,
    WHITE_V_MIN,
    LaneBand,
    linear_poly_fit,
    region_row,
    white_edge_mask,
    MIN_PIXELS,
    YELLOW_HSV_MAX,
    YELLOW_HSV_MIN,
    LaneDetection,
    obstacle_distance,
    color_thresholding_hsv,
    draw_box,
    image_selector,
    LANE_OVERLAYS,
    lane_caption,
    lane_overlay,
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
    duration: float | None = None  # s; None: 30 s, or with laps the time they need
    laps: float | None = None  # stop after this many laps (simulator)
    hsv_min: tuple[int, int, int] = YELLOW_HSV_MIN
    hsv_max: tuple[int, int, int] = YELLOW_HSV_MAX
    min_pixels: int = MIN_PIXELS
    lookahead: float = 0.5  # m ahead of the camera
    white_backup: bool = True  # the white edge line steers where the yellow one left the view (curves) ...
    backup_distance: float = 2.5  # m: ... for at most this far driven since the yellow line was last seen
    white_s_max: int = WHITE_S_MAX  # the white line: saturation at most (the HSV profile's white: section)
    white_v_min: int = WHITE_V_MIN  # ... and value at least
    turn_speed: bool = True
    stop_distance: float = 0.6  # m: the minimum stopping distance (section 1 of userInputs)
    speed_selector: float = 100.0  # %: of speed, the maximum speed (userInputs' Speed Selector)
    stop_offset: float = 0.0  # %: added to stop_distance (Stopping Distance Offset: 100 % doubles it)
    distance_to_lane: float = 100.0  # %: 0 follows the line itself, 100 the lane centre
    start_at: float = 0.0  # s: the start switch (the motor is armed from then)
    stop_at: float | None = None  # s: the stop switch (disarmed from then; None = never)
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
        if self.duration is not None and not (math.isfinite(self.duration) and 0.0 < self.duration <= 3600.0):
            raise InputError(f"--duration must be 0..3600 s, got {self.duration}")
        if self.laps is not None and not (math.isfinite(self.laps) and 0.0 < self.laps <= 100.0):
            raise InputError(f"--laps must be a positive number (at most 100), got {self.laps}")
        self.hsv_min = check_hsv(self.hsv_min, "--hsv-min")
        self.hsv_max = check_hsv(self.hsv_max, "--hsv-max")
        if self.hsv_min[1] > self.hsv_max[1] or self.hsv_min[2] > self.hsv_max[2]:
            raise InputError(f"--hsv-min {self.hsv_min} is above --hsv-max {self.hsv_max} in saturation or value")
        if not (math.isfinite(self.backup_distance) and 0.0 <= self.backup_distance <= 100.0):
            raise InputError(f"backup_distance must be 0..100 m, got {self.backup_distance}")
        for name in ("white_s_max", "white_v_min"):
            value = getattr(self, name)
            if not (isinstance(value, int) and 0 <= value <= 255):
                raise InputError(f"{name} must be a whole number 0..255, got {value!r}")
        if not (math.isfinite(self.lookahead) and 0.3 <= self.lookahead <= 1.5):
            raise InputError(f"--lookahead must be 0.3..1.5 m, got {self.lookahead}")
        if not (math.isfinite(self.stop_distance) and 0.0 <= self.stop_distance <= 1.2):
            raise InputError(f"--stop-distance must be 0..1.2 m, got {self.stop_distance}")
        for name in ("speed_selector", "stop_offset", "distance_to_lane"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and 0.0 <= value <= 100.0):
                raise InputError(f"--{name.replace('_', '-')} must be a percentage in 0..100, got {value}")
        if not (math.isfinite(self.start_at) and 0.0 <= self.start_at <= 3600.0):
            raise InputError(f"--start-at must be 0..3600 s, got {self.start_at}")
        if self.stop_at is not None and not (math.isfinite(self.stop_at) and self.start_at < self.stop_at <= 3600.0):
            raise InputError(f"--stop-at must be after --start-at ({self.start_at:g} s) and at most 3600 s, "
                             f"got {self.stop_at}")
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


def start_in_lane(world, lane: str, pose: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
    """The start pose for ``lane``: ``pose`` when given; in the left lane, the world's start (which
    is in the right lane) moved one lane width (0.4 m) to the car's left; else None (the world's)."""
    if pose is not None or lane != "left":
        return pose
    x, y, yaw = world.start
    d = 2.0 * LANE_HALF_WIDTH
    return (x - d * math.sin(yaw), y + d * math.cos(yaw), yaw)


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
#: The blocks of the lane example (sheet 5.3 and the lane-following block list), in its order.
BLOCKS = (
    BASIC_SPEED_ESTIMATION,
    BlockSpec("image_selector", "image_selector(image) -> image", "BGR (H, W, 3) -> the same, zero outside",
              "lane example block 1", "Keep the region where the tracked line is expected (same shape).", "image"),
    BlockSpec("color_thresholding_hsv", "color_thresholding_hsv(image_bgr) -> mask", "BGR uint8 -> uint8 0/255",
              "5.3 Task, lane example block 2", "Keep the yellow paint (the HSV ranges you tuned).", "mask"),
    BlockSpec("linear_poly_fit", "linear_poly_fit(mask) -> LineFit | None",
              "mask -> slope, intercept of u = slope v + intercept (px), pixels, rows",
              "lane example block 3 (steeringCalculation)",
              "A straight line through the line's pixels; None when there are too few."),
    BlockSpec("steering_calculation", "steering_calculation(fit, offset) -> steering",
              "LineFit | None, m (where the line lies from the lane centre, + = left) -> rad",
              "lane example block 3 (steeringCalculation)", "Steer onto the lane centre from the fitted line.",
              "steering"),
    BlockSpec("draw_box", "draw_box(shape, steering) -> (x0, y0, x1, y1)", "image shape, rad -> px",
              "lane example block 4 (obstacleDetection)", "The obstacle window, shifted where the car turns."),
    BlockSpec("calculate_distance", "calculate_distance(depth, box) -> distance", "m image, px -> m (0 = nothing)",
              "lane example block 4 (obstacleDetection)", "Mean depth of the obstacle window within 2 m."),
    BlockSpec("automated_driving", "automated_driving(desired_speed, obstacle_distance) -> speed", "m/s, m -> m/s",
              "lane example block 5", "Adaptive cruise: slower as an obstacle nears, 0 at the stop distance.",
              "speed"),
    TURN_SPEED_HANDLING,
    SPEED_CONTROLLER,
    INDICATOR_AND_LAMPS,
    BlockSpec("user_inputs", "user_inputs(speed_selector, stop_offset, distance_to_lane) -> "
              "(desired_speed, stop_distance, lane_gain)", "%, %, % -> m/s, m, 0..1", "lane example block 10",
              "The sliders: Speed Selector (% of the maximum speed), Stopping Distance Offset (% added to the "
              "0.6 m minimum), Distance To Lane (0 % the line, 100 % the lane centre); read at the start."),
)


class LaneFollowingLab(LabModel):
    """The lane example's diagram (sheet 5.3) as a block diagram; see the module docstring."""

    lab = "lane-follow"
    BLOCKS = BLOCKS

    def __init__(self, cfg: LaneFollowConfig, params: QCarParams, throttle_limit: float,
                 blocks: Mapping[str, Any] | None = None):
        self.cfg, self.p, self.throttle_limit = cfg, params, throttle_limit
        self.cam = LaneCamera.from_params(params)
        super().__init__(blocks)
        self.frame_dt = 1.0 / params.rgbd_rate
        self.next_frame = 0.0
        self.delta, self.last_seen, self.d_obs = 0.0, 0.0, 0.0
        self.det = LaneDetection(None, None)
        self._masks: Any = None  # None or what gives self.det its masks (see _detect)
        self.frame = self.box = self.shown = None
        self.frames = self.lost = self.white = self.yellow = 0
        self.since_yellow: float | None = None  # m driven (by the encoder) since the yellow line was last seen
        self.line_lost = False
        self.driven = 0.0  # m, by the encoder
        self.desired_speed, self.stop_distance, self.lane_gain = cfg.speed, cfg.stop_distance, 1.0
        self._keeps_black = LaneBand.keeps_black(cfg.hsv_min, cfg.hsv_max)  # (then no band: see detect)

    #: the blocks the lab's vision runs on a frame's lower band alone (:class:`LaneBand`) while they
    #: are qcarlab's; the obstacle window's blocks, on its rows of the depth alone
    BAND_BLOCKS = ("image_selector", "color_thresholding_hsv", "linear_poly_fit")
    WINDOW_BLOCKS = ("draw_box", "calculate_distance")

    def reference_blocks(self) -> dict[str, Any]:
        c = self.cfg
        self._reference = {
            "basic_speed_estimation": partial(basic_speed_estimation, params=self.p),
            "image_selector": partial(image_selector, lane=c.lane),
            "color_thresholding_hsv": partial(color_thresholding_hsv, hsv_min=c.hsv_min, hsv_max=c.hsv_max),
            "linear_poly_fit": partial(linear_poly_fit, min_pixels=c.min_pixels),
            "steering_calculation": partial(steering_calculation, cam=self.cam, lookahead=c.lookahead),
            "draw_box": draw_box,
            "calculate_distance": obstacle_distance,
            "automated_driving": self._automated_driving,
            "user_inputs": partial(user_inputs, max_speed=c.speed, min_stop_distance=c.stop_distance),
            "turn_speed_handling": turn_speed_handling,
            "speed_controller": SpeedController(c.kp, c.ki, c.kff, throttle_limit=self.throttle_limit),
            "indicator_and_lamps": indicator_and_lamps,
        }
        return self._reference

    def _reference_in(self, names: tuple[str, ...]) -> bool:
        """Whether the blocks ``names`` are qcarlab's (none replaced by a student's)."""
        return all(getattr(self, n) is self._reference[n] for n in names)

    def _automated_driving(self, desired_speed: float, obstacle_distance: float) -> float:
        """The reference automated_driving at the stop distance the user inputs set."""
        return automated_driving(desired_speed, obstacle_distance, stop_distance=self.stop_distance)

    def start(self, car: Any, dt: float) -> None:
        super().start(car, dt)
        inputs = self.user_inputs(self.cfg.speed_selector, self.cfg.stop_offset, self.cfg.distance_to_lane)
        try:
            v, d, g = (float(x) for x in inputs)
        except (TypeError, ValueError):
            from qcarlab.blocks import StudentBlockError

            raise StudentBlockError(f"block user_inputs returned {inputs!r}; expected (desired_speed m/s, "
                                    "stop_distance m, lane_gain 0..1)") from None
        if not (math.isfinite(v) and 0.0 <= v <= 3.0 and math.isfinite(d) and 0.0 <= d <= 2.4
                and math.isfinite(g) and 0.0 <= g <= 1.0):
            from qcarlab.blocks import StudentBlockError

            raise StudentBlockError(f"block user_inputs returned {inputs!r}: out of range (speed 0..3 m/s, "
                                    "stop distance 0..2.4 m, lane gain 0..1)")
        self.desired_speed, self.stop_distance, self.lane_gain = v, d, g

    def detect(self, color: np.ndarray | Any) -> LaneDetection:
        """The vision half of the diagram: the yellow line, else (backup) the lane's white edge line,
        only where the yellow line was seen less than ``backup_distance`` m ago (it left the view in a
        curve): the yellow line, found with the student's HSV range, is what the lab follows.

        ``color``: a BGR frame, or an RGBD frame (its colour). While :data:`BAND_BLOCKS` are
        qcarlab's, they run on the frame's lower band alone, converted to HSV once for both lines
        (:class:`LaneBand`: the same masks and fits; a simulated frame then draws those rows only)."""
        det, masks = self._detect(color)
        return masks(det) if masks is not None else det

    def _detect(self, color: np.ndarray | Any) -> tuple[LaneDetection, Any]:
        """:meth:`detect`, and None or the function that gives the detection its frame-sized masks
        (the band's: made for the frame a figure shows alone)."""
        c = self.cfg
        backup = c.white_backup and self.since_yellow is not None and self.since_yellow <= c.backup_distance
        if self._reference_in(self.BAND_BLOCKS) and not self._keeps_black:
            return self._detect_band(_band(color), backup)
        return self._detect_blocks(color, backup), None

    def _detect_blocks(self, color: np.ndarray | Any, backup: bool) -> LaneDetection:
        """:meth:`detect` through the blocks (a student's among them) on the whole frame."""
        c = self.cfg
        color = color if isinstance(color, np.ndarray) else color.color
        yellow = self.color_thresholding_hsv(self.image_selector(color))
        fit = self.linear_poly_fit(yellow)
        ny = int(np.count_nonzero(yellow))
        if fit is not None or not backup:
            return LaneDetection(fit, "yellow" if fit is not None else None, ny, 0, yellow, yellow)
        white = white_edge_mask(color, c.lane, c.white_s_max, c.white_v_min)
        fit = self.linear_poly_fit(white)
        return LaneDetection(fit, "white" if fit is not None else None, ny, int(np.count_nonzero(white)),
                             white if fit is not None else yellow, yellow)

    def _detect_band(self, band: LaneBand, backup: bool) -> tuple[LaneDetection, Any]:
        """:meth:`_detect` with qcarlab's vision blocks, on the frame's lower band alone."""
        c = self.cfg
        ymask, c0 = band.yellow(c.lane, c.hsv_min, c.hsv_max)
        ny = cv2.countNonZero(ymask)
        # (fewer pixels than min_pixels: no line of as many, the fit is None)
        fit = band.fit(ymask, c.min_pixels, c0)[0] if ny >= max(2, int(c.min_pixels)) else None
        if fit is not None or not backup:
            return (LaneDetection(fit, "yellow" if fit is not None else None, ny, 0),
                    partial(_band_masks, band, (ymask, c0), (ymask, c0)))
        edge = band.white_edge(c.lane, c.white_s_max, c.white_v_min)
        white = edge[1]
        fit = band.fit_edge(edge, c.min_pixels)
        nw = cv2.countNonZero(white) if white is not None else 0
        return (LaneDetection(fit, "white" if fit is not None else None, ny, nw),
                partial(_band_masks, band, (white, 0) if fit is not None else (ymask, c0), (ymask, c0)))

    def detection(self) -> LaneDetection:
        """The last frame's detection, with its masks."""
        return self._masks(self.det) if self._masks is not None else self.det

    def obstacle_distance(self, frame: Any, box: Any) -> float:
        """calculate_distance(frame's depth, box); while :data:`WINDOW_BLOCKS` are qcarlab's, on
        the box's rows of the depth alone (the same pixels: a simulated frame draws those rows)."""
        rows = getattr(frame, "depth_rows", None)
        if rows is None or not self._reference_in(self.WINDOW_BLOCKS):
            return float(self.calculate_distance(frame.depth, box))
        x0, y0, x1, y1 = (int(v) for v in box)
        return float(obstacle_distance(rows(y0, y1), (x0, 0, x1, y1 - y0)))

    def lost_line(self, t: float) -> bool:
        """Whether the yellow line is lost for good: not seen for ``backup_distance`` m driven (or,
        never seen, for that far from the start or 3 s armed, whichever is later); the run then ends."""
        c = self.cfg
        if self.since_yellow is None:
            driven = self.driven
            self.line_lost = driven > c.backup_distance and t >= c.start_at + 3.0
        else:
            self.line_lost = self.since_yellow > c.backup_distance
        return self.line_lost

    def step(self, t: float, r, dt: float) -> Step | object:
        c = self.cfg
        v = self.basic_speed_estimation(r.tach)
        self.driven += abs(v) * dt
        if self.since_yellow is not None:
            self.since_yellow += abs(v) * dt
        if t + 1e-9 >= self.next_frame:
            frame = self.read_rgbd()
            self.next_frame = (math.floor((t + 1e-9) / self.frame_dt) + 1) * self.frame_dt
            det, masks = self._detect(frame)
            self.frames += 1
            if det.source == "yellow":
                self.yellow += 1
                self.since_yellow = 0.0
            elif self.lost_line(t):
                return STOP
            if det.fit is not None:
                self.delta = self.steering_calculation(det.fit, self.lane_gain * line_offset(c.lane, det.source))
                self.last_seen = t
                self.white += det.source == "white"
            else:
                self.lost += 1
                if t - self.last_seen > c.hold_lost:
                    self.delta = 0.0
            box = self.draw_box(_shape(frame), self.delta)
            self.d_obs, self.box, self.det, self._masks, self.frame = (self.obstacle_distance(frame, box), box, det,
                                                                       masks, frame)
            if self.shown is None and det.source == "yellow" and t >= 1.0:
                self.shown = (frame, self.detection(), box)
        delta = self.delta
        armed = t + 1e-9 >= c.start_at and (c.stop_at is None or t + 1e-9 < c.stop_at)
        if armed:
            v_ref = self.automated_driving(self.desired_speed, self.d_obs)
            v_ref = self.turn_speed_handling(v_ref, delta) if c.turn_speed else v_ref
            throttle = self.speed_controller(v_ref, v, dt)
        else:  # the arm switch off: no motor command, the integrator held at zero
            v_ref, throttle = 0.0, 0.0
            reset = getattr(self.speed_controller, "reset", None)
            if callable(reset):
                reset()
        names = tuple(self.indicator_and_lamps(delta, v_ref))
        return Step(Command(throttle, delta, lamps_named(names)),
                    {"v_ref": v_ref, "v_meas": v, "line": self.det.source or "none", "obstacle_distance": self.d_obs,
                     "armed": int(armed), "lamps": "+".join(names)})


def _band_masks(band: LaneBand, mask: tuple[np.ndarray | None, int], yellow: tuple[np.ndarray, int],
                det: LaneDetection) -> LaneDetection:
    """``det`` with its frame-sized masks: the tracked one and the yellow one, each (band mask, column)."""
    yellow_full = band.full(*yellow)
    return replace(det, mask=yellow_full if mask[0] is yellow[0] else band.full(*mask), yellow_mask=yellow_full)


def _shape(frame: Any) -> tuple[int, int]:
    """An RGBD frame's (H, W), its depth's shape (without drawing a simulated frame's rows)."""
    shape = getattr(frame, "shape", None)
    return tuple(shape) if shape is not None else frame.depth.shape


def _band(frame: Any) -> LaneBand:
    """The lower band of a BGR frame or of an RGBD frame's colour, the frame's other rows not read
    (a simulated frame draws the rows asked for alone: ``color_rows``)."""
    rows = getattr(frame, "color_rows", None)
    if rows is None:
        return LaneBand.of(frame if isinstance(frame, np.ndarray) else frame.color)
    h, w = _shape(frame)
    return LaneBand(rows(region_row(h), h), (h, w))


class _Laps:
    """Ends a lane-follow run after ``laps`` laps of the lane centre (simulator)."""

    def __init__(self, model: LaneFollowingLab, car: Car, poly: Polyline, laps: float):
        self.model, self.car, self.poly, self.laps = model, car, poly, laps
        tr = car.truth()
        self.s = float(poly.nearest(np.array([[tr.x, tr.y]]))[1][0])
        self.along = 0.0

    def start(self, car: Car, dt: float) -> None:
        self.model.start(car, dt)

    def step(self, t: float, r, dt: float):
        out = self.model.step(t, r, dt)
        tr = self.car.truth()
        s = float(self.poly.nearest(np.array([[tr.x, tr.y]]))[1][0])
        L = self.poly.length
        self.along += abs((s - self.s + L / 2.0) % L - L / 2.0)
        self.s = s
        return STOP if self.along >= self.laps * L else out


def run_lane_follow(car: Car, cfg: LaneFollowConfig, world=None, *, blocks: Mapping[str, Any] | None = None,
                    wrap=None) -> Result:
    """Follow the lane at ``cfg.speed`` for ``cfg.duration`` s (or ``cfg.laps`` laps).

    ``blocks`` replaces any block of :data:`BLOCKS` by name; ``wrap(model) -> model`` wraps the
    model the loop runs (trials).
    """
    world = world if world is not None else getattr(car, "world", None)  # a local simulator's
    cfg.check()
    p = car.params
    dt = 1.0 / cfg.rate
    lab = LaneFollowingLab(cfg, p, car.throttle_limit, blocks)
    lab.read_rgbd = getattr(car, "read_rgbd_rows", car.read_rgbd)  # (a simulator's: the rows read drawn alone)
    warm = getattr(car, "warm_physics", None)  # a simulator's compiled physics: the camera loads numba anyway,
    if callable(warm):  # the kernel's load (some 10 ms then) costs less than the plain steps it replaces
        warm()
    truth0 = car.truth()
    centre = lane_centre(world, (truth0.x, truth0.y, truth0.yaw)) if (world is not None and truth0 is not None) else None
    model: Any = lab
    if cfg.laps is not None and centre is not None:
        model = _Laps(lab, car, Polyline(centre), cfg.laps)
    watch = WorldWatch.for_car(car, world)
    if watch is not None:
        model = watch.wrap(model)
    duration = cfg.duration
    if duration is None:  # --laps sets the time it needs (half as much again, for the turns)
        duration = min(3600.0, 1.5 * cfg.laps * Polyline(centre).length / cfg.speed + 10.0) \
            if (cfg.laps is not None and centre is not None) else 30.0
    log = run_loop(car, wrap(model) if wrap else model, duration, cfg.rate)
    cols = log.arrays()
    n = log.ticks
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
        "frames": lab.frames,
        "frames_line_lost": lab.lost,
        "frames_yellow": lab.yellow,
        "line_lost": lab.line_lost,
        "frames_white_backup": lab.white,
        "stopped_for_obstacle_s": float(np.count_nonzero((cols["v_ref"] == 0.0) & (cols["armed"] == 1)
                                                         & (cols["obstacle_distance"] > 0.0)) * dt) if n else 0.0,
        "brake_lamp_s": float(sum("brake" in str(x).split("+") for x in cols["lamps"]) * dt) if n else 0.0,
        "user_inputs": {"desired_speed_mps": lab.desired_speed, "stop_distance_m": lab.stop_distance,
                        "lane_gain": lab.lane_gain},
    })
    metrics["config"] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()}
    goal, why = True, ""
    if lab.line_lost:
        seen = (f"never found the yellow line in {lab.frames} frames" if not lab.yellow else
                f"lost the yellow line: not seen for {cfg.backup_distance:g} m driven, found in {lab.yellow} of "
                f"{lab.frames} frames")
        goal, why = False, (f"{seen} with the HSV range {list(cfg.hsv_min)}..{list(cfg.hsv_max)}: check it with "
                            "qcarlab lane-follow --hsv-tune")
    elif cfg.laps is not None and metrics["laps"] is not None and metrics["laps"] < cfg.laps - 0.02:
        goal, why = False, f"drove {metrics['laps']:.2f} of {cfg.laps:g} laps in the time limit"
    elif metrics["time_out_of_lane_s"]:
        goal, why = False, f"out of the lane for {metrics['time_out_of_lane_s']:.2f} s"
    finish(metrics, log, lab, watch, goal, why)

    result = Result("lane-follow", metrics, logs={"log.csv": _log_columns(cols)}, figures={})
    shown = lab.shown or ((lab.frame, lab.detection(), lab.box) if lab.frame is not None else None)
    if shown is not None:
        frame, det, box = shown
        frame = getattr(frame, "whole", lambda: frame)()  # (a frame read by rows: all of it)
        shown = (frame, det, box)
        result.data["frame"] = shown
        result.figures["frame.png"] = lambda f: save_figure(f, frame_figure(frame.color, det, box))
    if world is not None and "true_x" in cols and n:
        poses = np.stack([cols["true_x"], cols["true_y"], cols["true_yaw"]], axis=1)
        result.figures["lane.png"] = lambda f: save_figure(f, lane_figure(world, poses, centre, metrics))
    return result


def lane_figure(world, poses: np.ndarray, centre, metrics: Mapping[str, Any] | None = None) -> Any:
    """``lane.png``: the driven path against the lane's centre over the track, axes in metres, a
    legend (:func:`qcarlab.plots.lane_figure`). Returns the matplotlib Figure."""
    from qcarlab import plots
    from qcarlab.experiments.worlds import figure_map

    background, extent = figure_map(world, show_start=False)
    return plots.lane_figure(background, extent, poses[:: max(1, len(poses) // 2000)], centre, metrics)


def frame_figure(color: np.ndarray, det, box) -> Any:
    """``frame.png``: the camera frame the lane was last found in, with the tracked pixels, the fitted
    line and the obstacle window, and a legend saying which is which. Returns the Figure."""
    from qcarlab import plots

    return plots.camera_figure([(lane_overlay(color, det, box), lane_caption(det))], LANE_OVERLAYS,
                               "lane following: what the camera saw")



def _log_columns(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    keep = ["t", "line", "lateral_deviation", "obstacle_distance", "armed", "v_ref", "v_meas", "true_speed",
            "throttle", "steering", "lamps", "true_x", "true_y", "true_yaw"]
    return {k: cols[k] for k in keep if k in cols}


# ------------------------------------------------------------------------------- an obstacle
OBSTACLE_SIZE = (0.25, 0.25, 0.3)  # m: a box as long, wide and tall as a cardboard box on the road


def place_obstacle(world, start: tuple[float, float, float], distance: float) -> tuple[float, float, float]:
    """Put a box (:data:`OBSTACLE_SIZE`) in the car's lane, its near face ``distance`` m ahead of the
    front bumper of the car at ``start``, measured along the lane centre (straight ahead when the
    world has no lane), through :meth:`World.add_box`; returns its pose (x, y, yaw). For the
    sheet's obstacle detection (``lane-follow --obstacle``)."""
    if not (math.isfinite(distance) and 0.3 <= distance <= 20.0):
        raise InputError(f"--obstacle must be a distance of 0.3..20 m ahead, got {distance}")
    length, width, height = OBSTACLE_SIZE
    centre = lane_centre(world, start)
    x, y, yaw = start
    ahead = distance + world.params.length / 2.0 + length / 2.0  # car centre to box centre
    if centre is None:
        d = ahead
        pose = (x + d * math.cos(yaw), y + d * math.sin(yaw), yaw)
    else:
        poly = Polyline(centre)
        s0 = float(poly.nearest(np.array([start[:2]]))[1][0])
        _p, j = poly.point_at(s0)
        seg = centre[j + 1] - centre[j]
        forward = 1.0 if math.cos(math.atan2(seg[1], seg[0]) - yaw) >= 0 else -1.0
        s = (s0 + forward * ahead) % poly.length
        p, j = poly.point_at(s)
        seg = centre[j + 1] - centre[j]
        pose = (float(p[0]), float(p[1]), math.atan2(seg[1], seg[0]))
    world.add_box(pose[0], pose[1], length, width, pose[2], height)
    return pose


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


def hsv_tune(frames: list, cfg: LaneFollowConfig, params: QCarParams | None = None,
             blocks: Mapping[str, Any] | None = None) -> Result:
    """Threshold each ``(pose, RGBDFrame)`` of ``frames`` as the lab's chain does, with its blocks
    (the student's ``color_thresholding_hsv``, ``image_selector`` and ``linear_poly_fit`` when
    given, else qcarlab's with the HSV range): per spot the yellow pixel count (in the lane's region
    of interest and in the whole image), whether a line was fitted, and the figure
    ``hsv_tune.png``: colour | thresholded mask | lane mask (red over the kept pixels), one row
    per spot."""
    cfg.check()
    from qcarlab.constants import DEFAULT_PARAMS

    lab = LaneFollowingLab(cfg, params or DEFAULT_PARAMS, 1.0, blocks)
    spots, rows = [], []
    for pose, frame in frames:
        full = np.asarray(lab.color_thresholding_hsv(frame.color))
        roi = np.asarray(lab.image_selector(full))
        fit = lab.linear_poly_fit(roi)
        spots.append({
            "pose": [round(v, 3) for v in pose],
            "pixels_whole_image": int(np.count_nonzero(full)),
            "pixels_in_region": int(np.count_nonzero(roi)),
            "line_found": fit is not None,
            "slope": fit.slope if fit is not None else None,
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
    result = Result("lane-follow", metrics, figures={})
    if rows:
        title = f"HSV range {list(cfg.hsv_min)} .. {list(cfg.hsv_max)}: the line found at {metrics['spots_with_line']} " \
                f"of {len(spots)} spots"
        result.data["hsv_tune"] = rows
        result.figures["hsv_tune.png"] = lambda f: save_figure(f, hsv_tune_figure(rows, title))
    return result


#: What hsv_tune.png's panels show (the sheet: "the line must be coloured with red pixels").
TUNE_OVERLAYS = (("white: the pixels the HSV range keeps (whole image)", "white", "pixels"),
                 ("red: the kept pixels in the lane's region, the ones the lab fits its line to", "red", "pixels"))


def hsv_tune_figure(rows: list, title: str) -> Any:
    """``hsv_tune.png``: one row per spot, colour | HSV mask | lane mask, each titled, with a legend
    of what the white and red pixels are. Returns the Figure."""
    from qcarlab import plots

    return plots.camera_grid(rows, TUNE_OVERLAYS, title)


def _tune_row(color: np.ndarray, full: np.ndarray, roi: np.ndarray, spot: dict) -> list:
    found = "line found" if spot["line_found"] else "no line"
    x, y = (round(v, 2) + 0.0 for v in spot["pose"][:2])  # (+ 0.0: no "-0.00")
    return [(color, f"colour at x {x:.2f} m, y {y:.2f} m"),
            (full, f"HSV mask: {spot['pixels_whole_image']} px"),
            (lane_mask(color, roi), f"lane mask: {spot['pixels_in_region']} px in region ({found})")]
