"""Stop at a stop sign (lab sheet 5.1-5.2): the *Stop.slx* model on any car.

The model, :class:`StopSignLab`, is the sheet's Figure 50; each tick (``rate``, 100 Hz)::

    v     = basic_speed_estimation(tach)                      # encoder -> m/s
    on each new RGBD frame (30 Hz):
        mask  = color_thresholding_hsv(color)                 # the sheet's red
        obj   = find_objects(mask)                            # the largest red blob (or None)
        d     = calculate_distance(depth, obj.centroid, mask) # depth at the sign, 0 = no sign
    v_ref = stop_sign(d, v_desired)                           # the sheet's block (behaviour "sheet")
          | stop_sign_hold(t, d, new_frame, v, v_desired)     # Task 4: slow, stop, hold, go ("hold")
    u     = speed_controller(v_ref, v, dt)                    # feed-forward PI -> throttle
    steering = 0                                              # the road is straight

Every block is looked up by its sheet name: ``--use mylab/stop_sign.py`` runs the same model with
the student's ``stop_sign``. Between frames the last frame's distance is held (as Simulink's
zero-order hold does). Once the car is at rest with v_ref = 0 the speed controller gives throttle
0 and resets its integrator, so the integral wound up while braking does not back the car away.

The run ends: in the sheet mode when the car has stood still for ``settle`` seconds after
stopping for the sign (the sheet's car would wait there for ever); in the hold mode when the
car has driven ``pass_margin`` m past the sign after its stop; otherwise at ``max_time``.

Scoring (simulator only) uses the true pose and the world's sign: ``stop_distance_m`` is the
distance **from the car's front bumper** (centre + length / 2 along the heading) to the sign's
plate, measured along the heading, when the car came to rest. The camera is 2.25 cm behind the
bumper (``rgbd_x`` = 0.19 m), so the camera's own reading (``measured_distance_m``, the D435's
z-depth) is that much larger. The goal is reached when the car came to rest before the sign
(and, in the hold mode, drove on past it); a run that hits something or leaves the world fails.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from functools import partial
from typing import Any

import cv2
import numpy as np

from qcarlab.blocks import BlockSpec
from qcarlab.car.base import Car, Command, Readout
from qcarlab.car.lamps import ALL_OFF, parse_lamps
from qcarlab.constants import QCarParams
from qcarlab.control.speed import KFF, KI, KP, SpeedController, basic_speed_estimation
from qcarlab.control.stop_sign import (
    FAR,
    NEAR,
    STANDSTILL,
    StopSignHold,
    stop_sign,
)
from qcarlab.errors import InputError
from qcarlab.experiments.loop import STOP, Step, check_rate, run_loop
from qcarlab.experiments.model import BASIC_SPEED_ESTIMATION, SPEED_CONTROLLER, LabModel, finish
from qcarlab.experiments.result import Result, save_figure
from qcarlab.experiments.safety import WorldWatch
from qcarlab.perception.stop_sign import (
    MIN_AREA,
    RED_HSV_MAX,
    RED_HSV_MIN,
    StopSignDetection,
    depth_at,
    check_hsv,
    color_thresholding_hsv,
    DETECTION_OVERLAYS,
    detection_image,
    detection_panels,
    find_objects,
)
from qcarlab.perception.stop_signs import MAX_CIRCLES, MIN_RED_SHARE, circle_hough, red_share

BEHAVIOURS = ("sheet", "hold")
DETECTORS = ("hsv", "hough")  # the sheet's chain (5.1), the race-car report's (Circle Hough, red inside, depth < 2 m)
REPORT_RANGE = 2.0  # m: the report counts a sign whose depth is under 2 m
_BRAKE = parse_lamps(["brake"])
FRAME_EVERY = 3  # --frames keeps every 3rd camera frame (10 per second)


@dataclass
class StopSignConfig:
    """Everything that shapes a run."""

    speed: float = 0.3  # m/s desired
    behaviour: str = "sheet"
    detector: str = "hsv"
    hold: float = 3.0  # s, hold mode
    hsv_min: tuple[int, int, int] = RED_HSV_MIN
    hsv_max: tuple[int, int, int] = RED_HSV_MAX
    min_area: int = MIN_AREA  # px
    kp: float = KP
    ki: float = KI
    kff: float = KFF
    rate: float = 100.0  # Hz
    max_time: float | None = None  # s; default from the speed
    settle: float = 1.0  # s standing still that ends a sheet-mode run
    pass_margin: float = 0.3  # m past the sign that ends a hold-mode run
    frames: bool = False  # keep annotated camera frames for --out DIR/frames/
    near: float = NEAR  # m: the stop window of the sheet's block, near ..
    far: float = FAR  # m: .. far

    def check(self) -> None:
        if self.behaviour not in BEHAVIOURS:
            raise InputError(f"--behaviour must be one of {', '.join(BEHAVIOURS)}, got {self.behaviour!r}")
        if self.detector not in DETECTORS:
            raise InputError(f"--detector must be one of {', '.join(DETECTORS)}, got {self.detector!r}")
        if not (math.isfinite(self.speed) and self.speed > 0.0):
            raise InputError(f"--speed must be a positive number of m/s, got {self.speed}")
        if self.speed > 3.0:
            raise InputError(f"--speed {self.speed} m/s is beyond what the car can do at the throttle limit (3 m/s)")
        if not (math.isfinite(self.hold) and 0.0 <= self.hold <= 60.0):
            raise InputError(f"--hold must be 0..60 s, got {self.hold}")
        self.hsv_min = check_hsv(self.hsv_min, "--hsv-min")
        self.hsv_max = check_hsv(self.hsv_max, "--hsv-max")
        if self.hsv_min[1] > self.hsv_max[1] or self.hsv_min[2] > self.hsv_max[2]:
            raise InputError(f"--hsv-min {self.hsv_min} is above --hsv-max {self.hsv_max} in saturation or value")
        if not (isinstance(self.min_area, int) and self.min_area >= 1):
            raise InputError(f"--min-area must be a positive number of pixels, got {self.min_area}")
        for name in ("kp", "ki", "kff"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"--{name} must be a non-negative number, got {value}")
        if self.max_time is not None and not (math.isfinite(self.max_time) and self.max_time > 0):
            raise InputError(f"--max-time must be a positive number of seconds, got {self.max_time}")
        if not (math.isfinite(self.near) and math.isfinite(self.far) and 0.0 <= self.near < self.far <= 10.0):
            raise InputError(f"the stop window must be 0 <= near < far <= 10 m, got near {self.near}, far {self.far}")
        check_rate(self.rate)


def sign_ahead(world, pose: tuple[float, float, float]):
    """The world's stop sign the car at ``pose`` drives towards: the nearest sign ahead (at most
    1 m to the side of the car's line) whose face looks back at the car; None when there is none."""
    x, y, yaw = pose
    best, best_d = None, math.inf
    for sign in getattr(world, "signs", []) or []:
        dx, dy = sign.x - x, sign.y - y
        ahead = dx * math.cos(yaw) + dy * math.sin(yaw)
        lateral = -dx * math.sin(yaw) + dy * math.cos(yaw)
        if ahead <= 0.0 or abs(lateral) > 1.0:
            continue
        if math.cos(sign.facing - yaw) > -0.5:  # the face does not look at the car
            continue
        if ahead < best_d:
            best, best_d = sign, ahead
    return best


