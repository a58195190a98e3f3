"""``qcarlab stop-sign`` (lab sheet 5.1-5.2): detect the stop sign with the RGBD camera and stop."""

from __future__ import annotations

from typing import Annotated

import typer

from qcarlab import plots
from qcarlab.cli.app import app, stderr
from qcarlab.cli.common import recordable, sim_realism  # noqa: I001  (--record, --live, --realism)
from qcarlab.cli.common import (
    CarTokenOpt,
    StartOpt, WorldOpt, sim_world, parse_hsv, KpOpt, KiOpt, KffOpt, KP, KI, KFF, UseOpt, BlockOpt, student_blocks, apply_tunables,
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
from qcarlab.cli.trials import MinSuccessOpt, TrialsOpt, check_trials, progress, trials_summary
from qcarlab.constants import load_params
from qcarlab.errors import InputError
from qcarlab.experiments.result import Result
from qcarlab.experiments.stop_sign import (
    BEHAVIOURS,
    StopSignConfig,
    StopSignLab,
    run_stop_sign,
    sign_ahead,
)
from qcarlab.perception.stop_sign import MIN_AREA, RED_HSV_MAX, RED_HSV_MIN


def _fmt(value, unit: str = "m", scale: float = 1.0, digits: int = 3) -> str:
    return "n/a" if value is None else f"{value * scale:.{digits}f} {unit}"


def _summary(result: Result) -> None:
    m = result.metrics
    cfg = m["config"]
    title = f"stop-sign ({m['behaviour']}, {m['speed_mps']:g} m/s"
    title += f", hold {cfg['hold']:g} s)" if m["behaviour"] == "hold" else ")"
    table = summary_table(title)
    if m["detected_at_m"] is None:
        table.add_row("stop sign", "never detected")
    else:
        table.add_row("first detected at (camera)", f"{m['detected_at_m']:.2f} m, t = {m['detected_at_s']:.2f} s")
    table.add_row("stopped before the sign", "yes" if m["stopped"] else "NO")
    if m["stop_distance_m"] is not None:
        table.add_row("stop distance (bumper to sign, true)", _fmt(m["stop_distance_m"]))
    table.add_row("distance measured at the stop (camera)", _fmt(m["measured_distance_m"]))
    table.add_row("time to stop", _fmt(m["time_to_stop_s"], "s", digits=2))
    if m["braking_time_s"] is not None:
        table.add_row("braking time (decision to rest)", _fmt(m["braking_time_s"], "s", digits=2))
    if m["behaviour"] == "hold":
        table.add_row("held for", _fmt(m["hold_s"], "s", digits=2))
        table.add_row("drove on past the sign", "yes" if m["passed_sign"] else "no")
    if m["min_distance_m"] is not None and m["behaviour"] == "sheet":
        table.add_row("closest approach (bumper to sign)", _fmt(m["min_distance_m"]))
    table.add_row("frames with the sign", f"{m['frames_with_sign']} of {m['frames']}")
    stdout.print(table)


@app.command("stop-sign")
@recordable
def stop_sign_cmd(
    ctx: typer.Context,
    speed: Annotated[float, typer.Option(help="Desired speed, m/s.")] = 0.3,
    behaviour: Annotated[str, typer.Option(help="sheet: the sheet's stopSign block (stop while 0.05 < d < 0.40 m); "
                                           "hold: slow down, stop, wait --hold s, drive on (Task 4).")] = "sheet",
    hold: Annotated[float, typer.Option(help="hold: seconds to stand at the sign.")] = 3.0,
    detector: Annotated[str, typer.Option(help="hsv: the sheet's chain (HSV red, the largest blob, its depth; 5.1); "
                                          "hough: the race-car report's (Circle Hough, red inside the circle, "
                                          "depth < 2 m; blocks circle_hough, red_share).")] = "hsv",
    hsv_min: Annotated[str, typer.Option(help="Lower HSV bound H,S,V (H in OpenCV's 0..179 = deg/2; "
                                         "H_min > H_max wraps through red's 0).")] = ",".join(map(str, RED_HSV_MIN)),
    hsv_max: Annotated[str, typer.Option(help="Upper HSV bound H,S,V.")] = ",".join(map(str, RED_HSV_MAX)),
    min_area: Annotated[int, typer.Option(help="Smallest red blob taken for a sign, pixels.")] = MIN_AREA,
    kp: KpOpt = KP,
    ki: KiOpt = KI,
    kff: KffOpt = KFF,
    max_time: Annotated[float | None, typer.Option(help="Give up after this many seconds (default: from the "
                                                   "distance and speed).", show_default=False)] = None,
    frames: Annotated[bool, typer.Option("--frames", help="With --out: also write annotated camera frames "
                                         "(10 per second) to frames/.")] = False,
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
    """Drive straight, detect the stop sign (HSV red + depth, sheet 5.1) and stop in front of it (5.2).

    Examples:
      qcarlab stop-sign
      qcarlab stop-sign --speed 0.5 --out runs/stop
      qcarlab stop-sign --behaviour hold --hold 3 --json
      qcarlab stop-sign --use mylab/stop_sign.py

    The race-car report's stop sign:
      qcarlab stop-sign --detector hough --behaviour hold --speed 0.5

    Trials: start 2.1-2.9 m before the sign, the sign moved +-0.2 m:
      qcarlab stop-sign --trials 10

    Exit 0 when the car stopped before the sign (hold: and drove on; trials: in every trial), 1 when it
    did not, 2 for bad input.
    """
    if behaviour not in BEHAVIOURS:
        raise InputError(f"--behaviour must be one of {', '.join(BEHAVIOURS)}, got {behaviour!r}")
    cfg = StopSignConfig(speed=speed, behaviour=behaviour, detector=detector, hold=hold, hsv_min=parse_hsv(hsv_min, "--hsv-min"),
                         hsv_max=parse_hsv(hsv_max, "--hsv-max"), min_area=min_area, kp=kp, ki=ki, kff=kff,
                         rate=rate, max_time=max_time, frames=frames and out is not None)
    apply_tunables(cfg, params, ctx, ignore=("frames",))
    cfg.check()
    mine = student_blocks(StopSignLab, use, block, ctx)
    check_trials(trials, car, realtime)
    world_obj, pose = sim_world(car, world, start, "stop-sign", params)
    if trials is not None:
        from qcarlab.experiments.trials import STOP_SIGN, run_trials

        def one(c, w, wrap):
            tr = c.truth()
            return run_stop_sign(c, cfg, sign_ahead(w, (tr.x, tr.y, tr.yaw)), blocks=mine, world=w, wrap=wrap)

        result = run_trials("stop-sign", world_obj, one, trials, seed, STOP_SIGN, load_params(params), pose,
                            on_trial=progress(json_out, trials), min_success=min_success, realism=sim_realism())
        result.metrics.update({"car": car, "world": world_obj.name, "speed_mps": cfg.speed,
                               "behaviour": cfg.behaviour})
        emit(result, json_out, out, trials_summary)
        return
    sign = None
    if world_obj is not None:
        sign = sign_ahead(world_obj, pose or world_obj.start)
        if sign is None:
            stderr.print("warning: no stop sign ahead of the car in this world; the true stop distance is not "
                          "measured", markup=False)
    with open_from_options(car, world_obj, seed, realtime, params, start=pose, token=token, sensors=("rgbd",)) as qcar:
        result = run_stop_sign(qcar, cfg, sign, blocks=mine, world=world_obj)
    result.metrics.update({"car": car, "world": getattr(world_obj, "name", None), "seed": seed})
    log = result.logs["log.csv"]
    result.figures["speed.png"] = lambda f: plots.plot_speed(log, f)
    emit(result, json_out, out, _summary)
