"""What crosses between the trusted side and the student's process: plain values, never their pickles.

Unpickling runs code, so nothing the student's process sends is ever unpickled: it replies in
this small tagged format, which can only ever decode to these values::

    None, bool, int, float, str, bytes, list, tuple, dict (str keys),
    numpy.ndarray (numeric dtypes only, C order), and an object's public attributes
    (decoded as one of qcarlab's own result types when it names one, else a SimpleNamespace)

A reply is a 4-byte little-endian length and that many bytes; a message over ``MAX_MESSAGE``,
nesting deeper than ``MAX_DEPTH``, an unknown tag or a truncated value is :class:`CodecError`.
Arrays travel as their raw bytes; the trusted side's requests (pickles, which only the student's
process loads) send an image once while it is unchanged (:class:`Channel`).
"""

from __future__ import annotations

import copyreg
import functools
import io
import math
import pickle
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
# encoding (a call of a block is a round trip: these run twice per call each side, so the common
# values take one dictionary lookup and one struct.pack)
# --------------------------------------------------------------------------------------------
_HEADS: dict[tuple, bytes] = {}  # an array's header by (dtype, shape): a block sees the same few
_TAG_F64 = struct.Struct("<cd")
_TAG_I64 = struct.Struct("<cq")
_TAG_LEN = struct.Struct("<cI")


def encode(value: Any) -> bytes:
    out: list[bytes] = []
    _enc(value, out, 0)
    data = b"".join(out)
    if len(data) > MAX_MESSAGE:
        raise CodecError(f"a value of {len(data)} bytes is over the {MAX_MESSAGE // 2**20} MB limit")
    return data


def _enc(v: Any, out: list[bytes], depth: int) -> None:
    t = type(v)
    if t is float:
        out.append(_TAG_F64.pack(b"D", v))
    elif t is tuple or t is list:
        if depth > MAX_DEPTH:
            raise CodecError(f"a value nested deeper than {MAX_DEPTH}")
        out.append(_TAG_LEN.pack(b"U" if t is tuple else b"L", len(v)))
        for item in v:
            _enc(item, out, depth + 1)
    elif v is None:
        out.append(b"N")
    elif t is bool:
        out.append(b"T" if v else b"F")
    elif t is int:
        if -(2**63) <= v < 2**63:
            out.append(_TAG_I64.pack(b"I", v))
        else:
            text = str(v).encode()
            out.append(_TAG_LEN.pack(b"J", len(text)) + text)
    elif t is str:
        data = v.encode("utf-8", "surrogatepass")
        out.append(_TAG_LEN.pack(b"S", len(data)))
        out.append(data)
    else:
        _enc_other(v, out, depth)


def _enc_other(v: Any, out: list[bytes], depth: int) -> None:
    if depth > MAX_DEPTH:
        raise CodecError(f"a value nested deeper than {MAX_DEPTH}")
    if isinstance(v, np.ndarray):
        head = _HEADS.get((v.dtype, v.shape))
        if head is None:
            if v.dtype.char not in DTYPES:
                raise CodecError(f"an array of dtype {v.dtype} cannot be sent (numbers only)")
            dt = v.dtype.str.encode()
            head = b"A" + bytes([len(dt)]) + dt + bytes([v.ndim]) + b"".join(_I64.pack(n) for n in v.shape) \
                + _I64.pack(v.nbytes)
            if len(_HEADS) < 256:
                _HEADS[(v.dtype, v.shape)] = head
        out.append(head)
        out.append(v.tobytes())  # C order, a copy
    elif isinstance(v, (bool, np.bool_)):
        out.append(b"T" if v else b"F")
    elif isinstance(v, (int, np.integer)):
        _enc(int(v), out, depth)
    elif isinstance(v, (float, np.floating)):
        out.append(_TAG_F64.pack(b"D", float(v)))
    elif isinstance(v, str):
        _enc(str(v), out, depth)
    elif isinstance(v, (bytes, bytearray, memoryview)):
        data = bytes(v)
        out.append(_TAG_LEN.pack(b"B", len(data)))
        out.append(data)
    elif isinstance(v, (list, tuple)):
        _enc(list(v) if isinstance(v, list) else tuple(v), out, depth)
    elif isinstance(v, dict):
        out.append(_TAG_LEN.pack(b"M", len(v)))
        for k, item in v.items():
            _enc(str(k), out, depth + 1)
            _enc(item, out, depth + 1)
    else:  # an object: its public attributes (a dataclass's fields)
        if is_dataclass(v) and not isinstance(v, type):
            attrs = {f.name: getattr(v, f.name) for f in fields(v)}
        else:
            attrs = {k: a for k, a in getattr(v, "__dict__", {}).items() if not k.startswith("_") and not callable(a)}
        out.append(b"O")
        _enc(type(v).__name__, out, depth + 1)
        _enc(attrs, out, depth + 1)


