"""Options every lab subcommand shares (DESIGN.md section 2) and the output of results."""

from __future__ import annotations

import contextvars
import math
import sys
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich import table as _rich_table

from qcarlab.car import Car, open_car, parse_car_uri
from qcarlab.constants import load_params
from qcarlab.errors import InputError
from qcarlab.experiments.result import Result
from qcarlab.record import dumps

stderr = Console(stderr=True, highlight=False, soft_wrap=True)

CarOpt = Annotated[
    str, typer.Option("--car", help="Which car: [b]sim[/b] (built-in simulator) or [b]tcp://HOST:PORT[/b].")
]
SHIPPED = ", ".join(sorted(p.stem for p in (Path(__file__).parents[1] / "worlds").glob("*.yaml")))
WorldOpt = Annotated[
    str | None,
    typer.Option("--world", help=f"Shipped world ({SHIPPED}), a world YAML or a ROS map YAML (simulator only).",
                 show_default=False),
]
StartOpt = Annotated[
    str | None,
    typer.Option("--start", help="Place the car at X,Y,YAW (m, m, rad) instead of the world's start pose.",
                 show_default=False),
]
SeedOpt = Annotated[int, typer.Option("--seed", min=0, help="Seed of the simulator's noise; same seed, same numbers.")]
def check_out(out: Path | None) -> Path | None:
    """Refuse an --out that cannot be a folder before the run starts, not after it."""
    if out is None:
        return out
    try:
        if out.exists() and not out.is_dir():
            raise typer.BadParameter(f"{out} exists and is not a folder")
    except OSError as exc:  # a name longer than the file system allows, a folder we may not look into
        shown = str(out) if len(str(out)) <= 60 else str(out)[:57] + "..."
        raise typer.BadParameter(f"{shown}: {exc.strerror or exc}") from None
    return out


OutOpt = Annotated[
    Path | None,
    typer.Option("--out", help="Folder for results.json, the CSV log and the figures.", callback=check_out),
]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the results as JSON on stdout, nothing else.")]
RealtimeOpt = Annotated[
    bool, typer.Option("--realtime", help="Pace the simulator in real time (default: as fast as possible).")
]
DebugOpt = Annotated[bool, typer.Option("--debug", help="Show tracebacks on errors.")]
ParamsOpt = Annotated[
    Path | None,
    typer.Option("--params", help="YAML file: the simulated car's parameters (see qcarlab/constants.py) and, in "
                 "a lab: section, the lab's tunables (look-ahead, kp, ki, HSV ranges, ...; qcarlab template "
                 "writes one). Options given on the command line win."),
]
UseOpt = Annotated[
    list[Path] | None,
    typer.Option("--use", help="Your blocks: a Python file whose functions or classes named like this lab's "
                 "blocks replace them (qcarlab blocks LAB lists them). Repeatable.", show_default=False),
]
BlockOpt = Annotated[
    list[str] | None,
    typer.Option("--block", help="One block from your code: NAME=FILE.py:FUNCTION (e.g. "
                 "stop_sign=mylab/stop.py:my_stop). Repeatable.", show_default=False),
]
CarTokenOpt = Annotated[
    str | None,
    typer.Option("--token", envvar="QCARLAB_TOKEN", show_envvar=True, show_default=False,
                 help="The served car's token (qcarlab serve --token), for --car tcp://HOST:PORT."),
]
RateOpt = Annotated[float, typer.Option("--rate", help="Control loop rate in Hz, 1-2000 (the lab's Python loops "
                                        "run at 60-200).")]
RecordOpt = Annotated[Path | None, typer.Option(
    "--record", help="Record the run to FILE.mcap (opens in Foxglove; replay it with --car replay:FILE.mcap).",
    show_default=False)]
RecordExactOpt = Annotated[bool, typer.Option(
    "--record-exact", help="Record camera frames losslessly, every frame (an exact replay; ~1.3 MB per RGBD frame) "
    "instead of JPEG colour and 2 Hz depth.")]
LiveOpt = Annotated[bool, typer.Option("--live", help="Stream the run live to Foxglove (WebSocket, port 8765).")]
LivePortOpt = Annotated[str | None, typer.Option(
    "--live-port", help="Live view port, or HOST:PORT (not loopback: needs QCARLAB_TOKEN).", show_default=False)]
RealismOpt = Annotated[str | None, typer.Option(
    "--realism", help="The simulator's imperfections: [b]lab[/b] (the default: steering trim, play and delay, tyre "
    "slip, gyro drift, LIDAR dropouts, camera exposure and blur, as a real QCar has them; qcarlab/realism/lab.yaml "
    "gives each value and its source), [b]ideal[/b] (none: the exact model), or a profile YAML.",
    show_default=False)]
