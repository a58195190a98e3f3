"""Subcommands of the toolkit that this version does not provide yet.

Each is listed in ``qcarlab --help`` and, when run, says so in one line and exits 2: no fake
output. Remove a name from here when its module registers the real command.
"""

from __future__ import annotations

import typer

from qcarlab.cli.app import app
from qcarlab.errors import NotBuiltError

PENDING: dict[str, tuple[str, str]] = {
    "grade": ("Grade a lab run against its lab sheet's criteria.", "a later issue"),
}


def _register(name: str, summary: str, when: str) -> None:
    def pending(ctx: typer.Context) -> None:
        raise NotBuiltError(f"'{name}' is not built yet; it arrives with {when}")

    pending.__doc__ = f"(not built yet) {summary}"
    app.command(
        name,
        context_settings={"allow_extra_args": True, "ignore_unknown_options": True, "help_option_names": []},
        add_help_option=False,
    )(pending)


def register_pending() -> None:
    """Register a 'not built yet' command for every toolkit command no module has registered."""
    built = {info.name for info in app.registered_commands}
    for name, (summary, when) in PENDING.items():
        if name not in built:
            _register(name, summary, when)
