"""What a recording holds: topics, coordinate frames, and the conversions from qcarlab's types.

Topics (Foxglove's well-known schemas where one fits; else qcarlab's own, protobuf for the
per-tick readouts, commands and truth, JSON with a JSON Schema for the rest)::

    /qcar/readout          qcarlab.Readout       every read(): encoder, tach, current, battery, IMU (protobuf)
    /qcar/command          qcarlab.Command       every write() and stop(): what was applied (protobuf)
    /qcar/truth            qcarlab.Truth         the simulator's ground truth (simulated cars; protobuf)
    /qcar/lab              qcarlab.LabValues     the lab's own logged values (v_ref, state, ...; JSON)
    /qcar/lidar            foxglove.LaserScan    each new scan, frame "lidar"
    /qcar/rgbd/color       foxglove.CompressedImage (JPEG) | foxglove.RawImage bgr8 (exact)
    /qcar/rgbd/depth       foxglove.RawImage     16UC1 mm (compact) | 32FC1 m (exact)
    /qcar/rgbd/calibration foxglove.CameraCalibration
    /qcar/csi/<view>       foxglove.CompressedImage | RawImage, views right, rear, left, front
    /qcar/pose/true        foxglove.PoseInFrame  in "world"
    /qcar/pose/estimate    foxglove.PoseInFrame  dead reckoning from the readouts, in "world"
    /tf                    foxglove.FrameTransforms  world->base_link, world->base_link_estimate,
                                                 base_link->lidar, ->camera_color_optical_frame, ->csi_*
    /qcar/scene            foxglove.SceneUpdate  the world's static shapes, the reference path, balls
    /qcarlab/frames        qcarlab.FrameInfo     per sensor frame: its exact time (and LIDAR angles
                                                 when they change), so a replay gives the lab the
                                                 very numbers it had

Times: a message's log time is ``t0_ns + round(t * 1e9)`` with ``t`` the car's time (s since it
was opened) and ``t0_ns`` (in the file's ``qcarlab`` metadata) the wall clock less the car's time
when recording started: the run's first messages are stamped when it started, whatever time the
car's clock showed then (a served or real-time car's start-up). The messages carry ``t`` as the exact float (recordings of version 1 wrote readouts,
commands and truth as JSON; the reader reads both).

LIDAR no-returns (range 0 in qcarlab) are written as NaN, which Foxglove leaves out of the scan;
a replay turns them back into 0.
"""

from __future__ import annotations

import base64
import json
import math
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from qcarlab.errors import InputError
from qcarlab.record import to_jsonable

# ------------------------------------------------------------------------------------ topics
READOUT = "/qcar/readout"
COMMAND = "/qcar/command"
TRUTH = "/qcar/truth"
LAB = "/qcar/lab"
LIDAR = "/qcar/lidar"
COLOR = "/qcar/rgbd/color"
DEPTH = "/qcar/rgbd/depth"
CALIBRATION = "/qcar/rgbd/calibration"
CSI_VIEWS = ("right", "rear", "left", "front")
CSI = {view: f"/qcar/csi/{view}" for view in CSI_VIEWS}
POSE_TRUE = "/qcar/pose/true"
POSE_ESTIMATE = "/qcar/pose/estimate"
TF = "/tf"
SCENE = "/qcar/scene"
FRAMES = "/qcarlab/frames"

# ------------------------------------------------------------------------------------ frames
WORLD_FRAME = "world"
BASE_FRAME = "base_link"
ESTIMATE_FRAME = "base_link_estimate"
LIDAR_FRAME = "lidar"
CAMERA_FRAME = "camera_color_optical_frame"
CSI_FRAMES = {view: f"csi_{view}_optical_frame" for view in CSI_VIEWS}
CSI_YAW = {"right": -math.pi / 2.0, "rear": math.pi, "left": math.pi / 2.0, "front": 0.0}

SENSOR_TOPICS = {"lidar": (LIDAR,), "rgbd": (COLOR, DEPTH, CALIBRATION), "csi": tuple(CSI.values())}