def bumper_distance(pose: tuple[float, float, float], plate: tuple[float, float], half_length: float) -> float:
    """Distance (m) along the heading from the front bumper at ``pose`` to the sign plate at ``plate``."""
    x, y, yaw = pose
    return (plate[0] - x) * math.cos(yaw) + (plate[1] - y) * math.sin(yaw) - half_length


def sign_distance(depth: np.ndarray, centroid, mask: np.ndarray | None = None) -> float:
    """The stop-sign lab's ``calculate_distance``: the median depth (m) of the red pixels around the
    sign's centroid, or of every valid pixel there when no red pixel has depth; 0 = unknown."""
    if centroid is None:
        return 0.0
    d = depth_at(depth, centroid, mask=mask)
    return d if d > 0.0 else depth_at(depth, centroid)


#: The blocks of the Stop.slx diagram (sheet 5.2, Figure 50), in the sheet's order.
BLOCKS = (
    BASIC_SPEED_ESTIMATION,
    BlockSpec("color_thresholding_hsv", "color_thresholding_hsv(image_bgr) -> mask", "BGR uint8 -> uint8 0/255",
              "5.1, Figure 47", "Keep the pixels whose HSV is the sign's red (hue wraps through 0).", "mask"),
    BlockSpec("find_objects", "find_objects(mask) -> ImageObject | None", "mask -> centroid (u, v) px, bbox, area",
              "5.1, Image Find Objects", "The largest blob of the mask: the sign."),
    BlockSpec("calculate_distance", "calculate_distance(depth, centroid, mask) -> distance", "m image, px, mask -> m",
              "5.1, Figure 48", "Depth at the sign's centroid; 0 when unknown (the camera reads 0)."),
    BlockSpec("stop_sign", "stop_sign(distance_to_sign, desired_speed) -> speed_cmd", "m, m/s -> m/s",
              "5.2 Task 1, Figure 51", "0 while the sign is between 0.05 and 0.40 m, else the desired speed.",
              "speed",
              fill="Fill the stopSign function: make the QCar stop if the sign is between 5 and 40 cm, and "
              "make the speed output equal to the desired speed input if the sign is not in that range. "
              "(Not between 0 and 40 cm: the sensor gives a distance of 0 when it does not find the sign.)",
              example="stop_sign(0.30, 0.5) == 0.0; stop_sign(0.02, 0.5) == 0.5; stop_sign(0.45, 0.5) == 0.5"),
    BlockSpec("stop_sign_hold", "stop_sign_hold(t, distance_to_sign, new_frame, speed, desired_speed) -> speed_cmd",
              "s, m (0 = no sign; held between frames), True on a new frame, m/s, m/s -> m/s",
              "5.2 Task 4 (improvements; the race-car report's 3 s stop)",
              "The improved stopSign (--behaviour hold): slow on approach, stop before the sign, stand still "
              "3 s, drive on and ignore that sign.", "speed", stateful=True,
              fill="Task 4, suggest improvements, then build them: the sheet's stopSign brakes only inside "
              "0.40 m (so where the car stops depends on its speed), drives off at full speed the moment the "
              "sign leaves the camera's view (the distance reads 0), and never drives on. Make the car stop "
              "0.05-0.40 m before the sign at any speed up to 1 m/s, stand still about 3 s (the race-car "
              "report's stop), then drive on at the desired speed past the sign. Called every tick (100 Hz); "
              "a new camera frame comes every third tick (new_frame True), between frames the last distance "
              "is held: dead-reckon with speed * dt when you need it.",
              example="stop_sign_hold(t, 0.0, True, 0.0, 1.0) == 1.0 (no sign: drive)"),
    BlockSpec("circle_hough", "circle_hough(image_bgr) -> circles", "BGR uint8 -> (n, 3) array of u, v, r px",
              "race-car report, stop sign (--detector hough)",
              "The Circle Hough Transform: the image's circles, best-voted first."),
    BlockSpec("red_share", "red_share(image_bgr, circle) -> share", "BGR uint8, (u, v, r) px -> 0..1",
              "race-car report, stop sign (--detector hough)",
              "The share of red pixels inside the circle: a stop sign's is 0.6..0.95 (white letters and rim).",
              fill="The race-car report's colour check (--detector hough): the Circle Hough Transform found a "
              "circle (u, v, r) in pixels; return the share (0..1) of the pixels inside it that are the sign's "
              "red (HSV, the hue wrapping through 0). A circle is taken for the sign when the share is at least "
              "0.5; a circle that is not wholly in the image should give 0.",
              example="red_share(image, (320.0, 200.0, 30.0)) -> 0.84 on the simulator's sign 2 m ahead"),
    SPEED_CONTROLLER,
)


