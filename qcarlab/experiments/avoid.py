"""LIDAR obstacle detection and avoidance (lab sheet section 6.1) on any car.

Each tick (``rate``, 100 Hz by default)::

    v      = basic_speed_estimation(tach)                      # encoder -> m/s
    scan   = car.read_lidar()                                  # a new turn every 0.1 s (10 Hz)
    on a new scan:
        stop:     v_ref = lidar_stop(scan, speed, stop_distance), delta = 0      (Task 1-2)
        steer:    v_ref = speed, delta = lidar_steer(scan)                      (Task 3)
        combined: v_ref, delta = LidarAvoid.step(scan, speed)                   (Task 4)
    u      = speed_controller(v_ref, v)                        # feed-forward PI -> throttle

The PI controller is disarmed (integrator reset, throttle 0) while ``v_ref = 0`` and the car is at
rest, so a stopped car does not creep on the integrator's charge.

Collisions. The simulator does not model contact, so the run checks it itself, every tick, from
the true pose: the exact distance between the car's footprint (a ``length`` x ``width`` =
0.425 x 0.192 m rectangle about its centre) and every solid of the world that reaches below the
car's roof (walls, boxes, posts, sign plates: :meth:`World.static_solids`) and every ball at that
instant (:meth:`World.obstacles_at`, as a circle of the ball's radius: the body is as high as the
ball's equator). Polygons are compared edge by edge (a separating-axis test for crossing, else the
nearest vertex-edge distance, which is exact for disjoint convex pieces), circles by the distance
from their centre to the rectangle. ``min_clearance_m`` is the smallest distance over the run; a
distance of 0 is a collision, which ends the run (the car is stopped). Only a simulated car in a
local world is checked (``collisions`` is null otherwise).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from qcarlab.car.base import Car, Command, Readout
from qcarlab.car.lamps import parse_lamps
from qcarlab.constants import QCarParams
from qcarlab.control.lidar_avoid import LidarAvoid, forward_range, lidar_steer, lidar_stop
from qcarlab.control.speed import KFF, KI, KP, SpeedController, basic_speed_estimation
from qcarlab.errors import InputError
from qcarlab.experiments.lidar_scan import lidar_world_pose
from qcarlab.experiments.loop import STOP, check_rate, run_loop
from qcarlab.experiments.result import Result
from qcarlab.experiments.safety import Clearance

STRATEGIES = ("stop", "steer", "combined")
REST_SPEED = 0.01  # m/s: below this the car counts as at rest


@dataclass
class AvoidConfig:
    """Everything that shapes a run; the defaults are the lab's."""

    strategy: str = "combined"
    speed: float = 0.3  # m/s desired
    stop_distance: float = 0.4  # m from the LIDAR (over the car's centre)
    half_width: float = 0.15  # m, the stop window's half width (car half width 0.096 + 5 cm)
    duration: float = 20.0  # s
    rate: float = 100.0  # Hz
    kp: float = KP
    ki: float = KI
    kff: float = KFF

    def check(self, params: QCarParams) -> None:
        if self.strategy not in STRATEGIES:
            raise InputError(f"--strategy must be one of {', '.join(STRATEGIES)}, got {self.strategy!r}")
        if not (math.isfinite(self.speed) and 0.0 < self.speed <= 3.0):
            raise InputError(f"--speed must be in (0, 3] m/s, got {self.speed}")
        front = params.length / 2.0 + params.lidar_x
        if not (math.isfinite(self.stop_distance) and front < self.stop_distance <= params.lidar_max_range):
            raise InputError(f"--stop-distance must be in ({front:g}, {params.lidar_max_range:g}] m (measured from "
                             f"the LIDAR, {front:g} m behind the front bumper), got {self.stop_distance}")
        if not (math.isfinite(self.half_width) and 0.0 < self.half_width <= 2.0):
            raise InputError(f"--half-width must be in (0, 2] m, got {self.half_width}")
        if not (math.isfinite(self.duration) and 0.0 < self.duration <= 3600.0):
            raise InputError(f"--duration must be in (0, 3600] s, got {self.duration}")
        check_rate(self.rate)


# --------------------------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------------------------
_LAMPS: dict[str, tuple[float, ...]] = {}


def _lamps(names: str) -> tuple[float, ...]:
    if names not in _LAMPS:
        _LAMPS[names] = parse_lamps(names)
    return _LAMPS[names]


