"""The wire format: header, codecs, sensor arrays, the frame reader (issue 5, docs/protocol.md)."""

from __future__ import annotations

import math
import socket
import struct
import threading

import numpy as np
import pytest

from qcarlab.car.base import Readout, Truth
from qcarlab.wire import protocol as P
from qcarlab.wire.protocol import MsgType as M


def test_header_layout_is_16_little_endian_bytes():
    h = P.pack_header(M.COMMAND, 7, 3, 116)
    assert len(h) == P.HEADER_SIZE == 16
    assert h[:2] == b"QC" and h[2] == 1 and h[3] == 0x10
    assert struct.unpack("<III", h[4:]) == (7, 3, 116)


def test_struct_sizes_match_the_documented_ones():
    assert (P.COMMAND.size, P.APPLIED.size, P.READOUT.size, P.TRUTH.size, P.SCALAR.size) == (116, 112, 204, 72, 8)
    assert (P.ARRAYS_HEAD.size, P.ARRAY_DESC.size) == (16, 16)


def test_command_and_readout_round_trip_exactly():
    leds = tuple(i / 11 for i in range(12))
    assert P.unpack_command(P.pack_command(0.1, -0.2, leds, 1)) == (0.1, -0.2, leds, 1)
    r = Readout(1.25, -123456789012, 5.5, 0.7, 12.1, np.array([0.1, 0.2, 0.3]), np.array([1.0, 2.0, 9.81]),
                0.05, 0.1, leds)
    fields, status = P.unpack_readout(P.pack_readout(r, P.STATUS_WATCHDOG))
    back = Readout(**fields)
    assert status == P.STATUS_WATCHDOG
    assert back.t == r.t and back.encoder_counts == r.encoder_counts and back.leds == leds
    assert np.array_equal(back.gyro, r.gyro) and np.array_equal(back.accel, r.accel)
    tr = Truth(1.0, 2.0, 3.0, -1.5, 0.5, 0.6, 0.1, 10.0, 11.0)
    assert Truth(**P.unpack_truth(P.pack_truth(tr))) == tr


def test_wrong_payload_sizes_are_bad_payload():
    with pytest.raises(P.ProtocolError) as exc:
        P.unpack_command(b"\0" * 10)
    assert exc.value.code == "bad_payload" and not exc.value.fatal
    with pytest.raises(P.ProtocolError):
        P.decode_json(b"\xff\xfe", "hello")
    with pytest.raises(P.ProtocolError):
        P.decode_json(b"[1, 2]", "hello")


def test_sensor_arrays_travel_raw_and_aligned():
    color = np.arange(480 * 640 * 3, dtype=np.uint32).astype(np.uint8).reshape(480, 640, 3)
    depth = np.linspace(0, 10, 480 * 640, dtype=np.float32).reshape(480, 640)
    odd = np.arange(5, dtype=">f4")  # big-endian and a length that needs padding
    parts = P.pack_arrays(2.5, [color, depth, odd])
    payload = b"".join(bytes(memoryview(p).cast("B")) if not isinstance(p, bytes) else p for p in parts)
    assert len(payload) == 16 + 3 * 16 + color.nbytes + depth.nbytes + 24  # 20 bytes padded to 24
    t, arrays = P.unpack_arrays(payload, "rgbd")
    assert t == 2.5
    assert arrays[0].dtype == np.uint8 and np.array_equal(arrays[0], color)
    assert arrays[1].dtype == np.float32 and np.array_equal(arrays[1], depth)
    assert np.array_equal(arrays[2], odd.astype("<f4"))


@pytest.mark.parametrize("payload", [b"", b"\0" * 15, P.ARRAYS_HEAD.pack(0.0, 99, 0),
                                     P.ARRAYS_HEAD.pack(0.0, 1, 0) + P.ARRAY_DESC.pack(1, 1, 0, 100, 0, 0)])
def test_truncated_or_absurd_sensor_frames_are_refused(payload):
    with pytest.raises(P.ProtocolError):
        P.unpack_arrays(payload, "lidar")


@pytest.mark.parametrize("head,http", [(b"GET / HTTP/1.1", True), (b"POST", True), (b"GE", True),
                                       (b"QC\x01", False), (b"\x16\x03\x01", False), (b"", False)])
def test_http_is_recognised(head, http):
    assert P.looks_like_http(head) is http


def _pair():
    a, b = socket.socketpair()
    a.settimeout(2.0)
    b.settimeout(2.0)
    return a, b


def test_reader_reassembles_frames_sent_byte_by_byte_and_back_to_back():
    a, b = _pair()
    frames = P.pack_header(M.PING, 1, 0, 3) + b"abc" + P.pack_header(M.READ, 2, 0, 0)
    reader = P.FrameReader(a, 1024, bufsize=64)
    for i in range(len(frames)):
        b.sendall(frames[i : i + 1])
    f1, f2 = reader.read_frame(), reader.read_frame()
    assert (f1.type, f1.seq, bytes(f1.payload)) == (M.PING, 1, b"abc")
    assert (f2.type, f2.seq, len(f2.payload)) == (M.READ, 2, 0)
    b.close()
    assert reader.read_frame() is None  # clean end between frames
    a.close()


def test_reader_receives_large_payloads_in_place():
    a, b = _pair()
    big = np.random.default_rng(0).integers(0, 256, 3_000_000, dtype=np.uint8)
    sender = threading.Thread(target=P.send_frame, args=(b, M.RGBD, 1, 1, big))
    sender.start()
    frame = P.FrameReader(a, P.MAX_REPLY).read_frame()
    sender.join(5)
    assert isinstance(frame.payload, bytearray) and np.array_equal(np.frombuffer(frame.payload, np.uint8), big)
    a.close()
    b.close()


@pytest.mark.parametrize(
    "data,code",
    [
        (b"XX" + b"\0" * 14, "bad_magic"),
        (P.HEADER.pack(P.MAGIC, 9, M.PING, 1, 0, 0), "bad_version"),
        (P.HEADER.pack(P.MAGIC, 1, M.PING, 1, 0, 10_000), "oversized"),
    ],
)
def test_reader_refuses_bad_headers(data, code):
    a, b = _pair()
    b.sendall(data)
    with pytest.raises(P.ProtocolError) as exc:
        P.FrameReader(a, 1024).read_frame()
    assert exc.value.code == code and exc.value.fatal
    a.close()
    b.close()


def test_reader_reports_a_frame_cut_short():
    a, b = _pair()
    b.sendall(P.pack_header(M.PING, 1, 0, 10) + b"abc")
    b.close()
    with pytest.raises(P.IncompleteFrame):
        P.FrameReader(a, 1024).read_frame()
    a.close()


def test_json_refuses_nan():
    with pytest.raises(ValueError):
        P.encode_json({"x": math.nan})
