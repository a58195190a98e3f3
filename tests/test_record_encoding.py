"""The recording's hand-made encodings: qcarlab's protobuf readouts, commands and truth decode bit
for bit with the descriptors the file carries; the lab's values' JSON is the general encoder's;
the poses, transforms and scans decode as the SDK's own messages, with Foxglove's schemas."""

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


def qcarlab_decoder(topic):
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool()
    for f in descriptor_pb2.FileDescriptorSet.FromString(C.pb_descriptor()).file:
        pool.Add(f)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(C.PB_SCHEMAS[topic]))
    return lambda data: C.pb_dict(cls.FromString(data))


def same(a, b) -> bool:
    """Equal as the same 8 bytes (NaN included, -0.0 told from 0.0)."""
    return np.array(a, dtype="<f8").tobytes() == np.array(b, dtype="<f8").tobytes()


@settings(max_examples=200, deadline=None)
@given(st.tuples(*[anyfloat] * 12), st.integers(-2**62, 2**62), st.sampled_from([(), ("brake",), ("hazard", "headlamps")]))
def test_readout_bytes_decode_bit_for_bit(vals, counts, lamps):
    t, tach, cur, vbat, g0, g1, g2, a0, a1, a2, ste, thr = vals
    leds = parse_lamps(list(lamps))
    r = Readout(t, counts, tach, cur, vbat, np.array([g0, g1, g2]), np.array([a0, a1, a2]), ste, thr, leds)
    back = qcarlab_decoder(C.READOUT)(C.readout_pb(r))
    assert set(back) == set(C.READOUT_FIELDS) and back["encoder_counts"] == counts
    assert same([back[k] for k in ("t", "tach", "motor_current", "battery_voltage", "steering", "throttle")],
                [t, tach, cur, vbat, ste, thr])
    assert same(back["gyro"], [g0, g1, g2]) and same(back["accel"], [a0, a1, a2]) and same(back["leds"], leds)


@settings(max_examples=200, deadline=None)
@given(anyfloat, anyfloat, anyfloat, st.booleans())
def test_command_bytes_decode_bit_for_bit(t, thr, ste, stop):
    cmd = Command(thr, ste, parse_lamps(["brake", "left-indicators"]))
    back = qcarlab_decoder(C.COMMAND)(C.command_pb(t, cmd, stop))
    assert same([back["t"], back["throttle"], back["steering"]], [t, thr, ste])
    assert same(back["leds"], cmd.leds) and back["stop"] is stop


@settings(max_examples=200, deadline=None)
@given(st.tuples(*[anyfloat] * 9))
def test_truth_bytes_decode_bit_for_bit(vals):
    back = qcarlab_decoder(C.TRUTH)(C.truth_pb(Truth(*vals)))
    assert same([back[k] for k in C.TRUTH_FIELDS], vals)


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(st.text(max_size=12), st.one_of(
    anyfloat, st.integers(-2**70, 2**70), st.booleans(), st.none(), st.text(max_size=80),
    anyfloat.map(np.float64), st.integers(-100, 100).map(np.int64), st.lists(anyfloat, max_size=3),
    st.tuples(finite, finite)), max_size=8))
def test_lab_values_json_is_the_general_encoding(values):
    assert json.loads(C.values_bytes(values)) == json.loads(C.json_bytes(values))


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


def test_a_version_1_recording_with_json_readouts_still_replays(tmp_path):
    """Recordings made before the protobuf messages (version 1) carry readouts, commands and the
    truth as JSON: the reader reads them as before."""
    pytest.importorskip("mcap")
    from mcap.writer import Writer

    from qcarlab.recording.reader import Recording

    f = tmp_path / "v1.mcap"
    t0 = 1_700_000_000_000_000_000
    with f.open("wb") as out:
        w = Writer(out)
        w.start(profile="", library="qcarlab 0.1 (version 1)")
        w.add_metadata("qcarlab", {"version": "1", "profile": "compact", "t0_ns": str(t0)})
        ids = {}
        for topic, name in ((C.READOUT, "qcarlab.Readout"), (C.COMMAND, "qcarlab.Command"), (C.TRUTH, "qcarlab.Truth")):
            schema = w.register_schema(name=name, encoding="jsonschema", data=b'{"type": "object"}')
            ids[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=schema)
        for k in range(3):
            t = 0.01 * k
            ns = t0 + round(t * 1e9)
            msgs = {
                C.READOUT: {"t": t, "encoder_counts": 10 * k, "tach": 1.5 * k, "motor_current": 0.25, "battery_voltage": 12.1,
                            "gyro": [0.0, 0.0, 0.125], "accel": [0.0, 0.0, 9.81], "steering": 0.1, "throttle": 0.2,
                            "leds": [1.0] + [0.0] * 11},
                C.COMMAND: {"t": t, "throttle": 0.2, "steering": 0.1, "leds": [0.0] * 12},
                C.TRUTH: {"t": t, "x": 0.5 * k, "y": 0.0, "yaw": 0.0, "speed": 0.3, "wheel_speed": 0.3, "steering": 0.1,
                          "distance": 0.003 * k, "wheel_distance": 0.003 * k},
            }
            for topic, msg in msgs.items():
                w.add_message(channel_id=ids[topic], log_time=ns, publish_time=ns, data=json.dumps(msg).encode())
        w.finish()
    tape = Recording(f).tape()
    assert [r.encoder_counts for r in tape.readouts] == [0, 10, 20] and tape.readouts[2].tach == 3.0
    assert tape.readouts[0].leds[0] == 1.0 and list(tape.readouts[1].gyro) == [0.0, 0.0, 0.125]
    assert [c.throttle for _, c, _ in tape.commands] == [0.2] * 3 and tape.truths[2].x == 1.0
