"""``qcarlab warm``: start, show or stop the warm server that starts lab commands typed at a terminal
(:mod:`qcarlab.warm`)."""

from __future__ import annotations

import sys
import time
from typing import Annotated

import typer

from qcarlab.cli.app import app
from qcarlab.cli.common import DebugOpt, JsonOpt, Table, stdout
from qcarlab.errors import CarError
from qcarlab.record import dumps


@app.command("warm")
def warm_cmd(
    status_only: Annotated[bool, typer.Option("--status", help="Only say whether it runs (exit 0) or not (exit 1).")] = False,
    stop_it: Annotated[bool, typer.Option("--stop", help="Stop it (the commands it runs finish first).")] = False,
    json_out: JsonOpt = False,
    debug: DebugOpt = False,
) -> None:
    """Keep lab commands quick to start: a warm server that has loaded qcarlab once forks each one.

    A lab command typed at a terminal (stop-sign, lane-follow, avoid, path-follow, camera, ...)
    is run by this server when it is up: the imports and the compiled kernels (some 0.75 s of
    every cold start) are already loaded, and the output, files and exit status are a cold run's.
    The first lab command at a terminal starts it by itself (so do qcarlab --help, labs and
    template, typed before a lab's first command); this starts it now and waits until it is warm.
    After an install it compiles the simulator's kernels first (some 15-30 s, once), so that the
    labs do not: a simulator's lab typed meanwhile waits for it and says so. It is yours alone,
    serves this install and environment, and leaves after 20 idle minutes (QCARLAB_WARM_IDLE,
    seconds). QCARLAB_WARM=0 runs every command cold; QCARLAB_WARM=1 uses it in scripts too (off a
    terminal it is not used unless asked). Linux only.

    Examples:
      qcarlab warm
      qcarlab warm --status
      qcarlab warm --stop
    """
    from qcarlab import warm

    if not sys.platform.startswith("linux"):
        raise CarError("the warm server runs on Linux only; here every command starts cold")
    where = warm.place()
    if where is None:
        raise CarError("no private folder for the warm server (set QCARLAB_WARM_DIR to a folder only you may enter)")
    if stop_it:
        stopped = warm.stop(where)
        _say({"stopped": stopped}, "stopped" if stopped else "no warm server was running", json_out)
        return
    info = warm.status(where)
    if info is not None and info.get("key") != where.key:  # qcarlab changed since it started
        warm.stop(where)
        time.sleep(0.05)
        info = None
    if info is None and not status_only:
        started = time.monotonic()
        warm.start_server(where)  # unless one is starting
        conn = warm.wait_starting(where)  # (at a terminal: says so while it compiles the kernels)
        if conn is not None:
            conn.close()
            info = warm.status(where)
        if info is None:
            raise CarError(f"the warm server did not start (its log: {where.log})")
        info["waited_s"] = round(time.monotonic() - started, 3)
    if info is None:
        _say({"running": False}, "no warm server is running (the next lab command at a terminal starts one)", json_out)
        raise typer.Exit(1)
    info["running"] = True
    if json_out:
        sys.stdout.write(dumps(info) + "\n")
        return
    table = Table(title="warm server", show_header=False)
    table.add_column("")
    table.add_column("", justify="right")
    table.add_row("process", str(info["pid"]))
    table.add_row("warm-up", f"{info['warm_in_s']:.2f} s")
    table.add_row("commands served", str(info["served"]))
    table.add_row("running now", str(info["commands_running"]))
    table.add_row("up for", f"{(time.time() - info['since']) / 60:.1f} min")
    table.add_row("leaves after idle", f"{info['idle_s'] / 60:.0f} min")
    table.add_row("socket", info["socket"])
    stdout.print(table)


def _say(data: dict, text: str, json_out: bool) -> None:
    if json_out:
        sys.stdout.write(dumps(data) + "\n")
    else:
        stdout.print(text, markup=False)