_realism_choice: contextvars.ContextVar[str | None] = contextvars.ContextVar("realism", default=None)
_opened_realism: contextvars.ContextVar[str | None] = contextvars.ContextVar("opened_realism", default=None)


DEFAULT_REALISM = "lab"  # a lab command's simulator is the real car's (the Python API's default is ideal)


def sim_realism() -> str:
    """The realism profile a simulated car of this command gets: --realism, else ``lab``."""
    return _realism_choice.get() or DEFAULT_REALISM


TopicsOpt = Annotated[str | None, typer.Option(
    "--topics", help="--car replay:BAG: the rosbag2's topics for the car's sensors, e.g. "
    "scan=/scan,color=/camera/color/image_raw,depth=/camera/depth/image_rect_raw.", show_default=False)]
ReplayToleranceOpt = Annotated[float | None, typer.Option(
    "--replay-tolerance", min=0.0, help="--car replay: the largest throttle and steering (rad) difference counted as "
    "the same command (default 1e-9, or 0.02 on a compact recording's camera frames); beyond it, exit 1.",
    show_default=False)]


def mark_run_start(out: Path | None) -> None:
    """Mark --out as holding a run in progress (removed when the run's results are saved), so a run
    killed before saving never leaves an earlier run's results there looking like its own. (Done
    when the command runs, not when its options are parsed: the grader parses commands too.)"""
    if out is not None:
        from qcarlab.record import mark_in_progress

        mark_in_progress(out, "qcarlab " + " ".join(sys.argv[1:]))


def recordable(command):
    """Give a driving command --record, --record-exact, --live, --live-port, --topics and
    --realism (one decorator line under ``@app.command``); the car it opens is then recorded or
    replayed, and a simulated one has the realism profile asked for (``lab`` by default). Its
    --out is marked as holding a run in progress (:func:`mark_run_start`); a long run shows a
    progress bar on a terminal (:mod:`qcarlab.cli.progress`)."""
    import functools
    import inspect
    from typing import get_type_hints

    added = {"record": (RecordOpt, None), "record_exact": (RecordExactOpt, False), "live": (LiveOpt, False),
             "live_port": (LivePortOpt, None), "topics": (TopicsOpt, None), "realism": (RealismOpt, None),
             "replay_tolerance": (ReplayToleranceOpt, None)}

    label = command.__name__.removesuffix("_cmd").replace("_", "-")
    # a progress bar for a long run on a terminal, but not beside a live view of the command's own
    # (keyboard-drive, io-test's table) nor --trials' lines
    bars = label not in ("keyboard-drive", "io-test")

    @functools.wraps(command)
    def run(*args, record=None, record_exact=False, live=False, live_port=None, topics=None, realism=None,
            replay_tolerance=None, **kwargs):
        from qcarlab.cli import recording
        from qcarlab.cli.progress import progress_bars

        token, opened = _realism_choice.set(realism), _opened_realism.set(None)
        mark_run_start(kwargs.get("out"))
        quiet = not bars or bool(kwargs.get("json_out")) or bool(kwargs.get("trials"))
        try:
            with recording.request(record, record_exact, live, live_port, topics, replay_tolerance), \
                    progress_bars(label, quiet):
                return command(*args, **kwargs)
        finally:
            _realism_choice.reset(token)
            _opened_realism.reset(opened)

    sig = inspect.signature(command, eval_str=True)
    extra = [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=annotation)
             for name, (annotation, default) in added.items()]
    run.__signature__ = sig.replace(parameters=[*sig.parameters.values(), *extra])
    run.__annotations__ = {**get_type_hints(command, include_extras=True),
                           **{name: annotation for name, (annotation, _) in added.items()}}
    return run

stdout = Console(highlight=False)


def opencv_single_threaded() -> None:
    """OpenCV's calls in this process on the calling thread only (``cv2.setNumThreads(1)``), for a
    run on the simulator. Its thread pool splits a 640x480 frame's colour conversion and
    thresholds across the cores, which costs more than it saves at that size: a 15 s lane-follow
    took 1.18 s of CPU and 0.90 s by the clock with the pool, 0.85 s and 0.85 s without (2-core
    Xeon VM, benchmarks/bench_record.py's plain runs), and a grader running one task per core
    gets nothing from it. The numbers are the same either way."""
    import cv2

    cv2.setNumThreads(1)