# --------------------------------------------------------------------------------------------
# decoding
# --------------------------------------------------------------------------------------------
_DTYPES_SEEN: dict[bytes, np.dtype] = {}
_F64_AT = struct.Struct("<d").unpack_from
_I64_AT = struct.Struct("<q").unpack_from
_U32_AT = struct.Struct("<I").unpack_from


def decode(data: bytes) -> Any:
    try:
        value, end = _dec(data, 0, 0)
    except (struct.error, IndexError, UnicodeDecodeError):
        raise CodecError("a truncated or malformed value") from None
    if end != len(data):
        raise CodecError("bytes left over after the value")
    return value


def _span(data: bytes, i: int, n: int) -> int:
    if i + n > len(data):
        raise CodecError("a truncated value")
    return i + n


def _count(data: bytes, i: int, depth: int, what: str) -> tuple[int, int]:
    """A list's or mapping's item count at ``i`` (each item is at least one byte of what is left)."""
    if depth > MAX_DEPTH:
        raise CodecError(f"a value nested deeper than {MAX_DEPTH}")
    n = _U32_AT(data, i)[0]
    if n > MAX_ITEMS or n > len(data) - i - 4:
        raise CodecError(f"a {what} of {n} items")
    return n, i + 4


def _dec(data: bytes, i: int, depth: int) -> tuple[Any, int]:
    tag = data[i]
    i += 1
    if tag == 68:  # D
        return _F64_AT(data, i)[0], i + 8
    if tag == 85 or tag == 76:  # U, L
        n, i = _count(data, i, depth, "list")
        items = []
        for _ in range(n):
            item, i = _dec(data, i, depth + 1)
            items.append(item)
        return (tuple(items) if tag == 85 else items), i
    if tag == 78:  # N
        return None, i
    if tag == 84:  # T
        return True, i
    if tag == 70:  # F
        return False, i
    if tag == 73:  # I
        return _I64_AT(data, i)[0], i + 8
    if tag == 83 or tag == 66 or tag == 74:  # S, B, J
        n = _U32_AT(data, i)[0]
        i += 4
        end = _span(data, i, n)
        raw = data[i:end]
        if tag == 83:
            return str(raw, "utf-8", "surrogatepass"), end
        if tag == 66:
            return bytes(raw), end
        if n > 4300 or not raw.lstrip(b"-").isdigit():
            raise CodecError("a malformed integer")
        return int(raw), end
    if tag == 77:  # M
        n, i = _count(data, i, depth, "mapping")
        out = {}
        for _ in range(n):
            k, i = _dec(data, i, depth + 1)
            if not isinstance(k, str):
                raise CodecError("a mapping key that is not text")
            out[k], i = _dec(data, i, depth + 1)
        return out, i
    if tag == 65:  # A
        n = data[i]
        end = _span(data, i + 1, n)
        dt = bytes(data[i + 1:end])
        dtype = _DTYPES_SEEN.get(dt)
        if dtype is None:
            try:
                dtype = np.dtype(dt.decode("ascii", "replace"))
            except TypeError:
                raise CodecError(f"an unknown dtype {dt!r}") from None
            if dtype.char not in DTYPES:
                raise CodecError(f"an array of dtype {dt!r}")
            if len(_DTYPES_SEEN) < 64:
                _DTYPES_SEEN[dt] = dtype
        ndim = data[end]
        i = end + 1
        if ndim > 8:
            raise CodecError(f"an array of {ndim} dimensions")
        shape = []
        for _ in range(ndim):
            shape.append(_I64_AT(data, i)[0])
            i += 8
        if any(k < 0 for k in shape):
            raise CodecError("an array with a negative dimension")
        nbytes = _I64_AT(data, i)[0]
        i += 8
        if nbytes != math.prod(shape) * dtype.itemsize:
            raise CodecError("an array whose bytes do not match its shape")
        end = _span(data, i, nbytes)
        array = np.frombuffer(bytearray(data[i:end]), dtype=dtype).reshape(shape)  # writable, our own copy
        return array, end
    if tag == 79:  # O
        name, i = _dec(data, i, depth + 1)
        attrs, i = _dec(data, i, depth + 1)
        if not isinstance(name, str) or not isinstance(attrs, dict):
            raise CodecError("a malformed object")
        cls = _result_types().get(name)
        if cls is not None:
            try:
                return cls(**{f.name: _tuples(attrs[f.name]) for f in fields(cls)}), i
            except (KeyError, TypeError, ValueError):
                pass
        return types.SimpleNamespace(**attrs), i
    raise CodecError(f"an unknown tag {bytes([tag])!r}")