def live_topics(capabilities: Any, sensors: Any = None, scene: bool = True) -> set[str]:
    """The channels a run sends, which a live view advertises: the readouts, commands, the lab's
    values and the dead-reckoned pose always; the truth and true pose with a ``truth`` capability;
    the scene when there is a world or path; each of ``sensors`` ("lidar", "rgbd", "csi"; None:
    every one the car has) that the car has."""
    caps = set(capabilities or ())
    out = {READOUT, COMMAND, LAB, POSE_ESTIMATE, TF}
    if "truth" in caps:
        out |= {TRUTH, POSE_TRUE}
    if scene:
        out.add(SCENE)
    for sensor in (SENSOR_TOPICS if sensors is None else sensors):
        if sensor in caps:
            out.update(SENSOR_TOPICS[sensor])
    return out


PROFILES = ("compact", "exact")
JPEG_QUALITY = 80  # its artefacts (mean 2.2 levels) are below the simulated camera's own noise
DEPTH_EVERY = 15  # compact: every 15th depth frame (2 Hz at 30 fps)

# ------------------------------------------------------------------------------------ JSON schemas
_NUM = {"type": "number"}
_VEC3 = {"type": "array", "items": _NUM, "minItems": 3, "maxItems": 3}
JSON_SCHEMAS: dict[str, tuple[str, dict[str, Any]]] = {
    LAB: ("qcarlab.LabValues", {
        "type": "object",
        "title": "The lab's own values at one tick (v_ref, errors, state of the state machine, ...)",
        "properties": {"t": _NUM},
        "additionalProperties": True,
    }),
    FRAMES: ("qcarlab.FrameInfo", {
        "type": "object",
        "title": "A sensor frame's exact time, the tick the lab first read it at (and the LIDAR's beam angles "
                 "when they change)",
        "properties": {"sensor": {"type": "string"}, "t": _NUM, "stamp": {"type": "integer"}, "tick": _NUM,
                       "angles": {"type": "string", "contentEncoding": "base64"}},
    }),
}


def check_profile(profile: str) -> str:
    """``profile`` if it is one of PROFILES, else one line saying which are."""
    if profile not in PROFILES:
        raise InputError(f"recording profile must be one of {', '.join(PROFILES)}, got {profile!r}")
    return profile


def check_record_path(path: Path) -> Path:
    """``path`` if a recording can be made there (not a folder, its folder exists), else one line."""
    if path.is_dir():
        raise InputError(f"--record {path}: is a folder; give a file name such as run.mcap")
    if not path.parent.exists():
        raise InputError(f"--record {path}: folder {path.parent} does not exist")
    return path


def check_bgr(image: Any) -> np.ndarray:
    """``image`` as an array if it is a BGR uint8 image (H, W, 3), else one line saying what it is."""
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise InputError(f"recording: expected a BGR uint8 image, got {img.dtype} {img.shape}")
    return img


def stamp_ns(t0_ns: int, t: float) -> int:
    """The log time (ns since the epoch) of car time ``t`` (s)."""
    return int(t0_ns + round(float(t) * 1e9))


def json_bytes(values: Mapping[str, Any]) -> bytes:
    """A JSON message: floats written with repr (they read back bit for bit), NaN/inf as null."""
    try:  # plain Python numbers (readouts, commands): straight through
        return json.dumps(values, allow_nan=False, separators=(",", ":")).encode()
    except (TypeError, ValueError):  # numpy values, NaN, tuples of them: made plain first
        return json.dumps(to_jsonable(values), allow_nan=False, separators=(",", ":")).encode()


# --- the per-tick messages ------------------------------------------------------------------------
# A recorded run writes a readout, a command and the truth every tick. As JSON, writing each float
# as its shortest exact decimal (the only JSON that reads back bit for bit) cost more than the run's
# own step; these three are protobuf instead (schemas ``qcarlab.Readout``, ``qcarlab.Command``,
# ``qcarlab.Truth``, whose descriptors the file carries, so Foxglove and any protobuf reader decode
# them): doubles as their 8 bytes, exact, NaN and infinities included, packed by one struct call.
# The lab's values (free-form names) stay JSON, written from a template (values_bytes).
PB_PACKAGE = "qcarlab"
READOUT_FIELDS = ("t", "encoder_counts", "tach", "motor_current", "battery_voltage", "gyro", "accel",
                  "steering", "throttle", "leds")
COMMAND_FIELDS = ("t", "throttle", "steering", "leds", "stop", "step_t", "step_dt")
TRUTH_FIELDS = ("t", "x", "y", "yaw", "speed", "wheel_speed", "steering", "distance", "wheel_distance")
PB_SCHEMAS = {READOUT: "qcarlab.Readout", COMMAND: "qcarlab.Command", TRUTH: "qcarlab.Truth"}

