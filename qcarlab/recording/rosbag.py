"""Recordings from a real QCar's ROS 2 stack: a rosbag2 (sqlite3 or MCAP storage), via ``rosbags``.

    qcarlab lidar-scan --car replay:bags/drive1 --topics scan=/scan
    qcarlab stop-sign --car replay:bags/drive1 \\
        --topics color=/camera/color/image_raw,depth=/camera/depth/image_rect_raw,odom=/odom

``--topics`` maps the car's sensors to the bag's topics:

==========  =====================================================  ===============================
sensor      message types                                          becomes
==========  =====================================================  ===============================
scan        sensor_msgs/msg/LaserScan                              LIDAR scans (REP-103 angles;
                                                                   out-of-range / inf -> 0)
color       sensor_msgs/msg/Image (bgr8, rgb8, mono8), or          the RGBD colour image
            sensor_msgs/msg/CompressedImage (jpeg, png)
depth       sensor_msgs/msg/Image (16UC1 mm, 32FC1 m), or          the RGBD depth, float32 m, paired
            CompressedImage (png, ``compressedDepth``)             with the colour frame nearest it
csi_<view>  Image / CompressedImage (view: right, rear, left,      the CSI cameras
            front)
odom        nav_msgs/msg/Odometry                                  readouts: tach = v / 6.866e-6,
                                                                   gyro z = the yaw rate
imu         sensor_msgs/msg/Imu                                    readouts' gyro and accelerometer
==========  =====================================================  ===============================

Times are the bag's receive times, from its first message (t = 0). A bag has no ground truth and
no recorded commands, so a replay reports what the lab would command, with nothing to compare.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from qcarlab.car.base import Readout
from qcarlab.errors import InputError
from qcarlab.recording import require
from qcarlab.recording.reader import Tape, raw_color, raw_depth
from qcarlab.sensors import CSIFrames, LidarScan, RGBDFrame

SENSORS = ("scan", "color", "depth", "csi_right", "csi_rear", "csi_left", "csi_front", "odom", "imu")
PAIR_WINDOW = 0.02  # s: a depth image this close to a colour image is its pair
TYPES = {
    "scan": ("sensor_msgs/msg/LaserScan",),
    "odom": ("nav_msgs/msg/Odometry",),
    "imu": ("sensor_msgs/msg/Imu",),
}
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


def bag_folder(path: Path) -> Path:
    """The bag's folder (with metadata.yaml) for the folder itself or one of its storage files."""
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise InputError(f"rosbag2 {path}: no metadata.yaml in the folder")
        return path
    if (path.parent / "metadata.yaml").is_file():
        return path.parent
    raise InputError(f"rosbag2 {path}: give the bag's folder (the one with metadata.yaml)")