def open_from_options(
    car: str,
    world: str | None = None,
    seed: int = 0,
    realtime: bool = False,
    params: Path | None = None,
    **extra: Any,
) -> Car:
    """Open the car the shared options describe; with --record/--live, wrapped to record it
    (``path=`` is the reference path for the recording's scene)."""
    from qcarlab.cli import recording

    path = extra.pop("path", None)
    sensors = extra.pop("sensors", None)  # those the command reads: a live view advertises their channels
    if parse_car_uri(car)[0] == "replay":
        extra.setdefault("topics", recording.replay_topics())
    if parse_car_uri(car)[0] == "sim":
        extra.setdefault("realism", sim_realism())
        if sensors is None or set(sensors) & {"rgbd", "csi"} or "cv2" in sys.modules:
            opencv_single_threaded()  # (a LIDAR lab draws nothing with OpenCV: not imported for it, 0.02-0.05 s)
    elif _realism_choice.get() is not None:
        extra["realism"] = _realism_choice.get()  # refused by open_car with the reason
    qcar = open_car(car, world=world, seed=seed, realtime=realtime, params=params, **extra)
    if getattr(qcar, "realism", None) is not None:
        _opened_realism.set(qcar.realism.name)
    return recording.wrap(qcar, car=car, world=world, seed=seed, path=path, start=extra.get("start"), sensors=sensors)


#: The options that only set qcarlab's own block of that name: a student's block in its place makes
#: them meaningless (it is called with the sheet's arguments, not with these).
SETS_BLOCK = {"speed_controller": ("kp", "ki", "kff"), "color_thresholding_hsv": ("hsv_min", "hsv_max"),
              "find_objects": ("min_area",), "linear_poly_fit": ("min_pixels",)}


def _typed(ctx: Any, name: str) -> bool:
    """True when the command's option ``name`` was typed on the command line (not its default)."""
    if ctx is None or name not in {p.name for p in ctx.command.params}:
        return False
    try:
        source = ctx.get_parameter_source(name)
    except Exception:  # noqa: BLE001
        return False
    return getattr(source, "name", None) == "COMMANDLINE"


def student_blocks(model: Any, use: list[Path] | None, block: list[str] | None, ctx: Any = None) -> dict[str, Any]:
    """The student's blocks for a lab model class from --use/--block; says on stderr which are used,
    and (given the command's context) warns, one line each, of a typed option a student's block
    makes meaningless."""
    from qcarlab.blocks import resolve_student_blocks

    found = resolve_student_blocks(model.specs(), model.lab, use or (), block or ())
    if found:
        listed = ", ".join(f"{name} ({b.source})" for name, b in found.items())
        stderr.print(f"{model.lab}: your blocks: {listed}", markup=False)
    for name in found:
        for option in SETS_BLOCK.get(name, ()):
            if _typed(ctx, option):
                flag = "--" + option.replace("_", "-")
                stderr.print(f"{model.lab}: warning: {flag} is not used: it sets qcarlab's {name}, which your "
                             f"{name} replaces", markup=False)
    return found


#: Where a block that was never called would have been (the option that runs it).
_CALLED_WITH = {"follow_the_carrot": "--controller carrot", "stanley": "--controller stanley",
                "pure_pursuit": "--controller pure-pursuit", "lidar_stop": "--strategy stop",
                "lidar_steer": "--strategy steer", "lidar_avoid": "--strategy student",
                "depth_windows": "--strategy depth", "depth_avoid": "--strategy depth"}


def never_called(metrics: dict[str, Any]) -> list[str]:
    """The student's blocks a run that ticked never called (a sweep: its best run's), each as a warning."""
    mine = metrics.get("student_blocks")
    loop = metrics.get("loop") or {}
    best = metrics.get("best")
    if mine is None and isinstance(best, dict):
        mine, loop = best.get("student_blocks"), best.get("loop") or {}
    if not isinstance(mine, dict) or not loop.get("ticks"):
        return []
    out = []
    for block, timing in mine.items():
        if isinstance(timing, dict) and timing.get("calls") == 0:
            hint = f"; {_CALLED_WITH[block]} uses it" if block in _CALLED_WITH else \
                "; this run's options do not use it"
            out.append(f"your {block} ({timing.get('source')}) was never called in this run{hint}")
    return out


