"""What crosses between the trusted side and the student's process: plain values, never pickles.

Unpickling runs code, so nothing the student's process sends is ever unpickled. Both directions
use this small tagged format instead, which can only ever decode to these values::

    None, bool, int, float, str, bytes, list, tuple, dict (str keys),
    numpy.ndarray (numeric dtypes only, C order), and an object's public attributes
    (decoded as one of qcarlab's own result types when it names one, else a SimpleNamespace)

A message is a 4-byte little-endian length and that many bytes; a message over ``MAX_MESSAGE``,
nesting deeper than ``MAX_DEPTH``, an unknown tag or a truncated value is :class:`CodecError`.
Arrays travel as their raw bytes (a 640x480 BGR frame is one 921,600-byte copy each way).
"""

from __future__ import annotations

import math
import socket
import struct
import types
from dataclasses import fields, is_dataclass
from typing import Any

import numpy as np

MAX_MESSAGE = 256 * 2**20  # bytes: 256 MB, far over any block's argument or value
MAX_DEPTH = 32
MAX_ITEMS = 1_000_000  # elements of one list, tuple or dict
#: numpy dtypes that may cross (no objects, no structured or void types)
DTYPES = frozenset("?bBhHiIlLqQefdgFD")

_LEN = struct.Struct("<I")
_I64 = struct.Struct("<q")
_F64 = struct.Struct("<d")


class CodecError(ValueError):
    """A message that is not a value of this format (or too large, or too deep)."""


def _result_types() -> dict[str, type]:
    """qcarlab's own block result types, rebuilt as themselves on the other side."""
    from qcarlab.perception.lane import LineFit
    from qcarlab.perception.stop_sign import ImageObject

    return {"LineFit": LineFit, "ImageObject": ImageObject}


# --------------------------------------------------------------------------------------------
# encoding
# --------------------------------------------------------------------------------------------
def encode(value: Any) -> bytes:
    out = bytearray()
    _enc(value, out, 0)
    if len(out) > MAX_MESSAGE:
        raise CodecError(f"a value of {len(out)} bytes is over the {MAX_MESSAGE // 2**20} MB limit")
    return bytes(out)


def _enc(v: Any, out: bytearray, depth: int) -> None:
    if depth > MAX_DEPTH:
        raise CodecError(f"a value nested deeper than {MAX_DEPTH}")
    if v is None:
        out += b"N"
    elif v is True or v is False:
        out += b"T" if v else b"F"
    elif isinstance(v, np.ndarray):
        if v.dtype.char not in DTYPES:
            raise CodecError(f"an array of dtype {v.dtype} cannot be sent (numbers only)")
        a = np.ascontiguousarray(v)
        dt = a.dtype.str.encode()
        out += b"A" + bytes([len(dt)]) + dt + bytes([a.ndim])
        for n in a.shape:
            out += _I64.pack(n)
        data = a.tobytes()
        out += _I64.pack(len(data)) + data
    elif isinstance(v, (bool, np.bool_)):
        out += b"T" if v else b"F"
    elif isinstance(v, (int, np.integer)):
        iv = int(v)
        if -(2**63) <= iv < 2**63:
            out += b"I" + _I64.pack(iv)
        else:
            text = str(iv).encode()
            out += b"J" + _LEN.pack(len(text)) + text
    elif isinstance(v, (float, np.floating)):
        out += b"D" + _F64.pack(float(v))
    elif isinstance(v, str):
        data = v.encode("utf-8", "surrogatepass")
        out += b"S" + _LEN.pack(len(data)) + data
    elif isinstance(v, (bytes, bytearray, memoryview)):
        data = bytes(v)
        out += b"B" + _LEN.pack(len(data)) + data
    elif isinstance(v, (list, tuple)):
        out += (b"L" if isinstance(v, list) else b"U") + _LEN.pack(len(v))
        for item in v:
            _enc(item, out, depth + 1)
    elif isinstance(v, dict):
        out += b"M" + _LEN.pack(len(v))
        for k, item in v.items():
            _enc(str(k), out, depth + 1)
            _enc(item, out, depth + 1)
    else:  # an object: its public attributes (a dataclass's fields)
        if is_dataclass(v) and not isinstance(v, type):
            attrs = {f.name: getattr(v, f.name) for f in fields(v)}
        else:
            attrs = {k: a for k, a in getattr(v, "__dict__", {}).items() if not k.startswith("_") and not callable(a)}
        name = type(v).__name__
        out += b"O"
        _enc(name, out, depth + 1)
        _enc(attrs, out, depth + 1)