class RosBag:
    """A rosbag2 opened for reading, with the ``topics`` map from the car's sensors to its topics."""

    def __init__(self, path: str | Path, topics: dict[str, str] | None):
        require("reading a rosbag2", "rosbags")
        from rosbags.typesys import Stores, get_typestore

        self.path = bag_folder(Path(path))
        self.topics = dict(topics or {})
        self.typestore = get_typestore(Stores.ROS2_HUMBLE)
        with self._reader() as reader:
            self.start_ns = int(reader.start_time)
            self.end_ns = int(reader.end_time)
            self.types = {c.topic: c.msgtype for c in reader.connections}
            self.counts = {t: info.msgcount for t, info in reader.topics.items()}
        for sensor, topic in self.topics.items():
            if topic not in self.types:
                raise InputError(f"--topics {sensor}={topic}: the bag has no topic {topic} "
                                 f"(it has {', '.join(sorted(self.types)) or 'none'})")
            wanted = TYPES.get(sensor, IMAGE_TYPES)
            if self.types[topic] not in wanted:
                raise InputError(f"--topics {sensor}={topic}: {self.types[topic]} is not a {' or '.join(wanted)}")

    def _reader(self):
        from rosbags.rosbag2 import Reader

        try:
            reader = Reader(self.path)
            reader.open()
        except Exception as exc:  # rosbags' own errors: a broken or unknown bag
            raise InputError(f"rosbag2 {self.path}: cannot read ({exc})") from None
        return _Closing(reader)

    def _messages(self, sensors: list[str]) -> Iterator[tuple[str, float, Any]]:
        """(sensor, t, message) in time order for the mapped ``sensors``."""
        by_topic: dict[str, list[str]] = {}
        for s in sensors:
            if s in self.topics:
                by_topic.setdefault(self.topics[s], []).append(s)
        if not by_topic:
            return
        with self._reader() as reader:
            conns = [c for c in reader.connections if c.topic in by_topic]
            for conn, ns, raw in reader.messages(connections=conns):
                try:
                    msg = self.typestore.deserialize_cdr(raw, conn.msgtype)
                except Exception as exc:
                    raise InputError(f"rosbag2 {self.path}: a {conn.msgtype} on {conn.topic} does not decode "
                                     f"({exc})") from None
                for sensor in by_topic[conn.topic]:
                    yield sensor, (ns - self.start_ns) / 1e9, msg

    # --- qcarlab replay info --------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        duration = (self.end_ns - self.start_ns) / 1e9
        topics = {}
        for topic in sorted(self.types):
            n = self.counts.get(topic, 0)
            topics[topic] = {"schema": self.types[topic], "encoding": "cdr", "count": n, "first_s": None,
                             "last_s": None, "rate_hz": n / duration if duration > 0 and n > 1 else None}
        mapped = {topic: sensor for sensor, topic in self.topics.items()}
        for topic, entry in topics.items():
            entry["first_s"], entry["last_s"] = 0.0, duration
            if topic in mapped:
                entry["sensor"] = mapped[topic]
        return {"file": str(self.path), "format": "rosbag2", "bytes": None, "complete": True,
                "duration_s": duration, "messages": sum(self.counts.values()), "start_ns": self.start_ns,
                "profile": None, "world": None, "car": None, "command": None, "topics": topics}

    # --- the tape -------------------------------------------------------------------------------
    def tape(self) -> Tape:
        tape = Tape(source=str(self.path), metadata={"format": "rosbag2", "topics": self.topics},
                    span=(0.0, (self.end_ns - self.start_ns) / 1e9))
        p = tape.params
        last_gyro, last_accel = np.zeros(3), np.array([0.0, 0.0, p.gravity])
        for sensor, t, msg in self._messages(["scan", "odom", "imu"]):
            if sensor == "scan":
                tape.scans.append(laser_scan(t, msg))
            elif sensor == "imu":
                last_gyro = np.array([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z])
                last_accel = np.array([msg.linear_acceleration.x, msg.linear_acceleration.y,
                                       msg.linear_acceleration.z])
                if "odom" not in self.topics:
                    tape.readouts.append(_readout(t, 0.0, last_gyro, last_accel))
            else:
                v = float(msg.twist.twist.linear.x)
                gyro = last_gyro.copy() if "imu" in self.topics else np.array([0.0, 0.0, msg.twist.twist.angular.z])
                tape.readouts.append(_readout(t, v / p.speed_per_count, gyro, last_accel))
        if "color" in self.topics:
            tape.rgbd = self._rgbd
        views = [s for s in SENSORS if s.startswith("csi_") and s in self.topics]
        if views:
            if len(views) < 4:
                raise InputError(f"--topics: the CSI cameras need all four views (csi_right, csi_rear, csi_left, "
                                 f"csi_front); got {', '.join(views)}")
            tape.csi = self._csi
        tape.notes.append("a rosbag2 has no recorded commands: the replay shows what the lab would command")
        return tape

    def _rgbd(self) -> Iterator[tuple[float, Callable[[], RGBDFrame]]]:
        depth = None  # (t, message)
        pending = None
        for sensor, t, msg in self._messages(["color", "depth"]):
            if sensor == "depth":
                depth = (t, msg)
                if pending is not None and abs(t - pending[0]) <= PAIR_WINDOW:
                    yield _rgbd_item(pending, depth)
                    pending = None
                continue
            if pending is not None:
                yield _rgbd_item(pending, depth)
            pending = (t, msg)
            if "depth" not in self.topics or (depth is not None and abs(depth[0] - t) <= PAIR_WINDOW):
                yield _rgbd_item(pending, depth)
                pending = None
        if pending is not None:
            yield _rgbd_item(pending, depth)

    def _csi(self) -> Iterator[tuple[float, Callable[[], CSIFrames]]]:
        latest: dict[str, Any] = {}
        for sensor, t, msg in self._messages([s for s in SENSORS if s.startswith("csi_")]):
            latest[sensor[4:]] = msg
            if sensor == "csi_front" and len(latest) == 4:
                views = dict(latest)
                yield t, (lambda t=t, views=views: CSIFrames(t=t, **{k: ros_color(v) for k, v in views.items()}))


