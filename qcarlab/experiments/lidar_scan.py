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


TARGET_DEPTH, TARGET_WIDTH = 0.3, 0.6  # m: the carton box, along and across the line of sight
MAX_TARGET_M = 20.0  # beyond the model's 18 m range (the sheet's table says 12 m): "no return" is a lesson too


def room_ahead(world, pose: tuple[float, float, float], target: float, params) -> float:
    """Free floor (m) straight ahead of the LIDAR at car ``pose``, over the width the box at
    ``target`` m would cover: the first solid the LIDAR sees there (inf: nothing within its range)."""
    from qcarlab.sim.lidar import Lidar

    half = math.atan2(TARGET_WIDTH / 2.0, target)
    ranges = Lidar(world, params, beams=9, fov=2.0 * half).true_ranges(pose)
    return float(np.min(ranges)) if ranges.size else math.inf


def open_hall(target: float, params):
    """A bare floor with room for the box ``target`` m ahead and nothing else for the LIDAR to
    see: the car at (0, 0) heading -Y, as in the studio."""
    from qcarlab.sim.world import world_from_dict

    length = target + 3.0
    return world_from_dict({"name": "open-hall", "description": f"a bare {length:g} m floor for lidar-scan --target",
                            "floor": {"size": [4.0, length], "origin": [-2.0, -(length - 1.5)], "color": "concrete"},
                            "start": [0.0, 0.0, -math.pi / 2.0]}, "open-hall", "lidar-scan --target", params)


def target_world(world, pose: tuple[float, float, float] | None, target: float, params, chosen: bool):
    """The world with the sheet's carton box ``target`` m in front of the LIDAR, and a note when it
    is not ``world``: a world (or ``--start``) the user ``chosen`` without room for the box is
    refused in one line; the default one without room gives way to :func:`open_hall` (the box
    was placed behind the studio's wall, and the wall was measured)."""
    from qcarlab.errors import InputError

    if not (math.isfinite(target) and 0.0 < target <= MAX_TARGET_M):
        raise InputError(f"--target must be a distance in (0, {MAX_TARGET_M:g}] m, got {target}")
    at = pose or world.start
    need = target + TARGET_DEPTH
    room = room_ahead(world, at, target, params)
    note = None
    if room < need:
        if chosen:
            raise InputError(f"--target {target:g}: the world '{world.name}' has {room:.2f} m of room ahead of the "
                             f"LIDAR, the box needs {need:.2f} m; give a shorter --target, another --start or --world, "
                             "or leave --world and --start out for an open hall")
        note = (f"the box {target:g} m ahead does not fit in the world '{world.name}' ({room:.2f} m of room ahead); "
                "scanning in an open hall instead")
        world, at = open_hall(target, params), None
    place_target(world, at or world.start, target, params)
    return world, at, note


def place_target(world, pose: tuple[float, float, float], target: float, params) -> None:
    """Put a 0.3 m deep, 0.6 m wide box ``target`` m in front of the LIDAR at ``pose`` (the sheet's
    carton box, for the range check of ``lidar-scan --target``)."""
    x, y, yaw = pose
    d = params.lidar_x + target + TARGET_DEPTH / 2.0
    world.add_box(x + d * math.cos(yaw), y + d * math.sin(yaw), TARGET_DEPTH, TARGET_WIDTH, yaw)


def capture(car: Car, scans: int = 1, drive: bool = False, target: float | None = None,
            on_scan=None) -> Result:
    """Take ``scans`` LIDAR turns; return the summary, the last scan and the world point cloud."""
    rate = car.params.lidar_rate
    tick = 0.01
    clouds, poses = [], []
    ahead = []  # with a target: the range straight ahead in each scan (its precision over the scans)
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
        if target is not None and (r := range_ahead(scan)) is not None:
            ahead.append(r)
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
                             "error_m": None if measured is None else measured - target,
                             "scans_with_return": len(ahead), "mean_m": float(np.mean(ahead)) if ahead else None,
                             "std_m": float(np.std(ahead)) if ahead else None}
    return Result("lidar-scan", metrics, logs={"scan.csv": {"angle_rad": scan.angles, "range_m": scan.ranges}},
                  data={"scan": scan, "cloud": np.vstack(clouds) if clouds else np.zeros((0, 2)), "poses": poses})
