"""The qcarlab wire protocol, version 1: framing, message types, payload codecs.

Every message is one frame: a 16-byte little-endian header followed by ``length`` payload bytes::

    offset  size  field
    0       2     magic    b"QC"
    2       1     version  1
    3       1     type     message type (MsgType)
    4       4     seq      the sender's frame counter: 1 for its first frame, +1 for each next one
    8       4     ref      in a reply, the seq of the request it answers; 0 otherwise
    12      4     length   payload bytes that follow (requests: at most 65536)

Small messages carry JSON (hello, welcome, error, bye) or fixed little-endian structs (command,
readout, truth, time); sensor frames carry raw arrays (no base64). ``docs/protocol.md`` is the
reference a MATLAB or C++ client can be written from; this module is what the code does.
"""

from __future__ import annotations

import json
import math
import os
import select
import socket
import struct
import time
from enum import IntEnum
from typing import Any, NamedTuple

import numpy as np

_yield = getattr(os, "sched_yield", lambda: None)
MAGIC = b"QC"
VERSION = 1
DEFAULT_PORT = 18960
HEADER = struct.Struct("<2sBBIII")
HEADER_SIZE = HEADER.size  # 16
MAX_REQUEST = 64 * 1024  # largest payload a server accepts from a client
MAX_REPLY = 64 * 1024 * 1024  # largest payload a client accepts from a server
MAX_PING = 64  # largest ping payload echoed
MAX_ADVANCE = 60.0  # s, largest single lock-step advance
N_LAMPS = 12


class MsgType(IntEnum):
    HELLO = 0x01  # C->S JSON {"protocol", "role", "token", "client"}
    WELCOME = 0x02  # S->C JSON: identity, capabilities, limits, mode
    OK = 0x03  # S->C empty: done (reply to STOP)
    COMMAND = 0x10  # C->S <2d12dI: throttle, steering, 12 lamps, flags
    APPLIED = 0x11  # S->C <2d12d: the command as applied after the server's limits
    READ = 0x12  # C->S empty
    READOUT = 0x13  # S->C READOUT struct
    GET_TRUTH = 0x14  # C->S empty
    TRUTH = 0x15  # S->C <9d
    ADVANCE = 0x16  # C->S <d dt (lock-step only)
    TIME = 0x17  # S->C <d t
    GET_TIME = 0x18  # C->S empty
    STOP = 0x19  # C->S empty: throttle 0, wheels straight (the backend's stop)
    GET_LIDAR = 0x20  # C->S empty
    LIDAR = 0x21  # S->C arrays: angles, ranges
    GET_RGBD = 0x22  # C->S empty
    RGBD = 0x23  # S->C arrays: color (480,640,3) u8, depth (480,640) f32
    GET_CSI = 0x24  # C->S empty
    CSI = 0x25  # S->C arrays: right, rear, left, front
    PING = 0x30  # C->S up to 64 bytes, echoed
    PONG = 0x31  # S->C the ping's payload
    ERROR = 0x7E  # S->C JSON {"code", "message", "fatal"}
    BYE = 0x7F  # either way, JSON {"reason"} or empty


MSG_NAMES = {int(m): m.name for m in MsgType}

# flags of COMMAND
FLAG_READ_BACK = 0x1  # reply with a READOUT taken right after applying, instead of APPLIED
FLAGS_KNOWN = FLAG_READ_BACK  # a COMMAND with any other bit set is refused (bad_value)

# status bits of READOUT
STATUS_WATCHDOG = 0x1  # the watchdog stopped the car since the last command
STATUS_CONTROLLED = 0x2  # a controller is connected
STATUS_LOCKSTEP = 0x4  # the server runs in lock-step
STATUS_CACHED = 0x8  # a lock-step monitor's copy of the controller's last readout

COMMAND = struct.Struct("<2d12dI")  # 116 bytes
APPLIED = struct.Struct("<2d12d")  # 112 bytes
READOUT = struct.Struct("<dqddd3d3d2d12dI")  # 204 bytes
TRUTH = struct.Struct("<9d")  # 72 bytes
SCALAR = struct.Struct("<d")  # 8 bytes: ADVANCE dt, TIME t
ARRAYS_HEAD = struct.Struct("<dII")  # t, number of arrays, reserved
ARRAY_DESC = struct.Struct("<BBH3I")  # dtype code, ndim, reserved, dims[3]


