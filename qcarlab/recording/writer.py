"""The :class:`Recorder`: everything a run produced, as an MCAP file and/or a live Foxglove view.

    rec = Recorder("run.mcap")                  # or Recorder(None, live=LiveView(port=8765))
    rec.readout(car.read()); rec.scan(car.read_lidar()); rec.log_values(t, {"v_ref": 0.3})
    rec.close()                                 # writes the summary (index, statistics)

Written with foxglove-sdk's MCAP writer: messages go into zstd-compressed chunks of about 1 MB as
they come (COMPRESSION_LEVEL), so a run stopped by Ctrl-C or SIGTERM (the CLI turns SIGTERM into Ctrl-C) closes the
file with its summary, and a run killed outright (SIGKILL) loses at most the chunk being filled
(and the last few milliseconds of messages, below); :mod:`qcarlab.recording.reader` reads such a
file without its summary.

The per-tick messages (readouts, commands, the truth, the lab's values, LIDAR scans, and the poses
and transforms they give) are queued as they come and written in batches, at the latest
FLUSH_PERIOD_S (20 ms) after they came: a run pays the encoding in one tight loop rather than a
little of it at every tick, where the simulator's own work has pushed the recorder's code and data
out of the caches. Camera frames join the same queue, in their place: a compact frame's JPEG
colour and millimetre depth are encoded meanwhile on a thread of their own (:class:`_Frames`;
OpenCV's encoder and NumPy let go of the interpreter lock), from a copy, while the lab goes on with
the frame, and written when encoded (at most _Frames.WAITING images wait; then the caller does).
Every message keeps its place and its exact time: the file is the same whichever thread encoded.
A run killed outright (SIGKILL) also loses the images still being encoded (a few frames at most).

A command's ``--record`` runs this Recorder in a process of its own where it can
(:mod:`qcarlab.recording.process`: the same calls, the same file); in the lab's process it runs
for a live view, on one core, and for Python code that makes one directly.

Two profiles for the cameras (the rest is always lossless):

- ``compact`` (default): colour as JPEG (quality 80, 4:2:0) every frame, depth as 16-bit
  millimetres (the D435's own z16 format) every 15th frame (2 Hz at 30 fps). A 60 s lane-follow
  is about 70 MB. Replays of camera labs see the JPEG colour and the held depth, so their decisions can
  differ slightly from the recorded ones (LIDAR labs replay exactly).
- ``exact``: colour as raw bgr8 and depth as 32-bit float metres, every frame: a replay gives
  the lab the very pixels it had (about 1.3 MB per RGBD frame after compression).
"""

from __future__ import annotations

import json
import math
import os
import queue
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.errors import InputError
from qcarlab.recording import channels as C
from qcarlab.recording import require

VERSION = 2  # 2: readouts, commands and truth as protobuf (1: JSON)
COMPRESSION_THREADS = 1  # zstd compresses the chunks on a thread of its own, beside the run
COMPRESSION_LEVEL = {"compact": 1,  # zstd's fastest: most of the file is JPEG, which no level shrinks (3: 2.5x the CPU, 7 % smaller)
                     "exact": 3}  # zstd's default: raw images, which level 3 makes 11 % smaller than level 1
CALIBRATION_EVERY = 30  # RGBD frames between two camera calibration messages
BALLS_PERIOD = 0.1  # s between two updates of the moving balls in the scene
MOUNTS_PERIOD_NS = 1_000_000_000  # the static sensor transforms are repeated once a second
POSE_PERIOD_NS = 20_000_000  # poses and transforms: 50 Hz (the readouts and the truth: every one)
_PB_POSE, _PB_TF, _PB_SCAN = "pb:PoseInFrame", "pb:FrameTransforms", "pb:LaserScan"  # encoded by messages.pb_*
FLUSH_EVENTS = 256  # the per-tick messages are written in batches of at most this many ...
FLUSH_PERIOD_S = 0.02  # ... or this old (wall clock): what a live viewer waits at most


