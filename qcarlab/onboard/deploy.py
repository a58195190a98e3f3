"""``qcarlab deploy USER@HOST``: copy the car-side server to a QCar over ssh/scp and say how to start it.

    steps = plan(Target.parse("nvidia@192.168.2.15"), token="...", local_file=Path("/tmp/x.py"))
    report = run_plan(steps, run=subprocess.run)      # tests pass their own ``run``

Every command is an argument list run without a local shell. The remote side runs its commands
through the car's login shell (that is how ssh works), so every remote word is quoted with
``shlex.quote``; the token never appears on a command line: it is written to the car's
``~/.qcarlab_token`` (mode 600) through ssh's standard input.

The steps: probe the car's Python (version, NumPy, Quanser's API), copy the file with scp, check
that the car's Python runs it (``--version``), store the token. The car type decides the start
command: a QCar 1 (Python 3.6) runs it under sudo, as Quanser requires there.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from qcarlab.errors import CarError, InputError
from qcarlab.onboard import DEFAULT_NAME, TOKEN_FILE

SSH_OPTIONS = (
    "-o", "ConnectTimeout=10",
    # one password prompt for the whole deploy (Quanser's cars ship with a password login)
    "-o", "ControlMaster=auto", "-o", "ControlPath=~/.ssh/qcarlab-%r@%h:%p", "-o", "ControlPersist=60",
)
PROBE = (  # no single quotes: it travels inside one
    "import json, platform\n"
    "info = dict(python=platform.python_version(), machine=platform.machine(), numpy=None, quanser=False)\n"
    "try:\n    import numpy\n    info[\"numpy\"] = numpy.__version__\nexcept Exception:\n    pass\n"
    "try:\n    import quanser.hardware\n    info[\"quanser\"] = True\nexcept Exception:\n    pass\n"
    "print(json.dumps(info))\n"
)
# neither part may start with "-" (ssh would read it as an option)
_TARGET = re.compile(r"^(?P<user>[A-Za-z0-9._][A-Za-z0-9._-]*)@(?P<host>[A-Za-z0-9.][A-Za-z0-9.-]*|\[[0-9A-Fa-f:.%]+\])$")

Runner = Callable[..., Any]


@dataclass(frozen=True)
class Target:
    user: str
    host: str

    @classmethod
    def parse(cls, text: str) -> Target:
        m = _TARGET.match((text or "").strip())
        if not m:
            raise InputError(f"{text!r}: expected USER@HOST, e.g. nvidia@192.168.2.15")
        return cls(m["user"], m["host"])

    def __str__(self) -> str:
        return f"{self.user}@{self.host}"

    @property
    def bare_host(self) -> str:
        return self.host.strip("[]")


@dataclass
class Step:
    what: str
    argv: list[str]
    stdin: bytes | None = None
    capture: bool = False
    secret: str | None = None  # text to hide when the step is printed


@dataclass
class Report:
    python: str | None = None
    numpy: str | None = None
    quanser: bool | None = None
    car_type: int | None = None
    server_version: str | None = None
    done: list[str] = field(default_factory=list)


def plan(target: Target, *, token: str, local_file: Path, remote_name: str = DEFAULT_NAME,
         python: str = "python3") -> list[Step]:
    """The commands ``deploy`` runs, in order."""
    dest = f"{target}"
    py = shlex.quote(python)
    return [
        Step("probe the car's Python", ["ssh", *SSH_OPTIONS, dest, f"{py} -c {shlex.quote(PROBE)}"], capture=True),
        Step(f"copy the server to {dest}:{remote_name}",
             ["scp", "-q", *SSH_OPTIONS, str(local_file), f"{dest}:{remote_name}"]),
        Step("check that the car's Python runs it",
             ["ssh", *SSH_OPTIONS, dest, f"{py} {shlex.quote(remote_name)} --version"], capture=True),
        Step(f"store the token in ~/{TOKEN_FILE} (mode 600)",
             ["ssh", *SSH_OPTIONS, dest, f"umask 077 && cat > {shlex.quote(TOKEN_FILE)}"],
             stdin=(token + "\n").encode("utf-8"), secret=token),
    ]


def car_type_from_python(version: str | None) -> int | None:
    """A QCar 1 ships Python 3.6 (Ubuntu 18.04), a QCar 2 Python 3.8 (Ubuntu 20.04)."""
    if not version:
        return None
    if version.startswith("3.6."):
        return 1
    if version.startswith("3.8."):
        return 2
    return None


def run_plan(steps: list[Step], run: Runner = subprocess.run, timeout: float = 120.0) -> Report:
    """Run the steps; the first failure raises CarError naming the step and ssh's last words."""
    report = Report()
    for step in steps:
        try:
            proc = run(step.argv, input=step.stdin, capture_output=True, timeout=timeout)
        except FileNotFoundError:
            raise CarError(f"{step.argv[0]} is not installed on this machine (needed to {step.what})") from None
        except subprocess.TimeoutExpired:
            raise CarError(f"{step.what}: no answer within {timeout:g} s") from None
        if proc.returncode != 0:
            said = _last_line(proc.stderr) or _last_line(proc.stdout) or f"exit code {proc.returncode}"
            raise CarError(f"{step.what} failed: {said}")
        out = _text(proc.stdout)
        if step.what.startswith("probe"):
            try:
                info = json.loads(out.strip().splitlines()[-1])
            except (ValueError, IndexError):
                raise CarError(f"{step.what}: unexpected answer {out.strip()[:80]!r}") from None
            report.python, report.numpy, report.quanser = info.get("python"), info.get("numpy"), info.get("quanser")
            if not report.python or tuple(int(x) for x in report.python.split(".")[:2]) < (3, 6):
                raise CarError(f"the car's python3 is {report.python}; the car-side server needs 3.6 or newer")
        elif step.what.startswith("check"):
            report.server_version = out.strip() or _text(proc.stderr).strip()
        report.done.append(step.what)
    return report


def start_command(car_type: int | None, *, remote_name: str = DEFAULT_NAME, port: int = 18960,
                  python: str = "python3") -> str:
    """The one command to type on the car (in an ssh session) to start the server."""
    args = f"{shlex.quote(remote_name)} --host 0.0.0.0 --token-file {TOKEN_FILE}"
    if port != 18960:
        args += f" --port {port}"
    if car_type in (1, 2):
        args += f" --car-type {car_type}"
    if car_type == 2:
        return f"{python} {args}"
    # a QCar 1 (or an unknown car): Quanser runs Python under sudo there, keeping PYTHONPATH for its API
    return f"sudo PYTHONPATH=$PYTHONPATH {python} {args}"


def shown(step: Step) -> str:
    """A step as a copy-pasteable command line (the token replaced by <token>)."""
    text = shlex.join(step.argv)
    if step.stdin is not None:
        text += " < " + ("<token>" if step.secret else "<stdin>")
    return text


def _text(data: Any) -> str:
    if data is None:
        return ""
    return data.decode("utf-8", "replace") if isinstance(data, bytes) else str(data)


def _last_line(data: Any) -> str:
    lines = [ln.strip() for ln in _text(data).splitlines() if ln.strip()]
    return lines[-1][:200] if lines else ""
