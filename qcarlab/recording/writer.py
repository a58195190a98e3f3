"""The :class:`Recorder`: everything a run produced, as an MCAP file and/or a live Foxglove view.

    rec = Recorder("run.mcap")                  # or Recorder(None, live=LiveView(port=8765))
    rec.readout(car.read()); rec.scan(car.read_lidar()); rec.log_values(t, {"v_ref": 0.3})
    rec.close()                                 # writes the summary (index, statistics)

Written with foxglove-sdk's MCAP writer: messages go into zstd-compressed chunks of about 1 MB as
they come, so a run stopped by Ctrl-C or SIGTERM (the CLI turns SIGTERM into Ctrl-C) closes the
file with its summary, and a run killed outright (SIGKILL) loses at most the chunk being filled;
:mod:`qcarlab.recording.reader` reads such a file without its summary.

Two profiles for the cameras (the rest is always lossless):

- ``compact`` (default): colour as JPEG (quality 90) every frame, depth as 16-bit millimetres
  (the D435's own z16 format) every 15th frame (2 Hz at 30 fps). A 60 s lane-follow is about
  80 MB. Replays of camera labs see the JPEG colour and the held depth, so their decisions can
  differ slightly from the recorded ones (LIDAR labs replay exactly).
- ``exact``: colour as raw bgr8 and depth as 32-bit float metres, every frame: a replay gives
  the lab the very pixels it had (about 1.3 MB per RGBD frame after compression).
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.errors import InputError
from qcarlab.recording import channels as C
from qcarlab.recording import require

VERSION = 1
COMPRESSION_THREADS = 1  # zstd compresses the chunks on a thread of its own, beside the run
CALIBRATION_EVERY = 30  # RGBD frames between two camera calibration messages
BALLS_PERIOD = 0.1  # s between two updates of the moving balls in the scene
MOUNTS_PERIOD_NS = 1_000_000_000  # the static sensor transforms are repeated once a second
POSE_PERIOD_NS = 20_000_000  # poses and transforms: 50 Hz (the readouts and the truth: every one)


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
    ):
        require("--record" if path is not None else "--live")
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        if profile not in C.PROFILES:
            raise InputError(f"recording profile must be one of {', '.join(C.PROFILES)}, got {profile!r}")
        self.profile = profile
        self.exact = profile == "exact"
        self.params = params
        self.path = Path(path) if path is not None else None
        self.t0_ns = time.time_ns()
        self.ctx = foxglove.Context()
        self.writer = None
        if self.path is not None:
            if self.path.is_dir():
                raise InputError(f"--record {self.path}: is a folder; give a file name such as run.mcap")
            if not self.path.parent.exists():
                raise InputError(f"--record {self.path}: folder {self.path.parent} does not exist")
            try:
                self.writer = foxglove.open_mcap(
                    self.path, allow_overwrite=True, context=self.ctx,
                    writer_options=MCAPWriteOptions(compression=MCAPCompression.Zstd, compression_threads=COMPRESSION_THREADS,
                                                    profile=""))
            except Exception as exc:  # the SDK's own error type: a path we cannot write
                raise InputError(f"--record {self.path}: cannot write ({exc})") from None
        self._channels: dict[str, Any] = {}
        self.live = live
        self._scene: dict[str, Any] = {}  # the scene's entities by id, sent again to a live viewer who joins later
        self._scene_due = False
        if live is not None:
            # every channel exists before a viewer connects: it gets them in its first advertisement
            # (a channel advertised while a client is connected can refuse a subscription that comes
            # within milliseconds, foxglove-sdk 0.30)
            image = "RawImage" if self.exact else "CompressedImage"
            for topic, kind in ((C.READOUT, None), (C.COMMAND, None), (C.TRUTH, None), (C.LAB, None),
                                (C.LIDAR, "LaserScan"), (C.COLOR, image), (C.DEPTH, "RawImage"),
                                (C.CALIBRATION, "CameraCalibration"), (C.POSE_TRUE, "PoseInFrame"),
                                (C.POSE_ESTIMATE, "PoseInFrame"), (C.TF, "FrameTransforms"),
                                (C.SCENE, "SceneUpdate"), *((C.CSI[v], image) for v in C.CSI_VIEWS)):
                self._channel(topic, kind)
            live.attach(self.ctx, on_subscribe=self._subscribed)
        self._angles: np.ndarray | None = None
        self._rgbd_count = 0
        self._estimator = None
        self._last_readout_t: float | None = None
        self._truth_pose: tuple[float, float, float] | None = None
        self._has_truth = False
        self._world = None
        self._balls_t = -math.inf
        self._mounts_ns = -MOUNTS_PERIOD_NS
        self._pose_ns = -POSE_PERIOD_NS
        self.counts: dict[str, int] = {}
        self.closed = False
        meta = {"version": VERSION, "profile": profile, "t0_ns": self.t0_ns, "argv": sys.argv[1:]}
        meta.update(metadata or {})
        self.metadata("qcarlab", meta)
        self.metadata("qcarlab.params", _params_dict(params))

    # --- plumbing -------------------------------------------------------------------------------
    def ns(self, t: float) -> int:
        return C.stamp_ns(self.t0_ns, t)

    def _channel(self, topic: str, kind: str | None = None):
        ch = self._channels.get(topic)
        if ch is None:
            if kind is None:  # JSON with a named JSON Schema
                import foxglove

                name, schema = C.JSON_SCHEMAS[topic]
                ch = foxglove.Channel(topic, context=self.ctx, message_encoding="json",
                                      schema=foxglove.Schema(name=name, encoding="jsonschema",
                                                             data=json.dumps(schema).encode()))
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
            ch.log(C.json_bytes(msg), log_time=ns)
        else:
            ch.log(msg, log_time=ns)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def metadata(self, name: str, values: dict[str, Any]) -> None:
        """An MCAP metadata record (string values; others as JSON)."""
        if self.writer is not None:
            self.writer.write_metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()})

    def _subscribed(self, topic: str) -> None:
        if topic == C.SCENE:  # a viewer joined: the static scene was logged before they came
            self._scene_due = True

    def _resend_scene(self, ns: int) -> None:
        from qcarlab.recording import messages as M

        self._scene_due = False
        if self._scene:
            self._log(C.SCENE, "SceneUpdate", M.scene_update(list(self._scene.values())), ns)

    # --- what the car says ---------------------------------------------------------------------
    def readout(self, r: Any) -> None:
        """A basic-sensor readout; also advances the dead-reckoning pose estimate."""
        ns = self.ns(r.t)
        if self._scene_due:
            self._resend_scene(ns)
        self._log(C.READOUT, None, C.readout_json(r), ns)
        est = self._estimate(r)
        if not self._has_truth:
            self._poses(ns, None, est)

    def command(self, t: float, cmd: Any, stop: bool = False) -> None:
        self._log(C.COMMAND, None, C.command_json(t, cmd, stop), self.ns(t))

    def truth(self, tr: Any) -> None:
        ns = self.ns(tr.t)
        if self._scene_due:
            self._resend_scene(ns)
        self._has_truth = True
        self._log(C.TRUTH, None, C.truth_json(tr), ns)
        self._truth_pose = (tr.x, tr.y, tr.yaw)
        est = self._est_pose if self._estimator is not None else None
        self._poses(ns, self._truth_pose, est)
        world = self._world
        if world is not None and getattr(world, "balls", None) and tr.t - self._balls_t >= BALLS_PERIOD:
            from qcarlab.recording import messages as M

            self._balls_t = tr.t
            self._log(C.SCENE, "SceneUpdate", M.scene_update([M.balls_entity(world.obstacles_at(tr.t), ns)]), ns)

    def start_pose(self, pose: tuple[float, float, float]) -> None:
        """Where the dead-reckoning estimate starts (the true start pose, when known)."""
        from qcarlab.control.pose import BicyclePoseEstimator

        self._estimator = BicyclePoseEstimator(self.params)
        self._est_pose = tuple(pose)

    def _estimate(self, r: Any) -> tuple[float, float, float] | None:
        from qcarlab.control.speed import basic_speed_estimation

        if self._estimator is None:
            self.start_pose((0.0, 0.0, 0.0))
        if self._last_readout_t is not None:
            dt = float(r.t) - self._last_readout_t
            if 0.0 < dt < 1.0:
                self._est_pose = self._estimator(self._est_pose, basic_speed_estimation(r.tach, self.params),
                                                 float(r.steering), dt, yaw_rate=float(r.gyro[2]))
        self._last_readout_t = float(r.t)
        return self._est_pose

    def _poses(self, ns: int, true_pose, estimate) -> None:
        from qcarlab.recording import messages as M

        if ns - self._pose_ns < POSE_PERIOD_NS:  # poses and transforms at most at 50 Hz
            return
        self._pose_ns = ns

        tf = self._wanted(C.TF, "FrameTransforms")
        if tf is not None:  # the sensor mounts (static) once a second, the car's pose every time
            mounts = None
            if ns - self._mounts_ns >= MOUNTS_PERIOD_NS:
                self._mounts_ns = ns
                mounts = M.mounts(self.params, ns)
            tf.log(M.transforms(ns, true_pose, estimate, mounts), log_time=ns)
            self.counts[C.TF] = self.counts.get(C.TF, 0) + 1
        if true_pose is not None:
            self._log(C.POSE_TRUE, "PoseInFrame", M.pose_in_frame(true_pose, ns), ns)
        if estimate is not None:
            self._log(C.POSE_ESTIMATE, "PoseInFrame", M.pose_in_frame(estimate, ns), ns)

    # --- sensors --------------------------------------------------------------------------------
    def scan(self, scan: Any) -> None:
        from qcarlab.recording import messages as M

        ns = self.ns(scan.t)
        info: dict[str, Any] = {"sensor": "lidar", "t": float(scan.t), "stamp": ns}
        angles = np.asarray(scan.angles, dtype=np.float64)
        if self._angles is None or self._angles.shape != angles.shape or not np.array_equal(self._angles, angles):
            self._angles = angles.copy()
            info["angles"] = C.encode_angles(angles)
        if self.writer is not None:  # replay needs it; the live view does not
            self._log(C.FRAMES, None, info, ns)
        ch = self._wanted(C.LIDAR, "LaserScan")
        if ch is not None:
            ch.log(M.laser_scan(scan, ns), log_time=ns)
            self.counts[C.LIDAR] = self.counts.get(C.LIDAR, 0) + 1

    def rgbd(self, frame: Any) -> None:
        from qcarlab.recording import messages as M

        ns = self.ns(frame.t)
        k = self._rgbd_count
        self._rgbd_count += 1
        with_depth = self.exact or k % C.DEPTH_EVERY == 0
        if self.writer is not None:
            self._log(C.FRAMES, None, {"sensor": "rgbd", "t": float(frame.t), "stamp": ns, "depth": with_depth}, ns)
        if k % CALIBRATION_EVERY == 0:
            self._log(C.CALIBRATION, "CameraCalibration", M.calibration(self.params, ns), ns)
        kind = "RawImage" if self.exact else "CompressedImage"
        ch = self._wanted(C.COLOR, kind)
        if ch is not None:
            ch.log(M.color_image(frame.color, ns, C.CAMERA_FRAME, self.exact), log_time=ns)
            self.counts[C.COLOR] = self.counts.get(C.COLOR, 0) + 1
        if with_depth:
            ch = self._wanted(C.DEPTH, "RawImage")
            if ch is not None:
                ch.log(M.depth_image(frame.depth, ns, self.exact), log_time=ns)
                self.counts[C.DEPTH] = self.counts.get(C.DEPTH, 0) + 1

    def csi(self, frames: Any) -> None:
        from qcarlab.recording import messages as M

        ns = self.ns(frames.t)
        if self.writer is not None:
            self._log(C.FRAMES, None, {"sensor": "csi", "t": float(frames.t), "stamp": ns}, ns)
        kind = "RawImage" if self.exact else "CompressedImage"
        for view, image in zip(C.CSI_VIEWS, frames.as_list()):
            ch = self._wanted(C.CSI[view], kind)
            if ch is not None:
                ch.log(M.color_image(image, ns, C.CSI_FRAMES[view], self.exact), log_time=ns)
                self.counts[C.CSI[view]] = self.counts.get(C.CSI[view], 0) + 1

    # --- what the lab says ----------------------------------------------------------------------
    def log_values(self, t: float, values: dict[str, Any]) -> None:
        """The lab's own values at time ``t`` (s): v_ref, cross-track error, state, ..."""
        self._log(C.LAB, None, {"t": float(t), **values}, self.ns(t))

    def scene(self, world: Any = None, path: Any = None, t: float = 0.0) -> None:
        """The world's static shapes and/or the reference path (x, y points), once."""
        from qcarlab.recording import messages as M

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
            if self.writer is not None:
                self.writer.close()
        finally:
            if self.live is not None:
                self.live.stop()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _params_dict(params: QCarParams) -> dict[str, str]:
    from dataclasses import fields

    return {f.name: repr(getattr(params, f.name)) for f in fields(params)}