def lab_section(params: Path | None) -> dict[str, Any]:
    """The ``lab:`` section of a --params file (the lab's tunables), or {}."""
    if params is None:
        return {}
    from qcarlab.yamlio import load_yaml

    data = load_yaml(params, "parameter file")
    lab = data.get("lab") if isinstance(data, dict) else None
    if lab is None:
        return {}
    if not isinstance(lab, dict):
        raise InputError(f"{params}: lab: expected a mapping of tunable: value, got {type(lab).__name__}")
    return lab


def apply_tunables(cfg: Any, params: Path | None, ctx: typer.Context | None, ignore: tuple[str, ...] = ()) -> Any:
    """Set the config's fields from the --params file's ``lab:`` section; an option typed on the
    command line wins over the file. Unknown names are refused with the known ones listed."""
    import dataclasses

    lab = lab_section(params)
    if not lab:
        return cfg
    known = {f.name: f for f in dataclasses.fields(cfg) if f.name not in ignore}
    for key, value in lab.items():
        name = str(key).replace("-", "_")
        if name in ignore:  # set by the command itself (e.g. a look-ahead sweep)
            continue
        if name not in known:
            raise InputError(f"{params}: lab: unknown tunable {key!r} (known: {', '.join(known)})")
        if ctx is not None:
            try:
                source = ctx.get_parameter_source(name)
            except Exception:  # noqa: BLE001 - not a CLI option of this command
                source = None
            if getattr(source, "name", None) == "COMMANDLINE":  # click's enum (typer may vendor click)
                continue
        current = getattr(cfg, name)
        if value is None and current is not None:  # the template leaves the student's choices empty
            raise InputError(f"{params}: lab: {key} is empty: it is yours to choose (see the comment above it "
                             f"in the file); fill it in, or give --{name.replace('_', '-')} on the command line")
        if isinstance(current, tuple) and isinstance(value, list):
            value = tuple(value)
        if isinstance(current, bool) and not isinstance(value, bool):
            raise InputError(f"{params}: lab: {key} must be true or false, got {value!r}")
        if isinstance(current, (int, float)) and not isinstance(current, bool) and (
                isinstance(value, bool) or not isinstance(value, (int, float))):
            raise InputError(f"{params}: lab: {key} must be a number, got {value!r}")
        if isinstance(current, float) and isinstance(value, int):
            value = float(value)
        setattr(cfg, name, value)
    return cfg


def interactive(json_out: bool) -> bool:
    """Live views and progress bars only on a terminal, never with --json."""
    return not json_out and sys.stdout.isatty()


def emit(result: Result, json_out: bool, out: Path | None, summary) -> None:
    """Save to --out, then print JSON (with --json) or the human summary (and, after a replay,
    what the lab would have commanded beside what was commanded); then the exit code.

    A run that missed its goal (``goal_reached`` false: time limit, collision, left the world,
    stopped past the sign) says why on stderr and exits 1; an interrupted run exits 130 after
    its results were saved. Student blocks slower than the tick on a real-time car are reported.
    """
    from qcarlab.cli import recording
    from qcarlab.cli.invocation import record_invocation, write_for_grader

    if _opened_realism.get() is not None:  # the simulator's realism profile, beside the numbers it made
        result.metrics.setdefault("realism", _opened_realism.get())
    record_invocation(result.metrics)  # the command and parameters, so qcarlab grade knows the run
    after = recording.after_run(result)
    written = result.save(out) if out is not None else []
    m = result.metrics
    write_for_grader(m)  # $QCARLAB_RESULTS, set by qcarlab grade
    if json_out:
        sys.stdout.write(dumps(m) + "\n")
    else:
        summary(result)
        recording.print_after(after, stdout)
        if written:
            stdout.print(f"wrote {len(written)} file(s) to {out}: " + ", ".join(p.name for p in written))
    name = m.get("experiment", result.name)
    for block, timing in (m.get("student_blocks") or {}).items():
        if timing.get("over_budget"):
            stderr.print(f"{name}: warning: your {block} took longer than the {timing['budget_s'] * 1000:.1f} ms tick "
                         f"{timing['over_budget']} time(s) (worst {timing['worst_s'] * 1000:.1f} ms)", markup=False)
    for warning in never_called(m):
        stderr.print(f"{name}: warning: {warning}", markup=False)
    for note in m.get("notes") or ():
        stderr.print(f"{name}: note: {note}", markup=False)
    loop = m.get("loop") or {}
    if loop.get("overruns"):
        stderr.print(f"{name}: warning: {loop['overruns']} tick(s) started late (worst gap "
                     f"{loop['worst_tick_s'] * 1000:.0f} ms); the blocks were given the real dt", markup=False)
    if m.get("interrupted"):
        stderr.print(f"qcarlab {name}: interrupted; the car was stopped"
                     + (f"; the run so far was saved to {out}" if written else ""), markup=False)
        import importlib

        _app = importlib.import_module("qcarlab.cli.app")  # the module (qcarlab.cli.app is also the Typer)

        _app.interrupt_reported = True
        raise typer.Exit(130)
    if m.get("goal_reached") is False and "replay" not in m:  # a replay's car did what was recorded
        stderr.print(f"qcarlab {name}: goal missed: {m.get('failure') or 'see the results'}", markup=False)
        raise typer.Exit(1)
    replay = m.get("replay") or {}
    if replay.get("recorded_ticks") and not replay.get("within_tolerance", True) and replay.get("lossy"):
        stderr.print(f"{name}: note: the replay's commands differ from the recording in "
                     f"{replay['ticks_beyond_tolerance']} tick(s): the recording keeps the camera's frames "
                     "compressed (JPEG colour, 2 Hz depth), so the lab saw other pixels than the car did; record "
                     "with --record-exact for a replay that must reproduce them (or give --replay-tolerance to "
                     "hold this one to a bound)", markup=False)
    elif replay.get("recorded_ticks") and not replay.get("within_tolerance", True):
        stderr.print(f"qcarlab {name}: the replay differs from the recording: {replay['ticks_beyond_tolerance']} "
                     f"tick(s) beyond the tolerance ({replay['tolerance']:.3g}; largest difference throttle "
                     f"{replay['max_throttle_difference']:.3g}, steering {replay['max_steering_difference_rad']:.3g} rad)",
                     markup=False)
        raise typer.Exit(1)


