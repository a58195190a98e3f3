"""``qcarlab avoid`` (lab sheet section 6.1): LIDAR obstacle stop, steer, and both combined."""

from __future__ import annotations

from dataclasses import asdict
from typing import Annotated

import typer

from qcarlab.cli.app import app
from qcarlab.cli.common import recordable, sim_realism  # noqa: I001  (--record, --live, --realism)
from qcarlab.cli.common import (
    CarTokenOpt,
    StartOpt, WorldOpt, sim_world, UseOpt, BlockOpt, student_blocks, apply_tunables,
    CarOpt, DebugOpt, JsonOpt, OutOpt, ParamsOpt, RateOpt, RealtimeOpt, SeedOpt,
    emit, open_from_options, stdout, summary_table,
)
from qcarlab.constants import load_params
from qcarlab.errors import InputError
from qcarlab.experiments.avoid import STRATEGIES, AvoidConfig, AvoidLab, avoid, drive_figure
from qcarlab.experiments.result import Result
from qcarlab.cli.trials import MinSuccessOpt, TrialsOpt, check_trials, given, progress, trials_summary

BALL_TRIAL_TIME = 90.0  # s: a trial in a world with a ball ends 1 s after the ball rolled by, at the latest here


def _summary(result: Result) -> None:
    m = result.metrics
    cfg = m["config"]
    table = summary_table(f"avoid ({m['strategy']}, {cfg['speed']:g} m/s, stop distance {cfg['stop_distance']:g} m, "
                          f"world {m.get('world') or 'remote'})")
    if m["collisions"] is None:
        table.add_row("collisions", "not checked (no simulated world)")
    else:
        hit = m["collision"]
        table.add_row("collisions", "0" if not hit else
                      f"1 at t = {hit['t']:.2f} s, ({hit['x']:+.2f}, {hit['y']:+.2f}) (run ended)")
        table.add_row("min clearance (footprint to obstacles)", f"{m['min_clearance_m'] * 100:.1f} cm")
    table.add_row("distance driven", f"{m['distance_m']:.2f} m in {m['duration_s']:.1f} s")
    table.add_row("mean speed", f"{m['mean_speed_mps']:.3f} m/s")
    if m["stopped_before_obstacle"] is not None:
        gap = m["stop_gap_m"]
        table.add_row("stopped before obstacle", f"{m['stopped_before_obstacle']:.3f} m from the LIDAR at "
                      f"t = {m['stopped_at_s']:.2f} s" + ("" if gap is None else f" (bumper gap {gap * 100:.1f} cm)"))
    elif m["strategy"] == "stop":
        table.add_row("stopped before obstacle", "no (nothing came within the stop distance)")
    if "backups" in m:
        table.add_row("back-ups", str(m["backups"]))
        table.add_row("time per state", ", ".join(f"{k} {v:.1f} s" for k, v in m["time_in_state_s"].items()))
    stdout.print(table)


@app.command("avoid")
@recordable
def avoid_cmd(
    ctx: typer.Context,
    strategy: Annotated[str, typer.Option(help="stop (sheet Task 1-2: lidar_stop, speed 0 near an obstacle), "
                                          "steer (Task 3: lidar_steer, up to +-0.5 rad away from it, speed "
                                          "untouched), combined (Task 4: lidar_avoid, avoid, stop and back up "
                                          "before contact), student (your own lidar_avoid from --use) or depth (the race-car "
                                          "report's left/middle/right depth windows and state machine, with Back, "
                                          "on the RGBD camera).")]
    = "combined",
    speed: Annotated[float, typer.Option(help="Desired speed, m/s.")] = 0.3,
    stop_distance: Annotated[float, typer.Option(help="Stop when a return in the forward window is closer than "
                                                 "this, m from the LIDAR (0.223 m behind the front bumper).")] = 0.4,
    half_width: Annotated[float, typer.Option(help="Half width of the forward window, m (car half width 0.096 + "
                                              "margin).")] = 0.15,
    duration: Annotated[float, typer.Option(help="Run length, s (a collision ends it earlier; trials in a world "
                                            f"with a ball: {BALL_TRIAL_TIME:g} s, ended 1 s after the ball "
                                            "rolled by).")] = 20.0,
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
    """LIDAR obstacle detection and avoidance (sheet 6.1): stop, steer or both, with collisions checked.

    Examples:
      qcarlab avoid --strategy stop
      qcarlab avoid --world hallway --duration 30 --out runs/hall
      qcarlab avoid --strategy steer --start 0.5,0,-1.57 --json
      qcarlab avoid --strategy student --use mylab/lidar.py

    Trials: the success rate over N randomised runs, as the race-car report measured it:
      qcarlab avoid --world hallway --trials 20 --speed 0.5 --out runs/ball

    Exit 0 when the car drove the whole duration without touching anything (trials: every trial did), 1
    after a collision, 2 for bad input.
    """
    if strategy not in STRATEGIES:
        raise InputError(f"--strategy must be one of {', '.join(STRATEGIES)}, got {strategy!r}")
    cfg = AvoidConfig(strategy=strategy, speed=speed, stop_distance=stop_distance, half_width=half_width,
                      duration=duration, rate=rate)
    apply_tunables(cfg, params, ctx)
    cfg.check(load_params(params))
    mine = student_blocks(AvoidLab, use, block, ctx)
    check_trials(trials, car, realtime)
    world_obj, pose = sim_world(car, world, start, "obstacles", params)
    if trials is not None:
        from qcarlab.experiments.trials import AVOID, run_trials

        if world_obj.balls and not given(ctx, "duration"):
            cfg.duration = BALL_TRIAL_TIME
        result = run_trials("avoid", world_obj, lambda c, w, wrap: avoid(c, cfg, world=w, blocks=mine, wrap=wrap),
                            trials, seed, AVOID, load_params(params), pose,
                            on_trial=progress(json_out, trials), min_success=min_success, realism=sim_realism())
        result.metrics.update({"car": car, "world": world_obj.name, "strategy": cfg.strategy, "speed_mps": cfg.speed,
                               "config": asdict(cfg)})
        emit(result, json_out, out, trials_summary)
        return
    sensors = ("rgbd",) if cfg.strategy == "depth" else ("lidar",)  # (what it reads: its live view shows those)
    with open_from_options(car, world_obj, seed, realtime, params, start=pose, token=token, sensors=sensors) as qcar:
        if pose is not None and world_obj is not None:
            from qcarlab.experiments.safety import Clearance

            if Clearance(world_obj, qcar.params)(*pose)[0] <= 0.0:
                raise InputError(f"--start {start}: the car would stand inside an obstacle of '{world_obj.name}'")
        result = avoid(qcar, cfg, world=world_obj, blocks=mine)
    result.metrics.update({"car": car, "world": getattr(world_obj, "name", None), "seed": seed})
    if world_obj is not None:
        from qcarlab import plots

        result.figures["drive.png"] = lambda f: plots.save_figure(drive_figure(world_obj, result), f)
    emit(result, json_out, out, _summary)


__all__ = ["avoid_cmd"]
