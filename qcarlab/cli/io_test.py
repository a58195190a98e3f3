"""``qcarlab io-test``: the lab sheet's Basic I/O test (section 3.3)."""

from __future__ import annotations

import time
from typing import Annotated

import typer
from rich.live import Live

from qcarlab.car.lamps import known_lamp_words, lamps_on, parse_lamps
from qcarlab.cli.app import app
from qcarlab.cli.common import recordable  # noqa: I001  (--record, --live)
from qcarlab.cli.common import (
    Table,
    CarTokenOpt,
    CarOpt, DebugOpt, JsonOpt, OutOpt, ParamsOpt, RateOpt, RealtimeOpt, SeedOpt, WorldOpt, UseOpt, BlockOpt,
    emit, interactive, open_from_options, stdout, student_blocks, summary_table,
)
from qcarlab.errors import InputError
from qcarlab.experiments.io_test import BasicIOLab, io_test
from qcarlab.experiments.loop import check_rate
from qcarlab.experiments.result import Result


def _live_table(t: float, r, cmd, speed: float) -> Table:
    table = Table(title=f"QCar basic I/O  t = {t:5.2f} s", title_justify="left")
    table.add_column("channel")
    table.add_column("value", justify="right")
    table.add_row("encoder 0 (counts)", f"{r.encoder_counts:,}")
    table.add_row("tach (counts/s)", f"{r.tach:,.0f}")
    table.add_row("speed, basic_speed_estimation (m/s)", f"{speed:.3f}")
    table.add_row("motor current, analog 5 (A)", f"{r.motor_current:.3f}")
    table.add_row("battery, analog 6 (V)", f"{r.battery_voltage:.2f}")
    table.add_row("steering, ch 1000 (rad)", f"{cmd.steering:+.3f}")
    table.add_row("throttle, PWM 0 (duty)", f"{cmd.throttle:+.3f}")
    table.add_row("gyro z (rad/s)", f"{r.gyro[2]:+.3f}")
    table.add_row("lamps", ", ".join(lamps_on(cmd.leds)) or "-")
    return table


def _summary(result: Result) -> None:
    m = result.metrics
    table = summary_table("io-test")
    table.add_row("command", f"throttle {m['command']['throttle']:+.3f}, steering {m['steering_rad']:+.3f} rad")
    table.add_row("duration", f"{m['duration_s']:.2f} s")
    table.add_row("encoder counts", f"{m['encoder_counts']:,}")
    table.add_row("mean speed (encoder, basic_speed_estimation)", f"{m['mean_speed_mps']:.3f} m/s")
    table.add_row("wheel distance (encoder, basic_speed_estimation)", f"{m['distance_m']:.3f} m")
    table.add_row("motor current (mean / max)", f"{m['motor_current_a']:.3f} / {m['motor_current_max_a']:.3f} A")
    table.add_row("battery (mean / min)", f"{m['battery_v']:.2f} / {m['battery_min_v']:.2f} V"
                  + ("  LOW: charge it" if m["battery_low"] else ""))
    table.add_row("lamps on", ", ".join(m["leds_on"]) or "-")
    if "truth" in m:
        tr = m["truth"]
        table.add_row("simulator truth: ground speed", f"{tr['mean_speed_mps']:.3f} m/s")
        table.add_row("simulator truth: ground distance", f"{tr['distance_m']:.3f} m")
    stdout.print(table)


@app.command("io-test")
@recordable
def io_test_cmd(
    throttle: Annotated[float, typer.Option(help="Motor PWM duty fraction (the sheet's % / 100), limited to +-0.3.")] = 0.1,
    steering: Annotated[float, typer.Option(help="Steering angle in rad, + = left, limited to +-0.5.")] = 0.0,
    leds: Annotated[
        str,
        typer.Option(help="Lamps to switch on, comma separated: " + ", ".join(known_lamp_words()) + "."),
    ] = "",
    duration: Annotated[float, typer.Option(help="How long to hold the command, s.")] = 2.0,
    on_stand: Annotated[
        bool, typer.Option("--on-stand/--on-floor", help="Car on its stand (wheels turn, car stays put) or on the floor.")
    ] = True,
    throttle_limit: Annotated[float, typer.Option(help="Throttle limit (duty fraction).")] = 0.3,
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
    """Basic I/O test (sheet 3.3): hold throttle, steering and lamps; read encoder, current, battery, IMU.

    Example:
      qcarlab io-test --on-floor --throttle 0.1 --duration 2 --json
    """
    if not 0.0 < duration <= 3600.0:  # (NaN fails the comparison too)
        raise InputError(f"--duration must be in (0, 3600] s, got {duration}")
    lamp_state = parse_lamps(leds)
    check_rate(rate)
    mine = student_blocks(BasicIOLab, use, block)
    live = interactive(json_out)
    with open_from_options(car, world, seed, realtime, params, on_stand=on_stand, throttle_limit=throttle_limit,
                           token=token, sensors=()) as qcar:
        qcar.validate(throttle, steering, lamp_state)
        if live:
            with Live(refresh_per_second=10, console=stdout, transient=True) as view:
                last = [0.0]

                def show(t, r, cmd, speed):
                    now = time.monotonic()
                    if now - last[0] >= 0.1:
                        last[0] = now
                        view.update(_live_table(t, r, cmd, speed))

                result = io_test(qcar, throttle, steering, lamp_state, duration, rate, on_tick=show, blocks=mine)
        else:
            result = io_test(qcar, throttle, steering, lamp_state, duration, rate, blocks=mine)
        result.metrics.update({"car": car, "seed": seed, "on_stand": on_stand})
    emit(result, json_out, out, _summary)
