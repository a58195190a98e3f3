"""A recording as a car: ``--car replay:FILE.mcap`` (or a rosbag2 with a ``--topics`` map).

    with open_car("replay:run.mcap") as car:        # a stepped car: time moves with advance(dt)
        r = car.read()                              # the recorded readout of this instant
        scan = car.read_lidar()                     # the latest recorded scan at or before it
        car.write(0.1, 0.0)                         # noted as what the lab would have commanded
    print(car.comparison())                         # beside what was commanded

Two ways to play, chosen by how the run was recorded:

- **by time** (a stepped simulator's recording, a rosbag2): the clock starts at the recording's
  first instant and moves only with :meth:`advance`. ``read`` returns the recorded readouts in
  order (the n-th read of an instant gets the n-th readout recorded at it), the sensors the
  latest frame the lab had read at or before now, ``truth`` the recorded ground truth.
- **by tick** (a real-time run: a real car, a served car, ``--realtime``): its ticks came when the
  wall clock let them, not every 1/rate s. Each :meth:`advance` moves to the next recorded tick,
  whatever ``dt``; ``read`` returns that tick's readout, the sensors the frames the lab had at that
  tick, ``truth`` the truth recorded in it, and :meth:`recorded_step` the ``t`` and ``dt`` the
  lab's step was given then (the control loop gives the step the same).

Commands change nothing (the recording already happened): they are kept, and :meth:`comparison`
pairs them tick by tick with the recorded ones, within a tolerance (:func:`default_tolerance`).
Once the recording has run out, :attr:`ended` is True and the control loop stops.
"""

from __future__ import annotations

import bisect
import math
from pathlib import Path
from typing import Any

import numpy as np

from qcarlab.car.base import Car, Command, Identity, Readout, Truth
from qcarlab.car.lamps import ALL_OFF
from qcarlab.errors import InputError, NotBuiltError
from qcarlab.recording.reader import EPS, open_recording

MAX_LISTED = 5  # differing ticks listed in the summary
EXACT_TOLERANCE = 1e-9  # throttle (duty fraction) and steering (rad): a lossless recording replays bit for bit
LOSSY_TOLERANCE = 0.02  # the same, for a lab on a compact recording's JPEG colour and held depth


def default_tolerance(tape: Any) -> float:
    """The largest throttle and steering difference a replay of ``tape`` counts as the same command:
    EXACT_TOLERANCE, or LOSSY_TOLERANCE when the lab may see lossy camera frames (compact profile)."""
    lossy = tape.rgbd is not None or tape.csi is not None
    return LOSSY_TOLERANCE if lossy and tape.metadata.get("profile", "compact") != "exact" else EXACT_TOLERANCE


def parse_topics(text: str | None) -> dict[str, str] | None:
    """``scan=/scan,color=/camera/color/image_raw`` -> {"scan": "/scan", ...}."""
    if text is None or not text.strip():
        return None
    from qcarlab.recording.rosbag import SENSORS

    out: dict[str, str] = {}
    for item in text.split(","):
        key, sep, topic = item.partition("=")
        key, topic = key.strip(), topic.strip()
        if not sep or not key or not topic:
            raise InputError(f"--topics {text!r}: expected SENSOR=/topic pairs separated by commas "
                             "(e.g. scan=/scan,color=/camera/color/image_raw)")
        if key not in SENSORS:
            raise InputError(f"--topics: unknown sensor {key!r} (known: {', '.join(SENSORS)})")
        out[key] = topic
    return out