def framed(payload: struct.Struct) -> struct.Struct:
    """The header and a fixed-size payload as one struct: a whole frame packed (or unpacked) in
    one call, its values the header's six (magic, version, type, seq, ref, length) then the payload's."""
    return struct.Struct(HEADER.format + payload.format.lstrip("<"))


COMMAND_FRAME = framed(COMMAND)  # 132 bytes
APPLIED_FRAME = framed(APPLIED)  # 128 bytes
READOUT_FRAME = framed(READOUT)  # 220 bytes

DTYPES: dict[int, np.dtype] = {
    1: np.dtype("<u1"),
    2: np.dtype("<u2"),
    3: np.dtype("<i4"),
    4: np.dtype("<f4"),
    5: np.dtype("<f8"),
}
DTYPE_CODES = {dt: code for code, dt in DTYPES.items()}

# which arrays each sensor frame carries, in order
FRAME_FIELDS: dict[int, tuple[str, ...]] = {
    MsgType.LIDAR: ("angles", "ranges"),
    MsgType.RGBD: ("color", "depth"),
    MsgType.CSI: ("right", "rear", "left", "front"),
}

# error codes; the fatal ones close the connection after the error frame
FATAL_CODES = frozenset(
    {"bad_magic", "bad_version", "oversized", "sequence", "bad_hello", "bad_token", "busy",
     "too_many_clients", "timeout", "shutting_down", "control_lost"}
)
ERROR_CODES = FATAL_CODES | {
    "unknown_type", "bad_payload", "bad_value", "read_only", "not_lockstep", "unsupported",
    "no_data", "car_error",
}

HTTP_METHODS = (b"GET ", b"POST", b"HEAD", b"PUT ", b"DELE", b"OPTI", b"PATC", b"CONN", b"TRAC", b"PRI ")