# --------------------------------------------------------------------------------------------
# decoding
# --------------------------------------------------------------------------------------------
class _Reader:
    def __init__(self, data: bytes):
        self.data, self.i = memoryview(data), 0

    def take(self, n: int) -> memoryview:
        if n < 0 or self.i + n > len(self.data):
            raise CodecError("a truncated value")
        chunk = self.data[self.i: self.i + n]
        self.i += n
        return chunk

    def u32(self) -> int:
        return _LEN.unpack(self.take(4))[0]

    def i64(self) -> int:
        return _I64.unpack(self.take(8))[0]


def decode(data: bytes) -> Any:
    r = _Reader(data)
    value = _dec(r, 0)
    if r.i != len(r.data):
        raise CodecError("bytes left over after the value")
    return value


def _dec(r: _Reader, depth: int) -> Any:
    if depth > MAX_DEPTH:
        raise CodecError(f"a value nested deeper than {MAX_DEPTH}")
    tag = bytes(r.take(1))
    if tag == b"N":
        return None
    if tag == b"T":
        return True
    if tag == b"F":
        return False
    if tag == b"I":
        return r.i64()
    if tag == b"J":
        text = bytes(r.take(r.u32()))
        if len(text) > 4300 or not text.lstrip(b"-").isdigit():
            raise CodecError("a malformed integer")
        return int(text)
    if tag == b"D":
        return _F64.unpack(r.take(8))[0]
    if tag == b"S":
        return str(bytes(r.take(r.u32())), "utf-8", "surrogatepass")
    if tag == b"B":
        return bytes(r.take(r.u32()))
    if tag in (b"L", b"U"):
        n = r.u32()
        if n > MAX_ITEMS:
            raise CodecError(f"a list of {n} items")
        items = [_dec(r, depth + 1) for _ in range(n)]
        return items if tag == b"L" else tuple(items)
    if tag == b"M":
        n = r.u32()
        if n > MAX_ITEMS:
            raise CodecError(f"a mapping of {n} items")
        out = {}
        for _ in range(n):
            k = _dec(r, depth + 1)
            if not isinstance(k, str):
                raise CodecError("a mapping key that is not text")
            out[k] = _dec(r, depth + 1)
        return out
    if tag == b"A":
        dt = bytes(r.take(r.take(1)[0])).decode("ascii", "replace")
        try:
            dtype = np.dtype(dt)
        except TypeError:
            raise CodecError(f"an unknown dtype {dt!r}") from None
        if dtype.char not in DTYPES:
            raise CodecError(f"an array of dtype {dt!r}")
        ndim = r.take(1)[0]
        if ndim > 8:
            raise CodecError(f"an array of {ndim} dimensions")
        shape = tuple(r.i64() for _ in range(ndim))
        if any(n < 0 for n in shape):
            raise CodecError("an array with a negative dimension")
        nbytes = r.i64()
        if nbytes != math.prod(shape) * dtype.itemsize:
            raise CodecError("an array whose bytes do not match its shape")
        return np.frombuffer(bytearray(r.take(nbytes)), dtype=dtype).reshape(shape)  # writable, our own copy
    if tag == b"O":
        name, attrs = _dec(r, depth + 1), _dec(r, depth + 1)
        if not isinstance(name, str) or not isinstance(attrs, dict):
            raise CodecError("a malformed object")
        cls = _result_types().get(name)
        if cls is not None:
            try:
                return cls(**{f.name: _tuples(attrs[f.name]) for f in fields(cls)})
            except (KeyError, TypeError, ValueError):
                pass
        return types.SimpleNamespace(**attrs)
    raise CodecError(f"an unknown tag {tag!r}")


def _tuples(v: Any) -> Any:
    return tuple(v) if isinstance(v, list) else v


# --------------------------------------------------------------------------------------------
# framing on a stream socket
# --------------------------------------------------------------------------------------------
def send(sock: socket.socket, value: Any) -> None:
    data = encode(value)
    sock.sendall(_LEN.pack(len(data)) + data if len(data) < 65536 else _LEN.pack(len(data)))
    if len(data) >= 65536:
        sock.sendall(data)


def recv(sock: socket.socket) -> Any:
    """The next value; EOFError when the other side closed (or died)."""
    n = _LEN.unpack(_exactly(sock, 4))[0]
    if n > MAX_MESSAGE:
        raise CodecError(f"a message of {n} bytes is over the {MAX_MESSAGE // 2**20} MB limit")
    return decode(_exactly(sock, n))


def _exactly(sock: socket.socket, n: int) -> bytes:
    buf = bytearray(n)
    view, got = memoryview(buf), 0
    while got < n:
        k = sock.recv_into(view[got:], n - got)
        if k == 0:
            raise EOFError("the other side closed the connection")
        got += k
    return bytes(buf)


__all__ = ["CodecError", "decode", "encode", "recv", "send"]