def _tuples(v: Any) -> Any:
    return tuple(v) if isinstance(v, list) else v


# --------------------------------------------------------------------------------------------
# framing on a stream socket
# --------------------------------------------------------------------------------------------
_REQUEST = struct.Struct("<II")  # a request's pickle: its bytes, its out-of-band buffers
_BUFFER = struct.Struct("<BBQ")  # an out-of-band buffer: what follows (below), its slot, its bytes
_NEW, _KEEP, _SAME, _READONLY = 0, 1, 2, 4  # its bytes follow / follow, kept in the slot / are the slot's; a flag
KEEP_MIN = 1 << 16  #: bytes: a buffer this large (an image) goes out of band, kept by both ends, resent once changed
KEEP_MAX = 1 << 24  #: bytes: a buffer larger than this is sent each time (a copy kept on each side would cost more)
KEEP_SLOTS = 4  #: buffers kept (a block's image and depth, another block's)


def _scalar(x: np.generic) -> tuple:
    """A numpy scalar as its type and its Python value: ``numpy.float64(0.5)`` pickles as the
    type (a reference, once per pickle) and a float, where numpy's own reduction pickles its
    dtype and its bytes (some 2 us each way per scalar: a pose of three is most of a call's
    pickle). Exact for these types (a float64 is a Python float; float32, the integers and bool
    widen and narrow back unchanged), so the student's block gets the same values of the same types."""
    return type(x), (x.item(),)


def _small_array(a: np.ndarray) -> tuple:
    """A small numeric array (a target point, a pose: under ``KEEP_MIN`` bytes, C order) as its
    bytes, dtype string and shape, rebuilt by :func:`_array`: numpy's own reduction pickles the
    dtype as an object (some 3 us each way). Writable or not as it was, as numpy's in-band pickle
    makes it; any other array as numpy pickles it."""
    if a.dtype.kind in "biufc" and a.nbytes < KEEP_MIN and a.flags.c_contiguous and a.dtype.fields is None:
        data = memoryview(a)  # (bytes(a) of a 0-d integer array would be that many zero bytes)
        return _array, ((bytearray if a.flags.writeable else bytes)(data), a.dtype.str, a.shape)
    return a.__reduce_ex__(5)


def _array(data: bytes | bytearray, dtype: str, shape: tuple) -> np.ndarray:
    """The student's side of :func:`_small_array`."""
    return np.frombuffer(data, dtype).reshape(shape)


_REQUEST_REDUCERS: dict[type, Any] = {t: _scalar for t in (np.float64, np.float32, np.int64, np.int32, np.bool_)}
_REQUEST_REDUCERS[np.ndarray] = _small_array


class _RequestPickler(pickle.Pickler):
    """The trusted side's pickler: numpy scalars by :func:`_scalar`, small arrays by
    :func:`_small_array`, everything else as ``pickle.dumps``."""

    dispatch_table = {**copyreg.dispatch_table, **_REQUEST_REDUCERS}


