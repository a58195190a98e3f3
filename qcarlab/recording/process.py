"""The recorder in a process of its own, so a recorded run pays almost nothing for its file.

    rec = open_recorder("run.mcap")      # a RecorderProcess where it can, else a Recorder
    with RecordingCar(car, rec) as car:  # the same calls as a Recorder: readout, scan, rgbd, ...
        ...

:class:`RecorderProcess` has a :class:`~qcarlab.recording.writer.Recorder`'s calls and runs the
Recorder itself in a child process: the MCAP writing, the JPEG and depth encoding, the zstd chunks
and the poses and transforms all happen there, on the other core, and none of it takes the lab's
interpreter lock. What the lab's process still does, per call:

- a camera image is copied into a ring of shared memory (``os.memfd_create``, RING_BYTES; about
  0.1 ms for a 640x480 colour frame); the child frees each image once it has encoded it, and the
  lab waits only when the ring is full (a recording never drops a frame);
- every other call (readouts, commands, truth, scans, the lab's values, the image's place among
  them) is appended to a list, pickled and written to the child's pipe in batches of at most
  FLUSH_EVENTS calls or FLUSH_PERIOD_S old.

The child gets the same calls in the same order and the parent's start time and command line, so
the file holds the same messages, with the same times, as an in-process Recorder's. The child is in
a session of its own and ignores SIGINT and SIGTERM: a Ctrl-C reaches only the lab, which closes the
recorder; if the lab's process dies outright (SIGKILL), the child reads the end of its pipe and
closes the file with its summary, losing only the calls not sent yet (FLUSH_PERIOD_S at most).

The in-process Recorder is used instead for a live view (its WebSocket server belongs to the lab's
process), on one core (the child would only take turns with the lab), and where the platform has no
``memfd_create`` (not Linux). ``RecorderProcess.ENABLED = False``, or the environment variable
``QCARLAB_RECORD_PROCESS=0``, keeps every recording in the lab's process.
"""

from __future__ import annotations

import mmap
import os
import pickle
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from qcarlab.car.base import Command, Readout, Truth
from qcarlab.constants import DEFAULT_PARAMS, QCarParams
from qcarlab.errors import InputError, QcarlabError
from qcarlab.recording import channels as C
from qcarlab.recording import require
from qcarlab.recording.writer import FLUSH_EVENTS, FLUSH_PERIOD_S
from qcarlab.sensors import CSIFrames, LidarScan, RGBDFrame

RING_BYTES = 16 << 20  # shared memory for images on their way to the child (about 18 colour frames)
_HEADER = 64  # the ring's first bytes: the child's count of bytes freed (int64), then padding
_ALIGN = 64  # every image starts on a cache line
_LEN = struct.Struct("<Q")  # the length of each pickled batch on the pipe; 0 = the end
_WAIT_S = 0.0005  # polling step while the ring is full
POLL_S, POLL_MAX_S = 0.001, 0.004  # the child's pauses between reads of its pipe (see _batches)


def open_recorder(path: str | Path | None, *, profile: str = "compact", live: Any = None,
                  params: QCarParams = DEFAULT_PARAMS, metadata: dict[str, Any] | None = None,
                  t0_ns: int | None = None, live_topics: Any = None) -> Any:
    """A :class:`RecorderProcess` for a file-only recording where a child can help (see the module
    docstring), else an in-process :class:`~qcarlab.recording.writer.Recorder`. ``t0_ns``: the
    wall clock (ns) at which the car's clock read 0 (now, when not given)."""
    if path is not None and live is None and RecorderProcess.available():
        return RecorderProcess(path, profile=profile, params=params, metadata=metadata, t0_ns=t0_ns)
    from qcarlab.recording.writer import Recorder

    return Recorder(path, profile=profile, live=live, params=params, metadata=metadata, t0_ns=t0_ns,
                    live_topics=live_topics)