class ReplayCar(Car):
    """The car a recording describes, played back tick by tick."""

    def __init__(self, source: str | Path, topics: dict[str, str] | None = None, params=None,
                 throttle_limit: float | None = None):
        tape = open_recording(source, topics).tape()
        limit = throttle_limit if throttle_limit is not None else tape.throttle_limit
        super().__init__(params if params is not None else tape.params, limit)
        self.tape = tape
        self.source = str(source)
        self._readout_t = [r.t for r in tape.readouts]
        self._scan_t = tape.scan_ticks if len(tape.scan_ticks) == len(tape.scans) else [s.t for s in tape.scans]
        self._truth_t = [tr.t for tr in tape.truths]
        self._clock = tape.start
        self._reads = 0  # reads since the clock last moved
        self._tick_t: float | None = None  # time of the readout of this tick (commands belong to it)
        self._cursors: dict[str, list] = {}
        self.replayed: list[tuple[float, Command]] = []
        # by tick: the recorded ticks (the times of the commands written, one tick each) and the
        # (t, dt) each one's step was given
        self._ticks: list[float] = []
        self._steps: list[tuple[float, float] | None] = []
        if tape.realtime and tape.readouts:
            for (t, _cmd, stop), step in zip(tape.commands, tape.steps):
                if stop:
                    continue
                if self._ticks and abs(t - self._ticks[-1]) <= EPS:  # a second write in one tick
                    continue
                self._ticks.append(t)
                self._steps.append(step)
        self.by_tick = bool(self._ticks)
        self._k = 0  # by tick: the index of this tick
        if self.by_tick:
            self._clock = self._ticks[0]
        if not (tape.readouts or tape.scans or tape.truths or tape.rgbd or tape.csi):
            raise InputError(f"recording {source}: nothing a car could replay (no readouts, scans or frames); "
                             "a rosbag2 needs --topics")

    # --- time -----------------------------------------------------------------------------------
    @property
    def stepped(self) -> bool:
        return True

    @property
    def time(self) -> float:
        return self._now()

    @property
    def ended(self) -> bool:
        """True once the clock has passed the recording's last readout (its last instant without
        any); by tick, once every recorded tick has been played."""
        if self.by_tick:
            return self._k >= len(self._ticks)
        last = self._readout_t[-1] if self._readout_t and self.tape.span is None else self.tape.end
        return self._clock > last + EPS

    def advance(self, dt: float) -> None:
        if not (math.isfinite(dt) and dt >= 0.0):
            raise InputError(f"advance: dt must be a non-negative number of seconds, got {dt!r}")
        if self.by_tick:  # the next recorded tick, however long the recorded run took to reach it
            if dt > 0.0 and self._k < len(self._ticks):
                self._k += 1
                self._clock = self._ticks[self._k] if self._k < len(self._ticks) else max(self.tape.end,
                                                                                          self._clock) + dt
                self._reads = 0
                self._tick_t = None
            return
        if dt > 0.0:
            self._clock += dt
            self._reads = 0
            self._tick_t = None

    def recorded_step(self) -> tuple[float, float] | None:
        """By tick: the (t, dt) the lab's step was given at this tick when the run was recorded (for
        recordings that do not say, the time since the first tick and since the tick before);
        None by time (the control loop's own t and dt are the recorded ones there)."""
        if not self.by_tick or self._k >= len(self._ticks):
            return None
        k = self._k
        step = self._steps[k]
        if step is not None:
            return step
        return (self._ticks[k] - self._ticks[0], self._ticks[k] - self._ticks[k - 1]) if k > 0 else None

    def _now(self) -> float:
        """The clock, snapped to a recorded readout's exact time when it is that instant."""
        i = bisect.bisect_right(self._readout_t, self._clock + EPS) - 1
        if i >= 0 and abs(self._readout_t[i] - self._clock) <= EPS:
            return self._readout_t[i]
        return self._clock

    @staticmethod
    def _latest(times: list[float], now: float) -> int:
        """Index of the last item at or before ``now`` (the first one before the recording starts)."""
        return max(0, bisect.bisect_right(times, now + EPS) - 1)

    # --- sensors --------------------------------------------------------------------------------
    def read(self) -> Readout:
        readouts = self.tape.readouts
        if not readouts:  # a bag with no basic sensors: a car standing still
            r = Readout(t=self._clock, encoder_counts=0, tach=0.0, motor_current=0.0, battery_voltage=0.0,
                        gyro=np.zeros(3), accel=np.array([0.0, 0.0, self.params.gravity]))
            self._tick_t = r.t
            return r
        if self.by_tick and self._k < len(self._ticks):  # the tick's readouts: from its time to the next tick's
            first = bisect.bisect_left(self._readout_t, self._clock - EPS)
            end = bisect.bisect_left(self._readout_t, self._next_tick() - EPS)
            if first < end:
                r = readouts[min(first + self._reads, end - 1)]
                self._reads += 1
                self._tick_t = self._clock
                return r
        i = bisect.bisect_right(self._readout_t, self._clock + EPS) - 1
        if i < 0:
            i = 0
        group = bisect.bisect_left(self._readout_t, self._readout_t[i])
        r = readouts[min(group + self._reads, i)]
        self._reads += 1
        self._tick_t = r.t if abs(r.t - self._clock) <= EPS else self._clock  # a held readout: this tick
        return r

    def _next_tick(self) -> float:
        k = self._k + 1
        return self._ticks[k] if k < len(self._ticks) else math.inf

    def truth(self) -> Truth | None:
        if not self.tape.truths:
            return None
        if self.by_tick and self._tick_t is not None:  # read this tick: the truth recorded in it (after its read)
            return self.tape.truths[max(0, bisect.bisect_left(self._truth_t, self._next_tick() - EPS) - 1)]
        return self.tape.truths[self._latest(self._truth_t, self._now())]

    def read_lidar(self) -> Any:
        if not self.tape.scans:
            raise NotBuiltError(f"recording {self.source} has no LIDAR scans")
        return self.tape.scans[self._latest(self._scan_t, self._now())]

    def _stream(self, kind: str, make) -> Any:
        """The latest frame of a streamed camera at or before now, decoded once."""
        if make is None:
            raise NotBuiltError(f"recording {self.source} has no {'RGBD' if kind == 'rgbd' else 'CSI'} frames")
        cur = self._cursors.get(kind)
        if cur is None:
            it = make()
            first = next(it, None)
            if first is None:
                raise NotBuiltError(f"recording {self.source} has no {kind} frames")
            cur = self._cursors[kind] = [it, first, next(it, None), None]  # iterator, current, next, decoded
        now = self._now()
        while cur[2] is not None and cur[2][0] <= now + EPS:
            cur[1], cur[2], cur[3] = cur[2], next(cur[0], None), None
        if cur[3] is None:
            cur[3] = cur[1][1]()
        return cur[3]

    def read_rgbd(self) -> Any:
        return self._stream("rgbd", self.tape.rgbd)

    def read_csi(self) -> Any:
        return self._stream("csi", self.tape.csi)

    # --- commands -------------------------------------------------------------------------------
    def _apply(self, cmd: Command) -> None:
        self.replayed.append((self._tick_t if self._tick_t is not None else self._now(), cmd))

    def stop(self) -> None:
        """Nothing to stop: the recorded car stopped long ago."""

    def identity(self) -> Identity:
        caps = ["replay", "lockstep"]
        caps += ["encoder", "imu"] if self.tape.readouts else []
        caps += ["truth"] if self.tape.truths else []
        caps += ["lidar"] if self.tape.scans else []
        caps += ["rgbd"] if self.tape.rgbd else []
        caps += ["csi"] if self.tape.csi else []
        return Identity(name=f"replay of {Path(self.source).name}", backend="replay", capabilities=caps,
                        extra={"source": self.source, "recorded": self.tape.metadata.get("argv")})

    # --- what the lab would have done -----------------------------------------------------------
    def comparison(self, tolerance: float | None = None) -> dict[str, Any]:
        """The replayed commands beside the recorded ones, tick by tick (paired by time).

        ``identical``: every tick's command the same, bit for bit. ``within_tolerance``: every
        replayed tick's throttle and steering within ``tolerance`` (default: :func:`default_tolerance`)
        of the recorded ones with the same lamps, and no tick commanded in one and not the other,
        except the recorded ticks after the replay's last (a replay asked to run shorter:
        ``not_replayed``)."""
        tol = default_tolerance(self.tape) if tolerance is None else float(tolerance)
        if not (math.isfinite(tol) and tol >= 0.0):
            raise InputError(f"replay tolerance must be a non-negative number, got {tolerance!r}")
        recorded = [(t, c) for t, c, stop in self.tape.commands if not stop]
        replayed = self.replayed
        rows: dict[str, list] = {k: [] for k in ("t", "recorded_throttle", "replayed_throttle", "recorded_steering",
                                                 "replayed_steering", "recorded_leds", "replayed_leds", "same")}
        i = j = 0
        paired = differ = missing = extra = beyond = not_replayed = 0
        d_thr = d_ste = 0.0
        end = replayed[-1][0] if replayed else -math.inf
        listed: list[dict[str, Any]] = []
        while i < len(recorded) or j < len(replayed):
            a = recorded[i] if i < len(recorded) else None
            b = replayed[j] if j < len(replayed) else None
            if a is not None and b is not None and abs(a[0] - b[0]) <= EPS:
                i, j = i + 1, j + 1
                paired += 1
                same = a[1].throttle == b[1].throttle and a[1].steering == b[1].steering and a[1].leds == b[1].leds
                dt_, ds_ = abs(a[1].throttle - b[1].throttle), abs(a[1].steering - b[1].steering)
                d_thr, d_ste = max(d_thr, dt_), max(d_ste, ds_)
                if not same and not (dt_ <= tol and ds_ <= tol and a[1].leds == b[1].leds):
                    beyond += 1
            elif b is None or (a is not None and a[0] < b[0]):
                i += 1
                missing += 1
                same, b = False, None
                if a[0] > end + EPS:
                    not_replayed += 1
                else:
                    beyond += 1
            else:
                j += 1
                extra += 1
                beyond += 1
                same, a = False, None
            if not same:
                differ += 1
                if len(listed) < MAX_LISTED:
                    listed.append({"t": (a or b)[0], "recorded": _cmd(a), "replayed": _cmd(b)})
            rows["t"].append((a or b)[0])
            for name, pair in (("recorded", a), ("replayed", b)):
                rows[f"{name}_throttle"].append(pair[1].throttle if pair else math.nan)
                rows[f"{name}_steering"].append(pair[1].steering if pair else math.nan)
                rows[f"{name}_leds"].append(_lamps(pair[1].leds) if pair else "")
            rows["same"].append(int(same))
        changes, last = [], None  # the lamps the lab switched (its decisions: brake, indicators)
        for t, c in replayed:
            if c.leds != last:
                if len(changes) < MAX_LISTED * 2:
                    changes.append({"t": t, "lamps": _lamps(c.leds)})
                last = c.leds
        summary = {
            "source": self.source,
            "replayed_lamp_changes": changes,
            "recorded_ticks": len(recorded),
            "replayed_ticks": len(replayed),
            "ticks_compared": paired,
            "ticks_differing": differ,
            "recorded_only": missing,
            "replayed_only": extra,
            "identical": differ == 0,
            "tolerance": tol,
            "ticks_beyond_tolerance": beyond,
            "within_tolerance": beyond == 0,
            # the lab saw compressed camera frames (compact profile) and no tolerance was asked for: its
            # decisions may move a few ticks, which is said, not failed (--record-exact replays exactly)
            "lossy": tolerance is None and default_tolerance(self.tape) == LOSSY_TOLERANCE,
            "not_replayed": not_replayed,
            "by_tick": self.by_tick,
            "max_throttle_difference": d_thr,
            "max_steering_difference_rad": d_ste,
            "first_differences": listed,
            "notes": list(self.tape.notes),
        }
        return {"summary": summary, "rows": rows}


def _cmd(pair) -> dict[str, Any] | None:
    if pair is None:
        return None
    c = pair[1]
    return {"throttle": c.throttle, "steering": c.steering, "lamps": _lamps(c.leds)}


def _lamps(leds: tuple[float, ...]) -> str:
    from qcarlab.car.lamps import LAMP_NAMES

    if tuple(leds) == ALL_OFF:
        return ""
    return ",".join(name for name, v in zip(LAMP_NAMES, leds) if v > 0) or "on"
