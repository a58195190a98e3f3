"""qcarlab's sensor data as Foxglove's well-known messages (foxglove-sdk), one function per kind.

Pure conversions: numbers in, ``foxglove.messages`` objects out; no files, no channels.

The messages a recording writes many times a second (``pb_*``: the poses, the transforms and the
LIDAR scans) are written straight to their protobuf bytes in the same Foxglove schemas
(``foxglove.PoseInFrame``, ``foxglove.FrameTransforms``, ``foxglove.LaserScan``, the SDK's own
descriptors): building the SDK's objects field by field cost more than everything else a tick
records. Protobuf's wire format for these is fixed: a tag byte ``(field << 3) | wire type`` before
each field, doubles as 8 little-endian bytes (type 1), nested messages, strings and packed
repeated doubles as a length-prefixed run (type 2), integers as varints (type 0).
"""

from __future__ import annotations

import struct
from typing import Any

import cv2
import numpy as np
from foxglove.messages import (
    CameraCalibration,
    CompressedImage,
    CubePrimitive,
    CylinderPrimitive,
    FrameTransform,
    FrameTransforms,
    LaserScan,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    PoseInFrame,
    Quaternion,
    RawImage,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    Timestamp,
    TriangleListPrimitive,
    Vector3,
)

from qcarlab.errors import InputError
from qcarlab.recording import channels as C


def timestamp(ns: int) -> Timestamp:
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _pose(x: float, y: float, z: float, q: tuple[float, float, float, float]) -> Pose:
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))


# ------------------------------------------------------------------------------------ sensors
def laser_scan(scan: Any, ns: int) -> LaserScan:
    """A LIDAR turn as ``foxglove.LaserScan`` in frame ``lidar``: angles from the first to the last
    beam (Foxglove spaces the beams evenly between them), no-returns (0) as NaN."""
    angles = np.asarray(scan.angles, dtype=np.float64)
    ranges = np.asarray(scan.ranges, dtype=np.float64)
    shown = np.where(ranges > 0.0, ranges, np.nan)
    return LaserScan(timestamp=timestamp(ns), frame_id=C.LIDAR_FRAME,
                     start_angle=float(angles[0]) if angles.size else 0.0,
                     end_angle=float(angles[-1]) if angles.size else 0.0,
                     ranges=shown.tolist())


def color_image(image: np.ndarray, ns: int, frame_id: str, exact: bool) -> CompressedImage | RawImage:
    """A BGR uint8 image: JPEG (quality C.JPEG_QUALITY, 4:2:0) or, ``exact``, raw ``bgr8`` (lossless)."""
    img = np.ascontiguousarray(C.check_bgr(image))
    if exact:
        h, w = img.shape[:2]
        return RawImage(timestamp=timestamp(ns), frame_id=frame_id, width=w, height=h, encoding="bgr8",
                        step=w * 3, data=img.tobytes())
    ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, C.JPEG_QUALITY])
    if not ok:
        raise InputError("recording: the JPEG encoder refused a camera frame")
    return CompressedImage(timestamp=timestamp(ns), frame_id=frame_id, format="jpeg", data=jpg.tobytes())


def depth_image(depth: np.ndarray, ns: int, exact: bool) -> RawImage:
    """Depth (float32 m, 0 = no data): ``32FC1`` metres (exact) or ``16UC1`` millimetres, the
    D435's own z16 format (compact; nearest mm, 0 stays 0)."""
    d = np.asarray(depth)
    h, w = d.shape[:2]
    if exact:
        data = np.ascontiguousarray(d, dtype="<f4").tobytes()
        return RawImage(timestamp=timestamp(ns), frame_id=C.CAMERA_FRAME, width=w, height=h, encoding="32FC1",
                        step=w * 4, data=data)
    mm = np.multiply(d, np.float32(1000.0), dtype=np.float32)  # (in place from here on: one array, no copies)
    mm += np.float32(0.5)
    bad = ~np.isfinite(mm)  # NaN, inf: no data (0)
    if bad.any():
        mm[bad] = 0.0
    np.clip(mm, 0.0, 65535.0, out=mm)
    mm = mm.astype("<u2")
    return RawImage(timestamp=timestamp(ns), frame_id=C.CAMERA_FRAME, width=w, height=h, encoding="16UC1",
                    step=w * 2, data=mm.tobytes())


