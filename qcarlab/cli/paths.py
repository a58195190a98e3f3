"""``qcarlab path-gen`` and ``qcarlab path-follow`` (lab sheet section 4)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from qcarlab import paths, plots
from qcarlab.car import parse_car_uri
from qcarlab.cli.app import app, stderr
from qcarlab.cli.common import recordable  # noqa: I001  (--record, --live)
from qcarlab.cli.common import (
    Table,
    CarTokenOpt,
    KpOpt, KiOpt, KffOpt, KP, KI, KFF, UseOpt, BlockOpt, student_blocks, apply_tunables,
    check_out,
    CarOpt, DebugOpt, JsonOpt, OutOpt, ParamsOpt, RateOpt, RealtimeOpt, SeedOpt, WorldOpt,
    emit, open_from_options, sim_world, stdout, summary_table,
)
from qcarlab.constants import DEFAULT_PARAMS, load_params
from qcarlab.errors import InputError
from qcarlab.experiments.path_follow import CONTROLLERS, POSE_SOURCES, FollowConfig, PathFollowingLab, follow_path, lookahead_sweep
from qcarlab.experiments.result import Result
from qcarlab.experiments.step_response import step_response, step_start
from qcarlab.record import dumps

SHAPES = ", ".join(paths.BUILTIN)

# the shape options both commands accept
LengthOpt = Annotated[float | None, typer.Option(help="line: length in m (sheet Task 1: 3).", show_default=False)]
PointsOpt = Annotated[int | None, typer.Option(help="line: number of waypoints (sheet: 4).", show_default=False)]
RadiusOpt = Annotated[float | None, typer.Option(help="circle: radius in m (sheet Task 2: 1.5).", show_default=False)]
StepOpt = Annotated[float | None, typer.Option(help="circle: angle step in rad (sheet: 0.1).", show_default=False)]
SizeOpt = Annotated[
    float | None,
    typer.Option(help="butterfly: the sheet's wingWidth = wingHeight in m (4 = p3, 2 = p4); x = W sin(wt), y = -H sin(2wt), so the path spans 2S x 2S.", show_default=False),
]
WidthOpt = Annotated[float | None, typer.Option(help="butterfly: wingWidth W in m (x spans -W..W).", show_default=False)]
HeightOpt = Annotated[float | None, typer.Option(help="butterfly: wingHeight H in m (y spans -H..H).", show_default=False)]


def _shape_options(shape: str, length, points, radius, step, size, width, height) -> dict:
    given = {"length": length, "points": points, "radius": radius, "step": step, "size": size,
             "width": width, "height": height}
    allowed = {"line": {"length", "points"}, "circle": {"radius", "step"},
               "butterfly": {"size", "width", "height"}}.get(shape, set())
    extra = [k for k, v in given.items() if v is not None and k not in allowed]
    if extra:
        raise InputError(f"--{extra[0]} does not apply to '{shape}' (it takes: "
                         + ", ".join(f"--{k}" for k in sorted(allowed)) + ")")
    opts = {k: v for k, v in given.items() if v is not None}
    if "size" in opts:
        size = opts.pop("size")
        opts.setdefault("width", size)
        opts.setdefault("height", size)
    return opts


def _load_path(spec: str, options: dict) -> tuple[np.ndarray, str]:
    """A built-in name (with its options) or a path file."""
    if spec in paths.BUILTIN:
        return paths.builtin(spec, **options), spec
    if options:
        raise InputError(f"shape options ({', '.join('--' + k for k in options)}) apply to built-in paths only")
    file = Path(spec)
    if not file.exists() and not file.suffix:
        raise InputError(f"'{spec}' is neither a built-in path ({SHAPES}) nor a file")
    return paths.read_path(file), file.stem


def _warn_tight_spots(summary: dict) -> None:
    spots = summary["tight_spots"]
    if not spots:
        return
    r_min = DEFAULT_PARAMS.min_turning_radius
    where = "; ".join(f"({s['x']:+.2f}, {s['y']:+.2f}) r = {s['radius_m']:.2f} m" for s in spots)
    stderr.print(f"warning: the path turns tighter than the car can (minimum turning radius {r_min:.3f} m) "
                 f"at {len(spots)} place(s): {where}", markup=False)


@app.command("path-gen")
def path_gen_cmd(
    shape: Annotated[str, typer.Argument(help=f"Built-in path: {SHAPES}.")],
    length: LengthOpt = None,
    points: PointsOpt = None,
    radius: RadiusOpt = None,
    step: StepOpt = None,
    size: SizeOpt = None,
    width: WidthOpt = None,
    height: HeightOpt = None,
    fmt: Annotated[str, typer.Option("--format", help="File format: csv (header x,y), npy or yaml.")] = "csv",
    name: Annotated[str | None, typer.Option(help="File name without extension (default: the shape).")] = None,
    out: Annotated[Path, typer.Option("--out", help="Folder for the path file and its plot.", callback=check_out)] = Path("."),
    plot: Annotated[bool, typer.Option("--plot/--no-plot", help="Write a PNG plot of the path.")] = True,
    json_out: JsonOpt = False,
    debug: DebugOpt = False,
) -> None:
    """Generate a reference path (sheet 4.2.1): the line p1, the circle p2, the butterflies p3/p4.

    Examples:
      qcarlab path-gen line --length 3 --points 4
      qcarlab path-gen circle
      qcarlab path-gen butterfly --size 2 --out paths/
    """
    if fmt not in paths.FORMATS:
        raise InputError(f"--format must be one of {', '.join(paths.FORMATS)}, got {fmt!r}")
    if shape not in paths.BUILTIN:
        raise InputError(f"unknown path '{shape}' (built-in paths: {SHAPES})")
    if name is not None and (not name.strip() or any(c in name for c in "/\\\0") or name in (".", "..")):
        raise InputError(f"--name must be a file name without a folder (no / or \\), got {name!r}; the folder is --out")
    path = paths.builtin(shape, **_shape_options(shape, length, points, radius, step, size, width, height))
    summary = paths.summary(path)
    from qcarlab.record import prepare_out_dir

    folder = prepare_out_dir(out)
    stem = name or shape
    files = [paths.write_path(path, folder / f"{stem}.{fmt}", fmt)]
    if plot:
        files.append(plots.plot_path(path, folder / f"{stem}.png", title=f"{shape} ({len(path)} points)",
                                     tight_spots=summary["tight_spots"]))
    summary = {"shape": shape, **summary, "files": [str(f) for f in files]}
    if json_out:
        print(dumps(summary))
        return
    _warn_tight_spots(summary)
    table = summary_table(f"path-gen {shape}")
    table.add_row("points", str(summary["points"]))
    table.add_row("length", f"{summary['length_m']:.3f} m")
    x0, y0, x1, y1 = summary["bbox"]
    table.add_row("bounding box", f"x {x0:+.2f}..{x1:+.2f} m, y {y0:+.2f}..{y1:+.2f} m")
    r = summary["tightest_radius_m"]
    table.add_row("tightest radius", "straight" if r is None else f"{r:.3f} m")
    table.add_row("files", ", ".join(str(f) for f in files))
    stdout.print(table)


def _parse_lookaheads(text: str) -> list[float]:
    values = []
    for word in text.split(","):
        try:
            value = float(word)
        except ValueError:
            raise InputError(f"--lookahead: '{word.strip()}' is not a number (e.g. 0.3 or 0.2,0.3,0.5)") from None
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"--lookahead must be positive metres, got {word.strip()}")
        values.append(value)
    return values


def _follow_summary(result: Result) -> None:
    m = result.metrics
    table = summary_table(f"path-follow ({m['config']['controller']}, look-ahead {m['config']['lookahead']} m)")
    table.add_row("RMS cross-track error", f"{m['rms_cross_track_m'] * 100:.1f} cm")
    table.add_row("max cross-track error", f"{m['max_cross_track_m'] * 100:.1f} cm at "
                  f"({m['worst_point'][0]:+.2f}, {m['worst_point'][1]:+.2f})")
    table.add_row("completion", f"{m['completion'] * 100:.1f} %")
    table.add_row("duration", f"{m['duration_s']:.2f} s")
    table.add_row("mean speed", f"{m['mean_speed_mps']:.3f} m/s")
    table.add_row("speed RMS error", f"{m['speed_rms_error_mps']:.3f} m/s")
    table.add_row("final distance to goal", f"{m['final_distance_to_goal_m'] * 100:.1f} cm"
                  + ("" if m["stopped_at_goal"] else "  (where its estimate put the end)"
                     if m.get("reached_by_estimate") else "  (did not stop: time limit)"))
    if "pose_drift_m" in m:
        table.add_row(f"pose estimate drift ({plots.estimate_label(m['config']['pose'], short=True)})", f"{m['pose_drift_m'] * 100:.1f} cm"
                      + (f"  ({m['pose_drift_per_m'] * 100:.1f} cm per m driven)" if "pose_drift_per_m" in m else ""))
    if m.get("realism"):
        table.add_row("simulator realism", str(m["realism"]))
    stdout.print(table)


def _sweep_summary(result: Result) -> None:
    runs = result.metrics["runs"]
    estimated = all("rms_cross_track_estimate_m" in r for r in runs)
    table = Table(title="look-ahead sweep, ranked by the tracking error the controller sees"
                  + (" (its pose estimate against the path)" if estimated else ""), title_justify="left")
    cols = ["rank", "L_a m", "track RMS cm"] + (["true RMS cm", "drift cm"] if estimated else []) \
        + ["max cm", "done %", "goal"]
    for col in cols:
        table.add_column(col, justify="left" if col == "goal" else "right")
    for i, run in enumerate(runs, 1):
        row = [str(i), f"{run['lookahead']:.2f}"]
        if estimated:
            drift = run.get("pose_drift_m")
            row += [f"{run['rms_cross_track_estimate_m'] * 100:.1f}", f"{run['rms_cross_track_m'] * 100:.1f}",
                    "-" if drift is None else f"{drift * 100:.1f}"]
        else:
            row.append(f"{run['rms_cross_track_m'] * 100:.1f}")
        row += [f"{run['max_cross_track_m'] * 100:.1f}", f"{run['completion'] * 100:.1f}",
                "reached" if run.get("goal_reached", True) else "MISSED"]
        table.add_row(*row)
    stdout.print(table)
    for run in runs:
        if not run.get("goal_reached", True):
            stdout.print(f"look-ahead {run['lookahead']:g} m missed its goal: {run.get('failure') or 'not reached'}")
    best = result.metrics["best"]
    err = best.get("rms_cross_track_estimate_m", best["rms_cross_track_m"])
    stdout.print(f"best look-ahead: {best['lookahead']} m (tracking RMS {err * 100:.1f} cm"
                 + (f", true RMS {best['rms_cross_track_m'] * 100:.1f} cm with the drift" if estimated else "") + ")")
    if estimated:
        stdout.print("small look-aheads weave round the path, large ones cut its corners; the true error adds the "
                     "dead reckoning's drift, which no look-ahead sees (--pose truth removes it)", style="dim")


def _step_summary(result: Result) -> None:
    m = result.metrics
    yours = m["controller"].startswith("your")
    gains = "your speed_controller" if yours else f"Kp {m['kp']}, Ki {m['ki']}, Kff {m['kff']}"
    table = summary_table(f"speed step 0 -> {m['speed_step_mps']} m/s ({gains})")
    if yours:
        table.add_row("controller", m["controller"].removeprefix("your speed_controller ").strip("()"))

    def fmt(v, unit):
        return "n/a" if v is None else f"{v:.3f} {unit}"

    table.add_row("rise time (10-90 %)", fmt(m["rise_time_s"], "s"))
    table.add_row("overshoot", f"{m['overshoot_pct']:.1f} %")
    table.add_row("settling time (2 %)", fmt(m["settling_time_s"], "s") if m["settling_time_s"] is not None
                  else "not settled")
    table.add_row("steady-state error", fmt(m["steady_state_error_mps"], "m/s"))
    if "throttle_chatter" in m:
        table.add_row("throttle chatter (RMS change a tick, last s)", f"{m['throttle_chatter']:.4f}")
        table.add_row("throttle at its limit", f"{m['throttle_saturated_s']:.2f} s")
    stdout.print(table)


@app.command("path-follow")
@recordable
def path_follow_cmd(
    ctx: typer.Context,
    path_spec: Annotated[str, typer.Argument(metavar="PATH", help=f"A built-in path ({SHAPES}) or a CSV/npy/YAML path file.")],
    length: LengthOpt = None,
    points: PointsOpt = None,
    radius: RadiusOpt = None,
    step: StepOpt = None,
    size: SizeOpt = None,
    width: WidthOpt = None,
    height: HeightOpt = None,
    controller: Annotated[str, typer.Option(help="Steering: pure-pursuit (delta = atan(2 L sin(alpha) / l_d)), "
                                            "carrot (delta = K_carrot Psi_e) or stanley.")] = "pure-pursuit",
    lookahead: Annotated[str, typer.Option(help="Look-ahead distance l_d in m (pure pursuit: from the rear "
                                           "axle; far below the 0.47 m turning radius the car weaves); a list "
                                           "(0.2,0.3,0.5,0.8) runs a sweep ranked by the tracking error (sheet 4.2.2 Tasks 3-4).")] = "0.3",
    k_carrot: Annotated[float, typer.Option(help="Follow-the-carrot gain K_carrot.")] = 1.0,
    k_stanley: Annotated[float, typer.Option(help="Stanley cross-track gain.")] = 2.0,
    speed: Annotated[float, typer.Option(help="Desired speed, m/s.")] = 0.5,
    kp: KpOpt = KP,
    ki: KiOpt = KI,
    kff: KffOpt = KFF,
    pose: Annotated[str, typer.Option(help="Pose estimate: bicycle (encoder + steering, the sheet's model), "
                                      "gyro (encoder + gyro yaw rate) or truth (simulator only).")] = "bicycle",
    goal_tolerance: Annotated[float, typer.Option(help="Stop within this distance of the last point, m.")] = 0.1,
    laps: Annotated[int, typer.Option(help="Laps of a closed path.")] = 1,
    turn_speed: Annotated[bool, typer.Option("--turn-speed/--no-turn-speed",
                                             help="Slow down in turns (turn_speed_handling).")] = False,
    step_response_: Annotated[bool, typer.Option("--step-response", help="Instead of a path: drive a speed step "
                                                 "of --speed and report rise/settling time, overshoot (sheet 4.2.3).")] = False,
    max_time: Annotated[float | None, typer.Option(help="Give up after this many simulated seconds.",
                                                   show_default=False)] = None,
    rate: RateOpt = 100.0,
    car: CarOpt = "sim",
    token: CarTokenOpt = None,
    world: WorldOpt = None,
    seed: SeedOpt = 0,
    out: OutOpt = None,
    json_out: JsonOpt = False,
    realtime: RealtimeOpt = False,
    params: ParamsOpt = None,
    use: UseOpt = None,
    block: BlockOpt = None,
    debug: DebugOpt = False,
) -> None:
    """Follow a path with pure pursuit (or carrot, stanley) and the feed-forward PI speed controller.

    Examples:
      qcarlab path-follow circle
      qcarlab path-follow butterfly --size 2 --lookahead 0.2,0.3,0.5,0.8
      qcarlab path-follow my_path.csv --out runs/1
      qcarlab path-follow line --step-response --kp 0.5 --ki 2

    With your own blocks and tunables (qcarlab template path-follow --out mylab):
      qcarlab path-follow butterfly --use mylab/pure_pursuit.py
      qcarlab path-follow butterfly --params mylab/params.yaml

    Exit 0 when the car reached the end of the path, 1 when it did not (time limit, a wall, out of the
    world), 2 for bad input.
    """
    if controller not in CONTROLLERS:
        raise InputError(f"--controller must be one of {', '.join(CONTROLLERS)}, got {controller!r}")
    if pose not in POSE_SOURCES:
        raise InputError(f"--pose must be one of {', '.join(POSE_SOURCES)}, got {pose!r}")
    lookaheads = _parse_lookaheads(lookahead)
    if max_time is not None and not (math.isfinite(max_time) and max_time > 0):
        raise InputError(f"--max-time must be a positive number of seconds, got {max_time}")
    options = _shape_options(path_spec, length, points, radius, step, size, width, height) \
        if path_spec in paths.BUILTIN else {k: v for k, v in dict(length=length, points=points, radius=radius,
                                                                   step=step, size=size, width=width,
                                                                   height=height).items() if v is not None}
    ref, label = _load_path(path_spec, options)
    mine = student_blocks(PathFollowingLab, use, block, ctx)
    world_obj, _ = sim_world(car, world, None, "studio", params)

    def open_car():
        return open_from_options(car, world_obj, seed, realtime, params, path=ref, token=token, sensors=())

    if step_response_:  # the speed loop alone, with the student's speed blocks and the params' gains
        cfg = FollowConfig(speed=speed, kp=kp, ki=ki, kff=kff, rate=rate)
        apply_tunables(cfg, params, ctx)  # --kp/--ki/--kff/--speed typed here win over the file
        start = step_start(world_obj, load_params(params)) if parse_car_uri(car)[0] == "sim" else None
        with open_from_options(car, world_obj, seed, realtime, params, path=ref, token=token, start=start,
                               sensors=()) as qcar:
            result = step_response(qcar, cfg, duration=max_time or 6.0, blocks=mine, world=world_obj)
        result.metrics.update({"car": car, "seed": seed})
        result.figures["step.png"] = lambda f: plots.plot_step_response(result.logs["log.csv"], result.metrics, f)
        emit(result, json_out, out, _step_summary)
        return

    def run(la: float) -> Result:
        cfg = FollowConfig(controller=controller, lookahead=la, k_carrot=k_carrot, k_stanley=k_stanley,
                           speed=speed, kp=kp, ki=ki, kff=kff, pose=pose, goal_tolerance=goal_tolerance,
                           laps=laps, rate=rate, turn_speed=turn_speed, max_time=max_time)
        apply_tunables(cfg, params, ctx, ignore=() if len(lookaheads) == 1 else ("lookahead",))
        cfg.check()
        with open_car() as qcar:
            res = follow_path(qcar, ref, cfg, blocks=mine, world=world_obj)
        res.metrics["path"] = label
        res.metrics.update({"car": car, "seed": seed})
        return res

    if len(lookaheads) == 1:
        result = run(lookaheads[0])
        log = result.logs["log.csv"]
        result.figures["path.png"] = lambda f: plots.plot_follow(ref, log, result.metrics, f)
        result.figures["speed.png"] = lambda f: plots.plot_speed(log, f)
        emit(result, json_out, out, _follow_summary)
        return

    runs = [run(la) for la in lookaheads]
    sweep = lookahead_sweep(runs, label)
    ranked = sweep.data["ranked"]
    sweep.figures["sweep.png"] = lambda f: plots.plot_sweep(ref, [(r.metrics["config"]["lookahead"], r.logs["log.csv"],
                                                                   r.metrics) for r in ranked], f)
    emit(sweep, json_out, out, _sweep_summary)