class Recorder:
    """Writes the channels of :mod:`~qcarlab.recording.channels` to ``path`` (MCAP) and/or ``live``."""

    def __init__(
        self,
        path: str | Path | None,
        *,
        profile: str = "compact",
        live: Any = None,
        params: QCarParams = DEFAULT_PARAMS,
        metadata: dict[str, Any] | None = None,
        t0_ns: int | None = None,
        live_topics: Any = None,
    ):
        require("--record" if path is not None else "--live")
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        from qcarlab.control.pose import BicyclePoseEstimator
        from qcarlab.control.speed import basic_speed_estimation
        from qcarlab.recording import messages

        self._M = messages  # (imported here: foxglove is the optional extra)
        self._speed = basic_speed_estimation
        self._estimator_cls = BicyclePoseEstimator

        self.profile = C.check_profile(profile)
        self.exact = profile == "exact"
        self.params = params
        self.path = Path(path) if path is not None else None
        self.t0_ns = time.time_ns() if t0_ns is None else int(t0_ns)  # (given: a RecorderProcess's child)
        self.ctx = foxglove.Context()
        self.writer = None
        if self.path is not None:
            C.check_record_path(self.path)
            try:
                self.writer = foxglove.open_mcap(
                    self.path, allow_overwrite=True, context=self.ctx,
                    writer_options=MCAPWriteOptions(compression=MCAPCompression.Zstd, compression_threads=COMPRESSION_THREADS,
                                                    compression_level=COMPRESSION_LEVEL[profile],
                                                    profile=""))
            except Exception as exc:  # the SDK's own error type: a path we cannot write
                raise InputError(f"--record {self.path}: cannot write ({exc})") from None
        self._channels: dict[str, Any] = {}
        self._pb_schema: bytes | None = None
        self.counts: dict[str, int] = {}  # messages written per topic
        self._pending: deque[tuple[Any, Any]] = deque()  # the messages not written yet: (fn, args) or (None, _Job)
        self._jobs: deque[_Job] = deque()  # the images in the queue (encoded or being encoded), in order
        self._frames = _Frames()
        self._flush_lock = threading.Lock()
        self._flushed_at = time.monotonic()
        self.live = live
        self._scene: dict[str, Any] = {}  # the scene's entities by id, sent again to a live viewer who joins later
        self._scene_due = False
        if live is not None:
            # the channels this run will send exist before a viewer connects: it gets them in its
            # first advertisement (a channel advertised while a client is connected can refuse a
            # subscription that comes within milliseconds, foxglove-sdk 0.30). ``live_topics``: those
            # channels (None: all of them); one not among them is made when first sent.
            image = "RawImage" if self.exact else "CompressedImage"
            for topic, kind in ((C.READOUT, None), (C.COMMAND, None), (C.TRUTH, None), (C.LAB, None),
                                (C.LIDAR, _PB_SCAN), (C.COLOR, image), (C.DEPTH, "RawImage"),
                                (C.CALIBRATION, "CameraCalibration"), (C.POSE_TRUE, _PB_POSE),
                                (C.POSE_ESTIMATE, _PB_POSE), (C.TF, _PB_TF),
                                (C.SCENE, "SceneUpdate"), *((C.CSI[v], image) for v in C.CSI_VIEWS)):
                if live_topics is None or topic in live_topics:
                    self._channel(topic, kind)
            live.attach(self.ctx, on_subscribe=self._subscribed)
        self._angles: np.ndarray | None = None
        self._angles_src: Any = None  # a read-only angles array known to equal _angles
        self._rgbd_count = 0
        self._estimator = None
        self._last_readout_t: float | None = None
        self._truth_pose: tuple[float, float, float] | None = None
        self._has_truth = False
        self._world = None
        self._balls_t = -math.inf
        self._mounts_ns = -MOUNTS_PERIOD_NS
        self._pose_ns = -POSE_PERIOD_NS
        self.closed = False
        meta = {"version": VERSION, "profile": profile, "t0_ns": self.t0_ns, "argv": sys.argv[1:]}
        meta.update(metadata or {})
        self.metadata("qcarlab", meta)
        self.metadata("qcarlab.params", _params_dict(params))

    # --- plumbing -------------------------------------------------------------------------------
    def ns(self, t: float) -> int:
        return self.t0_ns + round(float(t) * 1e9)  # C.stamp_ns, inlined: it runs several times a tick

    def _channel(self, topic: str, kind: str | None = None):
        ch = self._channels.get(topic)
        if ch is None:
            if kind is None and topic in C.PB_SCHEMAS:  # qcarlab's own protobuf messages
                import foxglove

                if self._pb_schema is None:
                    self._pb_schema = C.pb_descriptor()
                ch = foxglove.Channel(topic, context=self.ctx, message_encoding="protobuf",
                                      schema=foxglove.Schema(name=C.PB_SCHEMAS[topic], encoding="protobuf",
                                                             data=self._pb_schema))
            elif kind is None:  # JSON with a named JSON Schema
                import foxglove

                name, schema = C.JSON_SCHEMAS[topic]
                ch = foxglove.Channel(topic, context=self.ctx, message_encoding="json",
                                      schema=foxglove.Schema(name=name, encoding="jsonschema",
                                                             data=json.dumps(schema).encode()))
            elif kind.startswith("pb:"):  # a Foxglove schema, the bytes encoded here (messages.pb_*)
                import foxglove
                import foxglove.messages as fm

                ch = foxglove.Channel(topic, context=self.ctx, message_encoding="protobuf",
                                      schema=getattr(fm, kind[3:]).get_schema())
            else:
                import foxglove.channels as fc

                ch = getattr(fc, kind + "Channel")(topic, context=self.ctx)
            self._channels[topic] = ch
        return ch

    def _wanted(self, topic: str, kind: str | None = None):
        """The channel if anyone listens (always, when writing a file); None for a live view with no
        subscriber, so nothing is encoded for nobody."""
        ch = self._channel(topic, kind)
        return ch if (self.writer is not None or ch.has_sinks()) else None

    def _log(self, topic: str, kind: str | None, msg: Any, ns: int) -> None:
        ch = self._wanted(topic, kind)
        if ch is None:
            return
        if kind is None:
            ch.base.log(msg if type(msg) is bytes else C.json_bytes(msg), ns)
        else:
            ch.log(msg, log_time=ns)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _bytes(self, topic: str, encode, ns: int, *args: Any) -> None:
        """A per-tick message: ``encode(*args)`` (its bytes) is only called when someone listens."""
        ch = self._channels.get(topic) or self._channel(topic)
        if self.writer is None and not ch.has_sinks():
            return
        ch.base.log(encode(*args), ns)
        counts = self.counts
        counts[topic] = counts.get(topic, 0) + 1

    def metadata(self, name: str, values: dict[str, Any]) -> None:
        """An MCAP metadata record (string values; others as JSON)."""
        if self.writer is not None:
            self.writer.write_metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()})

    def _subscribed(self, topic: str) -> None:
        if topic == C.SCENE:  # a viewer joined: the static scene was logged before they came
            self._scene_due = True

    def _resend_scene(self, ns: int) -> None:
        M = self._M
        self._scene_due = False
        if self._scene:
            self._log(C.SCENE, "SceneUpdate", M.scene_update(list(self._scene.values())), ns)

    # --- deferred: the per-tick messages, written in batches ---------------------------------------
    def _defer(self, fn, args: tuple) -> None:
        """Queue ``fn(*args)``; the queue is written when it is FLUSH_EVENTS long or FLUSH_PERIOD_S
        old (a live viewer sees the car within that), before any camera frame, and on close."""
        pending = self._pending
        pending.append((fn, args))
        if len(pending) >= FLUSH_EVENTS or time.monotonic() - self._flushed_at >= FLUSH_PERIOD_S:
            if self._flush_lock.acquire(blocking=False):  # another thread writing the queue: it goes on
                try:
                    self._drain(block=False)
                finally:
                    self._flush_lock.release()

    def flush(self) -> None:
        """Write every queued message now, in the order they came."""
        with self._flush_lock:
            self._drain()

    def _drain(self, block: bool = True) -> None:
        """Write the queue in order (the flush lock held); ``block=False`` stops at the first image
        still being encoded."""
        pending = self._pending
        self._flushed_at = time.monotonic()
        while pending:
            fn, args = pending[0]
            if fn is None and not block and not args.ready():
                return
            pending.popleft()
            if fn is None:
                self._write_job(args)
            else:
                fn(*args)

    # --- what the car says ---------------------------------------------------------------------
    def readout(self, r: Any) -> None:
        """A basic-sensor readout; also advances the dead-reckoning pose estimate."""
        self._defer(self._readout, (r,))

    def command(self, t: float, cmd: Any, stop: bool = False, step: tuple[float, float] | None = None) -> None:
        """What was applied at the tick of time ``t``; ``step``: the (t, dt) the lab's step was given."""
        self._defer(self._command, (t, cmd, stop, step))

    def truth(self, tr: Any) -> None:
        self._defer(self._truth, (tr,))

    def _readout(self, r: Any) -> None:
        ns = self.ns(r.t)
        if self._scene_due:
            self._resend_scene(ns)
        self._bytes(C.READOUT, C.readout_pb, ns, r)
        est = self._estimate(r)
        if not self._has_truth:
            self._poses(ns, None, est)

    def _command(self, t: float, cmd: Any, stop: bool, step: tuple[float, float] | None = None) -> None:
        self._bytes(C.COMMAND, C.command_pb, self.ns(t), t, cmd, stop, step)

    def _truth(self, tr: Any) -> None:
        ns = self.ns(tr.t)
        if self._scene_due:
            self._resend_scene(ns)
        self._has_truth = True
        self._bytes(C.TRUTH, C.truth_pb, ns, tr)
        self._truth_pose = (tr.x, tr.y, tr.yaw)
        est = self._est_pose if self._estimator is not None else None
        self._poses(ns, self._truth_pose, est)
        world = self._world
        if world is not None and getattr(world, "balls", None) and tr.t - self._balls_t >= BALLS_PERIOD:
            M = self._M
            self._balls_t = tr.t
            self._log(C.SCENE, "SceneUpdate", M.scene_update([M.balls_entity(world.obstacles_at(tr.t), ns)]), ns)

    def start_pose(self, pose: tuple[float, float, float]) -> None:
        """Where the dead-reckoning estimate starts (the true start pose, when known)."""
        self.flush()
        self._estimator = self._estimator_cls(self.params)
        self._est_pose = tuple(pose)

    def _estimate(self, r: Any) -> tuple[float, float, float] | None:
        if self._estimator is None:
            self.start_pose((0.0, 0.0, 0.0))
        if self._last_readout_t is not None:
            dt = float(r.t) - self._last_readout_t
            if 0.0 < dt < 1.0:
                self._est_pose = self._estimator(self._est_pose, self._speed(r.tach, self.params),
                                                 float(r.steering), dt, yaw_rate=float(r.gyro[2]))
        self._last_readout_t = float(r.t)
        return self._est_pose

    def _poses(self, ns: int, true_pose, estimate) -> None:
        if ns - self._pose_ns < POSE_PERIOD_NS:  # poses and transforms at most at 50 Hz
            return
        M = self._M
        self._pose_ns = ns
        stamp = M.pb_timestamp(ns)
        counts = self.counts
        tf = self._wanted(C.TF, _PB_TF)
        if tf is not None:  # the sensor mounts (static) once a second, the car's pose every time
            mounts = b""
            if ns - self._mounts_ns >= MOUNTS_PERIOD_NS:
                self._mounts_ns = ns
                mounts = M.transforms(ns, static=M.mounts(self.params, ns)).encode()
            tf.base.log(M.pb_transforms(ns, true_pose, estimate, mounts, stamp), ns)
            counts[C.TF] = counts.get(C.TF, 0) + 1
        for topic, pose in ((C.POSE_TRUE, true_pose), (C.POSE_ESTIMATE, estimate)):
            if pose is not None:
                ch = self._wanted(topic, _PB_POSE)
                if ch is not None:
                    ch.base.log(M.pb_pose_in_frame(pose, ns, stamp), ns)
                    counts[topic] = counts.get(topic, 0) + 1

    # --- sensors --------------------------------------------------------------------------------
    def scan(self, scan: Any, tick: float | None = None) -> None:
        """A LIDAR scan (queued with the per-tick messages: its arrays are not written to after);
        ``tick``: the time of the tick at which the lab first read it."""
        self._defer(self._scan, (scan, tick))

    def _scan(self, scan: Any, tick: float | None = None) -> None:
        M = self._M
        ns = self.ns(scan.t)
        info: dict[str, Any] = {"sensor": "lidar", "t": float(scan.t), "stamp": ns}
        if tick is not None:
            info["tick"] = float(tick)
        src = scan.angles
        if src is not self._angles_src:  # (the simulator hands the same angles array every scan)
            angles = np.asarray(src, dtype=np.float64)
            if self._angles is None or self._angles.shape != angles.shape or not np.array_equal(self._angles, angles):
                self._angles = angles.copy()
                info["angles"] = C.encode_angles(angles)
            self._angles_src = src if isinstance(src, np.ndarray) and not src.flags.writeable else None
        if self.writer is not None:  # replay needs it; the live view does not
            self._log(C.FRAMES, None, info, ns)
        ch = self._wanted(C.LIDAR, _PB_SCAN)
        if ch is not None:
            ch.base.log(M.pb_laser_scan(scan, ns), ns)
            self.counts[C.LIDAR] = self.counts.get(C.LIDAR, 0) + 1

    def rgbd(self, frame: Any, tick: float | None = None) -> None:
        """An RGBD frame: its colour and (every DEPTH_EVERY-th, or every one when exact) depth,
        queued in order with the per-tick messages; JPEG and millimetre depth encoded meanwhile on
        the encoder's thread (see :class:`_Frames`). ``tick``: as for :meth:`scan`."""
        M = self._M
        ns = self.ns(frame.t)
        k = self._rgbd_count
        self._rgbd_count += 1
        with_depth = self.exact or k % C.DEPTH_EVERY == 0
        jobs = []
        kind = "RawImage" if self.exact else "CompressedImage"
        ch = self._wanted(C.COLOR, kind)
        if ch is not None:
            jobs.append(self._frames.color(ch, C.COLOR, frame.color, ns, C.CAMERA_FRAME, self.exact))
        if with_depth:
            ch = self._wanted(C.DEPTH, "RawImage")
            if ch is not None:
                jobs.append(self._frames.depth(ch, C.DEPTH, frame.depth, ns, self.exact))
        with self._flush_lock:  # (the frame's messages stay together, in the order they came)
            pending = self._pending
            if self.writer is not None:
                info = {"sensor": "rgbd", "t": float(frame.t), "stamp": ns, "depth": with_depth}
                if tick is not None:
                    info["tick"] = float(tick)
                pending.append((self._log, (C.FRAMES, None, info, ns)))
            if k % CALIBRATION_EVERY == 0:
                pending.append((self._log, (C.CALIBRATION, "CameraCalibration", M.calibration(self.params, ns), ns)))
            self._queue_jobs(jobs)

    def csi(self, frames: Any, tick: float | None = None) -> None:
        ns = self.ns(frames.t)
        kind = "RawImage" if self.exact else "CompressedImage"
        jobs = []
        for view, image in zip(C.CSI_VIEWS, frames.as_list()):
            ch = self._wanted(C.CSI[view], kind)
            if ch is not None:
                jobs.append(self._frames.color(ch, C.CSI[view], image, ns, C.CSI_FRAMES[view], self.exact))
        with self._flush_lock:
            if self.writer is not None:
                info = {"sensor": "csi", "t": float(frames.t), "stamp": ns}
                if tick is not None:
                    info["tick"] = float(tick)
                self._pending.append((self._log, (C.FRAMES, None, info, ns)))
            self._queue_jobs(jobs)

    def _queue_jobs(self, jobs: list[_Job]) -> None:
        """Queue encoded images (the flush lock held); write what is ready; wait when too many are
        still being encoded (a recording never drops a frame)."""
        pending, waiting = self._pending, self._jobs
        for job in jobs:
            pending.append((None, job))
            waiting.append(job)
        if waiting and waiting[0].ready():
            self._drain(block=False)
        while len(waiting) > _Frames.WAITING:
            waiting[0].wait()
            self._drain(block=False)

    def _write_job(self, job: _Job) -> None:
        self._jobs.popleft()
        msg = job.result()
        self._frames.release(job)
        job.channel.log(msg, log_time=job.ns)
        self.counts[job.topic] = self.counts.get(job.topic, 0) + 1

    # --- what the lab says ----------------------------------------------------------------------
    def log_values(self, t: float, values: dict[str, Any]) -> None:
        """The lab's own values at time ``t`` (s): v_ref, cross-track error, state, ..."""
        self._defer(self._values, (t, {"t": float(t), **values}))  # (a copy: the caller may reuse its dict)

    def _values(self, t: float, values: dict[str, Any]) -> None:
        self._bytes(C.LAB, C.values_bytes, self.ns(t), values)

    def scene(self, world: Any = None, path: Any = None, t: float = 0.0) -> None:
        """The world's static shapes and/or the reference path (x, y points), once."""
        self.flush()
        M = self._M
        ns = self.ns(t)
        entities = {}
        if world is not None:
            self._world = world
            entities["world"] = M.world_entity(world, ns)
        if path is not None and len(path):
            entities["path"] = M.path_entity(np.asarray(path, dtype=float), ns)
        if entities:
            self._scene.update(entities)
            self._log(C.SCENE, "SceneUpdate", M.scene_update(list(entities.values())), ns)

    # --- the end --------------------------------------------------------------------------------
    def close(self) -> None:
        """Finish the file (summary, index) and stop the live view; safe to call twice."""
        if self.closed:
            return
        self.closed = True
        try:
            try:
                try:
                    self.flush()
                finally:
                    self._frames.close()
            finally:
                if self.writer is not None:
                    self.writer.close()
        finally:
            if self.live is not None:
                self.live.stop()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Job:
    """One image message of the queue: its channel, topic and log time, and the message, encoded
    here (``value``) or on the encoder's thread (``encoder`` set; ``done`` once it is)."""

    __slots__ = ("channel", "topic", "ns", "value", "error", "done", "encoder", "buffer")

    def __init__(self, channel: Any, topic: str, ns: int, *, value: Any = None, encoder: _Encoder | None = None,
                 buffer: np.ndarray | None = None):
        self.channel, self.topic, self.ns = channel, topic, ns
        self.value, self.error, self.done = value, None, encoder is None
        self.encoder, self.buffer = encoder, buffer

    def ready(self) -> bool:
        return self.done

    def wait(self) -> None:
        if not self.done:
            assert self.encoder is not None
            self.encoder.wait(self)

    def result(self) -> Any:
        self.wait()
        if self.error is not None:
            raise self.error
        return self.value


