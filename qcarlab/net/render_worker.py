"""A served simulator's sensor frames, drawn in a process of their own.

Drawing a camera frame holds the interpreter lock in places (between its compiled and OpenCV
steps), and while it does no other thread of the server can run: not the controller's, not the
watchdog's. A real-time served simulator (``qcarlab serve``) therefore draws its frames here:

    worker = RenderWorker(car.sensor_recipe(), kinds=("lidar", "rgbd"))
    arrays = worker.draw("rgbd", pose, t, yaw_rate)   # the frame's arrays, in FRAME_FIELDS order

The worker process builds the same world and sensors as the served car (``SimCar(**recipe)``:
same seed and realism profile, so the noise streams and the profile's effects are the ones the
car would have drawn) and draws each frame it is
asked for, one thread and one pipe per sensor, so that a slow camera set does not hold up the
LIDAR. The server fixes every frame's time and pose under its drive lock as before; only the
drawing moves. If the worker dies the server draws in its own process again (one log line).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import threading
from typing import Any

import numpy as np

log = logging.getLogger("qcarlab.net")

KINDS = ("lidar", "rgbd", "csi")
FIELDS = {"lidar": ("angles", "ranges"), "rgbd": ("color", "depth"), "csi": ("right", "rear", "left", "front")}


class WorkerGone(Exception):
    """The render process is not there (it died, or could not start)."""


def _serve_kind(conn: Any, car: Any, kind: str) -> None:
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        pose, t, yaw_rate = msg
        try:
            frame = car.draw_frame(kind, pose, t, yaw_rate)
            conn.send(("ok", [np.ascontiguousarray(getattr(frame, f)) for f in FIELDS[kind]]))
        except Exception as exc:  # reported to the requester, who turns it into an error frame
            conn.send(("error", f"{type(exc).__name__}: {exc}"))


def _main(recipe: dict[str, Any], conns: dict[str, Any], ready: Any, build: bool) -> None:
    import os

    try:  # below the server's threads (whose real-time priority a child inherits): drawing yields to them
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):
        pass
    try:
        os.nice(5)
    except (AttributeError, OSError):
        pass
    try:
        from qcarlab.car.sim import SimCar

        beams = recipe.pop("lidar_beams", None)
        car = SimCar(recipe["params"], seed=recipe["seed"], world=recipe["world"], realtime=True,
                     realism=recipe.get("realism"))
        car.lidar_beams = beams
        if build:  # now, so that the first frame is as quick as the others
            for kind in conns:
                car._sensor(kind)
    except Exception as exc:
        ready.send(f"{type(exc).__name__}: {exc}")
        return
    ready.send("ready")
    threads = [threading.Thread(target=_serve_kind, args=(conn, car, kind), daemon=True) for kind, conn in conns.items()]
    for th in threads:
        th.start()
    for th in threads:
        th.join()


class RenderWorker:
    """The process that draws a served simulator's sensor frames (see the module's docstring)."""

    def __init__(self, recipe: dict[str, Any], kinds: tuple[str, ...] = KINDS, *, build: bool = True,
                 start_timeout: float = 120.0):
        ctx = mp.get_context("spawn")
        self._conns: dict[str, Any] = {}
        child_conns: dict[str, Any] = {}
        for kind in kinds:
            mine, theirs = ctx.Pipe()
            self._conns[kind] = mine
            child_conns[kind] = theirs
        self._locks = {kind: threading.Lock() for kind in kinds}
        ready_r, ready_w = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=_main, args=(dict(recipe), child_conns, ready_w, build), daemon=True,
                                name="qcarlab-render")
        self.proc.start()
        for conn in child_conns.values():
            conn.close()
        ready_w.close()
        self.alive = False
        if not ready_r.poll(start_timeout):
            self.close()
            raise WorkerGone(f"the render process did not start within {start_timeout:g} s")
        try:
            msg = ready_r.recv()
        except EOFError:
            msg = "it exited"
        if msg != "ready":
            self.close()
            raise WorkerGone(f"the render process could not build the sensors: {msg}")
        self.alive = True
        self.frames = {kind: 0 for kind in kinds}

    def draws(self, kind: str) -> bool:
        return self.alive and kind in self._conns

    def draw(self, kind: str, pose: Any, t: float, yaw_rate: float = 0.0) -> list[np.ndarray]:
        """The arrays of sensor ``kind``'s frame at ``t`` from ``pose``, turning at ``yaw_rate`` (rad/s,
        the realism profile's motion blur); WorkerGone if the process died, RuntimeError if drawing
        failed there."""
        conn = self._conns[kind]
        with self._locks[kind]:
            if not self.alive:
                raise WorkerGone("the render process is gone")
            try:
                conn.send((tuple(float(v) for v in pose), float(t), float(yaw_rate)))
                status, value = conn.recv()
            except (EOFError, OSError, BrokenPipeError) as exc:
                self.alive = False
                raise WorkerGone(f"the render process is gone ({type(exc).__name__})") from None
        if status != "ok":
            raise RuntimeError(value)
        self.frames[kind] += 1
        return value

    def close(self) -> None:
        self.alive = False
        for conn in self._conns.values():
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
            try:
                conn.close()
            except OSError:
                pass
        self.proc.join(2.0)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(2.0)
