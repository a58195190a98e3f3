"""The ``qcarlab`` command line: parse, call an experiment, print. Nothing else lives here.

Each module of :data:`qcarlab.cli._index.MODULES` registers its subcommands on ``app`` when it is
imported. ``main`` imports only the module of the command typed (:func:`load_command`), or all of
them (:func:`load_commands`) when the first word is no command of the index (an option, a typo,
shell completion); the bare ``qcarlab --help`` lists the commands from the index without importing
them. A new lab
adds a module, its name in the index's ``MODULES``, and its commands' lines in ``COMMANDS``
(``tests/test_cli_index.py`` prints them).
"""

from __future__ import annotations

import importlib

from qcarlab.cli.app import app, main

_loaded = False


def load_command(name: str) -> bool:
    """Import only the module of the command ``name`` (the index says which); False when the index
    does not know it (then :func:`load_commands` is the way)."""
    from qcarlab.cli._index import COMMANDS

    module = next((m for n, m, _ in COMMANDS if n == name), None)
    if module is None:
        return False
    importlib.import_module(f"qcarlab.cli.{module}")
    return True


def load_commands() -> None:
    """Import every command module (each registers its commands on ``app``); once a process."""
    global _loaded
    if _loaded:
        return
    from qcarlab.cli._index import MODULES

    for name in MODULES:
        importlib.import_module(f"qcarlab.cli.{name}")
    # the index's order, whichever module was imported first (a test may import one directly)
    rank = {m: i for i, m in enumerate(MODULES)}

    def where(callback) -> int:
        return rank.get(getattr(callback, "__module__", "").rsplit(".", 1)[-1], len(rank))

    app.registered_commands.sort(key=lambda c: where(c.callback))
    app.registered_groups.sort(key=lambda g: min((where(c.callback) for c in g.typer_instance.registered_commands),
                                                 default=len(rank)))
    _loaded = True


__all__ = ["app", "load_commands", "main"]