class _Encoder:
    """The encoder's thread: runs ``fn(*args)`` for each job handed to it, in order, and stores
    the result in the job. Lean on purpose (a job costs the caller one queue put, the thread two
    takes of the interpreter lock: waking up, and after OpenCV's encoder): a ThreadPoolExecutor's
    futures, locks and conditions cost the lab about 0.07 ms more a frame (measured in lane-follow)."""

    def __init__(self) -> None:
        self._todo: queue.SimpleQueue = queue.SimpleQueue()
        self._wake: queue.SimpleQueue = queue.SimpleQueue()  # a token after each job while someone waits
        self._waiting = False
        self._thread = threading.Thread(target=self._run, name="qcarlab-record-encoder", daemon=True)
        self._thread.start()

    def submit(self, job: _Job, fn, args: tuple) -> None:
        self._todo.put((job, fn, args))

    def _run(self) -> None:
        todo, wake = self._todo, self._wake
        while True:
            item = todo.get()
            if item is None:
                return
            job, fn, args = item
            try:
                job.value = fn(*args)
            except BaseException as exc:  # handed to whoever writes the job, in its place
                job.error = exc
            job.done = True  # (then the waiter's flag: see wait)
            if self._waiting:
                wake.put(None)

    def wait(self, job: _Job) -> None:
        """Block until ``job`` is done (one waiter at a time: the flush lock's holder)."""
        self._waiting = True  # (set before done is read: the thread sets done before it reads this)
        try:
            while not job.done:
                self._wake.get()
        finally:
            self._waiting = False

    def close(self) -> None:
        self._todo.put(None)
        self._thread.join()


