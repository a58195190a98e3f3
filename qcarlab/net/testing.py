"""Test and benchmark helpers for the network code: a car with synthetic sensors, a raw client,
and the malformed-frame fuzz (hypothesis strategies are built only when asked for).

    from qcarlab.net.server import CarServer
    from qcarlab.net.testing import RawClient, SyntheticCar

    with CarServer(SyntheticCar(), port=0) as server, RawClient(server.address) as raw:
        raw.hello("monitor")
        print(raw.request(MsgType.PING, b"hi"))
"""

from __future__ import annotations

import math
import socket
import struct
import time
from typing import Any

import numpy as np

from qcarlab.car.base import Car, Command, Identity, Readout
from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.errors import NotBuiltError
from qcarlab.wire import protocol as P
from qcarlab.wire.frames import make_frame
from qcarlab.wire.protocol import MsgType as M


class SyntheticCar(Car):
    """A car whose sensors return fixed synthetic frames (seeded); remembers the last command.

    ``stepped=True`` makes it a lock-step car (time moves on ``advance``); ``sensors`` picks which
    of lidar/rgbd/csi it has (the others raise NotBuiltError, as an unwired backend does);
    ``sensor_delay`` makes every sensor reading take that long (a slow device, a first render),
    read off the drive lock like the Quanser car's devices (``own_sensor_path=False``: under it).
    """

    def __init__(
        self,
        params: QCarParams = DEFAULT_PARAMS,
        throttle_limit: float | None = None,
        *,
        stepped: bool = False,
        sensors: tuple[str, ...] = ("lidar", "rgbd", "csi"),
        seed: int = 0,
        sensor_delay: float = 0.0,
        own_sensor_path: bool = True,
    ):
        super().__init__(params, throttle_limit)
        self._stepped = stepped
        self._t = 0.0
        self._t0 = time.monotonic()
        self.sensors = tuple(sensors)
        self.sensor_delay = sensor_delay  # s a sensor reading takes (a slow camera, a first render)
        self.own_sensor_path = own_sensor_path  # False: sensors read under the drive lock (the Car default)
        self.cmd = Command()
        self.n_commands = 0
        self.n_reads = 0
        self.n_stops = 0
        self.counts = 0.0
        rng = np.random.default_rng(seed)
        p = params
        n = p.lidar_beams
        self.lidar = (np.linspace(-math.pi, math.pi, n, endpoint=False), rng.uniform(0.15, 12.0, n))
        self.color = rng.integers(0, 256, (p.rgbd_height, p.rgbd_width, 3), dtype=np.uint8)
        self.depth = rng.uniform(0.0, 10.0, (p.rgbd_height, p.rgbd_width)).astype(np.float32)
        self.csi = [rng.integers(0, 256, (p.csi_height, p.csi_width, 3), dtype=np.uint8) for _ in range(4)]

    @property
    def stepped(self) -> bool:
        return self._stepped

    @property
    def time(self) -> float:
        return self._t if self._stepped else time.monotonic() - self._t0

    def advance(self, dt: float) -> None:
        if self._stepped:
            self.counts += self.cmd.throttle * 10000.0 * dt
            self._t += dt
        else:
            time.sleep(dt)

    def _apply(self, cmd: Command) -> None:
        self.cmd = cmd
        self.n_commands += 1

    def stop(self) -> None:
        self.n_stops += 1
        super().stop()

    def read(self) -> Readout:
        self.n_reads += 1
        return Readout(
            t=self.time,
            encoder_counts=int(self.counts),
            tach=self.cmd.throttle * 10000.0,
            motor_current=abs(self.cmd.throttle) * 2.0,
            battery_voltage=12.0,
            gyro=np.zeros(3),
            accel=np.array([0.0, 0.0, 9.81]),
            steering=self.cmd.steering,
            throttle=self.cmd.throttle,
            leds=self.cmd.leds,
        )

    def identity(self) -> Identity:
        return Identity("synthetic", "synthetic", ["drive", "lamps", "battery", *self.sensors])

    def _need(self, name: str) -> None:
        if name not in self.sensors:
            raise NotBuiltError(f"synthetic car: no {name}")
        if self.sensor_delay:
            time.sleep(self.sensor_delay)

    def sensor_job(self, kind: str) -> Any:
        if not self.own_sensor_path:
            return super().sensor_job(kind)
        return getattr(self, f"read_{kind}")

    def read_lidar(self) -> Any:
        self._need("lidar")
        return make_frame(M.LIDAR, self.time, list(self.lidar))

    def read_rgbd(self) -> Any:
        self._need("rgbd")
        return make_frame(M.RGBD, self.time, [self.color, self.depth])

    def read_csi(self) -> Any:
        self._need("csi")
        return make_frame(M.CSI, self.time, list(self.csi))