def _dumps(value: Any, buffer_callback: Any) -> bytes:
    out = io.BytesIO()
    _RequestPickler(out, protocol=5, buffer_callback=buffer_callback).dump(value)
    return out.getvalue()


class Channel:
    """Values over a stream socket, each direction in its own format. Reads what the socket has
    (usually a whole message in one call) into a buffer of its own.

    The student's replies are this module's plain values (a 4-byte little-endian length, then
    :func:`encode`'s bytes), decoded by :func:`decode`: a pickle from the student's process would
    run their code in the trusted one. The trusted side's requests are pickled (fast, in C; it is
    the student's process that unpickles them, and a pickle from the trusted side is no risk to
    it; numpy scalars and small arrays by :class:`_RequestPickler`'s cheaper reductions): the pickle's length and its out-of-band buffers' count (two 4-byte lengths), each such
    buffer's head (``_BUFFER``), the pickle, then the buffers' bytes, in one ``sendmsg`` from the
    arrays' own memory. An array of ``KEEP_MIN`` bytes or more (an image) goes out of band and,
    up to ``KEEP_MAX`` bytes, is kept by both ends in one of ``KEEP_SLOTS`` slots; when a later
    request carries the same bytes (compared in full: the trusted side keeps a copy), its head
    names the slot and the bytes are not sent again: the ``red_share`` calls of one frame send
    the frame once. The student's process gets every buffer as a fresh copy of its own (writable
    unless the trusted side's array was not), so what a block does to its argument changes
    nothing the next call gets.
    ``trusted_peer`` says which end this is: True in the student's process (its peer, qcarlab, is
    trusted)."""

    def __init__(self, sock: socket.socket, trusted_peer: bool):
        self.sock, self.trusted_peer = sock, trusted_peer
        self.buf = bytearray()
        self.chunk = bytearray(1 << 16)
        self.sent: list[tuple[int, np.ndarray]] = []  # the trusted side: (slot, a copy), least recently used first
        self.kept: dict[int, bytes] = {}  # the student's side: slot -> the bytes
        self.out_of_band: list[memoryview] = []  # the trusted side: the request's large buffers, while it is sent
        self.in_band = functools.partial(_in_band, out_of_band=self.out_of_band)

    def send(self, value: Any) -> None:
        if self.trusted_peer:  # the student's reply
            data = encode(value)
            if len(data) < 65536:
                self.sock.sendall(_LEN.pack(len(data)) + data)
            else:  # (not copied again to prepend the length)
                _send_parts(self.sock, [_LEN.pack(len(data)), data])
            return
        buffers = self.out_of_band  # (filled by self.in_band while pickling)
        buffers.clear()
        data = _dumps(value, self.in_band)
        if not buffers:
            self.sock.sendall(_REQUEST.pack(len(data), 0) + data)
            return
        try:
            heads, parts = [_REQUEST.pack(len(data), len(buffers))], []
            for raw in buffers:
                kind, slot = self._keep(raw) if raw.nbytes <= KEEP_MAX else (_NEW, 0)
                heads.append(_BUFFER.pack(kind | (_READONLY if raw.readonly else 0), slot, raw.nbytes))
                if kind != _SAME:
                    parts.append(raw)
            if parts:
                _send_parts(self.sock, [b"".join(heads), data, *parts])
            else:
                self.sock.sendall(b"".join(heads) + data)
        finally:
            buffers.clear()  # (views of the caller's arrays)

    def _keep(self, raw: memoryview) -> tuple[int, int]:
        """(_SAME, its slot) for bytes the student's process keeps already, else (_KEEP, the slot to keep them in)."""
        now = np.frombuffer(raw, np.uint8)
        for i in range(len(self.sent) - 1, -1, -1):  # the most recently sent first
            slot, copy = self.sent[i]
            if copy.size == now.size and _same(copy, now):
                self.sent.append(self.sent.pop(i))
                return _SAME, slot
        slot = len(self.sent) if len(self.sent) < KEEP_SLOTS else self.sent.pop(0)[0]
        self.sent.append((slot, now.copy()))
        return _KEEP, slot

    def recv(self) -> Any:
        """The next value; EOFError when the other side closed (or died)."""
        if self.trusted_peer:
            return self._request()
        buf = self.buf
        while len(buf) < 4:
            self._more()
        n = _U32_AT(buf, 0)[0]
        if n > MAX_MESSAGE:
            raise CodecError(f"a message of {n} bytes is over the {MAX_MESSAGE // 2**20} MB limit")
        del buf[:4]
        if n > len(buf) + len(self.chunk):  # a large value (an image): read straight into its own buffer
            data = bytearray(n)
            self._fill(memoryview(data))
            return decode(bytes(data))
        return decode(self._take(n))

    def _request(self) -> Any:
        buf = self.buf
        while len(buf) < _REQUEST.size:
            self._more()
        n, count = _REQUEST.unpack_from(buf)
        if n > MAX_MESSAGE or count > MAX_ITEMS:
            raise CodecError(f"a message of {n} bytes and {count} buffers")
        end = _REQUEST.size + count * _BUFFER.size + n
        if not count and end <= len(buf):  # a call with numbers: the whole message read already
            data = bytes(buf[_REQUEST.size:end])
            del buf[:end]
            return pickle.loads(data)
        del buf[:_REQUEST.size]
        heads = self._take(count * _BUFFER.size) if count else b""
        data = self._take(n)
        buffers: list[Any] = []
        for i in range(count):
            kind, slot, size = _BUFFER.unpack_from(heads, i * _BUFFER.size)
            if size > MAX_MESSAGE:
                raise CodecError(f"a buffer of {size} bytes is over the {MAX_MESSAGE // 2**20} MB limit")
            if kind & ~_READONLY == _SAME:
                kept = self.kept.get(slot)
                if kept is None or len(kept) != size:
                    raise CodecError(f"a buffer that names slot {slot}, which holds no such bytes")
                buffer = bytearray(kept)
            else:
                buffer = bytearray(size)
                self._fill(memoryview(buffer))
                if kind & ~_READONLY == _KEEP:
                    self.kept[slot] = bytes(buffer)
            buffers.append(bytes(buffer) if kind & _READONLY else buffer)
        return pickle.loads(data, buffers=buffers)

    def _take(self, n: int) -> bytes:
        """The next ``n`` bytes."""
        buf = self.buf
        if n > len(buf) + len(self.chunk):
            data = bytearray(n)
            self._fill(memoryview(data))
            return bytes(data)
        while len(buf) < n:
            self._more()
        data = bytes(buf[:n])
        del buf[:n]
        return data

    def _fill(self, view: memoryview) -> None:
        """``view`` filled with the next bytes: what was read already, then straight from the socket."""
        have = min(len(self.buf), len(view))
        view[:have] = self.buf[:have]
        del self.buf[:have]
        while have < len(view):
            k = self.sock.recv_into(view[have:])
            if k == 0:
                raise EOFError("the other side closed the connection")
            have += k

    def _more(self) -> None:
        k = self.sock.recv_into(self.chunk)
        if k == 0:
            raise EOFError("the other side closed the connection")
        self.buf += memoryview(self.chunk)[:k]


def _in_band(buffer: pickle.PickleBuffer, out_of_band: list[memoryview]) -> bool:
    """A pickle's buffer: True (in the pickle) when small, else its bytes go in ``out_of_band``."""
    raw = buffer.raw()
    if raw.nbytes < KEEP_MIN:
        return True
    out_of_band.append(raw)
    return False


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two byte arrays of one size hold the same bytes: a sample of them first (a new
    frame differs from the last one nearly everywhere), then all of them, 8 at a time where they can."""
    if a.size % 8 == 0:
        a, b = a.view(np.uint64), b.view(np.uint64)
    step = max(1, a.size // 64)
    return bool(np.array_equal(a[::step], b[::step]) and np.array_equal(a, b))


def _send_parts(sock: socket.socket, parts: list[Any]) -> None:
    """``parts`` one after the other, in as few ``sendmsg`` calls as the socket takes them."""
    views = [memoryview(p) for p in parts]
    while views:
        sent = sock.sendmsg(views)
        while views and sent >= views[0].nbytes:
            sent -= views.pop(0).nbytes
        if views and sent:
            views[0] = views[0][sent:]


__all__ = ["Channel", "CodecError", "decode", "encode"]