def avoid(car: Car, cfg: AvoidConfig, world: Any = None, on_tick=None) -> Result:
    """Drive ``car`` with the LIDAR strategy ``cfg.strategy``; return metrics, the log, the scans.

    ``world`` (the simulator's, when local) enables the collision check and the drive figure.
    """
    p = car.params
    cfg.check(p)
    truth0 = car.truth()
    checker = Clearance(world, p) if (world is not None and truth0 is not None) else None
    pi = SpeedController(cfg.kp, cfg.ki, cfg.kff, throttle_limit=car.throttle_limit)
    avoider = LidarAvoid(stop_distance=cfg.stop_distance, params=p) if cfg.strategy == "combined" else None
    dt = 1.0 / cfg.rate
    rec: dict[str, list] = {k: [] for k in ("v_ref", "v_meas", "front_range", "clearance", "state")}
    scans: list[tuple[np.ndarray, tuple[float, float, float] | None]] = []
    st: dict[str, Any] = {"scan_t": None, "v_ref": 0.0, "delta": 0.0, "front": math.inf, "state": "",
                          "min_clear": math.inf, "collision": None, "rest": None, "n_scans": 0,
                          "dist": 0.0, "d0": truth0.distance if truth0 is not None else 0.0,
                          "max_from_start": 0.0}

    def step(t: float, r: Readout) -> Command | object:
        v = basic_speed_estimation(r.tach, p)
        clear = math.nan
        if checker is not None:
            tr = car.truth()
            clear, where = checker(tr.x, tr.y, tr.yaw, tr.t)
            st["min_clear"] = min(st["min_clear"], clear)
            st["max_from_start"] = max(st["max_from_start"], math.hypot(tr.x - truth0.x, tr.y - truth0.y))
            if clear <= 0.0:
                st["collision"] = {"t": t, "x": tr.x, "y": tr.y, "yaw": tr.yaw,
                                   "obstacle": list(where) if where else None, "speed_mps": v}
                return STOP
        st["dist"] += abs(v) * dt
        scan = car.read_lidar()
        if scan is not None and scan.t != st["scan_t"]:
            st["scan_t"] = scan.t
            st["n_scans"] += 1
            st["front"] = forward_range(scan.ranges, scan.angles, cfg.half_width)
            if cfg.strategy == "stop":
                st["v_ref"], st["delta"] = lidar_stop(scan.ranges, scan.angles, cfg.speed, cfg.stop_distance,
                                                      cfg.half_width), 0.0
                st["state"] = "go" if st["v_ref"] > 0 else "stop"
            elif cfg.strategy == "steer":
                st["v_ref"], st["delta"] = cfg.speed, lidar_steer(scan.ranges, scan.angles)
                st["state"] = "steer"
            else:
                st["v_ref"], st["delta"] = avoider.step(scan, cfg.speed)
                st["state"] = avoider.state
            pose = lidar_world_pose(car, scan.t) if truth0 is not None else None
            scans.append((scan.points(), pose))
        v_ref, delta = st["v_ref"], st["delta"]
        at_rest = abs(v) < REST_SPEED
        if v_ref == 0.0 and at_rest and st["rest"] is None and math.isfinite(st["front"]):
            st["rest"] = {"t": t, "range_m": st["front"], "gap_m": clear if math.isfinite(clear) else None}
        throttle = pi(v_ref, v, dt)  # speed_controller holds a car at rest with throttle 0
        lamps = "brake" if v_ref == 0.0 else ("reverse" if v_ref < 0 else "")
        if delta > 0.2:
            lamps += ",left-indicators"
        elif delta < -0.2:
            lamps += ",right-indicators"
        for key, value in (("v_ref", v_ref), ("v_meas", v), ("front_range", st["front"]), ("clearance", clear),
                           ("state", st["state"])):
            rec[key].append(value)
        return Command(throttle, delta, _lamps(lamps.strip(",")))

    if avoider is not None:
        avoider.reset()
    log = run_loop(car, step, cfg.duration, cfg.rate, on_tick=on_tick)
    cols: dict[str, np.ndarray] = log.arrays()
    n = log.ticks
    for key in rec:
        cols[key] = np.asarray(rec[key][:n])
    truth1 = car.truth()
    duration = n * dt
    if truth1 is not None:
        distance = truth1.distance - st["d0"]
    else:
        distance = st["dist"]
    rest = st["rest"]
    states = {}
    if n and cfg.strategy == "combined":
        names, counts = np.unique(cols["state"], return_counts=True)
        states = {str(k): float(c) * dt for k, c in zip(names, counts)}
    metrics = {
        "experiment": "avoid",
        "strategy": cfg.strategy,
        "collisions": None if checker is None else (1 if st["collision"] else 0),
        "collision": st["collision"],
        "min_clearance_m": None if checker is None else float(st["min_clear"]),
        "distance_m": float(distance),
        "max_distance_from_start_m": float(st["max_from_start"]) if checker is not None else None,
        "duration_s": float(duration),
        "mean_speed_mps": float(distance / duration) if duration > 0 else 0.0,
        "stopped_before_obstacle": rest["range_m"] if rest else None,
        "stop_gap_m": rest["gap_m"] if rest else None,
        "stopped_at_s": rest["t"] if rest else None,
        "scans": st["n_scans"],
    }
    if avoider is not None:
        metrics["backups"] = avoider.backups
        metrics["time_in_state_s"] = states
    metrics["config"] = asdict(cfg)
    keep = ["t", "true_x", "true_y", "true_yaw", "true_speed", "throttle", "steering", "v_ref", "v_meas",
            "front_range", "clearance", "state"]
    log_cols = {k: cols[k] for k in keep if k in cols}
    return Result("avoid", metrics, logs={"log.csv": log_cols}, data={"scans": scans, "log": cols})


