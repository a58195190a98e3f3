"""The glue between the lab commands and :mod:`qcarlab.recording`: ``--record``, ``--live``, replays.

A driving command decorated with :func:`qcarlab.cli.common.recordable` gets ``--record FILE.mcap``,
``--record-exact``, ``--live``, ``--live-port`` and ``--topics``; while it runs, :func:`request`
holds them, :func:`wrap` (called by ``open_from_options``) wraps the car it opens in a
:class:`~qcarlab.recording.car.RecordingCar`, and :func:`after_run` (called by ``emit``) puts a
replayed car's comparison into the result. SIGTERM during a recorded run is Ctrl-C, so the file
is closed with its summary either way.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from qcarlab.car import Car, parse_car_uri
from qcarlab.errors import InputError


@dataclass
class _Request:
    record: Path | None = None
    exact: bool = False
    live: bool = False
    live_port: str | None = None
    topics: str | None = None
    cars: list[Any] = field(default_factory=list)  # RecordingCar / ReplayCar opened by this command
    recorded: bool = False
    tolerance: float | None = None  # --replay-tolerance


_REQ = _Request()


@contextlib.contextmanager
def request(record: Path | None, exact: bool, live: bool, live_port: str | None, topics: str | None,
            tolerance: float | None = None):
    """Hold a command's recording options while it runs; SIGTERM becomes Ctrl-C meanwhile."""
    global _REQ
    if exact and record is None:
        raise InputError("--record-exact needs --record FILE.mcap")
    if live_port is not None and not live:
        live = True  # --live-port alone asks for the live view too
    previous, handler_set = None, False
    if (record is not None or live) and threading.current_thread() is threading.main_thread():
        from qcarlab.wire import interrupts

        previous = signal.signal(signal.SIGTERM, interrupts.handler)
        handler_set = True
    _REQ = _Request(record, exact, live, live_port, topics, tolerance=tolerance)
    if record is not None and not live:
        from qcarlab.recording.process import prestart

        prestart()  # the recorder's child starts while the car and the world are opened
    try:
        yield _REQ
    finally:
        if record is not None and not live:
            from qcarlab.recording.process import discard_spare

            discard_spare()
        for car in _REQ.cars:  # a command that ended without closing its car (an exception)
            with contextlib.suppress(Exception):
                car.close()
        _REQ = _Request()
        if handler_set:
            signal.signal(signal.SIGTERM, previous)


def replay_topics() -> dict[str, str] | None:
    from qcarlab.car.replay import parse_topics

    return parse_topics(_REQ.topics)


def wrap(qcar: Car, car: str, world: Any = None, seed: int = 0, path: Any = None, start: Any = None,
         sensors: Any = None) -> Car:
    """The car as opened, or wrapped in a RecordingCar when the command asked for --record/--live;
    ``sensors``: those the command reads ("lidar", "rgbd", "csi"; None: any the car has), whose
    channels a live view advertises."""
    req = _REQ
    if parse_car_uri(car)[0] == "replay":
        req.cars.append(qcar)
    elif req.topics is not None:
        qcar.close()
        raise InputError("--topics maps a rosbag2's topics for --car replay:BAG")
    elif req.tolerance is not None:
        qcar.close()
        raise InputError("--replay-tolerance is for a replay (--car replay:FILE.mcap)")
    if req.record is None and not req.live:
        return qcar
    try:
        if req.recorded:
            raise InputError("--record/--live records one drive, and this command opens the car more than once "
                             "(e.g. --hsv-tune or a --lookahead sweep)")
        req.recorded = True
        world_obj = world if world is not None and not isinstance(world, (str, Path)) else getattr(qcar, "world", None)
        scene = (world_obj is not None and hasattr(world_obj, "static_solids")) or path is not None
        recorder = make_recorder(qcar, req.record, req.exact, req.live_port if req.live else None,
                                 os.environ.get("QCARLAB_TOKEN"), sensors=sensors, scene=scene, car=car, world=world,
                                 seed=seed, start=list(start) if start is not None else None)
    except BaseException:
        qcar.close()
        raise
    from qcarlab.recording.car import RecordingCar

    if world_obj is not None and hasattr(world_obj, "static_solids"):
        recorder.scene(world_obj, path, t=qcar.time)
    elif path is not None:
        recorder.scene(None, path, t=qcar.time)
    wrapped = RecordingCar(qcar, recorder)
    req.cars.append(wrapped)
    return wrapped