class RecorderProcess:
    """A :class:`~qcarlab.recording.writer.Recorder` running in a child process; the same calls."""

    ENABLED = True
    live = None  # (a live view stays in the lab's process: open_recorder gives a Recorder for it)

    @classmethod
    def available(cls) -> bool:
        """A child can help: enabled, ``memfd_create`` exists, and two or more cores for this process."""
        if not cls.ENABLED or not hasattr(os, "memfd_create") or os.environ.get("QCARLAB_RECORD_PROCESS") == "0":
            return False
        try:
            return len(os.sched_getaffinity(0)) >= 2
        except (AttributeError, OSError):  # pragma: no cover - not Linux
            return False

    def __init__(self, path: str | Path, *, profile: str = "compact", params: QCarParams = DEFAULT_PARAMS,
                 metadata: dict[str, Any] | None = None, t0_ns: int | None = None):
        require("--record")
        self.profile = C.check_profile(profile)
        self.path = C.check_record_path(Path(path))
        try:  # refused now, in one line, rather than by the child later
            with open(self.path, "ab"):
                pass
        except OSError as exc:
            raise InputError(f"--record {self.path}: cannot write ({exc.strerror or exc})") from None
        self.exact = profile == "exact"
        self.params = params
        self.t0_ns = time.time_ns() if t0_ns is None else int(t0_ns)
        self.counts: dict[str, int] = {}  # messages written per topic (known once closed)
        self.closed = False
        self._calls: list[tuple] = []
        self._rest = memoryview(b"")  # bytes of a batch not yet written to the pipe
        self._flushed_at = time.monotonic()
        self._rgbd_count = 0
        self._head = 0  # bytes of the ring handed out so far (the child counts the bytes it freed)
        self._angles: Any = None  # the last scan angles sent (the child keeps them)

        spawned = _take_spare() or _Spawned()
        self._proc, self._pipe, self._ring = spawned.proc, spawned.pipe, spawned.ring
        self._freed, self._data, self._cap = spawned.freed, spawned.data, spawned.size
        meta = {"argv": sys.argv[1:]}
        meta.update(metadata or {})
        self._calls.append(("__init__", (str(self.path), profile, params, meta, self.t0_ns)))
        self.flush()

    # --- the Recorder's calls ------------------------------------------------------------------
    # (readouts, commands and truths go as flat tuples of numbers: pickling a Readout's NumPy vectors
    # costs 8 us, its numbers 0.6 us; the child makes the same objects again)
    def readout(self, r: Any) -> None:
        g, a = r.gyro, r.accel
        self._call("_readout", (r.t, r.encoder_counts, r.tach, r.motor_current, r.battery_voltage,
                                g.tolist() if type(g) is np.ndarray else g, a.tolist() if type(a) is np.ndarray else a,
                                r.steering, r.throttle, r.leds))

    def command(self, t: float, cmd: Any, stop: bool = False, step: tuple[float, float] | None = None) -> None:
        self._call("_command", (t, cmd.throttle, cmd.steering, cmd.leds, stop, step))

    def truth(self, tr: Any) -> None:
        self._call("truth", tuple(tr))

    def log_values(self, t: float, values: dict[str, Any]) -> None:
        self._call("log_values", (t, dict(values)))  # (a copy: the caller may reuse its dict)

    def metadata(self, name: str, values: dict[str, Any]) -> None:
        self._call("metadata", (name, dict(values)))

    def start_pose(self, pose: tuple[float, float, float]) -> None:
        self._call("start_pose", (tuple(pose),))

    def scene(self, world: Any = None, path: Any = None, t: float = 0.0) -> None:
        self._call("scene", (world, None if path is None else np.asarray(path, dtype=float), t))

    def scan(self, scan: Any, tick: float | None = None) -> None:
        angles = scan.angles
        if angles is self._angles and isinstance(angles, np.ndarray) and not angles.flags.writeable:
            angles = None  # the child has them (the simulator hands the same read-only array each scan)
        else:
            self._angles = angles
        self._call("_scan", (scan.t, angles, scan.ranges, tick))

    def rgbd(self, frame: Any, tick: float | None = None) -> None:
        if self.closed:  # (a recorder that failed: the error was raised once; the run's last calls go nowhere)
            return
        k = self._rgbd_count
        self._rgbd_count += 1
        with_depth = self.exact or k % C.DEPTH_EVERY == 0  # (the Recorder's own rule: it counts the frames too)
        specs = self._images([frame.color, frame.depth] if with_depth else [frame.color], bgr=1)
        self._calls.append(("_rgbd", (frame.t, specs[0], specs[1] if with_depth else None, self._head, tick)))
        self.flush()  # (at once: the child encodes the image while it is still in the caches)

    def csi(self, frames: Any, tick: float | None = None) -> None:
        if self.closed:
            return
        images = self._images(frames.as_list(), bgr=4)
        self._calls.append(("_csi", (frames.t, images, self._head, tick)))
        self.flush()

    def flush(self) -> None:
        """Hand every queued call to the child now (nothing once closed). A Ctrl-C meanwhile loses
        nothing: the calls stay queued until their batch is pickled, and a batch cut short is
        finished first next time."""
        if not self.closed:
            self._flush()

    def _flush(self) -> None:
        self._flushed_at = time.monotonic()
        try:
            self._write()  # (the rest of a batch a Ctrl-C cut short)
            if self._calls:
                data = pickle.dumps(self._calls, protocol=5)
                self._rest = memoryview(_LEN.pack(len(data)) + data)
                self._calls = []
                self._write()
        except OSError:  # the child is gone: its report says why
            self._failed()

    def close(self) -> None:
        """Send the rest, let the child finish the file (summary, index), and take its counts; safe
        to call twice."""
        if self.closed:
            return
        proc = self._proc
        error = None
        try:
            self._flush()
        except QcarlabError as exc:
            error = exc
        self.closed = True
        try:
            if error is None:
                self._write()  # (what a Ctrl-C cut short, when there was nothing more to send)
                self._rest = memoryview(_LEN.pack(0))  # the end mark
                self._write()
        except OSError:
            pass
        try:
            proc.stdin.close()
        except OSError:
            pass
        report = _read_report(proc)
        proc.wait()
        proc.stdout.close()
        self._freed = self._data = None
        try:
            self._ring.close()
        except BufferError:  # pragma: no cover - a view still alive somewhere: the mapping goes with it
            pass
        if report is not None:
            self.counts = report.get("counts", {})
            if report.get("error") and error is None:
                error = QcarlabError(f"--record {self.path}: {report['error']}")
        elif error is None:
            error = QcarlabError(f"--record {self.path}: the recording process ended without a report "
                                 f"(exit {proc.returncode})")
        if error is not None:
            raise error

    def __enter__(self) -> RecorderProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- plumbing -------------------------------------------------------------------------------
    def _call(self, name: str, args: tuple) -> None:
        calls = self._calls
        calls.append((name, args))
        if len(calls) >= FLUSH_EVENTS or time.monotonic() - self._flushed_at >= FLUSH_PERIOD_S:
            self.flush()

    def _write(self) -> None:
        """Write ``_rest`` to the pipe; the progress is kept at every step, so an interrupted write
        (Ctrl-C while the pipe is full) goes on where it stopped, and the child never sees half a batch."""
        while self._rest:
            self._rest = self._rest[os.write(self._pipe, self._rest):]

    def _failed(self) -> None:
        self.closed = True
        report = _read_report(self._proc)
        self._proc.wait()
        self._proc.stdout.close()
        why = report.get("error") if report else f"the recording process ended (exit {self._proc.returncode})"
        raise QcarlabError(f"--record {self.path}: {why}")

    def _images(self, images: list[Any], bgr: int) -> list[tuple[int, tuple[int, ...], str]]:
        """Copy one frame's images (the first ``bgr`` of them BGR uint8, refused here otherwise) into
        the ring, side by side: (offset, shape, dtype) of each for the child. The frame takes one
        block of at most half the ring, so the child freeing the frames before it always makes room
        (wherever the block before it ended)."""
        arrays = [C.check_bgr(i) for i in images[:bgr]] + [np.asarray(i) for i in images[bgr:]]
        sizes = [-(-a.nbytes // _ALIGN) * _ALIGN for a in arrays]
        size, cap = sum(sizes), self._cap
        if 2 * size > cap:
            raise InputError(f"recording: a frame of {size} bytes is more than half the recorder's ring ({cap})")
        pos = self._head % cap
        if pos + size > cap:  # no room before the ring's end: skip to its start
            self._head += cap - pos
            pos = 0
        if self._head + size - int(self._freed[0]) > cap:
            self._wait_for(self._head + size - cap)
        specs = []
        for img, n in zip(arrays, sizes):
            np.copyto(self._data[pos:pos + img.nbytes].view(img.dtype).reshape(img.shape), img)
            specs.append((pos, img.shape, img.dtype.str))
            pos += n
        self._head += size
        return specs

    def _wait_for(self, freed: int) -> None:
        """Until the child has freed ``freed`` bytes of the ring (it is behind: send it what it lacks)."""
        self.flush()
        while int(self._freed[0]) < freed:
            if self._proc.poll() is not None:
                self._failed()
            time.sleep(_WAIT_S)


class _Spawned:
    """A child process and its ring: the shared memory (mapped, every page touched) and the pipe."""

    def __init__(self) -> None:
        self.size = RING_BYTES
        fd = os.memfd_create("qcarlab-record", os.MFD_CLOEXEC)
        try:
            os.ftruncate(fd, _HEADER + self.size)
            self.ring = mmap.mmap(fd, _HEADER + self.size)
            self.freed = np.frombuffer(self.ring, dtype=np.int64, count=1)
            self.data = np.frombuffer(self.ring, dtype=np.uint8, offset=_HEADER)
            self.data.fill(0)  # every page of the ring mapped now (a few ms), not by the frames' copies
            env = dict(os.environ)
            root = str(Path(__file__).resolve().parents[2])  # this qcarlab, whichever way it was found
            env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
            for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
                env[var] = "1"  # the child encodes one image at a time: no thread pools to start
            self.proc = subprocess.Popen(
                [sys.executable, "-c", "from qcarlab.recording.process import _child; _child()", str(fd)],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, pass_fds=(fd,),
                env=env, start_new_session=True, bufsize=0)
        finally:
            os.close(fd)  # (the child has its own; the mapping keeps ours)
        self.pipe = self.proc.stdin.fileno()
        try:
            import fcntl

            fcntl.fcntl(self.pipe, fcntl.F_SETPIPE_SZ, 1 << 20)  # room for a few batches ahead
        except (ImportError, AttributeError, OSError):  # pragma: no cover - a smaller pipe is only slower
            pass

    def discard(self) -> None:
        """End a child that was never used (it sees the pipe's end before any call)."""
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        self.proc.wait()
        self.proc.stdout.close()
        self.freed = self.data = None
        self.ring.close()


_spare: _Spawned | None = None


def prestart() -> None:
    """Start a child now for the next RecorderProcess of this process (a command with ``--record``
    calls this first thing): the child's start (a Python interpreter importing NumPy, OpenCV and
    foxglove, about 0.3 s) then overlaps the car's opening and the world's loading, instead of
    holding up the run's first frames. Does nothing where no child would be used."""
    global _spare
    if _spare is None and RecorderProcess.available():
        try:
            require("--record")
        except QcarlabError:  # (the recorder itself will say so, in one line)
            return
        _spare = _Spawned()


def discard_spare() -> None:
    """End a prestarted child that no recorder took (the command failed before it recorded)."""
    global _spare
    spare, _spare = _spare, None
    if spare is not None:
        spare.discard()


def _take_spare() -> _Spawned | None:
    global _spare
    spare, _spare = _spare, None
    if spare is not None and spare.proc.poll() is not None:  # (it died meanwhile: start another)
        spare.discard()
        return None
    return spare


def _read_report(proc: subprocess.Popen) -> dict[str, Any] | None:
    try:
        data = proc.stdout.read()
    except (OSError, ValueError):
        return None
    try:
        return pickle.loads(data) if data else None
    except Exception:
        return None


# ------------------------------------------------------------------------------------ the child
def _child() -> None:
    """The child's main: read batches of calls from stdin, run them on a Recorder, and write a
    pickled report ({"counts", "error"}) to stdout at the end."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the lab closes the recorder; a dead lab closes the pipe
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    out = os.fdopen(os.dup(1), "wb")  # the report's own descriptor: nothing printed here can reach it
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.close(devnull)
    fd = int(sys.argv[1])
    ring = mmap.mmap(fd, 0)
    os.close(fd)
    freed = np.frombuffer(ring, dtype=np.int64, count=1)
    data = np.frombuffer(ring, dtype=np.uint8, offset=_HEADER)
    rec = None
    error = None
    try:
        child = _Child(freed, data)
        for batch in _batches(0):
            for name, args in pickle.loads(batch):
                if name == "__init__":
                    rec = child.open(*args)
                else:
                    child.call(name, args)
    except BaseException as exc:  # reported to the lab, in one line
        error = f"{type(exc).__name__}: {exc}" if not isinstance(exc, QcarlabError) else str(exc)
    try:
        if rec is not None:
            rec.close()
    except BaseException as exc:
        error = error or f"{type(exc).__name__}: {exc}"
    out.write(pickle.dumps({"counts": dict(rec.counts) if rec is not None else {}, "error": error}))
    out.close()  # the lab reads the report to its end: it waits for nothing more
    os._exit(0)  # (the file is closed: no interpreter teardown, tens of ms with NumPy, OpenCV, foxglove)


def _batches(fd: int):
    """The pickled batches on ``fd`` (length-prefixed), until the end mark or the pipe's end (the
    lab's process gone). Read without blocking, sleeping between reads (POLL_S, doubled up to
    POLL_MAX_S while idle): a reader blocked on the pipe would be woken by every batch the lab
    writes, and on a virtual machine that wake-up, one core signalling the other, costs the lab
    about 0.1 ms a write (measured: a third of what the recording cost it)."""
    os.set_blocking(fd, False)
    buf = bytearray()
    pause = POLL_S
    n = None
    while True:
        try:
            chunk = os.read(fd, 1 << 20)
        except BlockingIOError:
            time.sleep(pause)
            pause = min(pause * 2, POLL_MAX_S)
            continue
        if not chunk:
            return  # the lab's process is gone: the file is closed all the same
        pause = POLL_S
        buf += chunk
        while True:
            if n is None:
                if len(buf) < _LEN.size:
                    break
                (n,) = _LEN.unpack_from(buf)
                del buf[:_LEN.size]
                if n == 0:
                    return
            if len(buf) < n:
                break
            body = bytes(buf[:n])
            del buf[:n]
            n = None
            yield body


class _Child:
    """The child's side of the calls: the Recorder, and the images read out of the ring."""

    def __init__(self, freed: np.ndarray, data: np.ndarray):
        self.freed, self.data = freed, data
        self.rec: Any = None
        self.angles: Any = None

    def open(self, path: str, profile: str, params: Any, meta: dict[str, Any], t0_ns: int) -> Any:
        from qcarlab.recording.writer import Recorder

        self.rec = Recorder(path, profile=profile, params=params, metadata=meta, t0_ns=t0_ns)
        self.rec._frames.THREADED = False  # this process is the helper: encode in order, here
        return self.rec

    def call(self, name: str, args: tuple) -> None:
        if name == "_readout":
            t, counts, tach, current, volts, g, a, steering, throttle, leds = args
            self.rec.readout(Readout(t, counts, tach, current, volts, np.asarray(g, dtype=float),
                                     np.asarray(a, dtype=float), steering, throttle, leds))
        elif name == "_command":
            t, throttle, steering, leds, stop, step = args
            self.rec.command(t, Command(throttle, steering, leds), stop, step)
        elif name == "truth":
            self.rec.truth(Truth(*args))
        elif name == "_scan":
            t, angles, ranges, tick = args
            if angles is not None:
                self.angles = angles
            self.rec.scan(LidarScan(t, self.angles, ranges), tick)
        elif name == "_rgbd":
            t, color, depth, end, tick = args
            self.rec.rgbd(RGBDFrame(t, self._view(color), None if depth is None else self._view(depth)), tick)
            self.freed[0] = end  # (encoded or copied: the ring's bytes can take another frame)
        elif name == "_csi":
            t, images, end, tick = args
            self.rec.csi(CSIFrames(t, *(self._view(i) for i in images)), tick)
            self.freed[0] = end
        else:
            getattr(self.rec, name)(*args)

    def _view(self, spec: tuple[int, tuple[int, ...], str]) -> np.ndarray:
        pos, shape, dtype = spec
        dt = np.dtype(dtype)
        n = int(np.prod(shape)) * dt.itemsize
        return self.data[pos:pos + n].view(dt).reshape(shape)
