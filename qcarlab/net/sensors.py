"""Sensor frames for a server's clients: taken off the drive lock, packed once, shared, and paced
for monitors.

- The frame's time and pose are fixed under the drive lock (``Car.sensor_job``: microseconds);
  the reading or rendering runs under a lock of its own sensor, so a slow sensor never delays a
  command or the watchdog, and two sensors never wait for each other.
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

import threading
import time
from typing import Any

from qcarlab.net import protocol as P
from qcarlab.net.frames import frame_arrays
from qcarlab.net.protocol import MsgType as M

# request type -> (reply type, capability / kind)
SENSORS = {M.GET_LIDAR: (M.LIDAR, "lidar"), M.GET_RGBD: (M.RGBD, "rgbd"), M.GET_CSI: (M.CSI, "csi")}


class NoData(Exception):
    """Lock-step: the controller has not read this sensor yet."""


class SensorHub:
    """The newest packed frame of each sensor of ``car``, shared by all sessions of one server."""

    def __init__(self, car: Any, drive_lock: Any, *, lockstep: bool, monitor_rate: float, stop_event: threading.Event):
        self.car = car
        self.drive_lock = drive_lock
        self.lockstep = lockstep
        self.period = 1.0 / monitor_rate
        self.stop_event = stop_event
        self.locks = {reply: threading.Lock() for reply, _ in SENSORS.values()}
        self.first_lock = threading.Lock()  # a sensor's first reading (it may build the world) runs alone
        self.started: set[int] = set()
        self.latest: dict[int, tuple[float, list[Any]]] = {}  # reply -> (time.monotonic() taken, parts)
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
        if reply in self.started:
            obj = job()
        else:
            with self.first_lock:
                obj = job()
                self.started.add(reply)
        t, arrays = frame_arrays(reply, obj, t_now)
        parts = P.pack_arrays(t, arrays)
        self.latest[reply] = (time.monotonic(), parts)
        self.readings[reply] += 1
        return parts