def make_recorder(qcar: Car, record: Path | None, exact: bool, live_port: str | None, token: str | None,
                  sensors: Any = None, scene: bool = True, **meta: Any):
    """A Recorder for ``qcar``: to ``record`` (MCAP) and/or a live view on ``live_port``, which
    advertises the channels the run sends (``sensors``, ``scene``: see channels.live_topics)."""
    from qcarlab.recording import require

    require("--record" if record is not None else "--live")
    from qcarlab.recording.live import LiveView, parse_live
    from qcarlab.recording.process import open_recorder

    live = None
    if live_port is not None:
        host, port = parse_live(live_port)
        live = LiveView(host, port, token=token, announce=_announce)
    world = meta.get("world")
    meta["world"] = getattr(world, "name", world) if world is not None else getattr(getattr(qcar, "world", None), "name", None)
    meta["world_source"] = getattr(world, "source", None) if world is not None and not isinstance(world, str) else None
    ident = qcar.identity()
    meta["identity"] = {"name": ident.name, "backend": ident.backend, "capabilities": ident.capabilities}
    # the car's clock on the machine's: a message's time is when it happened, from the run's start
    # (a served or real-time car's clock has run since it was opened: its start-up time)
    t0_ns = time.time_ns() - round(float(qcar.time) * 1e9)
    from qcarlab.recording.channels import live_topics

    return open_recorder(record, profile="exact" if exact else "compact", live=live, params=qcar.params, metadata=meta,
                         t0_ns=t0_ns, live_topics=live_topics(ident.capabilities, sensors, scene))


