"""Explore the LIDAR (lab sheet 3.5): capture scans, find the nearest obstacle, check the range.

``capture`` takes ``scans`` turns of the LIDAR (the car still, or driving a slow circle) and
returns the last scan, the points of every scan in the world frame (the sheet's point-cloud map,
Figure 25) and the nearest obstacle. With a target placed ``D`` m ahead, the measured range
straight ahead (the median of the beams within +-2 deg) is compared with the true distance: the
sheet's range and precision task.
"""

from __future__ import annotations

import math

import numpy as np

from qcarlab.car.base import Car
from qcarlab.experiments.result import Result
from qcarlab.sensors import LidarScan

DRIVE_COMMAND = (0.08, 0.3)  # throttle, steering of --drive's slow circle


def nearest_obstacle(scan: LidarScan) -> tuple[float, float] | None:
    """(distance m, bearing rad) of the closest return, or None if the scan saw nothing."""
    ok = scan.valid
    if not ok.any():
        return None
    i = int(np.argmin(np.where(ok, scan.ranges, np.inf)))
    return float(scan.ranges[i]), float(math.remainder(scan.angles[i], 2.0 * math.pi))


def sector_minima(scan: LidarScan, sectors: int = 8) -> list[float | None]:
    """Nearest return in each of ``sectors`` equal sectors, the first centred straight ahead."""
    width = 2.0 * math.pi / sectors
    idx = np.floor(((scan.angles + width / 2.0) % (2.0 * math.pi)) / width).astype(int) % sectors
    out: list[float | None] = []
    for k in range(sectors):
        r = scan.ranges[(idx == k) & scan.valid]
        out.append(float(r.min()) if r.size else None)
    return out


def range_ahead(scan: LidarScan, half_width: float = math.radians(2.0)) -> float | None:
    """Median range of the returns within +-``half_width`` of straight ahead."""
    bearing = np.abs(np.remainder(scan.angles + math.pi, 2.0 * math.pi) - math.pi)
    sel = (bearing <= half_width) & scan.valid
    return float(np.median(scan.ranges[sel])) if sel.any() else None


def to_world(scan: LidarScan, sensor_pose: tuple[float, float, float]) -> np.ndarray:
    """The scan's returns as (m, 2) world-frame points, given the LIDAR's world pose."""
    pts = scan.points()
    x, y, yaw = sensor_pose
    c, s = math.cos(yaw), math.sin(yaw)
    return np.column_stack((x + c * pts[:, 0] - s * pts[:, 1], y + s * pts[:, 0] + c * pts[:, 1]))


def lidar_world_pose(car: Car, t: float) -> tuple[float, float, float] | None:
    """The LIDAR's world pose from the car's ground truth (simulators, local or served), or None."""
    truth = car.truth()
    if truth is None:
        return None
    x, y, yaw = (truth.x, truth.y, truth.yaw)
    if hasattr(car, "pose_at"):  # the local simulator knows the pose at the scan's own time
        x, y, yaw = car.pose_at(t)
    lx = car.params.lidar_x
    return (x + lx * math.cos(yaw), y + lx * math.sin(yaw), yaw)


def place_target(world, pose: tuple[float, float, float], target: float, params) -> None:
    """Put a 0.3 m deep, 0.6 m wide box ``target`` m in front of the LIDAR at ``pose`` (the sheet's
    carton box, for the range check of ``lidar-scan --target``)."""
    x, y, yaw = pose
    depth = 0.3  # the box's size along the line of sight
    d = params.lidar_x + target + depth / 2.0
    world.add_box(x + d * math.cos(yaw), y + d * math.sin(yaw), depth, 0.6, yaw)


def capture(car: Car, scans: int = 1, drive: bool = False, target: float | None = None,
            on_scan=None) -> Result:
    """Take ``scans`` LIDAR turns; return the summary, the last scan and the world point cloud."""
    rate = car.params.lidar_rate
    tick = 0.01
    clouds, poses = [], []
    scan = None
    for k in range(scans):
        if k > 0 or drive:
            for _ in range(round(1.0 / (rate * tick))):
                if drive:
                    car.write(*DRIVE_COMMAND)
                car.advance(tick)
        scan = car.read_lidar()
        pose = lidar_world_pose(car, scan.t)
        if pose is not None:
            clouds.append(to_world(scan, pose))
            poses.append(pose)
        if on_scan is not None:
            on_scan(k, scan)
    car.stop()
    near = nearest_obstacle(scan)
    valid = scan.ranges[scan.valid]
    metrics = {
        "experiment": "lidar-scan",
        "scans": scans,
        "beams": int(scan.angles.size),
        "rate_hz": rate,
        "t": scan.t,
        "points_with_return": int(valid.size),
        "nearest_obstacle_m": near[0] if near else None,
        "nearest_bearing_rad": near[1] if near else None,
        "range_min_m": float(valid.min()) if valid.size else None,
        "range_max_m": float(valid.max()) if valid.size else None,
        "sensor_pose": list(poses[-1]) if poses else None,
        "angles_rad": scan.angles,
        "ranges_m": scan.ranges,
    }
    if target is not None:
        measured = range_ahead(scan)
        metrics["target"] = {"true_m": target, "measured_m": measured,
                             "error_m": None if measured is None else measured - target}
    return Result("lidar-scan", metrics, logs={"scan.csv": {"angle_rad": scan.angles, "range_m": scan.ranges}},
                  data={"scan": scan, "cloud": np.vstack(clouds) if clouds else np.zeros((0, 2)), "poses": poses})