# Readout {double t = 1; sfixed64 encoder_counts = 2; double tach = 3, motor_current = 4,
# battery_voltage = 5; repeated double gyro = 6, accel = 7 (packed, 3 each); double steering = 8,
# throttle = 9; repeated double leds = 10}: a tag byte ((field << 3) | wire type) before each value
_READOUT_PB = struct.Struct("<BdBqBdBdBdBB3dBB3dBdBd")
_COMMAND_PB = struct.Struct("<BdBdBd")  # Command {double t = 1, throttle = 2, steering = 3; leds = 4; bool stop = 5;
_STEP_PB = struct.Struct("<BdBd")  # double step_t = 6, step_dt = 7}: the t and dt the lab's step was given
_TRUTH_PB = struct.Struct("<" + "Bd" * 9)  # Truth {double t = 1 ... wheel_distance = 9}
_LEDS_PB: dict[tuple[int, Any], bytes] = {}  # (field tag, lamp tuple) -> the packed field (the same few tuples every tick)
_KEYS: dict[str, str] = {}  # a lab value's name -> its JSON key text
_STRS: dict[str, str] = {}  # a short string value (a state's name) -> its JSON text
_CACHE_MAX = 512
_FREPR = float.__repr__


def _packed(tag: int, values: Any) -> bytes:
    """A packed repeated double field (cached for hashable lamp tuples)."""
    try:
        return _LEDS_PB[(tag, values)]
    except (KeyError, TypeError):
        pass
    vals = [float(v) for v in values]
    out = bytes((tag,)) + _varint(8 * len(vals)) + struct.pack(f"<{len(vals)}d", *vals)
    try:
        if len(_LEDS_PB) >= _CACHE_MAX:
            _LEDS_PB.clear()
        _LEDS_PB[(tag, values)] = out
    except TypeError:  # a list: not cached
        pass
    return out


def _varint(n: int) -> bytes:
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


# (struct's "d" takes any number, NumPy's included, as float() would: no float() calls per value)
def readout_pb(r: Any) -> bytes:
    """A readout as ``qcarlab.Readout`` protobuf bytes."""
    g, a = r.gyro, r.accel
    if hasattr(g, "tolist"):
        g = g.tolist()
    if hasattr(a, "tolist"):
        a = a.tolist()
    return _READOUT_PB.pack(0x09, r.t, 0x11, int(r.encoder_counts), 0x19, r.tach, 0x21, r.motor_current,
                            0x29, r.battery_voltage, 0x32, 24, *g, 0x3A, 24, *a, 0x41, r.steering, 0x49, r.throttle
                            ) + _packed(0x52, r.leds)


def command_pb(t: float, cmd: Any, stop: bool = False, step: tuple[float, float] | None = None) -> bytes:
    """A command as ``qcarlab.Command`` protobuf bytes (``stop``: the car's stop(), not a write;
    ``step``: the (t, dt) the lab's step was called with at this tick, which a replay gives it again)."""
    out = _COMMAND_PB.pack(0x09, t, 0x11, cmd.throttle, 0x19, cmd.steering) + _packed(0x22, cmd.leds)
    if stop:
        out += b"\x28\x01"
    if step is not None:
        out += _STEP_PB.pack(0x31, step[0], 0x39, step[1])
    return out


def truth_pb(tr: Any) -> bytes:
    """The simulator's ground truth as ``qcarlab.Truth`` protobuf bytes."""
    return _TRUTH_PB.pack(0x09, tr.t, 0x11, tr.x, 0x19, tr.y, 0x21, tr.yaw, 0x29, tr.speed, 0x31, tr.wheel_speed,
                          0x39, tr.steering, 0x41, tr.distance, 0x49, tr.wheel_distance)


