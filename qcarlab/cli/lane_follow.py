"""``qcarlab lane-follow`` (lab sheet 5.3): follow the lane with the RGBD camera; ``--hsv-tune``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from qcarlab import plots
from qcarlab.cli.app import app
from qcarlab.cli.common import recordable, sim_realism  # noqa: I001  (--record, --live, --realism)
from qcarlab.cli.common import (
    CarTokenOpt,
    StartOpt, WorldOpt, sim_world, parse_hsv, UseOpt, BlockOpt, student_blocks, apply_tunables,
    CarOpt,
    DebugOpt,
    JsonOpt,
    OutOpt,
    ParamsOpt,
    RateOpt,
    RealtimeOpt,
    SeedOpt,
    emit,
    open_from_options,
    stdout,
    summary_table,
)
from qcarlab.cli.trials import MinSuccessOpt, TrialsOpt, check_trials, given, progress, trials_summary
from qcarlab.constants import load_params
from qcarlab.errors import InputError
from qcarlab.experiments.lane_follow import (
    LaneFollowingLab,
    start_in_lane,
    LaneFollowConfig,
    hsv_tune,
    lane_centre,
    run_lane_follow,
    tune_spots,
)
from qcarlab.experiments.result import Result
from qcarlab.perception.lane import LANES, YELLOW_HSV_MAX, YELLOW_HSV_MIN


def _fmt(value, unit: str = "m", digits: int = 3) -> str:
    return "n/a" if value is None else f"{value:.{digits}f} {unit}"


def _summary(result: Result) -> None:
    m = result.metrics
    if m.get("mode") == "hsv-tune":
        table = summary_table(f"lane-follow --hsv-tune ({m['lane']} lane, HSV {m['hsv_min']} .. {m['hsv_max']})")
        for s in m["spots"]:
            table.add_row(f"spot {s['pose'][0]:.2f}, {s['pose'][1]:.2f}",
                          f"{s['pixels_in_region']} px in region ({s['pixels_whole_image']} in image)"
                          + ("" if s["line_found"] else ", NO LINE"))
        stdout.print(table)
        return
    table = summary_table(f"lane-follow ({m['lane']} lane, {m['speed_mps']:g} m/s)")
    table.add_row("RMS lateral deviation", _fmt(m["rms_lateral_deviation_m"]))
    table.add_row("max lateral deviation", _fmt(m["max_lateral_deviation_m"]))
    table.add_row("time out of lane", _fmt(m["time_out_of_lane_s"], "s", 2))
    table.add_row("distance along the lane", _fmt(m["distance_along_lane_m"], "m", 2))
    table.add_row("laps", _fmt(m["laps"], "", 2))
    table.add_row("duration, mean speed", f"{m['duration_s']:.2f} s, {m['mean_speed_mps']:.3f} m/s")
    table.add_row("frames: yellow line / white backup / lost", f"{m['frames_yellow']} / {m['frames_white_backup']} / "
                  f"{m['frames_line_lost']} of {m['frames']}")
    u = m["user_inputs"]
    table.add_row("user inputs: speed, stop distance, lane", f"{u['desired_speed_mps']:.2f} m/s, "
                  f"{u['stop_distance_m']:.2f} m, {u['lane_gain'] * 100:.0f} %")
    if m["stopped_for_obstacle_s"]:
        table.add_row("stopped for an obstacle (brake lamp)", f"{m['stopped_for_obstacle_s']:.2f} s "
                      f"({m['brake_lamp_s']:.2f} s)")
    stdout.print(table)


@app.command("lane-follow")
@recordable
def lane_follow_cmd(
    ctx: typer.Context,
    speed: Annotated[float, typer.Option(help="Desired speed, m/s.")] = 0.3,
    lane: Annotated[str, typer.Option(help="Lane to drive in: right (yellow line on the car's left) or left.")] = "right",
    duration: Annotated[float | None, typer.Option(help="Run for this many seconds (default 30 s, or with "
                                                   "--laps the time those laps need).", show_default=False)] = None,
    laps: Annotated[float | None, typer.Option(help="Stop after this many laps (simulator).", show_default=False)] = None,
    hsv_tune_: Annotated[bool, typer.Option("--hsv-tune", help="Do not drive: threshold frames at 4 spots of the "
                                            "track and report/write them (hsv_tune.png with --out).")] = False,
    hsv_min: Annotated[str, typer.Option(help="Lower HSV bound H,S,V (H in OpenCV's 0..179 = deg/2).")]
    = ",".join(map(str, YELLOW_HSV_MIN)),
    hsv_max: Annotated[str, typer.Option(help="Upper HSV bound H,S,V.")] = ",".join(map(str, YELLOW_HSV_MAX)),
    hsv: Annotated[Path | None, typer.Option("--hsv", help="HSV profile YAML to drive with (the tuner's hsv.yaml; see "
                                             "qcarlab/hsv_profile.py). With --hsv-tune: where the tuned profile goes "
                                             "(default OUT/hsv.yaml).", show_default=False)] = None,
    lookahead: Annotated[float, typer.Option(help="Where the fitted line is read, m ahead of the camera.")] = 0.5,
    stop_distance: Annotated[float, typer.Option(help="automatedDriving's minimum stopping distance, m.")] = 0.6,
    speed_selector: Annotated[float, typer.Option(help="userInputs' Speed Selector: per cent of --speed (the "
                                                  "maximum speed).")] = 100.0,
    stop_offset: Annotated[float, typer.Option(help="userInputs' Stopping Distance Offset: per cent of "
                                               "--stop-distance added to it (0: 0.6 m, 100: 1.2 m).")] = 0.0,
    distance_to_lane: Annotated[float, typer.Option(help="userInputs' Distance To Lane, per cent: 0 follows the "
                                                    "line itself, 100 the lane centre.")] = 100.0,
    start_at: Annotated[float, typer.Option(help="The start switch: the motor is armed from this many seconds.")]
    = 0.0,
    stop_at: Annotated[float | None, typer.Option(help="The stop switch: disarmed (throttle 0, brake lamp) from "
                                                  "this many seconds.", show_default=False)] = None,
    obstacle: Annotated[float | None, typer.Option(help="Put a box in the lane this many metres ahead of the bumper (simulator): "
                                                   "automatedDriving slows down and stops before it.",
                                                   show_default=False)] = None,
    trials: TrialsOpt = None,
    min_success: MinSuccessOpt = 1.0,
    start: StartOpt = None,
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
    """Follow the lane with the RGBD camera (HSV yellow line, linear fit, pure pursuit; sheet 5.3).

    Examples:
      qcarlab lane-follow
      qcarlab lane-follow --laps 1 --out runs/lane
      qcarlab lane-follow --hsv-tune --hsv-min 20,100,100 --out runs/tune
      qcarlab lane-follow --hsv runs/tune/hsv.yaml
      qcarlab lane-follow --use mylab/lane.py

    Trials: each from a random spot round the lane:
      qcarlab lane-follow --trials 5 --duration 20

    Exit 0 when the car stayed in its lane (and drove --laps; trials: in every trial), 1 when it did not,
    2 for bad input.
    """
    if lane not in LANES:
        raise InputError(f"--lane must be one of {', '.join(LANES)}, got {lane!r}")
    cfg = LaneFollowConfig(speed=speed, lane=lane, duration=duration, laps=laps,
                           hsv_min=parse_hsv(hsv_min, "--hsv-min"), hsv_max=parse_hsv(hsv_max, "--hsv-max"),
                           lookahead=lookahead, stop_distance=stop_distance, speed_selector=speed_selector,
                           stop_offset=stop_offset, distance_to_lane=distance_to_lane, start_at=start_at,
                           stop_at=stop_at, rate=rate)
    apply_tunables(cfg, params, ctx)
    if hsv is not None and not hsv_tune_:  # a tuned profile: the yellow range it holds
        typed = [f"--{n.replace('_', '-')}" for n in ("hsv_min", "hsv_max") if given(ctx, n)]
        if typed:
            raise InputError(f"--hsv {hsv} gives the HSV range: leave out {' and '.join(typed)} (or the file)")
        from qcarlab.hsv_profile import load_hsv_profile

        profile = load_hsv_profile(hsv)
        cfg.hsv_min, cfg.hsv_max = profile.hsv_min, profile.hsv_max
        cfg.white_s_max, cfg.white_v_min = profile.white_s_max, profile.white_v_min  # the white backup's
    cfg.check()
    mine = student_blocks(LaneFollowingLab, use, block, ctx)
    world_obj, pose = sim_world(car, world, start, "track", params)
    if world_obj is not None:
        pose = start_in_lane(world_obj, lane, pose)
    if obstacle is not None:
        if world_obj is None:
            raise InputError("--obstacle puts a box in the simulated world: simulator only")
        from qcarlab.experiments.lane_follow import place_obstacle

        place_obstacle(world_obj, pose or world_obj.start, obstacle)
    check_trials(trials, car, realtime)
    if trials is not None:
        if hsv_tune_:
            raise InputError("--trials drives the lane; --hsv-tune does not drive: use one of them")
        from dataclasses import replace

        from qcarlab.experiments.trials import LANE_FOLLOW, run_trials

        s0 = pose or world_obj.start
        spec = replace(LANE_FOLLOW, along_path=lane_centre(world_obj, s0))
        result = run_trials("lane-follow", world_obj,
                            lambda c, w, wrap: run_lane_follow(c, cfg, w, blocks=mine, wrap=wrap),
                            trials, seed, spec, load_params(params), s0,
                            on_trial=progress(json_out, trials), min_success=min_success, realism=sim_realism())
        result.metrics.update({"car": car, "world": world_obj.name, "lane": cfg.lane, "speed_mps": cfg.speed})
        emit(result, json_out, out, trials_summary)
        return
    if hsv_tune_:
        if world_obj is None:
            raise InputError("--hsv-tune places the car at spots of the track: simulator only")
        s0 = pose or world_obj.start
        frames = []
        for spot in tune_spots(lane_centre(world_obj, s0), s0):
            with open_from_options(car, world_obj, seed, realtime, params, start=spot, token=token, sensors=("rgbd",)) as qcar:
                frames.append((spot, qcar.read_rgbd()))
        from qcarlab.cli.hsv_tune import run_hsv_tuner, tuned_metrics  # the sheet's tuner (issue 10)
        where = hsv if hsv is not None else (out / "hsv.yaml" if out else None)
        tuned = run_hsv_tuner([f.color for _, f in frames], None, where,
                              None if json_out else stdout, lane=lane, start=(cfg.hsv_min, cfg.hsv_max))
        result = hsv_tune(frames, cfg, load_params(params), mine)
        result.metrics["tuned"] = tuned_metrics(tuned, where)
    else:
        with open_from_options(car, world_obj, seed, realtime, params, start=pose, token=token, sensors=("rgbd",)) as qcar:
            result = run_lane_follow(qcar, cfg, world_obj, blocks=mine)
        log = result.logs["log.csv"]
        result.figures["speed.png"] = lambda f: plots.plot_speed(log, f)
    result.metrics.update({"car": car, "world": getattr(world_obj, "name", None), "seed": seed})
    emit(result, json_out, out, _summary)