class _Closing:
    def __init__(self, reader):
        self.reader = reader

    def __enter__(self):
        return self.reader

    def __exit__(self, *exc):
        self.reader.close()


def _readout(t: float, tach: float, gyro: np.ndarray, accel: np.ndarray) -> Readout:
    return Readout(t=t, encoder_counts=0, tach=float(tach), motor_current=0.0, battery_voltage=0.0,
                   gyro=np.asarray(gyro, dtype=np.float64), accel=np.asarray(accel, dtype=np.float64))


def laser_scan(t: float, msg: Any) -> LidarScan:
    """sensor_msgs/LaserScan -> LidarScan: angle_min + i * angle_increment, and 0 for a range that is
    not finite or outside [range_min, range_max]."""
    r = np.asarray(msg.ranges, dtype=np.float64)
    angles = msg.angle_min + np.arange(r.size) * msg.angle_increment
    ok = np.isfinite(r) & (r >= msg.range_min) & (r <= msg.range_max) & (r > 0.0)
    return LidarScan(t=t, angles=angles.astype(np.float64), ranges=np.where(ok, r, 0.0))


def ros_color(msg: Any) -> np.ndarray:
    if hasattr(msg, "format"):  # CompressedImage
        img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise InputError(f"rosbag2: cannot decode a compressed colour image ({msg.format!r})")
        return img
    return raw_color(msg.encoding, msg.width, msg.height, msg.step, bytes(msg.data))


def ros_depth(msg: Any) -> np.ndarray:
    if hasattr(msg, "format"):  # CompressedImage: png, or image_transport's compressedDepth (12-byte header)
        data = bytes(msg.data)
        if "compresseddepth" in msg.format.lower().replace(" ", ""):
            data = data[12:]
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None or img.ndim != 2:
            raise InputError(f"rosbag2: cannot decode a compressed depth image ({msg.format!r})")
        return img.astype(np.float32) * (np.float32(1e-3) if img.dtype == np.uint16 else np.float32(1.0))
    return raw_depth(msg.encoding, msg.width, msg.height, msg.step, bytes(msg.data), bool(msg.is_bigendian))


def _rgbd_item(pending, depth):
    t, color_msg = pending

    def load() -> RGBDFrame:
        color = ros_color(color_msg)
        d = ros_depth(depth[1]) if depth is not None else np.zeros(color.shape[:2], np.float32)
        if d.shape != color.shape[:2]:  # not aligned to the colour image: resized to it
            d = cv2.resize(d, (color.shape[1], color.shape[0]), interpolation=cv2.INTER_NEAREST)
        return RGBDFrame(t=t, color=color, depth=d)

    return t, load


__all__ = ["RosBag", "SENSORS", "laser_scan"]
