"""The bare ``qcarlab --help`` lists the commands from qcarlab/cli/_index.py without importing
their modules (issue 28: 0.38 -> 0.18 s); the index must say what the commands say."""

from __future__ import annotations

import os
import subprocess
import sys

import typer.main

from qcarlab import cli
from qcarlab.cli import _index


def index_source() -> str:
    """qcarlab/cli/_index.py's COMMANDS as the commands themselves give them."""
    cli.load_commands()
    group = typer.main.get_command(cli.app)
    modules = {}
    for info in cli.app.registered_commands:
        modules[info.name] = info.callback.__module__.rsplit(".", 1)[-1]
    for info in cli.app.registered_groups:  # (detect, replay: the module of their commands)
        modules[info.name] = next(c.callback.__module__ for c in info.typer_instance.registered_commands).rsplit(".", 1)[-1]
    lines = ["COMMANDS = ("]
    for name in group.list_commands(None):
        cmd = group.get_command(None, name)
        text = (cmd.short_help or cmd.help or "").split("\n\n")[0]
        lines += [f"    ({name!r}, {modules[name]!r},", f"     {text!r}),"]
    return "\n".join(lines + [")"])


def test_the_index_says_what_the_commands_say():
    want = index_source()
    have = "COMMANDS = (\n" + "\n".join(
        f"    ({n!r}, {m!r},\n     {t!r})," for n, m, t in _index.COMMANDS) + "\n)"
    assert have == want, f"qcarlab/cli/_index.py is stale; its COMMANDS should read:\n{want}"
    assert set(_index.MODULES) == {m for _, m, _ in _index.COMMANDS}


def _help(*prefix: str) -> str:
    env = {**os.environ, "COLUMNS": "100", "TERM": "dumb"}
    env.pop("_QCARLAB_COMPLETE", None)
    done = subprocess.run([sys.executable, *prefix], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_the_bare_help_lists_every_command_as_the_loaded_commands_do_without_importing_them():
    quick = _help("-c", "import sys; from qcarlab.cli import main; main(['--help'])")
    full = _help("-c", "from qcarlab import cli; cli.load_commands(); cli.main(['--help'])")
    assert quick == full and "stop-sign" in quick and "lane-follow" in quick
    probe = ("import sys\nfrom qcarlab.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
             "print('LOADED', sorted(m for m in sys.modules if m.startswith('qcarlab.cli.') and m[12:] not in ('app', 'helpfmt')"
             " and not m.endswith('_index')))")  # (helpfmt: the help pages' layout, no command)
    out = _help("-c", probe)
    assert out.strip().endswith("LOADED []"), out[-300:]