def calibration(params: Any, ns: int) -> CameraCalibration:
    """The RGBD colour camera's pinhole model (no distortion), so Foxglove can project into 3D."""
    fx, fy, cx, cy, w, h = C.rgbd_intrinsics(params)
    return CameraCalibration(timestamp=timestamp(ns), frame_id=C.CAMERA_FRAME, width=w, height=h,
                             distortion_model="plumb_bob", D=[0.0] * 5,
                             K=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
                             R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                             P=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0])


# ------------------------------------------------------------------------------------ poses
def pose_in_frame(pose: tuple[float, float, float], ns: int) -> PoseInFrame:
    x, y, yaw = pose
    return PoseInFrame(timestamp=timestamp(ns), frame_id=C.WORLD_FRAME, pose=_pose(x, y, 0.0, C.yaw_quaternion(yaw)))


def _tf(ns: int, parent: str, child: str, x: float, y: float, z: float, q) -> FrameTransform:
    return FrameTransform(timestamp=timestamp(ns), parent_frame_id=parent, child_frame_id=child,
                          translation=Vector3(x=x, y=y, z=z), rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))


def mounts(params: Any, ns: int) -> list[FrameTransform]:
    """The sensors on the car: base_link -> lidar, the RGBD optical frame and the four CSI cameras."""
    p = params
    out = [_tf(ns, C.BASE_FRAME, C.LIDAR_FRAME, p.lidar_x, 0.0, p.lidar_z, (0.0, 0.0, 0.0, 1.0)),
           _tf(ns, C.BASE_FRAME, C.CAMERA_FRAME, p.rgbd_x, 0.0, p.rgbd_z, C.camera_rotation(0.0, p.rgbd_pitch))]
    from qcarlab.constants import csi_mounts

    where = csi_mounts(p)
    for view in C.CSI_VIEWS:
        x, y, z, yaw = where[view]
        out.append(_tf(ns, C.BASE_FRAME, C.CSI_FRAMES[view], x, y, z, C.camera_rotation(yaw)))
    return out


def transforms(ns: int, true_pose=None, estimate=None, static: list[FrameTransform] | None = None) -> FrameTransforms:
    """world -> base_link (the true pose, else the estimate), world -> base_link_estimate, + mounts."""
    out = list(static or [])
    body = true_pose if true_pose is not None else estimate
    if body is not None:
        out.append(_tf(ns, C.WORLD_FRAME, C.BASE_FRAME, body[0], body[1], 0.0, C.yaw_quaternion(body[2])))
    if estimate is not None:
        out.append(_tf(ns, C.WORLD_FRAME, C.ESTIMATE_FRAME, estimate[0], estimate[1], 0.0,
                       C.yaw_quaternion(estimate[2])))
    return FrameTransforms(transforms=out)


# ------------------------------------------------------------------------------------ scene
def _is_convex(pts: np.ndarray) -> bool:
    d = np.roll(pts, -1, axis=0) - pts
    cross = d[:, 0] * np.roll(d[:, 1], -1) - d[:, 1] * np.roll(d[:, 0], -1)
    return bool(np.all(cross >= -1e-12) or np.all(cross <= 1e-12))


def _prism(points: np.ndarray, z0: float, z1: float, color) -> tuple[TriangleListPrimitive, LinePrimitive]:
    """A vertical prism as triangles (sides, and the top when convex) plus its top outline."""
    pts = np.asarray(points, dtype=float)
    tri: list[Point3] = []
    n = len(pts)
    for i in range(n):
        (ax, ay), (bx, by) = pts[i], pts[(i + 1) % n]
        a0, b0, a1, b1 = Point3(x=ax, y=ay, z=z0), Point3(x=bx, y=by, z=z0), Point3(x=ax, y=ay, z=z1), Point3(x=bx, y=by, z=z1)
        tri += [a0, b0, b1, a0, b1, a1]
    if n >= 3 and _is_convex(pts):
        for i in range(1, n - 1):
            tri += [Point3(x=pts[0][0], y=pts[0][1], z=z1), Point3(x=pts[i][0], y=pts[i][1], z=z1),
                    Point3(x=pts[i + 1][0], y=pts[i + 1][1], z=z1)]
    outline = LinePrimitive(type=LinePrimitiveLineType.LineLoop, thickness=0.005,
                            points=[Point3(x=x, y=y, z=z1) for x, y in pts], color=C.bgr_color((40, 40, 40)))
    return TriangleListPrimitive(points=tri, color=color), outline