class Table(_rich_table.Table):
    """rich's Table whose cells wrap at the terminal's width, a word wider than its column (a
    file's path, a long number) folding onto the next line instead of being cut with an ellipsis.
    A column can still ask for its own ``overflow``."""

    def add_column(self, *args: Any, overflow: Any = "fold", **kwargs: Any) -> None:
        super().add_column(*args, overflow=overflow, **kwargs)


def summary_table(title: str) -> Table:
    """The two-column "what / value" table every command's human summary prints."""
    table = Table(title=title, title_justify="left", show_header=False)
    table.add_column("what")
    table.add_column("value", justify="right")
    return table

from qcarlab.control.speed import KFF, KI, KP  # noqa: E402,F401  (the gains' defaults, written once)

KpOpt = Annotated[float, typer.Option("--kp", help="speed_controller proportional gain.")]
KiOpt = Annotated[float, typer.Option("--ki", help="speed_controller integral gain.")]
KffOpt = Annotated[float, typer.Option("--kff", help="speed_controller feed-forward gain.")]


def parse_start(text: str | None) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--start {text!r}: expected X,Y,YAW as three numbers") from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise InputError(f"--start {text!r}: expected X,Y,YAW as three finite numbers")
    return values


def sim_world(car: str, world: str | None, start: str | None, default: str, params: Path | None):
    """Load the world for a simulated car; refuse simulator-only options for a remote car."""
    pose = parse_start(start)
    scheme, where, _ = parse_car_uri(car)
    if scheme == "replay":  # the world and start the lab scores against: given, else the recording's
        from qcarlab.cli import recording

        recorded, recorded_pose = recording.recorded_world(where, params) if world is None else (None, None)
        from qcarlab.experiments.worlds import load_world

        return (load_world(world, load_params(params)) if world is not None else recorded), pose or recorded_pose
    if scheme != "sim":
        if world is not None or pose is not None:
            raise InputError("--world and --start apply to the simulator only; a remote car is where it is")
        return None, None
    from qcarlab.experiments.worlds import check_start, load_world

    p = load_params(params)
    world_obj = load_world(world or default, p)
    check_start(world_obj, pose, p)
    return world_obj, pose


def parse_hsv(text: str, option: str) -> tuple[int, int, int]:
    """'H,S,V' -> three ints (checked by the experiment's config: H 0..179, S and V 0..255)."""
    words = [w.strip() for w in text.split(",")]
    if len(words) != 3:
        raise InputError(f"{option} {text!r}: expected H,S,V as three numbers (e.g. 170,100,100)")
    try:
        values = [float(w) for w in words]
    except ValueError:
        raise InputError(f"{option} {text!r}: expected H,S,V as three numbers (e.g. 170,100,100)") from None
    if not all(math.isfinite(v) and v.is_integer() for v in values):
        raise InputError(f"{option} {text!r}: H,S,V must be whole numbers")
    return tuple(int(v) for v in values)
