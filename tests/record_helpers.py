"""Helpers for the recording tests: a small rosbag2 made with rosbags from the simulator's sensors."""

from __future__ import annotations

from pathlib import Path

import numpy as np

SCAN, COLOR, DEPTH, ODOM = "/scan", "/camera/color/image_raw", "/camera/depth/image_rect_raw", "/odom"
TOPICS = f"scan={SCAN},color={COLOR},depth={DEPTH},odom={ODOM}"


def make_bag(path: Path, world: str = "stop-sign", seconds: float = 5.0, storage: str = "sqlite3",
             throttle: float = 0.1) -> Path:
    """Drive the simulated car straight for ``seconds`` and write what a QCar's ROS 2 stack would
    publish: LaserScan at 10 Hz, colour (bgr8) and depth (16UC1 mm) Images at 30 Hz, Odometry at 50 Hz."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from qcarlab.car import open_car
    from qcarlab.control.speed import basic_speed_estimation

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    t0_ns = 1_700_000_000_000_000_000

    def header(t: float, frame: str):
        ns = t0_ns + int(round(t * 1e9))
        return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    def image(t: float, frame: str, arr: np.ndarray, encoding: str):
        h, w = arr.shape[:2]
        step = arr.strides[0]
        return T["sensor_msgs/msg/Image"](header=header(t, frame), height=h, width=w, encoding=encoding,
                                          is_bigendian=0, step=step, data=np.frombuffer(arr.tobytes(), np.uint8))

    with Writer(path, version=9, storage_plugin=plugin) as w:
        types = {SCAN: "sensor_msgs/msg/LaserScan", COLOR: "sensor_msgs/msg/Image",
                 DEPTH: "sensor_msgs/msg/Image", ODOM: "nav_msgs/msg/Odometry"}
        conns = {topic: w.add_connection(topic, msgtype, typestore=ts) for topic, msgtype in types.items()}

        def put(topic: str, t: float, msg) -> None:
            w.write(conns[topic], t0_ns + int(round(t * 1e9)), ts.serialize_cdr(msg, types[topic]))

        with open_car("sim", world=world, seed=0) as car:
            dt, k = 0.01, 0
            last = {"scan": None, "rgbd": None}
            while k * dt < seconds:
                t = k * dt
                car.write(throttle, 0.0)
                scan = car.read_lidar()
                if scan.t != last["scan"]:
                    last["scan"] = scan.t
                    a = scan.angles
                    r = np.where(scan.ranges > 0, scan.ranges, np.inf).astype(np.float32)
                    put(SCAN, t, T["sensor_msgs/msg/LaserScan"](
                        header=header(t, "laser"), angle_min=float(a[0]), angle_max=float(a[-1]),
                        angle_increment=float((a[-1] - a[0]) / (len(a) - 1)), time_increment=0.0, scan_time=0.1,
                        range_min=0.15, range_max=12.0, ranges=r, intensities=np.zeros(0, np.float32)))
                frame = car.read_rgbd()
                if frame.t != last["rgbd"]:
                    last["rgbd"] = frame.t
                    put(COLOR, t, image(t, "camera", frame.color, "bgr8"))
                    mm = np.round(frame.depth * 1000).astype("<u2")
                    put(DEPTH, t + 0.001, image(t + 0.001, "camera", mm, "16UC1"))
                if k % 2 == 0:
                    v = basic_speed_estimation(car.read().tach, car.params)
                    odom = T["nav_msgs/msg/Odometry"](
                        header=header(t, "odom"), child_frame_id="base_link",
                        pose=T["geometry_msgs/msg/PoseWithCovariance"](
                            pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                                             orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
                            covariance=np.zeros(36)),
                        twist=T["geometry_msgs/msg/TwistWithCovariance"](
                            twist=T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=v, y=0.0, z=0.0),
                                                               angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                            covariance=np.zeros(36)))
                    put(ODOM, t, odom)
                car.advance(dt)
                k += 1
    return path
