"""What a recording holds: topics, coordinate frames, and the conversions from qcarlab's types.

Topics (Foxglove's well-known schemas where one fits, JSON with a JSON Schema otherwise)::

    /qcar/readout          qcarlab.Readout       every read(): encoder, tach, current, battery, IMU
    /qcar/command          qcarlab.Command       every write() and stop(): what was applied
    /qcar/truth            qcarlab.Truth         the simulator's ground truth (simulated cars)
    /qcar/lab              qcarlab.LabValues     the lab's own logged values (v_ref, state, ...)
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
was opened) and ``t0_ns`` the wall clock when recording started (in the file's ``qcarlab``
metadata). The JSON messages carry ``t`` as the exact float.

LIDAR no-returns (range 0 in qcarlab) are written as NaN, which Foxglove leaves out of the scan;
a replay turns them back into 0.
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

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

PROFILES = ("compact", "exact")
JPEG_QUALITY = 90
DEPTH_EVERY = 15  # compact: every 15th depth frame (2 Hz at 30 fps)

# ------------------------------------------------------------------------------------ JSON schemas
_NUM = {"type": "number"}
_VEC3 = {"type": "array", "items": _NUM, "minItems": 3, "maxItems": 3}
JSON_SCHEMAS: dict[str, tuple[str, dict[str, Any]]] = {
    READOUT: ("qcarlab.Readout", {
        "type": "object",
        "title": "One read of the car's basic sensors (SI units)",
        "properties": {
            "t": _NUM, "encoder_counts": {"type": "integer"}, "tach": _NUM, "motor_current": _NUM,
            "battery_voltage": _NUM, "gyro": _VEC3, "accel": _VEC3, "steering": _NUM, "throttle": _NUM,
            "leds": {"type": "array", "items": _NUM},
        },
    }),
    COMMAND: ("qcarlab.Command", {
        "type": "object",
        "title": "A command as applied (throttle duty fraction, steering rad, + = left)",
        "properties": {"t": _NUM, "throttle": _NUM, "steering": _NUM, "leds": {"type": "array", "items": _NUM},
                       "stop": {"type": "boolean"}},
    }),
    TRUTH: ("qcarlab.Truth", {
        "type": "object",
        "title": "The simulator's ground truth",
        "properties": {k: _NUM for k in ("t", "x", "y", "yaw", "speed", "wheel_speed", "steering", "distance",
                                         "wheel_distance")},
    }),
    LAB: ("qcarlab.LabValues", {
        "type": "object",
        "title": "The lab's own values at one tick (v_ref, errors, state of the state machine, ...)",
        "properties": {"t": _NUM},
        "additionalProperties": True,
    }),
    FRAMES: ("qcarlab.FrameInfo", {
        "type": "object",
        "title": "A sensor frame's exact time (and the LIDAR's beam angles when they change)",
        "properties": {"sensor": {"type": "string"}, "t": _NUM, "stamp": {"type": "integer"},
                       "angles": {"type": "string", "contentEncoding": "base64"}},
    }),
}


def stamp_ns(t0_ns: int, t: float) -> int:
    """The log time (ns since the epoch) of car time ``t`` (s)."""
    return int(t0_ns + round(float(t) * 1e9))


def json_bytes(values: Mapping[str, Any]) -> bytes:
    """A JSON message: floats written with repr (they read back bit for bit), NaN/inf as null."""
    try:  # plain Python numbers (readouts, commands): straight through
        return json.dumps(values, allow_nan=False, separators=(",", ":")).encode()
    except (TypeError, ValueError):  # numpy values, NaN, tuples of them: made plain first
        return json.dumps(to_jsonable(values), allow_nan=False, separators=(",", ":")).encode()


# --- the per-tick messages, encoded straight to JSON text ----------------------------------------
# A recorded run writes a readout, a command, the truth and the lab's values every tick: building a
# dict and handing it to json.dumps costs more than the run's own step (float formatting aside).
# These write the same JSON (floats with repr, so they read back bit for bit) from a template, and
# fall back to the general path for anything unusual (a non-finite value, an unexpected type).
_FREPR = float.__repr__
_READOUT_FMT = ('{"t":%s,"encoder_counts":%d,"tach":%s,"motor_current":%s,"battery_voltage":%s,'
                '"gyro":[%s,%s,%s],"accel":[%s,%s,%s],"steering":%s,"throttle":%s,"leds":[%s]}')
_COMMAND_FMT = '{"t":%s,"throttle":%s,"steering":%s,"leds":[%s]%s}'
_TRUTH_FMT = ('{"t":%s,"x":%s,"y":%s,"yaw":%s,"speed":%s,"wheel_speed":%s,"steering":%s,"distance":%s,'
              '"wheel_distance":%s}')
_LEDS: dict[tuple, str | None] = {}  # a lamp tuple -> its JSON numbers (the same few tuples every tick)
_KEYS: dict[str, str] = {}  # a lab value's name -> its JSON key text
_STRS: dict[str, str] = {}  # a short string value (a state's name) -> its JSON text
_CACHE_MAX = 512


def _finite(values: tuple[float, ...]) -> bool:
    """All finite (a NaN or an infinity makes the sum non-finite; a sum that overflows takes the
    general path too, which is only slower)."""
    return math.isfinite(sum(values))


def _leds_text(leds: Any) -> str | None:
    """"v,v,...,v" of a lamp tuple, or None when a value is not a finite number."""
    try:
        text = _LEDS[leds]
    except (KeyError, TypeError):
        try:
            vals = tuple(float(v) for v in leds)
        except (TypeError, ValueError):
            return None
        text = ",".join(map(_FREPR, vals)) if all(math.isfinite(v) for v in vals) else None
        try:
            if len(_LEDS) >= _CACHE_MAX:
                _LEDS.clear()
            _LEDS[leds] = text
        except TypeError:  # not hashable (a list): not cached
            pass
    return text


def _three(v: Any) -> tuple[float, float, float]:
    a, b, c = v.tolist() if hasattr(v, "tolist") else v
    return float(a), float(b), float(c)


def readout_bytes(r: Any) -> bytes:
    """The readout's JSON message (as :func:`readout_json`, faster)."""
    try:
        g, a = _three(r.gyro), _three(r.accel)
        vals = (float(r.t), float(r.tach), float(r.motor_current), float(r.battery_voltage), *g, *a,
                float(r.steering), float(r.throttle))
        counts = int(r.encoder_counts)
    except (TypeError, ValueError):
        return json_bytes(readout_json(r))
    leds = _leds_text(r.leds)
    if leds is None or not _finite(vals):
        return json_bytes(readout_json(r))
    t, tach, cur, vbat, g0, g1, g2, a0, a1, a2, ste, thr = map(_FREPR, vals)
    return (_READOUT_FMT % (t, counts, tach, cur, vbat, g0, g1, g2, a0, a1, a2, ste, thr, leds)).encode()