class ProtocolError(Exception):
    """A peer broke the protocol; ``code`` is one of ERROR_CODES."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message

    @property
    def fatal(self) -> bool:
        return self.code in FATAL_CODES


class IncompleteFrame(ProtocolError):
    """The peer closed the connection in the middle of a frame."""

    def __init__(self, got: int):
        super().__init__("incomplete", f"connection closed in the middle of a frame ({got} bytes buffered)")


class Frame(NamedTuple):
    """One frame as read: its header's type, seq and ref, and its payload (an immutable named
    tuple: made for every frame, ``_new_frame`` makes it without a Python-level ``__init__``)."""

    type: int
    seq: int
    ref: int
    payload: bytes | bytearray | memoryview

    @property
    def name(self) -> str:
        return MSG_NAMES.get(self.type, f"0x{self.type:02x}")


_new_frame = tuple.__new__


def looks_like_http(data: bytes | bytearray) -> bool:
    """True when the first bytes a peer sent are an HTTP request line (or a prefix of one)."""
    head = bytes(data[:4])
    if not head:
        return False
    return any(m.startswith(head) if len(head) < 4 else head == m for m in HTTP_METHODS)


HTTP_REPLY = (
    b"HTTP/1.0 400 Bad Request\r\nContent-Type: text/plain\r\nConnection: close\r\n\r\n"
    b"This is a qcarlab car server: it speaks the qcarlab binary protocol (docs/protocol.md), "
    b"not HTTP. Use `qcarlab ping tcp://HOST:PORT` or --car tcp://HOST:PORT.\n"
)


# --- framing ------------------------------------------------------------------------------------
def pack_header(mtype: int, seq: int, ref: int, length: int) -> bytes:
    return HEADER.pack(MAGIC, VERSION, mtype, seq & 0xFFFFFFFF, ref & 0xFFFFFFFF, length)


def send_frame(sock: socket.socket, mtype: int, seq: int, ref: int, *parts: Any,
               waiter: Waiter | None = None, timeout: float | None = None) -> None:
    """Send one frame; ``parts`` are bytes-like objects (numpy arrays included) sent without copies.

    With a ``waiter`` the socket is non-blocking and the frame must make progress at least every
    ``timeout`` seconds (TimeoutError otherwise); without one the socket's own timeout applies.
    (A connection's small frames go through its :class:`FrameWriter`.)"""
    views = [memoryview(p).cast("B") if not isinstance(p, (bytes, bytearray)) else p for p in parts]
    length = sum(len(v) for v in views)
    header = pack_header(mtype, seq, ref, length)
    if waiter is not None:
        data = [header + b"".join(views)] if length <= 65536 else [header, *views]
        _send_nonblocking(sock, data, waiter, timeout)
        return
    if length <= 65536:
        sock.sendall(header + b"".join(views))
        return
    _send_all_parts(sock, [header, *views])


def _send_all_parts(sock: socket.socket, parts: list[Any]) -> None:
    views = [memoryview(p) for p in parts if len(p)]
    if not hasattr(sock, "sendmsg"):  # Windows
        for v in views:
            sock.sendall(v)
        return
    while views:
        sent = sock.sendmsg(views[:64])
        _consume(views, sent)


def _consume(views: list[memoryview], sent: int) -> None:
    while sent and views:
        first = len(views[0])
        if sent >= first:
            sent -= first
            views.pop(0)
        else:
            views[0] = views[0][sent:]
            sent = 0


def _send_nonblocking(sock: socket.socket, parts: list[Any], waiter: Waiter, timeout: float | None) -> None:
    views = [memoryview(p) for p in parts if len(p)]
    gather = hasattr(sock, "sendmsg")
    while views:
        try:
            sent = sock.sendmsg(views[:64]) if gather and len(views) > 1 else sock.send(views[0])
        except (BlockingIOError, InterruptedError):
            if not waiter.writable(timeout):
                raise TimeoutError(f"no progress sending for {timeout} s") from None
            continue
        _consume(views, sent)


class FrameWriter:
    """Sends the frames of one connection through one preallocated buffer: a small frame's header
    and payload are packed into it in place and go out in one system call (no concatenation, no
    new bytes object per frame); a large one goes through :func:`send_frame`. The socket is
    non-blocking: a frame that does not go out at once waits on ``waiter``, making progress at
    least every ``timeout`` seconds (TimeoutError otherwise)."""

    SMALL = 4096  # payloads up to this size are copied into the buffer

    def __init__(self, sock: socket.socket, waiter: Waiter, timeout: float | None):
        self.sock = sock
        self.waiter = waiter
        self.timeout = timeout
        self.buf = bytearray(HEADER_SIZE + self.SMALL)
        self.view = memoryview(self.buf)

    def send(self, mtype: int, seq: int, ref: int, *parts: Any) -> None:
        """One frame whose payload is ``parts`` (bytes-like objects, numpy arrays included)."""
        if len(parts) > 1 or (parts and not isinstance(parts[0], (bytes, bytearray))):
            send_frame(self.sock, mtype, seq, ref, *parts, waiter=self.waiter, timeout=self.timeout)
            return
        payload = parts[0] if parts else b""
        n = len(payload)
        if n > self.SMALL:
            send_frame(self.sock, mtype, seq, ref, payload, waiter=self.waiter, timeout=self.timeout)
            return
        HEADER.pack_into(self.buf, 0, MAGIC, VERSION, mtype, seq & 0xFFFFFFFF, ref & 0xFFFFFFFF, n)
        end = HEADER_SIZE + n
        self.buf[HEADER_SIZE:end] = payload
        self._out(end)

    def send_struct(self, frame: struct.Struct, mtype: int, seq: int, ref: int, values: tuple[Any, ...]) -> None:
        """One frame of a fixed-size payload: ``frame`` is :func:`framed` of the payload's struct,
        ``values`` the payload's values (struct.error, before anything is sent, for values that do
        not fit)."""
        size = frame.size
        frame.pack_into(self.buf, 0, MAGIC, VERSION, mtype, seq & 0xFFFFFFFF, ref & 0xFFFFFFFF, size - HEADER_SIZE,
                        *values)
        self._out(size)

    def _out(self, size: int) -> None:
        """Send the buffer's first ``size`` bytes; what does not go out at once is sent before the
        buffer is used again."""
        try:
            sent = self.sock.send(self.view[:size])
        except (BlockingIOError, InterruptedError):
            sent = 0
        if sent < size:
            _send_nonblocking(self.sock, [self.view[sent:size]], self.waiter, self.timeout)


class Waiter:
    """Waits until a non-blocking socket can be read or written (poll; select where there is none)."""

    def __init__(self, sock: socket.socket):
        self.sock = sock
        if hasattr(select, "poll"):
            fd = sock.fileno()
            self._r = select.poll()
            self._r.register(fd, select.POLLIN)
            self._w = select.poll()
            self._w.register(fd, select.POLLOUT)
        else:  # pragma: no cover (Windows)
            self._r = self._w = None

    def readable(self, timeout: float | None) -> bool:
        """True when the socket has data (or its end); False after ``timeout`` s (None: no limit)."""
        if self._r is not None:
            return bool(self._r.poll(None if timeout is None else max(0.0, timeout) * 1000.0))
        return bool(select.select([self.sock], [], [], timeout)[0])

    def writable(self, timeout: float | None) -> bool:
        if self._w is not None:
            return bool(self._w.poll(None if timeout is None else max(0.0, timeout) * 1000.0))
        return bool(select.select([], [self.sock], [], timeout)[1])


class FrameReader:
    """Reads frames from a socket through one buffer; large payloads go straight to their own buffer.

    ``read_frame`` returns None at a clean end of stream (between frames). A socket timeout while
    waiting raises ``TimeoutError``; ``mid_frame`` then says whether a frame was under way (the
    reader stays usable either way: nothing is consumed before a whole frame is in).

    Deadlines (the server's; a client leaves them unset and the socket's own timeout applies):

    - ``frame_timeout``: a frame's bytes must all arrive within this many seconds of its first
      byte (or, when it came with the previous frame, of the moment reading it began), however
      they trickle in (a byte every second does not keep a frame open);
    - ``deadline``: an absolute ``time.monotonic()`` that caps every wait (the whole HELLO);
    - ``idle_timeout``: how long to wait for the first byte of a frame (TimeoutError between
      frames, ``mid_frame`` False); None waits as long as the other deadlines allow.

    With a ``waiter`` the socket is non-blocking (``settimeout(0)``): a read that finds bytes costs
    one system call, and ``recv_timeout`` bounds each wait where no deadline does (a client's "no
    reply within 5 s").
    """

    def __init__(self, sock: socket.socket, max_payload: int, bufsize: int = 256 * 1024,
                 frame_timeout: float | None = None, waiter: Waiter | None = None):
        self.sock = sock
        self.waiter = waiter  # set: the socket is non-blocking and waits go through it
        self.recv_timeout: float | None = None  # with a waiter: the longest wait for more bytes
        self.max_payload = max_payload
        self.buf = bytearray(bufsize)
        self.view = memoryview(self.buf)
        self.start = 0
        self.end = 0
        self.broken = False
        self.bytes_in = 0
        self.frame_timeout = frame_timeout
        self.deadline: float | None = None
        self.idle_timeout: float | None = None
        self.first_byte_at = 0.0  # time.monotonic() when the frame under way began
        self.eof = False  # poll() saw the end of the stream
        self._resume = False  # a partial frame was left behind by the last frame returned

    @property
    def buffered(self) -> int:
        return self.end - self.start

    @property
    def mid_frame(self) -> bool:
        return self.end > self.start or self.broken

    def peek(self) -> bytes:
        return bytes(self.buf[self.start : self.end])

    def _limit(self, now: float) -> float | None:
        """The time.monotonic() by which more bytes must come (None: no limit)."""
        limit = self.deadline
        if self.frame_timeout is not None and self.mid_frame:
            own: float | None = self.first_byte_at + self.frame_timeout
        elif self.idle_timeout is not None:
            own = now + self.idle_timeout
        elif self.waiter is not None and self.recv_timeout is not None:
            own = now + self.recv_timeout
        else:
            own = None
        if own is not None:
            limit = own if limit is None else min(limit, own)
        return limit

    def _arm(self) -> None:
        """Set the socket's timeout to what the deadlines leave (no-op when none is set)."""
        if self.frame_timeout is None and self.deadline is None:
            return
        now = time.monotonic()
        limit = self._limit(now)
        if limit is None:
            self.sock.settimeout(None)
            return
        left = limit - now
        if left <= 0.0:
            raise TimeoutError("deadline passed")
        self.sock.settimeout(left)

    def _recv_into(self, view: memoryview) -> int:
        fresh = not self.mid_frame
        if self.waiter is None:
            self._arm()
            got = self.sock.recv_into(view)
        else:
            limit: float | None = -1.0  # fixed at the first wait: a wait is not extended by waking up
            while True:
                try:
                    got = self.sock.recv_into(view)
                    break
                except (BlockingIOError, InterruptedError):
                    now = time.monotonic()
                    if limit == -1.0:
                        limit = self._limit(now)
                    if limit is not None and limit <= now:
                        raise TimeoutError("deadline passed") from None
                    self.waiter.readable(None if limit is None else limit - now)
        if got and fresh:
            self.first_byte_at = time.monotonic()
        self.bytes_in += got
        return got

    def poll(self) -> int:
        """Take whatever bytes are already there without waiting (the socket must be non-blocking:
        ``settimeout(0)``, as it is with a waiter); returns the count, 0 when nothing is there. End
        of stream is left for ``read_frame`` to find."""
        if self.end == len(self.buf):
            return 0
        if self.start == self.end:
            self.start = self.end = 0
        fresh = not self.mid_frame
        try:
            got = self.sock.recv_into(self.view[self.end :])
        except (BlockingIOError, InterruptedError):
            return 0
        if got == 0:
            self.eof = True
            return 0
        if fresh:
            self.first_byte_at = time.monotonic()
        self.end += got
        self.bytes_in += got
        return got

    def _fill(self) -> bool:
        """Receive more bytes into the buffer; False at end of stream."""
        if self.eof:
            return False
        if self.end == len(self.buf):
            if self.start == 0:  # cannot happen for frames that fit, kept for safety
                raise ProtocolError("oversized", "frame larger than the receive buffer")
            n = self.end - self.start
            self.buf[:n] = self.buf[self.start : self.end]
            self.start, self.end = 0, n
        got = self._recv_into(self.view[self.end :])
        if got == 0:
            return False
        self.end += got
        return True

    def _ensure(self, n: int) -> bool:
        while self.end - self.start < n:
            if len(self.buf) - self.start < n:  # make room at the front
                m = self.end - self.start
                self.buf[:m] = self.buf[self.start : self.end]
                self.start, self.end = 0, m
            if not self._fill():
                return False
        return True

    def spin(self, seconds: float) -> None:
        """Look for bytes for up to ``seconds`` without sleeping, yielding the CPU between looks;
        returns as soon as some are buffered (or the stream ended). A reply on loopback comes within
        tens of microseconds, and a thread woken from sleep pays about as much again on a busy
        machine. (A non-blocking recv per look: measured a little faster than a poll(0) and then a
        recv once bytes are there.) OSError as the socket's recv raises it."""
        if self.end > self.start or self.eof or seconds <= 0.0:
            return
        clock = time.perf_counter
        end = clock() + seconds
        while not self.poll() and not self.eof and clock() < end:
            _yield()

    def read_frame(self) -> Frame | None:
        if self.broken:
            raise ProtocolError("incomplete", "the connection's stream is out of step")
        if self._resume:  # time spent between two calls (serving the last frame) is not the peer's
            self._resume = False
            self.first_byte_at = time.monotonic()
        start = self.start
        if self.end - start >= HEADER_SIZE:  # the common case: a whole frame is in (else the full checks below)
            magic, version, mtype, seq, ref, length = HEADER.unpack_from(self.buf, start)
            total = HEADER_SIZE + length
            if magic == MAGIC and version == VERSION and length <= self.max_payload and self.end - start >= total:
                payload = self.view[start + HEADER_SIZE : start + total].tobytes()
                self.start = start + total
                if self.start == self.end:
                    self.start = self.end = 0
                else:
                    self._resume = True
                return _new_frame(Frame, (mtype, seq, ref, payload))
        if not self._ensure(2):
            if self.buffered:
                raise IncompleteFrame(self.buffered)
            return None
        if self.buf[self.start : self.start + 2] != MAGIC:
            raise ProtocolError("bad_magic", "not a qcarlab frame (bad magic)")
        if not self._ensure(HEADER_SIZE):
            raise IncompleteFrame(self.buffered)
        _, version, mtype, seq, ref, length = HEADER.unpack_from(self.buf, self.start)
        if version != VERSION:
            raise ProtocolError(
                "bad_version", f"protocol version {version} is not supported (this side speaks version {VERSION})"
            )
        if length > self.max_payload:
            raise ProtocolError("oversized", f"payload of {length} bytes exceeds the limit of {self.max_payload}")
        total = HEADER_SIZE + length
        if total <= len(self.buf):
            if not self._ensure(total):
                raise IncompleteFrame(self.buffered)
            p0 = self.start + HEADER_SIZE
            payload = self.view[p0 : p0 + length].tobytes()
            self.start += total
            if self.start == self.end:
                self.start = self.end = 0
            else:  # the next frame's first bytes came with this one: its clock starts when it is read
                self._resume = True
            return _new_frame(Frame, (mtype, seq, ref, payload))
        # a large payload: copy what is buffered, receive the rest in place
        payload = bytearray(length)
        have = min(self.buffered - HEADER_SIZE, length)
        p0 = self.start + HEADER_SIZE
        payload[:have] = self.buf[p0 : p0 + have]
        self.start = self.end = 0
        view = memoryview(payload)
        self.broken = True  # until the payload is complete
        while have < length:
            got = self._recv_into(view[have:])
            if got == 0:
                raise IncompleteFrame(have)
            have += got
        self.broken = False
        return _new_frame(Frame, (mtype, seq, ref, payload))


# --- JSON payloads -----------------------------------------------------------------------------
def encode_json(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False, default=_json_default).encode("utf-8")


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    return str(obj)


def decode_json(payload: bytes | bytearray, what: str) -> dict[str, Any]:
    try:
        obj = json.loads(bytes(payload).decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        raise ProtocolError("bad_payload", f"{what}: payload is not valid UTF-8 JSON") from None
    if not isinstance(obj, dict):
        raise ProtocolError("bad_payload", f"{what}: payload must be a JSON object")
    return obj


def error_payload(code: str, message: str) -> bytes:
    return encode_json({"code": code, "message": message, "fatal": code in FATAL_CODES})


# --- struct payloads ---------------------------------------------------------------------------
def _check_size(payload: bytes | bytearray, st: struct.Struct, what: str) -> None:
    if len(payload) != st.size:
        raise ProtocolError("bad_payload", f"{what}: payload must be {st.size} bytes, got {len(payload)}")


def pack_command(throttle: float, steering: float, leds: tuple[float, ...], flags: int = 0) -> bytes:
    return COMMAND.pack(throttle, steering, *leds, flags)


def unpack_command(payload: bytes | bytearray) -> tuple[float, float, tuple[float, ...], int]:
    if len(payload) != COMMAND.size:
        _check_size(payload, COMMAND, "command")
    values = COMMAND.unpack(payload)
    return values[0], values[1], values[2:14], values[14]


def pack_applied(throttle: float, steering: float, leds: tuple[float, ...]) -> bytes:
    return APPLIED.pack(throttle, steering, *leds)


def unpack_applied(payload: bytes | bytearray) -> tuple[float, float, tuple[float, ...]]:
    _check_size(payload, APPLIED, "applied")
    values = APPLIED.unpack(payload)
    return values[0], values[1], tuple(values[2:])


def readout_payload_values(r: Any, status: int = 0) -> tuple[Any, ...]:
    """The values of a READOUT payload for a readout (``READOUT.pack(*...)``; ``READOUT_FRAME``
    after a header's values)."""
    g, a = r.gyro, r.accel
    return (r.t, int(r.encoder_counts), r.tach, r.motor_current, r.battery_voltage,
            float(g[0]), float(g[1]), float(g[2]), float(a[0]), float(a[1]), float(a[2]),
            r.steering, r.throttle, *r.leds, status)


def pack_readout(r: Any, status: int = 0) -> bytes:
    return READOUT.pack(*readout_payload_values(r, status))


READOUT_FIELDS = ("t", "encoder_counts", "tach", "motor_current", "battery_voltage", "gyro", "accel", "steering",
                  "throttle", "leds")


def readout_values(payload: bytes | bytearray) -> tuple[tuple[Any, ...], int]:
    """The readout's ten fields in :class:`qcarlab.car.base.Readout`'s order (``Readout._make``
    takes them as they are) and the server's status bits."""
    if len(payload) != READOUT.size:
        _check_size(payload, READOUT, "readout")
    v = READOUT.unpack(payload)
    return (v[0], v[1], v[2], v[3], v[4], np.array(v[5:8]), np.array(v[8:11]), v[11], v[12], v[13:25]), v[25]


def unpack_readout(payload: bytes | bytearray) -> tuple[dict[str, Any], int]:
    """The readout's fields by name (for :class:`qcarlab.car.base.Readout`) and the server's status bits."""
    values, status = readout_values(payload)
    return dict(zip(READOUT_FIELDS, values)), status


TRUTH_FIELDS = ("t", "x", "y", "yaw", "speed", "wheel_speed", "steering", "distance", "wheel_distance")


def pack_truth(tr: Any) -> bytes:
    return TRUTH.pack(*(float(getattr(tr, f)) for f in TRUTH_FIELDS))


def unpack_truth(payload: bytes | bytearray) -> dict[str, float]:
    _check_size(payload, TRUTH, "truth")
    return dict(zip(TRUTH_FIELDS, TRUTH.unpack(payload)))


def pack_scalar(value: float) -> bytes:
    return SCALAR.pack(value)


def unpack_scalar(payload: bytes | bytearray, what: str) -> float:
    _check_size(payload, SCALAR, what)
    return SCALAR.unpack(payload)[0]


# --- sensor frames (raw arrays) ----------------------------------------------------------------
def pack_arrays(t: float, arrays: list[np.ndarray]) -> list[Any]:
    """Payload parts of a sensor frame: head, descriptors, then each array's bytes 8-byte aligned."""
    parts: list[Any] = []
    descs = bytearray()
    data: list[Any] = []
    for arr in arrays:
        arr = np.asarray(arr)
        little = arr.dtype.newbyteorder("<")
        code = DTYPE_CODES.get(little)
        if code is None:  # anything else travels as float64
            arr, code = arr.astype("<f8"), 5
        elif arr.dtype.byteorder == ">":
            arr = arr.astype(little)
        if arr.ndim > 3:
            raise ValueError(f"sensor arrays have at most 3 dimensions, got shape {arr.shape}")
        arr = np.ascontiguousarray(arr)
        dims = list(arr.shape) + [0] * (3 - arr.ndim)
        descs += ARRAY_DESC.pack(code, arr.ndim, 0, *dims)
        data.append(arr)
        pad = (-arr.nbytes) % 8
        if pad:
            data.append(bytes(pad))
    parts.append(ARRAYS_HEAD.pack(float(t), len(arrays), 0) + bytes(descs))
    parts.extend(a for a in data if (len(a) if isinstance(a, bytes) else a.nbytes))
    return parts


def unpack_arrays(payload: bytes | bytearray, what: str) -> tuple[float, list[np.ndarray]]:
    """Arrays of a sensor frame as views on the payload buffer (no copy)."""
    if len(payload) < ARRAYS_HEAD.size:
        raise ProtocolError("bad_payload", f"{what}: frame too short")
    t, n, _ = ARRAYS_HEAD.unpack_from(payload, 0)
    if n > 16:
        raise ProtocolError("bad_payload", f"{what}: {n} arrays is more than 16")
    off = ARRAYS_HEAD.size
    if len(payload) < off + n * ARRAY_DESC.size:
        raise ProtocolError("bad_payload", f"{what}: frame too short for its descriptors")
    descs = []
    for i in range(n):
        code, ndim, _, d0, d1, d2 = ARRAY_DESC.unpack_from(payload, off + i * ARRAY_DESC.size)
        if code not in DTYPES or ndim > 3:
            raise ProtocolError("bad_payload", f"{what}: array {i} has an unknown dtype code {code} or ndim {ndim}")
        descs.append((DTYPES[code], (d0, d1, d2)[:ndim]))
    off += n * ARRAY_DESC.size
    arrays = []
    for i, (dtype, shape) in enumerate(descs):
        count = math.prod(shape)
        nbytes = count * dtype.itemsize
        if off + nbytes > len(payload):
            raise ProtocolError("bad_payload", f"{what}: array {i} runs past the end of the frame")
        arrays.append(np.frombuffer(payload, dtype=dtype, count=count, offset=off).reshape(shape))
        off += nbytes + ((-nbytes) % 8)
    return t, arrays
