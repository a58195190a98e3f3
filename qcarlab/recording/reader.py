"""Reading a recording back: ``qcarlab replay info`` and the data a replayed car plays.

    rec = open_recording("run.mcap")          # an MCAP (ours or any with Foxglove schemas)
    rec.info()                                # topics, schemas, counts, duration, rates
    tape = rec.tape()                         # readouts, commands, truth, scans, lab values
    for t, frame in tape.rgbd():              # camera frames, decoded one by one on demand

Read with the ``mcap`` library (protobuf messages through ``mcap-protobuf-support``, from the
schemas stored in the file). A file whose writer was killed (no summary at the end) is read
record by record up to its last complete chunk; :attr:`Recording.complete` says which it was.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from dataclasses import fields as dc_fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from qcarlab.car.base import Command, Readout, Truth
from qcarlab.car.lamps import ALL_OFF
from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.errors import InputError
from qcarlab.recording import channels as C
from qcarlab.recording import require
from qcarlab.sensors import CSIFrames, LidarScan, RGBDFrame

MAGIC = b"\x89MCAP0\r\n"
EPS = 1e-6  # s: two times closer than this are the same instant


# ------------------------------------------------------------------------------------ the tape
@dataclass
class Tape:
    """What a replayed car plays: light streams in memory, camera frames streamed on demand.

    ``rgbd()`` / ``csi()`` return iterators of ``(when, load)`` in time order, ``load()`` decoding
    the frame; a compact recording's RGBD frames without depth carry the latest depth before them.
    ``when`` (and ``scan_ticks``) is the time of the tick at which the lab first read the frame
    (the frame's own time in recordings that do not say). ``steps`` holds, beside each command, the
    (t, dt) the lab's step was given at its tick (None when not recorded). ``realtime``: recorded
    from a car whose clock is the wall's (a real car, a served or real-time simulator), whose
    ticks a replay plays one by one.
    """

    source: str
    params: QCarParams = DEFAULT_PARAMS
    throttle_limit: float | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    readouts: list[Readout] = field(default_factory=list)
    commands: list[tuple[float, Command, bool]] = field(default_factory=list)
    steps: list[tuple[float, float] | None] = field(default_factory=list)
    truths: list[Truth] = field(default_factory=list)
    scans: list[LidarScan] = field(default_factory=list)
    scan_ticks: list[float] = field(default_factory=list)
    lab: list[dict[str, Any]] = field(default_factory=list)
    rgbd: Callable[[], Iterator[tuple[float, Callable[[], RGBDFrame]]]] | None = None
    csi: Callable[[], Iterator[tuple[float, Callable[[], CSIFrames]]]] | None = None
    notes: list[str] = field(default_factory=list)  # what the replay should know (lossy frames, ...)
    span: tuple[float, float] | None = None  # (start, end) when the source knows it (a rosbag2)
    realtime: bool = False

    @property
    def start(self) -> float:
        """The first instant of the tape (s, car time)."""
        if self.span is not None:
            return self.span[0]
        times = [s[0].t for s in (self.readouts, self.scans, self.truths) if s]
        times += [self.commands[0][0]] if self.commands else []
        return min(times) if times else 0.0

    @property
    def end(self) -> float:
        if self.span is not None:
            return self.span[1]
        times = [s[-1].t for s in (self.readouts, self.scans, self.truths) if s]
        times += [self.commands[-1][0]] if self.commands else []
        return max(times) if times else 0.0


# ------------------------------------------------------------------------------------ decoding
def decode_color(msg: Any) -> np.ndarray:
    """foxglove CompressedImage (jpeg/png) or RawImage (bgr8, rgb8, mono8) -> BGR uint8."""
    fmt = getattr(msg, "format", None)
    if fmt is not None and hasattr(msg, "data") and not hasattr(msg, "encoding"):
        img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise InputError(f"recording: cannot decode a {fmt or 'compressed'} image")
        return img
    return raw_color(msg.encoding, msg.width, msg.height, msg.step, msg.data)


def raw_color(encoding: str, width: int, height: int, step: int, data: bytes) -> np.ndarray:
    enc = encoding.lower()
    channels = {"bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4, "mono8": 1, "8uc1": 1, "8uc3": 3}.get(enc)
    if channels is None:
        raise InputError(f"recording: colour image encoding {encoding!r} is not supported "
                         "(bgr8, rgb8, bgra8, rgba8, mono8)")
    rows = np.frombuffer(data, np.uint8)[: height * step].reshape(height, step)
    img = rows[:, : width * channels].reshape(height, width, channels)
    if enc in ("rgb8", "rgba8"):
        return cv2.cvtColor(img, cv2.COLOR_RGB2BGR if channels == 3 else cv2.COLOR_RGBA2BGR)
    if enc == "bgra8":
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if channels == 1:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    return img.copy()


def raw_depth(encoding: str, width: int, height: int, step: int, data: bytes, big_endian: bool = False) -> np.ndarray:
    """A depth image -> float32 metres: 32FC1 (m) as is, 16UC1 / mono16 (mm) / 1000; 0 = no data."""
    enc = encoding.upper()
    order = ">" if big_endian else "<"
    if enc == "32FC1":
        dtype, scale = np.dtype(order + "f4"), None
    elif enc in ("16UC1", "MONO16"):
        dtype, scale = np.dtype(order + "u2"), 1e-3
    else:
        raise InputError(f"recording: depth image encoding {encoding!r} is not supported (32FC1, 16UC1)")
    rows = np.frombuffer(data, np.uint8)[: height * step].reshape(height, step)
    d = rows[:, : width * dtype.itemsize].copy().view(dtype).reshape(height, width)
    if scale is None:
        out = d.astype(np.float32)
        out[~np.isfinite(out)] = 0.0
        return out
    return d.astype(np.float32) * np.float32(scale)


def decode_depth(msg: Any) -> np.ndarray:
    if hasattr(msg, "encoding"):
        return raw_depth(msg.encoding, msg.width, msg.height, msg.step, msg.data)
    img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)  # a 16-bit PNG
    if img is None or img.ndim != 2:
        raise InputError("recording: cannot decode a compressed depth image")
    return img.astype(np.float32) * (np.float32(1e-3) if img.dtype == np.uint16 else np.float32(1.0))


def _stamp(msg: Any) -> int | None:
    ts = getattr(msg, "timestamp", None)
    if ts is None:
        return None
    return int(ts.seconds) * 1_000_000_000 + int(ts.nanos)


def _params(values: dict[str, str]) -> QCarParams:
    known = {f.name: f for f in dc_fields(QCarParams)}
    changes: dict[str, Any] = {}
    for name, text in values.items():
        if name not in known:
            continue
        try:
            value = float(text)
        except ValueError:
            continue
        default = getattr(DEFAULT_PARAMS, name)
        value = int(value) if isinstance(default, int) and not isinstance(default, bool) else value
        if value != default and math.isfinite(value):
            changes[name] = value
    return replace(DEFAULT_PARAMS, **changes)


# ------------------------------------------------------------------------------------ the file
class Recording:
    """An MCAP file opened for reading."""

    def __init__(self, path: str | Path):
        require("reading a recording", "mcap")
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"recording {self.path}: no such file")
        with self.path.open("rb") as f:
            head = f.read(len(MAGIC))
        if head != MAGIC:
            raise InputError(f"recording {self.path}: not an MCAP file (no MCAP magic at the start)")
        self.complete = self._has_summary()
        self.metadata = self._metadata()

    def _records(self, f, topics: list[str] | None = None):
        """(schema, channel, message) of every message, in log-time order from a complete file, in
        file order, record by record, from a cut-off one (up to its partial last chunk)."""
        if self.complete:
            from mcap.reader import make_reader

            yield from make_reader(f).iter_messages(topics=topics)
            return
        from mcap.records import Channel, Message, Schema
        from mcap.stream_reader import StreamReader

        wanted = set(topics) if topics is not None else None
        schemas: dict[int, Any] = {}
        channels: dict[int, Any] = {}
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                if isinstance(rec, Message):
                    ch = channels.get(rec.channel_id)
                    if ch is not None and (wanted is None or ch.topic in wanted):
                        yield schemas.get(ch.schema_id), ch, rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Schema):
                    schemas[rec.id] = rec
        except Exception:  # the partial record where the writer was killed: the end of what there is
            return

    def _has_summary(self) -> bool:
        from mcap.reader import make_reader

        try:
            with self.path.open("rb") as f:
                return make_reader(f).get_summary() is not None
        except Exception:
            return False

    def _metadata(self) -> dict[str, dict[str, Any]]:
        from mcap.records import Metadata
        from mcap.stream_reader import StreamReader

        out: dict[str, dict[str, Any]] = {}
        records: list[Any] = []
        with self.path.open("rb") as f:
            try:
                if self.complete:
                    from mcap.reader import make_reader

                    records = list(make_reader(f).iter_metadata())
                else:
                    for rec in StreamReader(f, skip_magic=False).records:
                        if isinstance(rec, Metadata):
                            records.append(rec)
            except Exception:  # a cut-off file: what was read before the cut
                pass
        for m in records:
            values = {}
            for k, v in m.metadata.items():
                try:
                    values[k] = json.loads(v)
                except ValueError:
                    values[k] = v
            out[m.name] = values
        return out

    # --- messages -------------------------------------------------------------------------------
    def messages(self, topics: list[str] | None = None, decode: bool | set[str] = True
                 ) -> Iterator[tuple[str, str | None, int, Any]]:
        """(topic, schema name, log time ns, message) in log-time order (file order for a cut-off
        file). Decoded (JSON as dicts, protobuf as message objects) when ``decode`` is True or
        names the topic; raw bytes otherwise."""
        decoders: dict[int, Callable[[bytes], Any]] = {}
        factory = None
        with self.path.open("rb") as f:
            try:
                for schema, channel, message in self._records(f, topics):
                    name = schema.name if schema is not None else None
                    payload: Any = message.data
                    if decode is True or (decode and channel.topic in decode):
                        if channel.message_encoding == "json":
                            payload = json.loads(payload)
                        else:
                            fn = decoders.get(channel.id)
                            if fn is None:
                                if factory is None:
                                    require("reading a recording", "mcap_protobuf")
                                    from mcap_protobuf.decoder import DecoderFactory

                                    factory = DecoderFactory()
                                fn = factory.decoder_for(channel.message_encoding, schema)
                                if fn is None:
                                    raise InputError(f"recording {self.path}: topic {channel.topic} is "
                                                     f"{channel.message_encoding!r}, which qcarlab cannot decode")
                                decoders[channel.id] = fn
                            payload = fn(payload)
                    yield channel.topic, name, message.log_time, payload
            except InputError:
                raise
            except Exception as exc:
                if self.complete:
                    raise InputError(f"recording {self.path}: unreadable ({type(exc).__name__}: {exc})") from None
                # a cut-off file ends in a partial record: everything before it has been read

    def info(self) -> dict[str, Any]:
        """Topics (schema, encoding, count, first/last time, rate), duration, metadata."""
        topics: dict[str, dict[str, Any]] = {}
        schemas: dict[str, tuple[str | None, str]] = {}
        with self.path.open("rb") as f:
            try:
                for schema, channel, message in self._records(f):
                    entry = topics.get(channel.topic)
                    if entry is None:
                        entry = topics[channel.topic] = {"count": 0, "first_ns": message.log_time, "last_ns": message.log_time}
                        schemas[channel.topic] = (schema.name if schema else None, channel.message_encoding)
                    entry["count"] += 1
                    entry["first_ns"] = min(entry["first_ns"], message.log_time)
                    entry["last_ns"] = max(entry["last_ns"], message.log_time)
            except Exception:
                if self.complete:
                    raise
        if not topics and not self.complete:
            raise InputError(f"{self.path}: the recording was cut off before its first message (an interrupted "
                             "write or a partial copy): nothing to show")
        first = min((e["first_ns"] for e in topics.values()), default=0)
        last = max((e["last_ns"] for e in topics.values()), default=0)
        out_topics = {}
        for topic in sorted(topics):
            e = topics[topic]
            span = (e["last_ns"] - e["first_ns"]) / 1e9
            name, encoding = schemas[topic]
            out_topics[topic] = {
                "schema": name, "encoding": encoding, "count": e["count"],
                "first_s": (e["first_ns"] - first) / 1e9, "last_s": (e["last_ns"] - first) / 1e9,
                "rate_hz": (e["count"] - 1) / span if span > 0 and e["count"] > 1 else None,
            }
        qc = self.metadata.get("qcarlab", {})
        return {
            "file": str(self.path), "format": "mcap", "bytes": self.path.stat().st_size,
            "complete": self.complete, "duration_s": (last - first) / 1e9,
            "messages": sum(e["count"] for e in topics.values()),
            "start_ns": first, "profile": qc.get("profile"), "world": qc.get("world"),
            "car": (self.metadata.get("qcarlab.car") or {}).get("name"), "command": qc.get("argv"),
            "topics": out_topics,
        }

    # --- the tape -------------------------------------------------------------------------------
    def tape(self) -> Tape:
        """The recording as a replayed car plays it."""
        qc = self.metadata.get("qcarlab", {})
        car_meta = self.metadata.get("qcarlab.car", {})
        t0 = int(qc.get("t0_ns", 0) or 0)
        tape = Tape(source=str(self.path), params=_params(self.metadata.get("qcarlab.params", {})),
                    throttle_limit=car_meta.get("throttle_limit"), metadata=qc,
                    realtime=car_meta.get("stepped") is False)
        frame_t: dict[tuple[str, int], float] = {}
        frame_tick: dict[tuple[str, int], float] = {}  # when the lab first read the frame (recorded since v2.1)
        angles_at: list[tuple[int, np.ndarray]] = []
        depth_in: dict[int, bool] = {}
        laser: list[tuple[int, Any]] = []
        light = [C.READOUT, C.COMMAND, C.TRUTH, C.LAB, C.FRAMES, C.LIDAR]
        has_color = has_csi = False
        for topic, _name, ns, msg in self.messages(light + [C.COLOR] + list(C.CSI.values()), decode=set(light)):
            if topic in C.PB_SCHEMAS and not isinstance(msg, dict):  # version 2: protobuf (1: JSON)
                msg = C.pb_dict(msg)
            if topic == C.READOUT:
                tape.readouts.append(_readout(msg))
            elif topic == C.COMMAND:
                tape.commands.append((float(msg["t"]), Command(float(msg["throttle"]), float(msg["steering"]),
                                                               tuple(float(v) for v in msg.get("leds", ()))),
                                      bool(msg.get("stop", False))))
                step_dt = float(msg.get("step_dt", 0.0) or 0.0)  # (proto3: 0 when not recorded; a tick's dt is > 0)
                tape.steps.append((float(msg.get("step_t", 0.0)), step_dt) if step_dt > 0.0 else None)
            elif topic == C.TRUTH:
                tape.truths.append(Truth(**{k: float(msg[k]) for k in C.TRUTH_FIELDS}))
            elif topic == C.LAB:
                tape.lab.append(msg)
            elif topic == C.FRAMES:
                stamp = int(msg.get("stamp", ns))
                frame_t[(msg["sensor"], stamp)] = float(msg["t"])
                if msg.get("tick") is not None:
                    frame_tick[(msg["sensor"], stamp)] = float(msg["tick"])
                if msg.get("angles"):
                    angles_at.append((stamp, C.decode_angles(msg["angles"])))
                if msg["sensor"] == "rgbd":
                    depth_in[stamp] = bool(msg.get("depth", True))
            elif topic == C.LIDAR:
                laser.append((_stamp(msg) or ns, msg))
            elif topic == C.COLOR:
                has_color = True
            else:
                has_csi = True
        for seq in (tape.readouts, tape.truths):
            seq.sort(key=lambda r: r.t)
        order = sorted(range(len(tape.commands)), key=lambda i: tape.commands[i][0])  # (stable: a tick's in order)
        tape.commands = [tape.commands[i] for i in order]
        tape.steps = [tape.steps[i] for i in order]
        angles_at.sort(key=lambda a: a[0])
        k = -1
        for stamp, msg in sorted(laser, key=lambda m: m[0]):
            while k + 1 < len(angles_at) and angles_at[k + 1][0] <= stamp:
                k += 1
            ranges = np.asarray(msg.ranges, dtype=np.float64)
            ranges = np.where(np.isfinite(ranges) & (ranges > 0.0), ranges, 0.0)
            if k >= 0 and len(angles_at[k][1]) == len(ranges):
                angles = angles_at[k][1]
            else:
                angles = np.linspace(msg.start_angle, msg.end_angle, len(ranges)) if len(ranges) else np.zeros(0)
            t = frame_t.get(("lidar", stamp), (stamp - t0) / 1e9)
            tape.scans.append(LidarScan(t=t, angles=angles, ranges=ranges))
            when = frame_tick.get(("lidar", stamp), t)
            tape.scan_ticks.append(max(when, tape.scan_ticks[-1]) if tape.scan_ticks else when)
        if has_color:
            tape.rgbd = lambda: self._rgbd_frames(frame_t, depth_in, t0, frame_tick)
            if qc.get("profile", "compact") != "exact":
                tape.notes.append(f"camera frames are lossy (JPEG colour, depth every {C.DEPTH_EVERY}th frame held "
                                  "between): camera decisions can differ from the recorded ones; record with "
                                  "--record-exact for an exact replay")
        if has_csi:
            tape.csi = lambda: self._csi_frames(frame_t, t0, frame_tick)
        return tape

    def _rgbd_frames(self, frame_t, depth_in, t0, frame_tick) -> Iterator[tuple[float, Callable[[], RGBDFrame]]]:
        depth_msg = None
        pending = None  # (stamp, colour message) waiting for its depth
        for topic, _name, ns, msg in self.messages([C.COLOR, C.DEPTH]):
            stamp = _stamp(msg) or ns
            if topic == C.DEPTH:
                depth_msg = msg
                if pending is not None and pending[0] == stamp:
                    yield self._rgbd_item(pending, depth_msg, frame_t, t0, frame_tick)
                    pending = None
                continue
            if pending is not None:
                yield self._rgbd_item(pending, depth_msg, frame_t, t0, frame_tick)
            pending = (stamp, msg)
            if not depth_in.get(stamp, False):
                yield self._rgbd_item(pending, depth_msg, frame_t, t0, frame_tick)
                pending = None
        if pending is not None:
            yield self._rgbd_item(pending, depth_msg, frame_t, t0, frame_tick)

    @staticmethod
    def _rgbd_item(pending, depth_msg, frame_t, t0, frame_tick):
        stamp, color_msg = pending
        t = frame_t.get(("rgbd", stamp), (stamp - t0) / 1e9)

        def load() -> RGBDFrame:
            color = decode_color(color_msg)
            depth = decode_depth(depth_msg) if depth_msg is not None else np.zeros(color.shape[:2], np.float32)
            return RGBDFrame(t=t, color=color, depth=depth)

        return frame_tick.get(("rgbd", stamp), t), load

    def _csi_frames(self, frame_t, t0, frame_tick) -> Iterator[tuple[float, Callable[[], CSIFrames]]]:
        views: dict[str, Any] = {}
        current = None
        topics = {v: k for k, v in C.CSI.items()}
        for topic, _name, ns, msg in self.messages(list(C.CSI.values())):
            stamp = _stamp(msg) or ns
            if current is not None and stamp != current and len(views) == 4:
                yield self._csi_item(current, dict(views), frame_t, t0, frame_tick)
            current = stamp
            views[topics[topic]] = msg
        if current is not None and len(views) == 4:
            yield self._csi_item(current, dict(views), frame_t, t0, frame_tick)

    @staticmethod
    def _csi_item(stamp, views, frame_t, t0, frame_tick):
        t = frame_t.get(("csi", stamp), (stamp - t0) / 1e9)

        def load() -> CSIFrames:
            return CSIFrames(t=t, **{v: decode_color(views[v]) for v in C.CSI_VIEWS})

        return frame_tick.get(("csi", stamp), t), load


def _readout(msg: dict[str, Any]) -> Readout:
    return Readout(
        t=float(msg["t"]), encoder_counts=int(msg["encoder_counts"]), tach=float(msg["tach"]),
        motor_current=float(msg["motor_current"]), battery_voltage=float(msg["battery_voltage"]),
        gyro=np.asarray(msg["gyro"], dtype=np.float64), accel=np.asarray(msg["accel"], dtype=np.float64),
        steering=float(msg.get("steering", 0.0)), throttle=float(msg.get("throttle", 0.0)),
        leds=tuple(float(v) for v in msg.get("leds", ())) or ALL_OFF,
    )


def is_rosbag(path: Path) -> bool:
    """A rosbag2 folder (metadata.yaml) or one of its .db3 files."""
    return (path.is_dir() and (path / "metadata.yaml").is_file()) or path.suffix == ".db3"


def open_recording(path: str | Path, topics: dict[str, str] | None = None):
    """An MCAP recording, or a rosbag2 (folder, .db3, or an MCAP written by ROS 2) with ``topics``."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"recording {p}: no such file or folder")
    if is_rosbag(p) or topics:
        from qcarlab.recording.rosbag import RosBag

        return RosBag(p, topics)
    if p.is_dir():
        raise InputError(f"recording {p}: a folder without metadata.yaml is not a rosbag2")
    return Recording(p)