def command_bytes(t: float, cmd: Any, stop: bool = False) -> bytes:
    """The command's JSON message (as :func:`command_json`, faster)."""
    try:
        vals = (float(t), float(cmd.throttle), float(cmd.steering))
    except (TypeError, ValueError):
        return json_bytes(command_json(t, cmd, stop))
    leds = _leds_text(cmd.leds)
    if leds is None or not _finite(vals):
        return json_bytes(command_json(t, cmd, stop))
    return (_COMMAND_FMT % (*map(_FREPR, vals), leds, ',"stop":true' if stop else "")).encode()


def truth_bytes(tr: Any) -> bytes:
    """The truth's JSON message (as :func:`truth_json`, faster)."""
    try:
        vals = (float(tr.t), float(tr.x), float(tr.y), float(tr.yaw), float(tr.speed), float(tr.wheel_speed),
                float(tr.steering), float(tr.distance), float(tr.wheel_distance))
    except (TypeError, ValueError, AttributeError):
        return json_bytes(truth_json(tr))
    if not _finite(vals):
        return json_bytes(truth_json(tr))
    return (_TRUTH_FMT % tuple(map(_FREPR, vals))).encode()


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


def readout_json(r: Any) -> dict[str, Any]:
    return {
        "t": float(r.t), "encoder_counts": int(r.encoder_counts), "tach": float(r.tach),
        "motor_current": float(r.motor_current), "battery_voltage": float(r.battery_voltage),
        "gyro": [float(v) for v in r.gyro], "accel": [float(v) for v in r.accel],
        "steering": float(r.steering), "throttle": float(r.throttle), "leds": [float(v) for v in r.leds],
    }


def command_json(t: float, cmd: Any, stop: bool = False) -> dict[str, Any]:
    out = {"t": float(t), "throttle": float(cmd.throttle), "steering": float(cmd.steering),
           "leds": [float(v) for v in cmd.leds]}
    if stop:
        out["stop"] = True
    return out


def truth_json(tr: Any) -> dict[str, Any]:
    return {k: float(getattr(tr, k)) for k in ("t", "x", "y", "yaw", "speed", "wheel_speed", "steering",
                                               "distance", "wheel_distance")}


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