def pb_descriptor() -> bytes:
    """The FileDescriptorSet of the three messages (the schema data every one of their channels
    carries, as protobuf channels in MCAP and Foxglove do)."""
    from google.protobuf import descriptor_pb2 as D

    F = D.FieldDescriptorProto
    double, sfixed64, boolean = F.TYPE_DOUBLE, F.TYPE_SFIXED64, F.TYPE_BOOL
    one, many = F.LABEL_OPTIONAL, F.LABEL_REPEATED
    messages = {
        "Readout": [("t", double, one), ("encoder_counts", sfixed64, one), ("tach", double, one),
                    ("motor_current", double, one), ("battery_voltage", double, one), ("gyro", double, many),
                    ("accel", double, many), ("steering", double, one), ("throttle", double, one),
                    ("leds", double, many)],
        "Command": [("t", double, one), ("throttle", double, one), ("steering", double, one), ("leds", double, many),
                    ("stop", boolean, one), ("step_t", double, one), ("step_dt", double, one)],
        "Truth": [(name, double, one) for name in TRUTH_FIELDS],
    }
    fds = D.FileDescriptorSet()
    f = fds.file.add(name="qcarlab/recording.proto", package=PB_PACKAGE, syntax="proto3")
    for name, fields in messages.items():
        m = f.message_type.add(name=name)
        for number, (field, kind, label) in enumerate(fields, start=1):
            m.field.add(name=field, number=number, type=kind, label=label)
    return fds.SerializeToString()


def pb_dict(msg: Any) -> dict[str, Any]:
    """A decoded protobuf message as a dict of every field (repeated ones as lists)."""
    out = {}
    for f in msg.DESCRIPTOR.fields:
        v = getattr(msg, f.name)
        out[f.name] = v if isinstance(v, (bool, int, float, str, bytes)) else list(v)  # a repeated field
    return out


def values_bytes(values: Mapping[str, Any]) -> bytes:
    """A lab's values as JSON (as :func:`json_bytes`: non-finite floats as null), faster for the
    plain values labs log (floats, ints, bools, short strings, None)."""
    parts = []
    for key, v in values.items():
        k = _KEYS.get(key)
        if k is None:
            if not isinstance(key, str):
                return json_bytes(values)
            k = json.dumps(key) + ":"
            if len(_KEYS) >= _CACHE_MAX:
                _KEYS.clear()
            _KEYS[key] = k
        tv = type(v)
        if tv is float:
            text = _FREPR(v) if v - v == 0.0 else "null"  # inf - inf and nan - nan are nan
        elif tv is str:
            text = _STRS.get(v)
            if text is None:
                text = json.dumps(v)
                if len(v) <= 64:
                    if len(_STRS) >= _CACHE_MAX:
                        _STRS.clear()
                    _STRS[v] = text
        elif tv is bool:
            text = "true" if v else "false"
        elif tv is int:
            text = int.__repr__(v)
        elif v is None:
            text = "null"
        elif isinstance(v, np.floating):
            f = float(v)
            text = _FREPR(f) if math.isfinite(f) else "null"
        else:  # lists, arrays, numpy ints, ...: the general path
            return json_bytes(values)
        parts.append(k + text)
    return ("{" + ",".join(parts) + "}").encode()


def encode_angles(angles: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(angles, dtype="<f8").tobytes()).decode()


def decode_angles(text: str) -> np.ndarray:
    return np.frombuffer(base64.b64decode(text), dtype="<f8").astype(np.float64)


# ------------------------------------------------------------------------------------ geometry
def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by ``yaw`` about +z."""
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def quat_mul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    """Hamilton product a * b of (x, y, z, w) quaternions (apply b, then a)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


#: body (x forward, y left, z up) -> optical (x right, y down, z forward), REP-103's camera frame
OPTICAL = (-0.5, 0.5, -0.5, 0.5)


def camera_rotation(yaw: float = 0.0, pitch: float = 0.0) -> tuple[float, float, float, float]:
    """The optical frame of a camera turned ``yaw`` (+ = left) and pitched ``pitch`` (+ = down)."""
    q_pitch = (0.0, math.sin(pitch / 2.0), 0.0, math.cos(pitch / 2.0))
    return quat_mul(yaw_quaternion(yaw), quat_mul(q_pitch, OPTICAL))


def rgbd_intrinsics(params: Any) -> tuple[float, float, float, float, int, int]:
    """(fx, fy, cx, cy, width, height) of the RGBD colour camera, as the simulator renders it:
    square pixels with the focal length from the vertical field of view."""
    w, h = int(params.rgbd_width), int(params.rgbd_height)
    f = (h / 2.0) / math.tan(params.rgbd_vfov / 2.0)
    return f, f, (w - 1) / 2.0, (h - 1) / 2.0, w, h


def bgr_color(bgr: tuple[int, int, int], alpha: float = 1.0):
    from foxglove.messages import Color

    return Color(r=bgr[2] / 255.0, g=bgr[1] / 255.0, b=bgr[0] / 255.0, a=alpha)