def world_entity(world: Any, ns: int) -> SceneEntity:
    """The world's floor, floor paint, walls, boxes, posts and sign plates, as one scene entity."""
    x0, y0, x1, y1 = world.floor_bounds
    cubes = [CubePrimitive(pose=_pose((x0 + x1) / 2.0, (y0 + y1) / 2.0, -0.006, (0.0, 0.0, 0.0, 1.0)),
                           size=Vector3(x=x1 - x0, y=y1 - y0, z=0.01), color=C.bgr_color(world.floor_color))]
    lines, triangles, cylinders = [], [], []
    for m in getattr(world, "markings", []) or []:
        pts = np.asarray(m.points, dtype=float)
        kind = LinePrimitiveLineType.LineLoop if (m.closed or m.filled) else LinePrimitiveLineType.LineStrip
        lines.append(LinePrimitive(type=kind, thickness=float(m.width) if not m.filled else 0.01,
                                   points=[Point3(x=x, y=y, z=0.001) for x, y in pts], color=C.bgr_color(m.color)))
    for s in world.static_solids():
        z0, z1 = float(s.z0), float(s.height)
        if s.kind == "polygon" and s.points is not None:
            tri, outline = _prism(s.points, z0, z1, C.bgr_color(s.color))
            triangles.append(tri)
            lines.append(outline)
        elif s.center is not None:
            cylinders.append(CylinderPrimitive(
                pose=_pose(s.center[0], s.center[1], (z0 + z1) / 2.0, (0.0, 0.0, 0.0, 1.0)),
                size=Vector3(x=2.0 * s.radius, y=2.0 * s.radius, z=max(z1 - z0, 1e-3)),
                bottom_scale=1.0, top_scale=1.0, color=C.bgr_color(s.color)))
    return SceneEntity(timestamp=timestamp(ns), frame_id=C.WORLD_FRAME, id="world", cubes=cubes, lines=lines,
                       triangles=triangles, cylinders=cylinders)


def path_entity(path: np.ndarray, ns: int) -> SceneEntity:
    """The reference path, a green line on the floor."""
    pts = np.asarray(path, dtype=float).reshape(-1, 2)
    line = LinePrimitive(type=LinePrimitiveLineType.LineStrip, thickness=0.02,
                         points=[Point3(x=x, y=y, z=0.005) for x, y in pts], color=C.bgr_color((60, 200, 60)))
    return SceneEntity(timestamp=timestamp(ns), frame_id=C.WORLD_FRAME, id="path", lines=[line])


def balls_entity(circles: list[Any], ns: int) -> SceneEntity:
    """The moving balls at one instant (spheres resting on the floor)."""
    spheres = [SpherePrimitive(pose=_pose(c.x, c.y, c.radius, (0.0, 0.0, 0.0, 1.0)),
                               size=Vector3(x=2 * c.radius, y=2 * c.radius, z=2 * c.radius),
                               color=C.bgr_color(c.color)) for c in circles]
    return SceneEntity(timestamp=timestamp(ns), frame_id=C.WORLD_FRAME, id="balls", spheres=spheres)


def scene_update(entities: list[SceneEntity]) -> SceneUpdate:
    return SceneUpdate(entities=entities)


# ------------------------------------------------------------------------------------ protobuf bytes
_V3 = struct.Struct("<BdBdBd")  # Vector3 {x = 1, y = 2, z = 3}: doubles
_Q4 = struct.Struct("<BdBdBdBd")  # Quaternion {x = 1, y = 2, z = 3, w = 4}: doubles
_D = struct.Struct("<Bd")


def _varint(n: int) -> bytes:
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def _field(tag: int, payload: bytes) -> bytes:
    """A length-delimited field (a message, a string, packed numbers)."""
    return bytes((tag,)) + _varint(len(payload)) + payload


_SECONDS: dict[int, bytes] = {}  # the seconds' varint: the same for a whole second of messages


