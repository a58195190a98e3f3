"""Sensor frames for a server's clients: taken off the drive lock, packed once, shared, and paced
for monitors.

- The frame's time and pose are fixed under the drive lock (``Car.sensor_job``: microseconds);
  the reading or rendering runs under a lock of its own sensor, so a slow sensor never delays a
  command or the watchdog, and two sensors never wait for each other. A served real-time
  simulator draws its frames in a process of its own (:mod:`qcarlab.net.render_worker`), so that
  drawing does not even hold the interpreter lock the controller's thread needs.
- One packed copy of the newest frame of each sensor is kept; every client asking for it gets the
  same bytes (no copy per client).
- A monitor gets at most ``monitor_rate`` frames per second of each sensor: a request that comes
  sooner waits for its slot and then gets the newest frame (frames in between are dropped, never
  queued). A frame younger than ``1 / monitor_rate`` is reused instead of taking a new one, so any
  number of monitors costs at most ``monitor_rate`` readings per sensor per second.
- The controller is never paced and gets a frame read for its request (the backend decides how
  fresh: the simulator's frame k is the one taken at k / rate).
- Lock-step servers: monitors get the controller's last frame (never a new one: watching must
  not draw the simulator's noise); before the controller's first, ``no_data``.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from qcarlab.wire import protocol as P
from qcarlab.wire.frames import frame_arrays
from qcarlab.wire.protocol import MsgType as M
from qcarlab.net.render_worker import WorkerGone

log = logging.getLogger("qcarlab.net")

# request type -> (reply type, capability / kind)
SENSORS = {M.GET_LIDAR: (M.LIDAR, "lidar"), M.GET_RGBD: (M.RGBD, "rgbd"), M.GET_CSI: (M.CSI, "csi")}


class NoData(Exception):
    """Lock-step: the controller has not read this sensor yet."""


class SensorHub:
    """The newest packed frame of each sensor of ``car``, shared by all sessions of one server."""

    def __init__(self, car: Any, drive_lock: Any, *, lockstep: bool, monitor_rate: float, stop_event: threading.Event,
                 worker: Any = None):
        self.car = car
        self.worker = worker  # a RenderWorker that draws the frames in a process of its own, or None
        self.drive_lock = drive_lock
        self.lockstep = lockstep
        self.period = 1.0 / monitor_rate
        self.stop_event = stop_event
        self.locks = {reply: threading.Lock() for reply, _ in SENSORS.values()}
        self.first_lock = threading.Lock()  # a sensor's first reading (it may build the world) runs alone
        self.started: set[int] = set()
        self.latest: dict[int, tuple[float, list[Any]]] = {}  # reply -> (time.monotonic() taken, parts)
        self.keys: dict[int, Any] = {}  # reply -> the backend's key of the latest frame (the simulator's frame index)
        self.readings = {reply: 0 for reply, _ in SENSORS.values()}

    def frame(self, request: int, *, controller: bool, pace: dict[int, float] | None) -> tuple[int, list[Any]]:
        """(reply type, payload parts) for a sensor request; ``pace`` is the monitor's own next-slot
        table (None for the controller). Raises NoData (lock-step monitor before any frame)."""
        reply, kind = SENSORS[request]
        if not controller:
            self._wait_slot(reply, pace)
        try:
            if self.lockstep and not controller:
                got = self.latest.get(reply)
                if got is None:
                    raise NoData(kind)
                return reply, got[1]
            if not controller:
                got = self.latest.get(reply)
                if got is not None and time.monotonic() - got[0] < self.period:
                    return reply, got[1]
            with self.locks[reply]:
                if not controller:  # another monitor may have taken one while we waited
                    got = self.latest.get(reply)
                    if got is not None and time.monotonic() - got[0] < self.period:
                        return reply, got[1]
                return reply, self._take(reply, kind)
        finally:
            if pace is not None:
                pace[reply] = time.monotonic() + self.period

    def _wait_slot(self, reply: int, pace: dict[int, float] | None) -> None:
        if pace is None:
            return
        delay = pace.get(reply, 0.0) - time.monotonic()
        if delay > 0:
            self.stop_event.wait(delay)

    def _take(self, reply: int, kind: str) -> list[Any]:
        with self.drive_lock:
            job = self.car.sensor_job(kind)
            t_now = self.car.time
        key = getattr(job, "key", None)
        if key is not None and key == self.keys.get(reply) and reply in self.latest:
            return self.latest[reply][1]  # the same frame as last time: no new reading
        arrays = None
        worker = self.worker
        if worker is not None and worker.draws(kind) and getattr(job, "pose", None) is not None:
            try:
                arrays = worker.draw(kind, job.pose, job.t, getattr(job, "yaw_rate", 0.0))
                t = job.t
                drawn = getattr(job, "drawn", None)
                if drawn is not None:  # a recording car records the frame the worker drew
                    drawn(t, arrays)
            except WorkerGone as exc:
                log.warning("%s; drawing sensor frames in the server's own process from now on", exc)
                self.worker = None
                warm = getattr(self.car, "warm_physics", None)
                if callable(warm):
                    warm()  # drawing here loads numba: the physics' first compiled step now, not under the drive lock
        if arrays is None:
            if reply in self.started:
                obj = job()
            else:
                with self.first_lock:
                    obj = job()
                    self.started.add(reply)
            t, arrays = frame_arrays(reply, obj, t_now)
        parts = P.pack_arrays(t, arrays)
        self.latest[reply] = (time.monotonic(), parts)
        self.keys[reply] = key
        self.readings[reply] += 1
        return parts
