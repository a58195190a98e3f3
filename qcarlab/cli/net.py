"""``qcarlab serve`` (a car over TCP) and ``qcarlab ping`` (sheet 3.1's connectivity test)."""

from __future__ import annotations

import math
import signal
import struct
import sys
import threading
import time
from pathlib import Path
from typing import Annotated

import typer

from qcarlab.car import open_car, parse_car_uri
from qcarlab.cli.app import app
from qcarlab.cli.common import (DEFAULT_REALISM, DebugOpt, JsonOpt, LiveOpt, LivePortOpt, OutOpt, ParamsOpt, RealismOpt,
                                SeedOpt, WorldOpt)
from qcarlab.errors import CarError, InputError, NotBuiltError
from qcarlab.wire.protocol import DEFAULT_PORT, VERSION

TokenOpt = Annotated[
    str | None,
    typer.Option(
        "--token", envvar="QCARLAB_TOKEN", show_envvar=True,
        help="Shared secret, 16+ characters; needed to serve on anything but loopback (clients send the same). "
        "Prefer the QCARLAB_TOKEN variable: other users of the machine can read a command line.",
    ),
]


STOP_SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT")  # Ctrl-C, kill, the ssh session closing, Ctrl-backslash


@app.command("serve")
def serve_cmd(
    backend: Annotated[
        str, typer.Option(help="[b]sim[/b]: the built-in simulator; [b]quanser[/b]: the physical QCar (run on the car).")
    ] = "sim",
    host: Annotated[str, typer.Option(help="Address to listen on; anything but loopback needs a token.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(min=0, max=65535, help="TCP port (0 picks a free one and prints it).")] = DEFAULT_PORT,
    lockstep: Annotated[
        bool, typer.Option("--lockstep", help="Simulator time moves only when the client advances it (deterministic runs).")
    ] = False,
    token: TokenOpt = None,
    new_token: Annotated[
        bool, typer.Option("--new-token", help="Print a new random token (for QCARLAB_TOKEN) and exit.")
    ] = False,
    watchdog: Annotated[
        float, typer.Option(help="Stop the car (throttle 0, hazard lamps) after this many seconds without a command.")
    ] = 0.25,
    controller_timeout: Annotated[
        float | None,
        typer.Option(help="A controller silent this long after the watchdog stopped the car loses control to the "
                          "next one that asks (default: 4 watchdog periods)."),
    ] = None,
    monitor_rate: Annotated[
        float, typer.Option(help="Sensor frames per second each monitor gets, per sensor (the controller is not limited).")
    ] = 10.0,
    on_stand: Annotated[
        bool,
        typer.Option(
            "--on-stand/--on-floor",
            help="Simulated car on the floor (default: drive it) or on its stand (wheels turn, car stays put).",
        ),
    ] = False,
    throttle_limit: Annotated[float, typer.Option(help="Throttle limit enforced by the server, whatever clients send.")] = 0.3,
    max_clients: Annotated[
        int, typer.Option(min=2, max=1024, help="Most clients at once: one controller (its slot is kept) and the rest monitors.")
    ] = 24,
    world: WorldOpt = None,
    seed: SeedOpt = 0,
    realism: RealismOpt = None,
    params: ParamsOpt = None,
    live: LiveOpt = False,
    live_port: LivePortOpt = None,
    tls_cert: Annotated[
        Path | None,
        typer.Option("--tls-cert", help="Serve over TLS with this PEM certificate (clients then use tcps://HOST:PORT).",
                     show_default=False),
    ] = None,
    tls_key: Annotated[
        Path | None,
        typer.Option("--tls-key", help="The certificate's private key, PEM (default: in the --tls-cert file).",
                     show_default=False),
    ] = None,
    debug: DebugOpt = False,
) -> None:
    """Serve a car over TCP: the simulator (real time, or --lockstep) or the physical QCar.

    Example: serve the simulator, then drive it from another terminal:
      qcarlab serve --backend sim --port 18960
      qcarlab io-test --car tcp://127.0.0.1:18960
    """
    from qcarlab.net.guard import new_token as make_token
    from qcarlab.net.guard import token_problem
    from qcarlab.net.server import CarServer, is_loopback, process_settings, restore_process, tune_process

    if new_token:
        print(make_token(), flush=True)
        return
    backend = backend.strip().lower()
    if backend not in ("sim", "quanser"):
        raise InputError(f"--backend must be 'sim' or 'quanser', got {backend!r}")
    if not (math.isfinite(watchdog) and 0.01 <= watchdog <= 60.0):
        raise InputError(f"--watchdog must be between 0.01 and 60 s, got {watchdog}")
    token = token or None
    if token is not None and (problem := token_problem(token)):
        raise InputError(problem)
    if not is_loopback(host) and not token:
        raise InputError(
            f"refusing to serve on {host or 'all interfaces'} without a token: it is not a loopback address, anyone "
            "on that network could drive the car; set QCARLAB_TOKEN (qcarlab serve --new-token makes one), or bind to 127.0.0.1"
        )
    if tls_key is not None and tls_cert is None:
        raise InputError("--tls-key needs --tls-cert (the certificate it belongs to)")
    tls = None
    if tls_cert is not None:
        from qcarlab.wire.tls import server_context

        tls = server_context(tls_cert, tls_key)
    caught: list[str] = []
    servers: list[CarServer] = []
    previous = _catch_stop_signals(caught, servers)
    try:
        car, what = _open_served_car(backend, lockstep, world, seed, on_stand, params, throttle_limit, realism)
        from qcarlab.cli.recording import live_car

        car = live_car(car, live, live_port, token)  # --live: what the served car does, streamed to Foxglove
        with car:
            server = CarServer(car, host, port, token=token, watchdog=watchdog, controller_timeout=controller_timeout,
                               lockstep=lockstep, max_clients=max_clients, monitor_rate=monitor_rate, prepare=True,
                               render_process=True, tls=tls)
            saved = process_settings()
            tune_process()  # before the server's threads start: they inherit its priority
            try:
                server.start()
            except BaseException:
                restore_process(saved)
                raise
            servers.append(server)
            try:
                if caught:  # a signal came while the car was being opened
                    server.request_stop()
                mode = "lock-step" if lockstep else "real time"
                _say(
                    f"serving {what} on {server.uri} ({mode}, protocol v{VERSION}, watchdog {watchdog:g} s, "
                    f"controller timeout {server.controller_timeout:g} s, throttle limit {car.throttle_limit:g}"
                    f"{', token required' if token else ''}{', TLS' if tls else ''}); Ctrl-C to stop"
                )
                server.serve_forever()
            finally:
                server.stop()  # the car first, then every client is told bye
                restore_process(saved)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    why = f" ({caught[0]})" if caught else ""
    _say(f"stopped serving{why}; the car is stopped")


def _catch_stop_signals(caught: list[str], server_box: list) -> dict:
    """Every signal that ends ``serve`` stops the car first (Ctrl-C, kill, the ssh session closing)."""
    previous: dict = {}
    if threading.current_thread() is not threading.main_thread():
        return previous

    def handler(signum: int, _frame: object) -> None:
        caught.append(signal.Signals(signum).name)
        for server in server_box:
            server.request_stop()

    for name in STOP_SIGNALS:
        signum = getattr(signal, name, None)
        if signum is not None:
            try:
                previous[signum] = signal.signal(signum, handler)
            except (OSError, ValueError):
                pass
    return previous


def _say(line: str) -> None:
    """Print a line; a terminal that is gone (SIGHUP) or a closed pipe must not stop the shutdown."""
    try:
        print(line, flush=True)
    except (OSError, ValueError):
        pass


def _open_served_car(backend, lockstep, world, seed, on_stand, params, throttle_limit, realism=None):
    """The car ``serve`` exposes, and a phrase naming it."""
    if backend == "quanser":
        if lockstep:
            raise InputError("--lockstep needs --backend sim (the physical car's time does not wait)")
        if world is not None:
            raise InputError("--world is for --backend sim; the physical car lives in the real world")
        if realism is not None:
            raise InputError("--realism is for --backend sim; the physical car has its own imperfections")
        from qcarlab.car.quanser import QuanserCar
        from qcarlab.constants import DEFAULT_PARAMS, load_params

        car = QuanserCar(load_params(params) if params else DEFAULT_PARAMS, throttle_limit=throttle_limit)
        return car, f"the physical QCar ({car.identity().name})"
    try:
        car = open_car(
            "sim", world=world, seed=seed, on_stand=on_stand, realtime=not lockstep,
            params=params, throttle_limit=throttle_limit, realism=realism or DEFAULT_REALISM,
        )
    except ImportError as exc:
        raise NotBuiltError(f"--world {world!r}: simulator worlds are not built yet ({exc})") from None
    stand = "on its stand" if on_stand else "on the floor"
    return car, (f"the simulated QCar (seed {seed}, {stand}{', world ' + str(world) if world else ''}, "
                 f"realism {car.realism.name})")


def normalise_uri(uri: str) -> tuple[str, int]:
    """``tcp://HOST:PORT``, Quanser's ``tcpip://HOST:PORT`` or a bare ``HOST[:PORT]`` -> (host, port)."""
    text = (uri or "").strip()
    if text.startswith("tcpip://"):
        text = "tcp://" + text[len("tcpip://") :]
    if "://" not in text:
        if text in ("sim", ""):
            raise InputError(f"{uri!r}: ping needs a served car, tcp://HOST:PORT (the in-process simulator needs no ping)")
        host_part = text
        if host_part.count(":") == 1 or (host_part.startswith("[") and "]:" in host_part):
            text = "tcp://" + host_part
        else:
            text = f"tcp://{host_part}:{DEFAULT_PORT}"
    scheme, host, port = parse_car_uri(text)
    if scheme != "tcp" or host is None or port is None:
        raise InputError(f"{uri!r}: expected tcp://HOST:PORT")
    return host, port


@app.command("ping")
def ping_cmd(
    uri: Annotated[str, typer.Argument(help="The car: tcp://HOST:PORT (or HOST[:PORT], port 18960 by default; tcps:// for TLS).")],
    count: Annotated[int, typer.Option("--count", "-c", min=1, max=1_000_000, help="Round trips to make.")] = 5,
    interval: Annotated[float, typer.Option("--interval", "-i", min=0.0, max=3600.0, help="Seconds between round trips.")] = 0.2,
    timeout: Annotated[float, typer.Option(help="Seconds to wait for the connection and for each reply.")] = 2.0,
    token: TokenOpt = None,
    json_out: JsonOpt = False,
    out: OutOpt = None,
    debug: DebugOpt = False,
) -> None:
    """Round-trip latency, loss and identity of a car (sheet 3.1); exit 0 when it answers, 1 otherwise.

    Examples:
      qcarlab ping tcp://192.168.2.15:18960 --count 20 --interval 0.1
      qcarlab ping tcp://192.168.2.15:18960 --out runs/3.1-ping
    """
    from qcarlab.car.tcp import TcpCar, TcpConnectError

    if not (math.isfinite(timeout) and timeout > 0):
        raise InputError(f"--timeout must be a positive number of seconds, got {timeout}")
    tls = uri.strip().startswith("tcps://")  # TLS (serve --tls-cert); QCARLAB_TLS_CA names a self-signed certificate
    host, port = normalise_uri("tcp://" + uri.strip()[len("tcps://"):] if tls else uri)
    shown = f"{'tcps' if tls else 'tcp'}://{'[' + host + ']' if ':' in host else host}:{port}"
    try:
        car = TcpCar(host, port, role="monitor", token=token or None, timeout=timeout, connect_timeout=timeout,
                     client="qcarlab ping", tls=tls or None)
    except TcpConnectError as exc:
        _ping_results({"uri": shown, "reachable": False, "reason": exc.kind, "error": str(exc)}, [], [], json_out,
                      out)
        raise
    rtts: list[float] = []
    replied: list[int] = []  # which round trips came back (for rtt.csv)
    lost = 0
    with car:
        ident = car.identity()
        battery = None
        try:
            battery = car.read().battery_voltage
        except (CarError, NotBuiltError):
            pass  # e.g. a lock-step server before its controller's first read
        remote = ident.extra.get("remote_backend")
        if not json_out:
            batt = f"battery {battery:.2f} V" if battery is not None else "battery unknown"
            mode = ", lock-step" if car.stepped else ""
            print(f"PING {shown}: {ident.name}, backend {remote}, protocol v{car.protocol}, {batt}{mode}", flush=True)
        start = time.monotonic()
        for i in range(count):
            try:
                rtt = car.ping(struct.pack("<Q", i), timeout=timeout)
                rtts.append(rtt)
                replied.append(i + 1)
                if not json_out:
                    print(f"reply {i + 1}: {rtt * 1e3:.3f} ms", flush=True)
            except TimeoutError:
                lost += 1
                if not json_out:
                    print(f"reply {i + 1}: timed out after {timeout:g} s", flush=True)
            except TcpConnectError as exc:
                lost += count - i
                _ping_results({"uri": shown, "reachable": False, "reason": exc.kind, "error": str(exc)}, rtts,
                              replied, json_out, out)
                raise
            if i + 1 < count:
                delay = start + (i + 1) * interval - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
    stats = _stats(rtts)
    result = {
        "uri": shown,
        "reachable": bool(rtts),
        "name": ident.name,
        "backend": remote,
        "protocol": car.protocol,
        "capabilities": ident.capabilities,
        "lockstep": car.stepped,
        "battery_v": battery,
        "sent": count,
        "received": len(rtts),
        "loss": lost / count,
        "rtt_ms": stats,
        "samples_ms": [r * 1e3 for r in rtts],
    }
    _ping_results(result, rtts, replied, json_out, out)
    if not json_out:
        print(f"--- {shown}: {count} sent, {len(rtts)} received, {100.0 * lost / count:.0f}% loss")
        if rtts:
            print("rtt min/avg/max/jitter = {min:.3f}/{avg:.3f}/{max:.3f}/{jitter:.3f} ms".format(**stats))
        if out is not None:
            print(f"wrote results.json and rtt.csv to {out}")
    if not rtts:
        raise TcpConnectError(f"{shown}: no reply to any of {count} pings (timed out after {timeout:g} s each)", "timeout")


def _ping_results(result: dict, rtts: list[float], replied: list[int], json_out: bool, out) -> None:
    """What every run's results carry (the command that made them, for qcarlab grade), saved to
    --out (results.json and rtt.csv), written for the grader, and printed with --json."""
    from qcarlab.cli.invocation import record_invocation, write_for_grader
    from qcarlab.experiments.result import Result
    from qcarlab.record import dumps

    record_invocation(result)
    if out is not None:
        Result("ping", result, logs={"rtt.csv": {"reply": replied, "rtt_ms": [r * 1e3 for r in rtts]}}).save(out)
    write_for_grader(result)
    if json_out:
        sys.stdout.write(dumps(result) + "\n")


def _stats(rtts: list[float]) -> dict[str, float | None]:
    if not rtts:
        return {"min": None, "avg": None, "max": None, "jitter": None}
    ms = [r * 1e3 for r in rtts]
    jitter = sum(abs(b - a) for a, b in zip(ms, ms[1:])) / (len(ms) - 1) if len(ms) > 1 else 0.0
    return {"min": min(ms), "avg": sum(ms) / len(ms), "max": max(ms), "jitter": jitter}