class _Frames:
    """The camera images of a recording as messages. Compact ones (JPEG colour, millimetre depth)
    are encoded on a thread of their own (OpenCV's encoder and NumPy's conversions let go of the
    interpreter lock), from a copy of the frame (into a reused buffer: the lab may draw on its
    own frame), while the lab goes on with the frame; the recorder writes each message in its
    place in the queue once encoded. In the caller's thread instead: the exact profile's raw
    bytes (a copy, nothing to encode), and every image when no core is to spare (one core for
    this process, or a machine busy with other jobs: :meth:`_threaded`). ``THREADED``: None
    (that choice), True (always the thread), False (never). Whichever thread encodes, the file
    is the same byte for byte."""

    THREADED: bool | None = None
    WAITING = 4  # images queued and not yet written, at most: then the caller waits for the oldest

    def __init__(self) -> None:
        from qcarlab.recording import messages

        self._M = messages
        self._encoder: _Encoder | None = None  # the encoder's thread, started on first use
        self._free: dict[tuple, list[np.ndarray]] = {}  # reusable copy buffers by (shape, dtype)
        self._asked_at = -math.inf  # when _threaded last looked at the cores and the load
        self._use_thread = False

    def _threaded(self) -> bool:
        """Encode on the thread now? Only with a core to spare: two or more cores this process may
        use, and a load average (all the machine's runnable threads, this run's included) below
        their number. On a machine whose cores other jobs keep busy, the thread only takes turns
        with the lab and costs more CPU than it saves (measured, bench_record.py). Asked at most
        once a second."""
        if self.THREADED is not None:
            return self.THREADED
        now = time.monotonic()
        if now >= self._asked_at + 1.0:
            self._asked_at = now
            cores = _cores()
            try:
                load = os.getloadavg()[0]
            except OSError:  # pragma: no cover - no load average here
                load = 0.0
            self._use_thread = cores >= 2 and load < cores
        return self._use_thread

    def color(self, channel: Any, topic: str, image: Any, ns: int, frame_id: str, exact: bool) -> _Job:
        img = C.check_bgr(image)  # (refused here, in the caller's thread)
        if exact or not self._threaded():
            return _Job(channel, topic, ns, value=self._M.color_image(img, ns, frame_id, exact))
        return self._submit(channel, topic, ns, img, self._M.color_image, frame_id, exact)

    def depth(self, channel: Any, topic: str, depth: Any, ns: int, exact: bool) -> _Job:
        d = np.asarray(depth)
        if exact or not self._threaded():
            return _Job(channel, topic, ns, value=self._M.depth_image(d, ns, exact))
        return self._submit(channel, topic, ns, d, self._M.depth_image, exact)

    def _submit(self, channel: Any, topic: str, ns: int, array: np.ndarray, encode, *args: Any) -> _Job:
        key = (array.shape, array.dtype.str)
        free = self._free.get(key)
        buf = free.pop() if free else np.empty(array.shape, array.dtype)
        np.copyto(buf, array)
        if self._encoder is None:
            self._encoder = _Encoder()
        job = _Job(channel, topic, ns, encoder=self._encoder, buffer=buf)
        self._encoder.submit(job, encode, (buf, ns, *args))
        return job

    def release(self, job: _Job) -> None:
        """``job`` is written: its copy buffer can take another frame."""
        buf = job.buffer
        if buf is not None:
            job.buffer = None
            self._free.setdefault((buf.shape, buf.dtype.str), []).append(buf)

    def close(self) -> None:
        if self._encoder is not None:
            self._encoder.close()
            self._encoder = None
        self._free.clear()


def _cores() -> int:
    """How many cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _params_dict(params: QCarParams) -> dict[str, str]:
    from dataclasses import fields

    return {f.name: repr(getattr(params, f.name)) for f in fields(params)}
