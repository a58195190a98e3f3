"""Stop at a stop sign (lab sheet 5.1-5.2): the *Stop.slx* model on any car.

Each tick (``rate``, 100 Hz by default)::

    v     = basic_speed_estimation(tach)                      # encoder -> m/s
    det   = detect_stop_sign(color, depth)                    # on each new RGBD frame (30 Hz)
    v_ref = stop_sign(det.distance, v_desired)                # the sheet's block (behaviour "sheet")
          | StopSignBehaviour.step(t, v, det.distance)        # slow, stop, hold, go ("hold")
    u     = speed_controller(v_ref, v)                        # feed-forward PI -> throttle
    steering = 0                                              # the road is straight

Between frames the last frame's distance is held (as Simulink's zero-order hold does). Once the
car is at rest with v_ref = 0 the speed controller is disarmed (throttle 0, integrator reset): with
the PI alone the integral wound up while braking backs the car away from the sign at ~3 cm/s.

The run ends: in the sheet mode when the car has stood still for ``settle`` seconds after
stopping for the sign (the sheet's car would wait there for ever); in the hold mode when the
car has driven ``pass_margin`` m past the sign after its stop; otherwise at ``max_time``.

Scoring (simulator only) uses the true pose and the world's sign: ``stop_distance_m`` is the
distance **from the car's front bumper** (centre + length / 2 along the heading) to the sign's
plate, measured along the heading, when the car came to rest. The camera is 2.25 cm behind the
bumper (``rgbd_x`` = 0.19 m), so the camera's own reading (``measured_distance_m``, the D435's
z-depth) is that much larger.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from qcarlab.car.base import Car, Command, Readout
from qcarlab.car.lamps import ALL_OFF, parse_lamps
from qcarlab.control.speed import SpeedController, basic_speed_estimation
from qcarlab.control.stop_sign import (
    FAR,
    NEAR,
    STANDSTILL,
    StopSignBehaviour,
    stop_sign,
)
from qcarlab.errors import InputError
from qcarlab.experiments.loop import STOP, check_rate, run_loop
from qcarlab.experiments.result import Result
from qcarlab.perception.stop_sign import (
    MIN_AREA,
    RED_HSV_MAX,
    RED_HSV_MIN,
    StopSignDetection,
    check_hsv,
    detect_stop_sign,
    detection_image,
)

BEHAVIOURS = ("sheet", "hold")
_BRAKE = parse_lamps(["brake"])
FRAME_EVERY = 3  # --frames keeps every 3rd camera frame (10 per second)


@dataclass
class StopSignConfig:
    """Everything that shapes a run."""

    speed: float = 0.3  # m/s desired
    behaviour: str = "sheet"
    hold: float = 3.0  # s, hold mode
    hsv_min: tuple[int, int, int] = RED_HSV_MIN
    hsv_max: tuple[int, int, int] = RED_HSV_MAX
    min_area: int = MIN_AREA  # px
    kp: float = 0.3
    ki: float = 1.0
    kff: float = 0.1
    rate: float = 100.0  # Hz
    max_time: float | None = None  # s; default from the speed
    settle: float = 1.0  # s standing still that ends a sheet-mode run
    pass_margin: float = 0.3  # m past the sign that ends a hold-mode run
    frames: bool = False  # keep annotated camera frames for --out DIR/frames/

    def check(self) -> None:
        if self.behaviour not in BEHAVIOURS:
            raise InputError(f"--behaviour must be one of {', '.join(BEHAVIOURS)}, got {self.behaviour!r}")
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


def run_stop_sign(car: Car, cfg: StopSignConfig, sign=None) -> Result:
    """Drive straight at ``cfg.speed`` and stop for the stop sign; return metrics, log, figures.

    ``sign`` is the world's :class:`~qcarlab.sim.world.Sign` the car drives towards (for the true
    stop distance); without it (a real car) the true-distance metrics are None.
    """
    cfg.check()
    p = car.params
    dt = 1.0 / cfg.rate
    frame_dt = 1.0 / p.rgbd_rate
    pi = SpeedController(cfg.kp, cfg.ki, cfg.kff, throttle_limit=car.throttle_limit)
    beh = StopSignBehaviour(cfg.speed, hold=cfg.hold) if cfg.behaviour == "hold" else None
    truth0 = car.truth()
    plate = sign.plate_center[:2] if (sign is not None and truth0 is not None) else None
    half = p.length / 2.0
    start_distance = bumper_distance((truth0.x, truth0.y, truth0.yaw), plate, half) if plate is not None else None
    max_time = cfg.max_time or (2.0 * (start_distance or 3.0) / cfg.speed + (cfg.hold if beh else 0.0) + 8.0)

    rec: dict[str, list] = {k: [] for k in ("v_ref", "v_meas", "sign_found", "sign_distance", "true_distance", "state")}
    st = {
        "next_frame": 0.0, "det": StopSignDetection(False), "frame": None, "frames": 0, "detections": 0,
        "first_detection": None, "decision_t": None, "rest_t": None, "rest": None, "rest_frame": None,
        "go_t": None, "passed": False, "pass_t": None, "min_distance": math.inf, "best_frame": None,
        "kept": [],
    }

    def true_distance() -> float | None:
        if plate is None:
            return None
        tr = car.truth()
        return bumper_distance((tr.x, tr.y, tr.yaw), plate, half)

    def step(t: float, r: Readout) -> Command | object:
        v = basic_speed_estimation(r.tach, p)
        new = None
        if t + 1e-9 >= st["next_frame"]:  # a new camera frame is due
            frame = car.read_rgbd()
            st["next_frame"] = (math.floor((t + 1e-9) / frame_dt) + 1) * frame_dt
            det = detect_stop_sign(frame.color, frame.depth, cfg.hsv_min, cfg.hsv_max, cfg.min_area)
            st["det"], st["frame"] = det, frame
            st["frames"] += 1
            new = det.distance if det.found else 0.0
            if det.found:
                st["detections"] += 1
                if st["first_detection"] is None:
                    st["first_detection"] = (t, det.distance, true_distance())
                if st["best_frame"] is None or det.area >= st["best_frame"][1].area:
                    st["best_frame"] = (frame, det)
            if cfg.frames and st["frames"] % FRAME_EVERY == 1:
                st["kept"].append((t, cv2.imencode(".jpg", detection_image(frame.color, det))[1]))
        det: StopSignDetection = st["det"]
        d_meas = det.distance if det.found else 0.0
        if beh is None:
            v_ref = stop_sign(d_meas, cfg.speed, NEAR, FAR)
            state = "stop" if v_ref == 0.0 else "go"
        else:
            v_ref = beh.step(t, v, new)
            state = beh.state
        if v_ref == 0.0 and st["decision_t"] is None:
            st["decision_t"] = t
        d_true = true_distance()
        if d_true is not None:
            st["min_distance"] = min(st["min_distance"], d_true)
        # the first standstill after deciding to stop
        if st["decision_t"] is not None and st["rest_t"] is None and abs(v) < STANDSTILL and v_ref == 0.0:
            st["rest_t"] = t
            st["rest"] = (d_true, d_meas, t)
            st["rest_frame"] = (st["frame"], det)
        if st["rest_t"] is not None and st["go_t"] is None and v_ref > 0.0:
            st["go_t"] = t
        if d_true is not None and not st["passed"] and d_true < -(p.length + sign.post_radius * 2):
            st["passed"], st["pass_t"] = True, t  # the rear bumper is past the sign
        # at rest for a stop, speed_controller gives throttle 0 and resets its integrator, so the
        # integral the braking wound up does not creep the car backwards while it waits
        throttle = pi(v_ref, v, dt)
        for key, value in (("v_ref", v_ref), ("v_meas", v), ("sign_found", int(det.found)),
                           ("sign_distance", d_meas), ("true_distance", math.nan if d_true is None else d_true),
                           ("state", state)):
            rec[key].append(value)
        # end of the run
        if beh is None:
            if st["rest_t"] is not None and v_ref == 0.0 and t - st["rest_t"] >= cfg.settle:
                return STOP
            if st["passed"] and d_true is not None and d_true < -(p.length + cfg.pass_margin):
                return STOP
        elif st["go_t"] is not None:
            if d_true is not None:
                if d_true < -(p.length + cfg.pass_margin):
                    return STOP
            elif t - st["go_t"] >= 3.0:  # no truth: drive on for 3 s
                return STOP
        return Command(throttle, 0.0, _BRAKE if v_ref == 0.0 else ALL_OFF)

    log = run_loop(car, step, max_time, cfg.rate)
    cols = {k: np.asarray(v) for k, v in log.arrays().items()}
    n = log.ticks
    for key in rec:
        cols[key] = np.asarray(rec[key][:n])

    rest = st["rest"]
    first = st["first_detection"]
    stopped = rest is not None and (rest[0] is None or rest[0] > 0.0)  # came to rest before the sign
    metrics = {
        "experiment": "stop-sign",
        "behaviour": cfg.behaviour,
        "speed_mps": cfg.speed,
        "stopped": bool(stopped),
        "stop_distance_m": rest[0] if rest is not None else None,
        "measured_distance_m": rest[1] if rest is not None and rest[1] > 0 else None,
        "time_to_stop_s": rest[2] if rest is not None else None,
        "braking_time_s": (rest[2] - st["decision_t"]) if rest is not None else None,
        "detected_at_m": first[1] if first is not None else None,
        "detected_at_true_m": first[2] if first is not None else None,
        "detected_at_s": first[0] if first is not None else None,
        "start_distance_m": start_distance,
        "min_distance_m": st["min_distance"] if plate is not None else None,
        "frames": st["frames"],
        "frames_with_sign": st["detections"],
        "duration_s": float(cols["t"][-1] + dt) if n else 0.0,
        "distance_reference": "front bumper to the sign plate, along the heading (true pose)",
    }
    if beh is not None:
        metrics["hold_s"] = (st["go_t"] - st["rest_t"]) if st["go_t"] is not None else None
        metrics["passed_sign"] = bool(st["passed"]) if plate is not None else (st["go_t"] is not None)
        metrics["stops"] = beh.stops
    metrics["config"] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()}

    shown = st["rest_frame"] or st["best_frame"] or ((st["frame"], st["det"]) if st["frame"] is not None else None)
    result = Result("stop-sign", metrics, logs={"log.csv": _log_columns(cols)}, figures={})
    if shown is not None:
        frame, det = shown
        result.data["detection"] = (frame, det)
        result.figures["detection.png"] = lambda f: _imwrite(f, detection_image(frame.color, det, frame.depth))
    if st["kept"]:
        kept = st["kept"]
        result.figures["frames"] = lambda folder: _write_frames(folder, kept)
    return result


def _imwrite(file, image: np.ndarray) -> None:
    if not cv2.imwrite(str(file), image):
        raise InputError(f"cannot write {file}")


def _write_frames(folder, kept: list[tuple[float, np.ndarray]]) -> None:
    """The kept frames (JPEG bytes) as ``folder/frame_NNNN_tSSS.SS.jpg``."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, (t, jpg) in enumerate(kept):
        (folder / f"frame_{i:04d}_t{t:06.2f}.jpg").write_bytes(jpg.tobytes())


def _log_columns(cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    keep = ["t", "state", "sign_found", "sign_distance", "true_distance", "v_ref", "v_meas", "true_speed",
            "throttle", "steering", "true_x", "true_y", "true_yaw"]
    return {k: cols[k] for k in keep if k in cols}