def draw_drive(world: Any, result: Result, px_per_m: float = 80.0, every: int = 2) -> np.ndarray:
    """The top-down world with the driven path (red), the LIDAR returns of every ``every``-th scan
    in the world frame (blue dots; the last scan in orange), the car at the start (green) and at the end
    and, after a collision, a red cross where the car was. BGR image."""
    import cv2

    from qcarlab.sim.render import render_topdown, world_to_pixel

    log = result.data["log"]
    poses = np.column_stack((log["true_x"], log["true_y"], log["true_yaw"])) if "true_x" in log else None
    t_end = float(log["t"][-1]) if len(log.get("t", [])) else 0.0
    img = render_topdown(world, px_per_m, poses=poses, t=t_end, show_start=poses is None)
    if poses is not None and len(poses):  # the start of this run (which --start may have moved)
        x, y, yaw = poses[0]
        c, s = math.cos(yaw), math.sin(yaw)
        hl, hw = world.params.length / 2.0, world.params.width / 2.0
        box = [(x + c * u - s * v, y + s * u + c * v) for u, v in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw))]
        tip = [(x, y), (x + 0.35 * c, y + 0.35 * s)]
        green = (60, 170, 40)
        cv2.polylines(img, [np.round(world_to_pixel(world, box, px_per_m)).astype(np.int32)], True, green, 2,
                      cv2.LINE_AA)
        a, b = np.round(world_to_pixel(world, tip, px_per_m)).astype(int)
        cv2.arrowedLine(img, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), green, 2, cv2.LINE_AA, 0, 0.25)
    scans = [(pts, pose) for pts, pose in result.data["scans"] if pose is not None and len(pts)]
    for i, (pts, pose) in enumerate(scans):
        last = i == len(scans) - 1
        if not last and i % every:
            continue
        px = np.round(world_to_pixel(world, to_world_pts(pts, pose), px_per_m)).astype(int)
        color = (0, 140, 255) if last else (200, 120, 30)
        h, w = img.shape[:2]
        ok = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        for cx, cy in px[ok]:
            cv2.circle(img, (int(cx), int(cy)), 2 if last else 1, color, -1, cv2.LINE_AA)
    m = result.metrics
    hit = m.get("collision")
    if hit:
        c = np.round(world_to_pixel(world, [(hit["x"], hit["y"])], px_per_m)[0]).astype(int)
        cv2.drawMarker(img, (int(c[0]), int(c[1])), (0, 0, 255), cv2.MARKER_TILTED_CROSS, 24, 3, cv2.LINE_AA)
    text = (f"{m['strategy']}: {m['duration_s']:.1f} s, {m['distance_m']:.2f} m, "
            f"collisions {m['collisions']}, min clearance "
            + ("n/a" if m["min_clearance_m"] is None else f"{m['min_clearance_m'] * 100:.1f} cm"))
    band = np.full((30, img.shape[1], 3), 255, np.uint8)  # a title band above the map
    cv2.putText(band, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack((band, img))


def to_world_pts(pts: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
    """Body-frame LIDAR points (already dropped of no-returns) to the world, given the LIDAR's pose."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return np.column_stack((x + c * pts[:, 0] - s * pts[:, 1], y + s * pts[:, 0] + c * pts[:, 1]))
