"""``qcarlab onboard`` (write the car-side server) and ``qcarlab deploy`` (copy it to a QCar over ssh)."""

from __future__ import annotations

import secrets
import subprocess
import tempfile
from pathlib import Path
from typing import Annotated

import typer

from qcarlab.cli.app import app
from qcarlab.cli.common import DebugOpt
from qcarlab.errors import InputError
from qcarlab.onboard import DEFAULT_NAME, SERVER_FILE, TOKEN_FILE, server_source, write_server
from qcarlab.onboard import deploy as D

runner = subprocess.run  # tests replace it: deploy runs ssh and scp through this


@app.command("onboard")
def onboard_cmd(
    write: Annotated[
        Path | None, typer.Option("--write", help="Write the car-side server to this file (or folder).", show_default=False)
    ] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace the file if it exists.")] = False,
    debug: DebugOpt = False,
) -> None:
    """The car-side server: one Python file that runs on a QCar 1 (Python 3.6) or QCar 2 (3.8) as shipped.

    Example: write the server, then copy it to the car (or: qcarlab deploy nvidia@CAR):
      qcarlab onboard --write qcarlab_car_server.py
    """
    if write is None:
        print(f"the car-side server is {SERVER_FILE} ({len(server_source().splitlines())} lines, standard library only)")
        print(f"  qcarlab onboard --write {DEFAULT_NAME}       write it here, then copy it to the car")
        print("  qcarlab deploy nvidia@CAR_IP                    copy it over ssh and print the start command")
        print(f"  python3 {DEFAULT_NAME} --dry-run               serve a stationary car (no hardware) to check the link")
        return
    target = write_server(write, force=force)
    print(f"wrote {target}; on the car: python3 {target.name} --dry-run (check the link), then see --help")


@app.command("deploy")
def deploy_cmd(
    target: Annotated[str, typer.Argument(help="The car's login, USER@HOST (Quanser's cars: nvidia@IP).")],
    car_type: Annotated[
        str, typer.Option("--car-type", help="1, 2, or auto: by the car's Python (3.6: QCar 1, 3.8: QCar 2).")
    ] = "auto",
    token: Annotated[
        str | None,
        typer.Option("--token", envvar="QCARLAB_TOKEN", show_envvar=True,
                     help="The token to store on the car (default: a new random one, printed once)."),
    ] = None,
    port: Annotated[int, typer.Option(min=1, max=65535, help="The port the server will listen on.")] = 18960,
    remote_name: Annotated[str, typer.Option("--remote-name", help="File name in the car user's home.")] = DEFAULT_NAME,
    python: Annotated[str, typer.Option("--python", help="The car's Python command.")] = "python3",
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Print the ssh/scp commands; run nothing.")] = False,
    debug: DebugOpt = False,
) -> None:
    """Copy the car-side server to a QCar over ssh/scp, store a token there, print the command that starts it.

    Example:
      qcarlab deploy nvidia@192.168.2.15
    """
    where = D.Target.parse(target)
    if car_type not in ("auto", "1", "2"):
        raise InputError(f"--car-type must be auto, 1 or 2, got {car_type!r}")
    if "/" in remote_name or not remote_name.endswith(".py") or remote_name.startswith("-"):
        raise InputError(f"--remote-name must be a plain file name ending in .py, got {remote_name!r}")
    generated = not token
    token = token or secrets.token_urlsafe(24)
    if len(token) < 16 or not token.isprintable() or " " in token:
        raise InputError("--token must be 16 or more printable characters without spaces (or leave it out for a new one)")
    with tempfile.TemporaryDirectory(prefix="qcarlab-deploy-") as tmp:
        local = write_server(Path(tmp) / remote_name)
        steps = D.plan(where, token=token, local_file=local, remote_name=remote_name, python=python)
        if dry_run:
            print("would run (nothing was run):")
            for step in steps:
                print(f"  # {step.what}\n  {D.shown(step)}")
            report = D.Report()
        else:
            report = D.run_plan(steps, run=runner)
    kind = int(car_type) if car_type != "auto" else D.car_type_from_python(report.python)
    if not dry_run:
        have = f"Python {report.python}, NumPy {report.numpy or 'MISSING'}"
        quanser = "Quanser's API importable" if report.quanser else "Quanser's API not importable as this user"
        print(f"copied {remote_name} to {where} ({have}; {quanser}; {report.server_version})")
        if not report.numpy:
            print("warning: the car's Python has no NumPy: the server needs it for the hardware (--dry-run works without)")
    guess = {1: "QCar 1", 2: "QCar 2"}.get(kind, "car type unknown: use --car-type 1 or 2 to be sure")
    print(f"start it on the car ({guess}), in an ssh session (ssh {where}), with this one command:")
    print(f"  {D.start_command(kind, remote_name=remote_name, port=port, python=python)}")
    print("then, on this computer:")
    if generated:
        print(f"  export QCARLAB_TOKEN={token}      # the token stored in ~/{TOKEN_FILE} on the car")
    else:
        print(f"  (keep QCARLAB_TOKEN as it is: the same token is stored in ~/{TOKEN_FILE} on the car)")
    host = f"[{where.bare_host}]" if ":" in where.bare_host else where.bare_host
    print(f"  qcarlab ping tcp://{host}:{port}")