class StopSignLab(LabModel):
    """The sheet's Stop.slx (Figure 50) as a block diagram; see the module docstring."""

    lab = "stop-sign"
    BLOCKS = BLOCKS

    def __init__(self, cfg: StopSignConfig, params: QCarParams, throttle_limit: float, true_distance=None,
                 sign_length: float = 0.0, blocks: Mapping[str, Any] | None = None):
        self.cfg, self.p, self.throttle_limit = cfg, params, throttle_limit
        super().__init__(blocks)
        self.hold_mode = cfg.behaviour == "hold"
        self.stops = 0
        self.true_distance = true_distance  # () -> bumper-to-plate distance (m) or None (a real car)
        self.past = -(params.length + sign_length)  # true distance once the rear bumper is past the sign
        self.frame_dt = 1.0 / params.rgbd_rate
        self.next_frame = 0.0
        self.det = StopSignDetection(False)
        self.frame = None
        self.frames = self.detections = 0
        self.decided = self.rest_t = self.go_t = None
        self.passed = self._resting = False
        self.best = self.at_rest = None  # (frame, detection) to show
        self.kept: list[tuple[float, np.ndarray]] = []

    def reference_blocks(self) -> dict[str, Any]:
        c = self.cfg
        return {
            "basic_speed_estimation": partial(basic_speed_estimation, params=self.p),
            "color_thresholding_hsv": partial(color_thresholding_hsv, hsv_min=c.hsv_min, hsv_max=c.hsv_max),
            "find_objects": partial(find_objects, min_area=c.min_area),
            "calculate_distance": sign_distance,
            "stop_sign": partial(stop_sign, near=c.near, far=c.far),
            "stop_sign_hold": StopSignHold(hold=c.hold),
            "circle_hough": circle_hough,
            "red_share": red_share,
            "speed_controller": SpeedController(c.kp, c.ki, c.kff, throttle_limit=self.throttle_limit),
        }

    def detect(self, frame) -> StopSignDetection:
        """The vision half of the diagram on one RGBD frame: the sheet's chain (HSV threshold, the
        largest blob, the depth there) or the race-car report's (``--detector hough``: the best-voted
        circle with at least half its pixels red, the depth at its centre, a sign only within 2 m)."""
        if self.cfg.detector == "hough":
            return self.detect_hough(frame)
        mask = self.color_thresholding_hsv(frame.color)
        obj = self.find_objects(mask)
        if obj is None:
            return StopSignDetection(False, mask=mask)
        d = float(self.calculate_distance(frame.depth, obj.centroid, mask))
        return StopSignDetection(True, obj.centroid, obj.bbox, obj.area, d if math.isfinite(d) else 0.0, mask=mask)

    def detect_hough(self, frame) -> StopSignDetection:
        for u, v, radius in np.asarray(self.circle_hough(frame.color), float).reshape(-1, 3)[:MAX_CIRCLES]:
            if float(self.red_share(frame.color, (float(u), float(v), float(radius)))) < MIN_RED_SHARE:
                continue
            d = float(self.calculate_distance(frame.depth, (float(u), float(v)), None))
            if not (math.isfinite(d) and 0.0 < d < REPORT_RANGE):
                return StopSignDetection(False)
            r = int(round(radius))
            return StopSignDetection(True, (float(u), float(v)), (int(round(u)) - r, int(round(v)) - r, 2 * r, 2 * r),
                                     int(math.pi * radius * radius), d)
        return StopSignDetection(False)

    def step(self, t: float, r: Readout, dt: float) -> Step | object:
        c = self.cfg
        v = self.basic_speed_estimation(r.tach)
        new = None
        if t + 1e-9 >= self.next_frame:  # a new camera frame is due
            frame = self.read_rgbd()
            self.next_frame = (math.floor((t + 1e-9) / self.frame_dt) + 1) * self.frame_dt
            det = self.det = self.detect(frame)
            self.frame = frame
            self.frames += 1
            new = det.distance if det.found else 0.0
            self.detections += int(det.found)
            if det.found and (self.best is None or det.area >= self.best[1].area):
                self.best = (frame, det)
            if c.frames and self.frames % FRAME_EVERY == 1:
                self.kept.append((t, cv2.imencode(".jpg", detection_image(frame.color, det))[1]))
        det = self.det
        d_meas = det.distance if det.found else 0.0
        if not self.hold_mode:
            v_ref = self.stop_sign(d_meas, c.speed)
        else:
            v_ref = self.stop_sign_hold(t, d_meas, new is not None, v, c.speed)
        state = getattr(self.stop_sign_hold, "state", None) if self.hold_mode else None
        state = state if isinstance(state, str) else ("stop" if v_ref == 0.0 else "go")
        if v_ref == 0.0 and self.decided is None:
            self.decided = t
        d_true = self.true_distance() if self.true_distance is not None else None
        if self.decided is not None and self.rest_t is None and abs(v) < STANDSTILL and v_ref == 0.0:
            self.rest_t = t  # the first standstill after deciding to stop
            self.at_rest = (self.frame, det)
        resting = abs(v) < STANDSTILL and v_ref == 0.0
        if resting and not self._resting:
            self.stops += 1
        self._resting = resting
        if self.rest_t is not None and self.go_t is None and v_ref > 0.0:
            self.go_t = t
        if d_true is not None and not self.passed and d_true < self.past:
            self.passed = True
        throttle = self.speed_controller(v_ref, v, dt)
        log = {"v_ref": v_ref, "v_meas": v, "sign_found": int(det.found), "sign_distance": d_meas,
               "true_distance": math.nan if d_true is None else d_true, "state": state}
        beyond = d_true is not None and d_true < -(self.p.length + c.pass_margin)
        if not self.hold_mode:
            if self.rest_t is not None and v_ref == 0.0 and t - self.rest_t >= c.settle:
                return STOP
            if self.passed and beyond:
                return STOP
        elif self.go_t is not None and (beyond or (d_true is None and t - self.go_t >= 3.0)):
            return STOP  # (no truth: drive on for 3 s)
        return Step(Command(throttle, 0.0, _BRAKE if v_ref == 0.0 else ALL_OFF), log)