def _announce(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def live_car(qcar: Car, live: bool, live_port: str | None, token: str | None) -> Car:
    """``serve --live``: the served car, streamed to a live view (or the car itself without --live)."""
    if not live and live_port is None:
        return qcar
    from qcarlab.recording.car import RecordingCar

    try:
        world = getattr(qcar, "world", None)
        recorder = make_recorder(qcar, None, False, live_port or "8765", token, car="served",
                                 scene=world is not None and hasattr(world, "static_solids"))
        if world is not None and hasattr(world, "static_solids"):
            recorder.scene(world, t=qcar.time)
    except BaseException:
        qcar.close()
        raise
    return RecordingCar(qcar, recorder, follow_truth=True)  # its clients need not ask for the truth


def recorded_world(source: str, params: Path | None):
    """(world, start pose) of the simulated run a recording was made from, when the world can
    still be loaded (a shipped world or a file that is still there); (None, None) otherwise."""
    from qcarlab.recording.reader import Recording, is_rosbag

    p = Path(source)
    if not p.is_file() or is_rosbag(p):
        return None, None
    try:
        meta = Recording(p).metadata.get("qcarlab", {})
    except InputError:
        return None, None
    name, where = meta.get("world"), meta.get("world_source")
    start = meta.get("start")
    pose = tuple(float(v) for v in start) if isinstance(start, list) and len(start) == 3 else None
    from qcarlab.constants import load_params
    from qcarlab.experiments.worlds import list_worlds, load_world

    for candidate in (where, name):
        if not candidate:
            continue
        if candidate in {n for n, _ in list_worlds()} or Path(candidate).is_file():
            try:
                return load_world(candidate, load_params(params)), pose
            except InputError:
                continue
    return None, pose


# ------------------------------------------------------------------------------------ after the run
def after_run(result: Any) -> dict[str, Any]:
    """After a run on ``--car replay:``: the comparison in ``result.metrics["replay"]`` and, per
    tick, ``replay.csv`` in the result's logs; after a recorded run, the file in ``metrics["recording"]``."""
    if not _REQ.cars:  # neither replayed nor recorded (the replay's module, and OpenCV with it, not imported)
        return {"replay": None, "recording": result.metrics.get("recording")}
    from qcarlab.car.replay import ReplayCar

    comparison = None
    for car in _REQ.cars:
        inner = getattr(car, "inner", car)
        if isinstance(inner, ReplayCar) and comparison is None:
            comparison = inner.comparison(_REQ.tolerance)
            result.metrics["replay"] = comparison["summary"]
            result.logs["replay.csv"] = comparison["rows"]
        rec = getattr(car, "recorder", None)
        if rec is not None and rec.path is not None:
            result.metrics["recording"] = {"file": str(rec.path), "profile": rec.profile,
                                           "messages": sum(rec.counts.values()),
                                           "bytes": rec.path.stat().st_size if rec.path.exists() else None}
    return {"replay": comparison, "recording": result.metrics.get("recording")}


def print_after(info: dict[str, Any], console) -> None:
    """The replay's comparison table and notes; the line naming the recording."""
    rec = info.get("recording")
    if rec is not None:
        size = f"{rec['bytes'] / 1e6:.1f} MB" if rec["bytes"] is not None else "?"
        console.print(f"recorded {rec['messages']} messages ({size}, {rec['profile']}) to {rec['file']}: open it in "
                      f"Foxglove, or replay it with --car replay:{rec['file']}", markup=False, highlight=False,
                      soft_wrap=True)
    if info.get("replay") is not None:
        _print_replay(info["replay"], console)


def _print_replay(comparison: dict[str, Any], console) -> None:
    from qcarlab.cli.common import Table

    s = comparison["summary"]
    table = Table(title=f"replay of {s['source']}: what the lab would command beside what was commanded",
                  title_justify="left", show_header=False)
    table.add_column("what")
    table.add_column("value", justify="right")
    table.add_row("ticks compared", f"{s['ticks_compared']} (recorded {s['recorded_ticks']}, "
                  f"replayed {s['replayed_ticks']})")
    if s["recorded_ticks"] == 0 and s["replayed_ticks"] == 0:
        table.add_row("commands", "none recorded, none replayed (the lab only reads sensors)")
    elif s["recorded_ticks"] == 0:
        table.add_row("commands", f"{s['replayed_ticks']} replayed, none recorded to compare with "
                      "(per tick in replay.csv with --out)")
        for c in s["replayed_lamp_changes"]:
            table.add_row(f"t = {c['t']:.3f} s", f"lamps: {c['lamps'] or 'off'}")
        console.print(table)
        for note in s["notes"]:
            console.print(f"note: {note}", markup=False, soft_wrap=True)
        return
    else:
        table.add_row("commands identical", "yes, every tick" if s["identical"] else
                      f"NO: {s['ticks_differing']} tick(s) differ")
        table.add_row("within tolerance", f"{'yes' if s['within_tolerance'] else 'NO'} (+-{s['tolerance']:.3g}"
                      + (f"; {s['ticks_beyond_tolerance']} tick(s) beyond" if not s["within_tolerance"] else "")
                      + ")")
        if s.get("not_replayed"):
            table.add_row("not replayed", f"{s['not_replayed']} recorded tick(s) after the replay's end")
    if not s["identical"]:
        table.add_row("largest difference", f"throttle {s['max_throttle_difference']:.4g}, "
                      f"steering {s['max_steering_difference_rad']:.4g} rad")
        for d in s["first_differences"]:
            table.add_row(f"t = {d['t']:.3f} s", f"recorded {_fmt(d['recorded'])} | replayed {_fmt(d['replayed'])}")
    console.print(table)
    for note in s["notes"]:
        console.print(f"note: {note}", markup=False, soft_wrap=True)


def _fmt(cmd: dict[str, Any] | None) -> str:
    if cmd is None:
        return "-"
    lamps = f" [{cmd['lamps']}]" if cmd["lamps"] else ""
    thr = cmd["throttle"]
    return f"throttle {thr:+.6f}, steering {cmd['steering']:+.6f}{lamps}" if math.isfinite(thr) else "-"