def pb_timestamp(ns: int) -> bytes:
    """Field 1 ``timestamp`` (google.protobuf.Timestamp {seconds = 1, nanos = 2}) of every message here."""
    sec, nanos = divmod(int(ns), 1_000_000_000)
    head = _SECONDS.get(sec)
    if head is None:
        if len(_SECONDS) > 64:
            _SECONDS.clear()
        head = _SECONDS[sec] = b"\x08" + _varint(sec) + b"\x10"
    if nanos >= 1 << 28:  # (most of a second's nanoseconds: five bytes, written out)
        body = head + bytes(((nanos & 0x7F) | 0x80, ((nanos >> 7) & 0x7F) | 0x80, ((nanos >> 14) & 0x7F) | 0x80,
                             ((nanos >> 21) & 0x7F) | 0x80, nanos >> 28))
    else:
        body = head + _varint(nanos)
    return bytes((0x0A, len(body))) + body  # (a timestamp is under 128 bytes)


def _pb_pose(x: float, y: float, z: float, q: tuple[float, float, float, float]) -> bytes:
    """foxglove.Pose {position = 1, orientation = 2}: always 2 + 27 + 2 + 36 = 67 bytes."""
    return (b"\x0a\x1b" + _V3.pack(0x09, x, 0x11, y, 0x19, z)
            + b"\x12\x24" + _Q4.pack(0x09, q[0], 0x11, q[1], 0x19, q[2], 0x21, q[3]))


_WORLD = _field(0x12, C.WORLD_FRAME.encode())


def pb_pose_in_frame(pose: tuple[float, float, float], ns: int, stamp: bytes | None = None) -> bytes:
    """:func:`pose_in_frame` as foxglove.PoseInFrame bytes {timestamp = 1, frame_id = 2, pose = 3}."""
    x, y, yaw = pose
    return (stamp or pb_timestamp(ns)) + _WORLD + b"\x1a\x43" + _pb_pose(float(x), float(y), 0.0, C.yaw_quaternion(yaw))


_TO_BASE = _field(0x12, C.WORLD_FRAME.encode()) + _field(0x1A, C.BASE_FRAME.encode())
_TO_ESTIMATE = _field(0x12, C.WORLD_FRAME.encode()) + _field(0x1A, C.ESTIMATE_FRAME.encode())


def _pb_world_tf(stamp: bytes, frames: bytes, pose: tuple[float, float, float]) -> bytes:
    """One entry of FrameTransforms.transforms (field 1): foxglove.FrameTransform {timestamp = 1,
    parent_frame_id = 2, child_frame_id = 3, translation = 4, rotation = 5}."""
    x, y, yaw = pose
    q = C.yaw_quaternion(yaw)
    body = (stamp + frames + b"\x22\x1b" + _V3.pack(0x09, float(x), 0x11, float(y), 0x19, 0.0)
            + b"\x2a\x24" + _Q4.pack(0x09, q[0], 0x11, q[1], 0x19, q[2], 0x21, q[3]))
    return _field(0x0A, body)


def pb_transforms(ns: int, true_pose=None, estimate=None, static: bytes = b"", stamp: bytes | None = None) -> bytes:
    """:func:`transforms` as foxglove.FrameTransforms bytes; ``static`` is the encoded mounts
    (``transforms(ns, static=mounts(...)).encode()``: a FrameTransforms is its repeated field, so
    two encodings put together are the message with both lists)."""
    stamp = stamp or pb_timestamp(ns)
    out = static
    body = true_pose if true_pose is not None else estimate
    if body is not None:
        out += _pb_world_tf(stamp, _TO_BASE, body)
    if estimate is not None:
        out += _pb_world_tf(stamp, _TO_ESTIMATE, estimate)
    return out


_LIDAR = _field(0x12, C.LIDAR_FRAME.encode())


def pb_laser_scan(scan: Any, ns: int) -> bytes:
    """:func:`laser_scan` as foxglove.LaserScan bytes {timestamp = 1, frame_id = 2, start_angle = 4,
    end_angle = 5, ranges = 6 (packed doubles)}: no-returns (0) as NaN."""
    angles = np.asarray(scan.angles)
    ranges = np.asarray(scan.ranges, dtype=np.float64)
    shown = np.where(ranges > 0.0, ranges, np.nan).astype("<f8", copy=False)
    start, end = (float(angles[0]), float(angles[-1])) if angles.size else (0.0, 0.0)
    return (pb_timestamp(ns) + _LIDAR + _D.pack(0x21, start) + _D.pack(0x29, end)
            + _field(0x32, shown.tobytes()))
