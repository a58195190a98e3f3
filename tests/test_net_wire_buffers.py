"""The per-connection frame buffers of the round trip (issue 12): frames packed in place are the
protocol's bytes, survive sends that go out in pieces, and a reply that cannot be packed costs no
sequence number."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np

from qcarlab.car.base import Readout
from qcarlab.car.tcp import TcpCar
from qcarlab.errors import CarError
from qcarlab.net.server import CarServer
from qcarlab.net.testing import SyntheticCar
from qcarlab.wire import protocol as P
from qcarlab.wire.protocol import MsgType as M

LEDS = tuple(i / 11 for i in range(12))


def _pair() -> tuple[socket.socket, socket.socket]:
    a, b = socket.socketpair()
    a.settimeout(0.0)
    b.settimeout(2.0)
    return a, b


def _recv_exactly(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        assert chunk, "connection closed early"
        data += chunk
    return data


def test_frames_packed_in_place_are_the_protocols_bytes():
    """The car-side server (qcarlab/onboard) and other clients read these: header + payload as
    pack_header and the payload codecs make them, byte for byte."""
    a, b = _pair()
    writer = P.FrameWriter(a, P.Waiter(a), 2.0)
    r = Readout(1.25, -123456789012, 5.5, 0.7, 12.1, np.array([0.1, 0.2, 0.3]), np.array([1.0, 2.0, 9.81]),
                0.05, 0.1, LEDS)
    writer.send_struct(P.COMMAND_FRAME, M.COMMAND, 7, 0, (0.1, -0.2, *LEDS, P.FLAG_READ_BACK))
    writer.send_struct(P.READOUT_FRAME, M.READOUT, 8, 7, P.readout_payload_values(r, P.STATUS_CONTROLLED))
    writer.send_struct(P.APPLIED_FRAME, M.APPLIED, 9, 7, (0.1, -0.2, *LEDS))
    writer.send(M.PING, 2**32 + 10, 0, b"abc")  # seq wraps at 32 bits as pack_header's does
    expected = (P.pack_header(M.COMMAND, 7, 0, 116) + P.pack_command(0.1, -0.2, LEDS, P.FLAG_READ_BACK)
                + P.pack_header(M.READOUT, 8, 7, 204) + P.pack_readout(r, P.STATUS_CONTROLLED)
                + P.pack_header(M.APPLIED, 9, 7, 112) + P.pack_applied(0.1, -0.2, LEDS)
                + P.pack_header(M.PING, 10, 0, 3) + b"abc")
    assert _recv_exactly(b, len(expected)) == expected
    a.close()
    b.close()


class _Trickle:
    """A non-blocking socket that takes at most ``step`` bytes per send and is 'full' every
    other call (BlockingIOError), as a slow peer's socket is."""

    def __init__(self, sock: socket.socket, step: int):
        self.sock, self.step, self.calls = sock, step, 0

    def send(self, data) -> int:
        self.calls += 1
        if self.calls % 2:
            raise BlockingIOError
        return self.sock.send(bytes(data[: self.step]))

    def sendmsg(self, views) -> int:
        return self.send(views[0])

    def fileno(self) -> int:
        return self.sock.fileno()


def test_a_frame_that_goes_out_in_pieces_arrives_whole_before_the_buffer_is_reused():
    a, b = _pair()
    slow = _Trickle(a, 7)
    writer = P.FrameWriter(slow, P.Waiter(a), 2.0)
    writer.send_struct(P.COMMAND_FRAME, M.COMMAND, 1, 0, (0.1, 0.0, *LEDS, 0))
    writer.send_struct(P.COMMAND_FRAME, M.COMMAND, 2, 0, (0.2, 0.0, *LEDS, 1))  # the same buffer, next frame
    writer.send(M.PING, 3, 0, b"x" * 40)
    reader = P.FrameReader(b, 1024)
    frames = [reader.read_frame() for _ in range(3)]
    assert [(f.type, f.seq) for f in frames] == [(M.COMMAND, 1), (M.COMMAND, 2), (M.PING, 3)]
    assert P.unpack_command(frames[0].payload) == (0.1, 0.0, LEDS, 0)
    assert P.unpack_command(frames[1].payload) == (0.2, 0.0, LEDS, 1)
    assert frames[2].payload == b"x" * 40
    a.close()
    b.close()


def test_reader_gives_frames_split_anywhere_and_frames_that_came_together():
    """A frame arriving whole takes the reader's short path, one cut anywhere the full one: the
    frames are the same either way."""
    frames = (P.pack_header(M.COMMAND, 1, 0, 116) + P.pack_command(0.1, 0.0, LEDS, 1)
              + P.pack_header(M.READ, 2, 0, 0) + P.pack_header(M.PING, 3, 0, 2) + b"hi")
    for cut in range(1, len(frames)):
        a, b = _pair()
        a.settimeout(2.0)
        reader = P.FrameReader(a, 1024)
        b.sendall(frames[:cut])
        rest = threading.Timer(0.002, b.sendall, args=(frames[cut:],))  # while the reader waits mid-frame
        rest.start()
        got = [reader.read_frame() for _ in range(3)]
        rest.join()
        assert [(f.type, f.seq, bytes(f.payload)) for f in got] == [
            (M.COMMAND, 1, P.pack_command(0.1, 0.0, LEDS, 1)), (M.READ, 2, b""), (M.PING, 3, b"hi")], cut
        a.close()
        b.close()


def test_spin_returns_at_once_when_a_frame_is_already_buffered():
    """Two replies that came in one segment: looking for the second does not spin for nothing."""
    a, b = _pair()
    reader = P.FrameReader(a, 1024, waiter=P.Waiter(a))
    b.sendall(P.pack_header(M.PONG, 1, 1, 0) + P.pack_header(M.PONG, 2, 2, 0))
    reader.spin(1.0)
    assert reader.read_frame().seq == 1
    t0 = time.monotonic()
    reader.spin(2.0)
    assert time.monotonic() - t0 < 0.5
    assert reader.read_frame().seq == 2
    a.close()
    b.close()


class _HugeEncoder(SyntheticCar):
    """A backend whose readout does not fit the wire (an encoder count past 64 bits)."""

    bad = False

    def read(self):
        r = super().read()
        return r._replace(encoder_counts=2**70) if self.bad else r


def test_a_readout_that_cannot_be_packed_is_an_error_and_the_connection_stays_in_step():
    car = _HugeEncoder()
    with CarServer(car, "127.0.0.1", 0).start() as server:
        with TcpCar(*server.address, timeout=2.0) as ctl:
            assert ctl.write_read(0.1, 0.0).throttle == 0.1
            car.bad = True
            try:
                ctl.write_read(0.1, 0.0)
            except CarError as exc:
                assert "car_error" in str(exc)
            else:
                raise AssertionError("an unpackable readout went out")
            assert car.cmd.throttle == 0.0  # a failing command stops the car
            car.bad = False
            assert ctl.write_read(0.05, 0.0).throttle == 0.05  # replies still in sequence
            assert ctl.ping() > 0
