"""The commands a documentation page shows, run: find the markers, run them, render what they printed.

A page marks a command it shows with an HTML comment (invisible on GitHub and in the built site)::

    <!-- run: qcarlab path-gen butterfly --size 2 -->
    <!-- run: qcarlab stop-sign --json ;; json=stopped,stop_distance_m -->
    <!-- run: qcarlab path-gen butterfly --size 2 --out p4 ;; figure=p4/butterfly.png -->

Options after ``;;`` (space separated): ``exit=N`` the exit code the command must give (0 by
default; anything else fails the build), ``json=KEY,KEY`` keep only those keys of a JSON object
printed on stdout (dotted names reach into nested objects), ``tail=N`` / ``head=N`` keep the last
or first N lines, ``figure=FILE`` show the image the command wrote (a path inside the command's own
scratch folder) instead of its text, ``stderr`` show stderr too (what a student sees on a
terminal). ``docs/hooks.py`` replaces each marker at build time; ``tests/test_docs_site.py`` checks
without mkdocs that every marked command is a real qcarlab command with real options.
"""

from __future__ import annotations

import base64
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

MARKER = re.compile(r"<!-- run: (?P<body>.*?) -->")
ROOT = Path(__file__).resolve().parent.parent
TIMEOUT_S = 120.0


@dataclass(frozen=True)
class Run:
    """One marked command: the words after ``qcarlab`` and how to show its output."""

    command: str  # as the page shows it, "qcarlab path-gen butterfly --size 2"
    exit: int = 0
    json_keys: tuple[str, ...] = ()
    head: int = 0
    tail: int = 0
    figure: str = ""
    stderr: bool = False

    @property
    def argv(self) -> list[str]:
        """The command's words after ``qcarlab``."""
        return shlex.split(self.command)[1:]


def parse_marker(body: str, where: str = "") -> Run:
    """A marker's body (``qcarlab ... ;; opt=value ...``) as a :class:`Run`; ValueError naming ``where``."""
    command, _, opts = body.partition(";;")
    command = command.strip()
    if not command.startswith("qcarlab "):
        raise ValueError(f"{where}: a run marker's command must start with 'qcarlab ': {command!r}")
    kw: dict = {}
    for opt in opts.split():
        key, _, value = opt.partition("=")
        if key == "exit":
            kw["exit"] = int(value)
        elif key == "json":
            kw["json_keys"] = tuple(value.split(","))
        elif key in ("head", "tail"):
            kw[key] = int(value)
        elif key == "figure":
            kw["figure"] = value
        elif key == "stderr":
            kw["stderr"] = True
        else:
            raise ValueError(f"{where}: unknown run-marker option {opt!r} (exit, json, head, tail, figure, stderr)")
    return Run(command, **kw)


def find_runs(markdown: str, where: str = "") -> list[Run]:
    """Every run marker of a page, in order."""
    return [parse_marker(m.group("body"), where) for m in MARKER.finditer(markdown)]


def environment() -> dict[str, str]:
    """What the commands run with: this checkout's qcarlab, no colours, a 100-column terminal."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH", "")])])
    env.update({"NO_COLOR": "1", "TERM": "dumb", "COLUMNS": "100", "LINES": "50"})
    env.pop("FORCE_COLOR", None)
    return env


@dataclass(frozen=True)
class Output:
    """What a run printed, ready to go on the page (text), or the figure it wrote (PNG bytes)."""

    run: Run
    code: int
    text: str
    figure: bytes = b""


def _pick(data: object, keys: tuple[str, ...]) -> dict:
    out = {}
    for key in keys:
        value = data
        for part in key.split("."):
            value = value[int(part)] if isinstance(value, list) else value[part]  # KeyError: the page is stale
        out[key] = value
    return out


def execute(run: Run) -> Output:
    """Run one marked command in a scratch folder of its own; its output as the page shows it.

    Raises RuntimeError (one line: the command, its exit code, the end of its stderr) when the
    command does not exit as the marker says, or a JSON key or a figure it names is missing."""
    with tempfile.TemporaryDirectory(prefix="qcarlab-docs-") as tmp:
        done = subprocess.run([sys.executable, "-m", "qcarlab", *run.argv], cwd=tmp, env=environment(),
                              capture_output=True, text=True, timeout=TIMEOUT_S, stdin=subprocess.DEVNULL)
        if done.returncode != run.exit:
            last = " | ".join(done.stderr.strip().splitlines()[-3:])
            raise RuntimeError(f"docs: `{run.command}` exited {done.returncode}, the page says {run.exit}: {last}")
        if run.figure:
            path = Path(tmp) / run.figure
            if not path.is_file():
                raise RuntimeError(f"docs: `{run.command}` wrote no {run.figure}")
            return Output(run, done.returncode, "", path.read_bytes())
        text = done.stdout
        if run.json_keys:
            try:
                text = json.dumps(_pick(json.loads(done.stdout), run.json_keys), indent=2)
            except (KeyError, IndexError, ValueError) as e:
                raise RuntimeError(f"docs: `{run.command}`: no {e} in its JSON output") from None
        if run.stderr and done.stderr.strip():
            text = done.stderr.rstrip() + "\n" + text
        lines = text.rstrip().splitlines()
        if run.head and len(lines) > run.head:
            lines = lines[:run.head] + ["..."]
        if run.tail and len(lines) > run.tail:
            lines = ["..."] + lines[-run.tail:]
        return Output(run, done.returncode, "\n".join(lines))


def render(out: Output) -> str:
    """The Markdown that follows the marker: the command and its output, or its figure."""
    if out.figure:
        data = base64.b64encode(out.figure).decode("ascii")
        name = Path(out.run.figure).name
        return f"![{name}](data:image/png;base64,{data})\n\n*{name}, made by `{out.run.command}` when this page was built.*"
    shown = out.run.command + (f"   # exit {out.code}" if out.code else "")
    return f"```console\n$ {shown}\n{out.text}\n```"


__all__ = ["MARKER", "Output", "Run", "execute", "find_runs", "parse_marker", "render"]
