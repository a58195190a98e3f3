"""The recording's hand-made encodings are the messages the general ones make: the per-tick JSON
(readout, command, truth, the lab's values) and the protobuf bytes of the poses, transforms and
scans, decoded with the very Foxglove schemas the file carries."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("foxglove")
pytest.importorskip("google.protobuf")

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from qcarlab.car.base import Command, Readout, Truth  # noqa: E402
from qcarlab.car.lamps import parse_lamps  # noqa: E402
from qcarlab.constants import DEFAULT_PARAMS  # noqa: E402
from qcarlab.recording import channels as C  # noqa: E402
from qcarlab.recording import messages as M  # noqa: E402
from qcarlab.sensors import LidarScan  # noqa: E402

NS = 1_700_000_123_456_789_012
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
anyfloat = st.floats(width=64)


def decoder(message_type):
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    schema = message_type.get_schema()
    pool = descriptor_pool.DescriptorPool()
    for f in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name)).FromString


@settings(max_examples=200, deadline=None)
@given(st.tuples(*[anyfloat] * 12), st.integers(-2**40, 2**40), st.sampled_from([(), ("brake",), ("hazard", "headlamps")]))
def test_readout_json_is_the_general_encoding(vals, counts, lamps):
    t, tach, cur, vbat, g0, g1, g2, a0, a1, a2, ste, thr = vals
    r = Readout(t, counts, tach, cur, vbat, np.array([g0, g1, g2]), np.array([a0, a1, a2]), ste, thr, parse_lamps(list(lamps)))
    assert json.loads(C.readout_bytes(r)) == json.loads(C.json_bytes(C.readout_json(r)))


@settings(max_examples=200, deadline=None)
@given(anyfloat, anyfloat, anyfloat, st.booleans())
def test_command_json_is_the_general_encoding(t, thr, ste, stop):
    cmd = Command(thr, ste, parse_lamps(["brake", "left-indicators"]))
    assert json.loads(C.command_bytes(t, cmd, stop)) == json.loads(C.json_bytes(C.command_json(t, cmd, stop)))


@settings(max_examples=200, deadline=None)
@given(st.tuples(*[anyfloat] * 9))
def test_truth_json_is_the_general_encoding(vals):
    tr = Truth(*vals)
    assert json.loads(C.truth_bytes(tr)) == json.loads(C.json_bytes(C.truth_json(tr)))


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(st.text(max_size=12), st.one_of(
    anyfloat, st.integers(-2**70, 2**70), st.booleans(), st.none(), st.text(max_size=80),
    anyfloat.map(np.float64), st.integers(-100, 100).map(np.int64), st.lists(anyfloat, max_size=3),
    st.tuples(finite, finite)), max_size=8))
def test_lab_values_json_is_the_general_encoding(values):
    assert json.loads(C.values_bytes(values)) == json.loads(C.json_bytes(values))


def test_json_floats_read_back_bit_for_bit():
    r = Readout(0.1 + 0.2, 7, 1 / 3, math.pi, 12.6, np.array([1e-300, -0.0, 5e-324]), np.array([0.0, 0.0, 9.81]))
    back = json.loads(C.readout_bytes(r))
    assert back["t"] == 0.1 + 0.2 and back["tach"] == 1 / 3 and back["gyro"] == [1e-300, -0.0, 5e-324]
    assert math.copysign(1.0, back["gyro"][1]) == -1.0


def test_pose_and_transform_bytes_decode_as_the_sdks_messages():
    from foxglove.messages import FrameTransforms, PoseInFrame

    poses = [(1.25, -3.5, 0.7), (0.0, 0.0, 0.0), (-1e3, 2e-9, -math.pi)]
    decode = decoder(PoseInFrame)
    for p in poses:
        for ns in (NS, 0, 1_000_000_000, 999_999_999):
            assert decode(M.pb_pose_in_frame(p, ns)) == decode(M.pose_in_frame(p, ns).encode())
    decode = decoder(FrameTransforms)
    mounts = M.mounts(DEFAULT_PARAMS, NS)
    static = M.transforms(NS, static=mounts).encode()
    for true_pose, est in ((poses[0], poses[1]), (None, poses[2]), (poses[2], None), (None, None)):
        for st_bytes, st_objs in ((b"", None), (static, mounts)):
            mine = decode(M.pb_transforms(NS, true_pose, est, st_bytes))
            sdk = decode(M.transforms(NS, true_pose, est, st_objs).encode())
            assert mine == sdk


def test_scan_bytes_decode_as_the_sdks_message():
    from foxglove.messages import LaserScan

    decode = decoder(LaserScan)
    rng = np.random.default_rng(0)
    ranges = rng.uniform(0.15, 12.0, 400)
    ranges[::7] = 0.0  # no returns: NaN in the message
    angles = np.linspace(-math.pi, math.pi, 400, endpoint=False)
    for scan in (LidarScan(0.5, angles, ranges), LidarScan(0.6, np.zeros(0), np.zeros(0))):
        mine, sdk = decode(M.pb_laser_scan(scan, NS)), decode(M.laser_scan(scan, NS).encode())
        assert mine.timestamp == sdk.timestamp and mine.frame_id == sdk.frame_id == "lidar"
        assert mine.start_angle == sdk.start_angle and mine.end_angle == sdk.end_angle
        assert np.array_equal(np.array(mine.ranges), np.array(sdk.ranges), equal_nan=True)
        assert len(mine.ranges) == len(scan.ranges) and not mine.HasField("pose")