class RawClient:
    """Speaks raw frames (or raw bytes) to a server: for tests of bad input."""

    def __init__(self, address: tuple[str, int], timeout: float = 2.0, source: str | None = None):
        # source: the local address to connect from (on Linux any 127.x.y.z stands for another machine)
        self.sock = socket.create_connection(address, timeout=timeout,
                                             source_address=None if source is None else (source, 0))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.reader = P.FrameReader(self.sock, P.MAX_REPLY)
        self.seq = 0

    def __enter__(self) -> RawClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass

    def send(self, mtype: int, payload: bytes = b"", seq: int | None = None, version: int = P.VERSION) -> int:
        self.seq = self.seq + 1 if seq is None else seq
        header = P.HEADER.pack(P.MAGIC, version, mtype, self.seq, 0, len(payload))
        self.sock.sendall(header + payload)
        return self.seq

    def send_bytes(self, data: bytes) -> None:
        self.sock.sendall(data)

    def recv(self) -> P.Frame | None:
        """The next frame, or None when the server closed the connection."""
        try:
            return self.reader.read_frame()
        except (ConnectionResetError, P.IncompleteFrame):
            return None

    def request(self, mtype: int, payload: bytes = b"") -> P.Frame:
        self.send(mtype, payload)
        frame = self.recv()
        assert frame is not None, "server closed the connection"
        return frame

    def hello(self, role: str = "control", token: str | None = None, protocol: int = P.VERSION) -> P.Frame:
        msg: dict[str, Any] = {"protocol": protocol, "role": role, "client": "raw"}
        if token is not None:
            msg["token"] = token
        return self.request(M.HELLO, P.encode_json(msg))

    def closed_by_peer(self, timeout: float = 2.0) -> bool:
        """Read (and drop) until the server closes; False if it is still open after ``timeout``."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.sock.settimeout(max(0.01, deadline - time.monotonic()))
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                return False
            except OSError:
                return True
            if not data:
                return True
        return False


def error_of(frame: P.Frame | None) -> dict[str, Any]:
    """The JSON of an ERROR frame (asserts it is one)."""
    assert frame is not None, "expected an error frame, the connection was closed"
    assert frame.type == M.ERROR, f"expected ERROR, got {frame.name}"
    return P.decode_json(frame.payload, "error")


# --- the malformed-frame fuzz ---------------------------------------------------------------------
def fuzz_strategy() -> Any:
    """A hypothesis strategy of (say_hello, [chunks of bytes]) sent on one connection."""
    from hypothesis import strategies as st

    header_types = st.one_of(st.sampled_from([int(m) for m in M]), st.integers(0, 255))

    @st.composite
    def framed(draw: Any) -> bytes:
        mtype = draw(header_types)
        seq = draw(st.one_of(st.just(2), st.integers(0, 2**32 - 1)))
        version = draw(st.one_of(st.just(P.VERSION), st.integers(0, 255)))
        magic = draw(st.one_of(st.just(P.MAGIC), st.binary(min_size=2, max_size=2)))
        payload = draw(st.binary(max_size=300))
        length = draw(st.one_of(st.just(len(payload)), st.integers(0, 2**32 - 1)))
        return P.HEADER.pack(magic, version, mtype, seq, 0, length) + payload

    @st.composite
    def command(draw: Any) -> bytes:
        floats = st.floats(allow_nan=True, allow_infinity=True, width=64)
        lamp = st.one_of(st.sampled_from([0.0, 1.0]), floats)
        lamps = draw(st.one_of(st.just((0.0,) * 12), st.tuples(*[lamp] * 12)))
        values = [draw(st.one_of(st.floats(-1.0, 1.0), floats)), draw(floats), *lamps]
        flags = draw(st.integers(0, 2**32 - 1))
        payload = P.COMMAND.pack(*values, flags)
        mtype = draw(st.sampled_from([M.COMMAND, M.ADVANCE, M.READ, M.PING, M.GET_RGBD]))
        if mtype == M.ADVANCE:
            payload = struct.pack("<d", values[0])
        cut = draw(st.integers(0, len(payload)))
        payload = payload[:cut] if draw(st.booleans()) else payload
        return P.HEADER.pack(P.MAGIC, P.VERSION, mtype, 2, 0, len(payload)) + payload

    chunk = st.one_of(st.binary(min_size=1, max_size=200), framed(), command())
    return st.tuples(st.booleans(), st.lists(chunk, min_size=1, max_size=4))


def run_fuzz_case(address: tuple[str, int], hello: bool, chunks: list[bytes], timeout: float = 3.0) -> bool:
    """Send one fuzz case on a fresh connection (after a control hello when ``hello``), close our
    side, and wait for the server to close its side; returns False if it did not within timeout."""
    with RawClient(address, timeout=timeout) as raw:
        if hello:
            welcome = raw.hello("control")
            if welcome.type != M.WELCOME:
                return raw.closed_by_peer(timeout)
        try:
            for data in chunks:
                raw.send_bytes(data)
            raw.sock.shutdown(socket.SHUT_WR)
        except OSError:
            pass  # the server already closed on us: fine
        return raw.closed_by_peer(timeout)
