"""Subcommands of the toolkit that this version does not provide yet.

Each is listed in ``qcarlab --help`` and, when run, says so in one line and exits 2: no fake
output. Remove a name from here when its module registers the real command.
"""

from __future__ import annotations

import typer

from qcarlab.cli.app import app
from qcarlab.errors import NotBuiltError

PENDING: dict[str, tuple[str, str]] = {
    "ping": ("Round-trip latency and identity of a car (sheet 3.1).", "the TCP car (issue 5)"),
    "keyboard-drive": ("Drive the car from the keyboard (sheet 3.4).", "the TCP car (issue 5)"),
    "lidar-scan": ("Capture and plot LIDAR scans (sheet 3.5).", "the simulated sensors (issue 4)"),
    "camera": ("RGBD and CSI 360 camera frames (sheets 3.6, 3.7).", "the simulated sensors (issue 4)"),
    "path-gen": ("Generate reference paths: line, circle, butterfly (sheet 4.2.1).", "path following (issue 3)"),
    "path-follow": ("Follow a path with pure pursuit and PI speed control (sheet 4.2).", "path following (issue 3)"),
    "stop-sign": ("Stop in front of a stop sign with the RGBD camera (sheet 5.1-5.2).", "a later issue"),
    "lane-follow": ("Vision lane following with HSV tuning (sheet 5.3).", "a later issue"),
    "avoid": ("LIDAR obstacle stop and avoidance (sheet 6).", "a later issue"),
    "serve": ("Serve a car (simulated or physical) over TCP.", "the TCP car (issue 5)"),
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
