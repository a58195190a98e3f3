"""The typer app, the error style and the entry point.

One error style everywhere: a bad argument or file prints one line ``qcarlab CMD: error: ...`` on
stderr and exits 2; a runtime failure (car unreachable) exits 1; Ctrl-C exits 130 with the car
stopped. No traceback unless ``--debug`` (or QCARLAB_DEBUG=1).
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from typing import Any

import typer
import typer.main
from rich.console import Console

from qcarlab.cli.helpfmt import Typer
from qcarlab.errors import QcarlabError

app = Typer(
    name="qcarlab",
    help=(
        "The QCar self-driving lab, section by section, on a built-in simulator (--car sim, the "
        "default) or a real car (--car tcp://HOST:PORT).\n\n"
        "Start with:\n  qcarlab io-test --on-floor --throttle 0.1 --duration 2"
    ),
    no_args_is_help=True,
    add_completion=True,  # --install-completion / --show-completion (bash, zsh, fish, PowerShell)
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
    context_settings={"help_option_names": ["-h", "--help"]},
)

stderr = Console(stderr=True, highlight=False, soft_wrap=True)
interrupt_reported = False  # set when a command has said "interrupted" itself (cli.common.emit)


def _version(value: bool) -> None:
    if value:
        from qcarlab import __version__

        typer.echo(f"qcarlab {__version__}")
        raise typer.Exit(0)


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="Print qcarlab's version and exit."),
) -> None:
    """The QCar self-driving lab, section by section."""


class _OneLineHandler(logging.Handler):
    """Warnings from the library (e.g. a clamped command) as one plain line on stderr."""

    def emit(self, record: logging.LogRecord) -> None:
        stderr.print(f"{record.levelname.lower()}: {record.getMessage()}", markup=False)


def _setup_logging() -> None:
    logger = logging.getLogger("qcarlab")
    if not any(isinstance(h, _OneLineHandler) for h in logger.handlers):
        logger.addHandler(_OneLineHandler())
    logger.setLevel(logging.INFO)
    logger.propagate = False


def _command_name(argv: list[str]) -> str:
    for arg in argv:
        if not arg.startswith("-"):
            return f"qcarlab {arg}"
    return "qcarlab"


def _term_as_interrupt() -> object:
    """SIGTERM ends a run like Ctrl-C: the car is stopped and the results so far are saved. SIGINT
    is Ctrl-C even when the process was started with it ignored (a background job of a script).
    Both are held off while a request to a served car is on the wire (qcarlab.wire.interrupts).
    Returns what to restore."""
    if threading.current_thread() is not threading.main_thread():
        return None
    from qcarlab.wire import interrupts

    return signal.signal(signal.SIGINT, interrupts.handler), signal.signal(signal.SIGTERM, interrupts.handler)


def _listing_only(argv: list[str]) -> bool:
    """True for the bare ``qcarlab --help`` (or ``-h``), which lists the commands from the index
    (:mod:`qcarlab.cli._index`) without importing their modules; never under shell completion."""
    if any(k.endswith("_COMPLETE") for k in os.environ) or len(argv) != 1 or argv[0] not in ("--help", "-h"):
        return False
    from qcarlab import cli

    return not getattr(cli, "_loaded", False)


def _list_commands(argv: list[str]) -> int:
    """The bare help with a stand-in for each command (its name and help from the index), taken
    out of ``app`` again afterwards, so the commands' own modules are never imported for it."""
    from qcarlab.cli._index import COMMANDS

    before = list(app.registered_commands)

    def stand_in() -> None:  # pragma: no cover - listed, never run
        raise SystemExit(2)

    try:
        for name, _module, text in COMMANDS:
            app.command(name, help=text)(stand_in)
        return app(args=argv, prog_name="qcarlab", standalone_mode=False)
    finally:
        app.registered_commands[:] = before


_built: tuple[Any, Any] | None = None  # (the commands it was built from, the click group)


def _registry(typer_app: typer.Typer) -> tuple:
    """What a typer app's click group is built from: its callback, commands and sub-apps (the objects)."""
    return (typer_app.registered_callback, tuple(typer_app.registered_commands),
            tuple((g, _registry(g.typer_instance)) for g in typer_app.registered_groups if g.typer_instance))


def click_group() -> Any:
    """The app's click group, built once while its commands stay the same. ``app(...)`` has typer
    build every command's parser anew on each call: with all the commands loaded (a warm zygote
    has, for the graded tasks it forks) some 0.1 s of every task's CPU; this way the zygote builds
    it once and every task gets it with the fork. (With ``pretty_exceptions_enable=False`` typer's
    ``app(...)`` adds nothing else: its exception hook hands everything to Python's.)"""
    global _built
    key = _registry(app)
    if _built is None or _built[0] != key:
        _built = (key, typer.main.get_command(app))
    return _built[1]


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point: run the app with the house error style."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get("QCARLAB_DEBUG", "") not in ("", "0")
    _setup_logging()
    name = _command_name(argv)
    if not argv:
        argv = ["--help"]
    global interrupt_reported
    interrupt_reported = False
    previous = _term_as_interrupt()
    listing = _listing_only(argv)
    try:
        if listing:
            code = _list_commands(argv)
        else:
            from qcarlab.cli import load_command, load_commands

            completing = any(k.endswith("_COMPLETE") for k in os.environ)
            if completing or not load_command(argv[0]):  # the command typed: its module alone
                load_commands()
            code = click_group()(args=argv, prog_name="qcarlab", standalone_mode=False)
        if code == 130 and not interrupt_reported:  # typer turns a Ctrl-C into a silent return of 130
            raise KeyboardInterrupt
    except (KeyboardInterrupt, typer.Abort):
        stderr.print(f"{name}: interrupted; the car was stopped", markup=False)
        sys.exit(130)
    except QcarlabError as exc:
        if debug:
            raise
        from qcarlab.blocks import StudentBlockError

        tail = "\n(the run ended there; the car was stopped)" if isinstance(exc, StudentBlockError) else ""
        stderr.print(f"{name}: error: {exc}{tail}", markup=False)
        sys.exit(exc.exit_code)
    except Exception as exc:
        # typer's parser errors (click's, vendored or not), recognised by their class names
        kinds = {cls.__name__ for cls in type(exc).__mro__}
        if "Exit" in kinds:
            code = getattr(exc, "exit_code", 0)
            if code == 130 and not interrupt_reported:  # typer's own Ctrl-C handling exits 130 silently
                stderr.print(f"{name}: interrupted; the car was stopped", markup=False)
            sys.exit(code)
        if "Abort" in kinds:
            stderr.print(f"{name}: interrupted; the car was stopped", markup=False)
            sys.exit(130)
        if debug:
            raise
        if "ClickException" in kinds:
            stderr.print(f"{name}: error: {exc.format_message()}", markup=False)
            sys.exit(2 if "UsageError" in kinds else getattr(exc, "exit_code", 1))
        stderr.print(
            f"{name}: internal error: {type(exc).__name__}: {exc} (run again with --debug for the traceback)",
            markup=False,
        )
        sys.exit(1)
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous[0])
            signal.signal(signal.SIGTERM, previous[1])
    sys.exit(code if isinstance(code, int) else 0)