def run_stop_sign(car: Car, cfg: StopSignConfig, sign=None, *, blocks: Mapping[str, Any] | None = None,
                  world: Any = None, wrap=None) -> Result:
    """Drive straight at ``cfg.speed`` and stop for the stop sign; return metrics, log, figures.

    ``sign`` is the world's :class:`~qcarlab.sim.world.Sign` the car drives towards (for the true
    stop distance); without it (a real car) the true-distance metrics are None. ``blocks``
    replaces any block of :data:`BLOCKS` by name; ``wrap(model) -> model`` wraps the model the
    loop runs (trials).
    """
    world = world if world is not None else getattr(car, "world", None)  # a local simulator's
    cfg.check()
    p = car.params
    dt = 1.0 / cfg.rate
    truth0 = car.truth()
    plate = sign.plate_center[:2] if (sign is not None and truth0 is not None) else None
    half = p.length / 2.0
    start_distance = bumper_distance((truth0.x, truth0.y, truth0.yaw), plate, half) if plate is not None else None

    def true_distance() -> float:
        tr = car.truth()
        return bumper_distance((tr.x, tr.y, tr.yaw), plate, half)

    lab = StopSignLab(cfg, p, car.throttle_limit, true_distance if plate is not None else None,
                      sign.post_radius * 2 if sign is not None else 0.0, blocks)
    lab.read_rgbd = car.read_rgbd
    watch = WorldWatch.for_car(car, world)
    max_time = cfg.max_time or (2.0 * (start_distance or 3.0) / cfg.speed + (cfg.hold if lab.hold_mode else 0.0)
                                + 8.0)
    model = watch.wrap(lab) if watch else lab
    log = run_loop(car, wrap(model) if wrap else model, max_time, cfg.rate)
    cols = log.arrays()
    n = log.ticks
    found = np.flatnonzero(cols["sign_found"] == 1) if n else np.zeros(0, int)
    first = int(found[0]) if found.size else None
    rest = None
    if lab.rest_t is not None:
        k = int(np.searchsorted(cols["t"], lab.rest_t - 1e-9))
        td = cols["true_distance"][k]
        rest = (None if math.isnan(td) else float(td), float(cols["sign_distance"][k]), lab.rest_t)
    true_min = np.nanmin(cols["true_distance"]) if plate is not None and n else None
    stopped = rest is not None and (rest[0] is None or rest[0] > 0.0)  # came to rest before the sign
    metrics = {
        "experiment": "stop-sign",
        "behaviour": cfg.behaviour,
        "detector": cfg.detector,
        "speed_mps": cfg.speed,
        "stopped": bool(stopped),
        "stop_distance_m": rest[0] if rest is not None else None,
        "measured_distance_m": rest[1] if rest is not None and rest[1] > 0 else None,
        "time_to_stop_s": rest[2] if rest is not None else None,
        "braking_time_s": (rest[2] - lab.decided) if rest is not None else None,
        "detected_at_m": float(cols["sign_distance"][first]) if first is not None else None,
        "detected_at_true_m": (None if plate is None else float(cols["true_distance"][first]))
        if first is not None else None,
        "detected_at_s": float(cols["t"][first]) if first is not None else None,
        "start_distance_m": start_distance,
        "min_distance_m": float(true_min) if true_min is not None else None,
        "frames": lab.frames,
        "frames_with_sign": lab.detections,
        "duration_s": float(cols["t"][-1] + dt) if n else 0.0,
        "distance_reference": "front bumper to the sign plate, along the heading (true pose)",
    }
    goal = stopped
    if lab.hold_mode:
        metrics["hold_s"] = (lab.go_t - lab.rest_t) if lab.go_t is not None else None
        # drove on past the sign after its stop (a car that never stopped did not "drive on")
        metrics["passed_sign"] = bool(lab.passed and lab.go_t is not None) if plate is not None else (lab.go_t is not None)
        metrics["stops"] = lab.stops
        goal = stopped and metrics["passed_sign"]
    metrics["config"] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()}
    finish(metrics, log, lab, watch, goal, "the car did not stop before the sign" if not stopped
           else "the car did not drive on past the sign")

    shown = lab.at_rest or lab.best or ((lab.frame, lab.det) if lab.frame is not None else None)
    result = Result("stop-sign", metrics, logs={"log.csv": _log_columns(cols)}, figures={})
    if shown is not None and shown[0] is not None:
        frame, det = shown
        result.data["detection"] = (frame, det)
        result.figures["detection.png"] = lambda f: save_figure(f, detection_figure(frame.color, det, frame.depth))
    if lab.kept:
        kept = lab.kept
        result.figures["frames"] = lambda folder: _write_frames(folder, kept)
    return result


def detection_figure(color: np.ndarray, det: StopSignDetection, depth: np.ndarray | None = None) -> Any:
    """``detection.png``: the sheet's Figure 49 (colour with the box | the mask | the depth), panel
    titles and a legend of the overlays (:func:`qcarlab.plots.camera_figure`). Returns the Figure."""
    from qcarlab import plots

    return plots.camera_figure(detection_panels(color, det, depth), DETECTION_OVERLAYS,
                               "stop sign: what the camera saw (sheet 5.2, Figure 49)")



def _write_frames(folder, kept: list[tuple[float, np.ndarray]]) -> None:
    """The kept frames (JPEG bytes) as ``folder/frame_NNNN_tSSS.SS.jpg``."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, (t, jpg) in enumerate(kept):
        (folder / f"frame_{i:04d}_t{t:06.2f}.jpg").write_bytes(jpg.tobytes())


def _log_columns(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    keep = ["t", "state", "sign_found", "sign_distance", "true_distance", "v_ref", "v_meas", "true_speed",
            "throttle", "steering", "true_x", "true_y", "true_yaw"]
    return {k: cols[k] for k in keep if k in cols}
