"""The running command as a results file records it, and a task's command parsed like the CLI does.

``emit`` (every lab command's output) calls :func:`record_invocation`, so ``results.json`` says
which command and parameters made it (see :mod:`qcarlab.grading.invocation`), and writes the
results to ``$QCARLAB_RESULTS`` when ``qcarlab grade`` set it (:func:`write_for_grader`), so the
grader reads a run's results without parsing the student's prints on stdout.
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from typing import Any

from qcarlab.errors import InputError
from qcarlab.grading.invocation import files_of, jsonable

RESULTS_ENV = "QCARLAB_RESULTS"


def _current_context() -> Any:
    """The running command's click context (typer's click, vendored or not); None outside a command."""
    import typer

    base = next((c for c in typer.Context.__mro__[1:] if c.__name__ == "Context"), None)
    if base is None:
        return None
    try:
        glob = importlib.import_module(base.__module__.rsplit(".", 1)[0] + ".globals")
    except ImportError:
        return None
    return glob.get_current_context(silent=True)


def record_invocation(metrics: dict[str, Any]) -> None:
    """Add ``invocation`` (the command, its parsed parameters, the hashes of the files it read)
    to a run's metrics; nothing outside a running command."""
    ctx = _current_context()
    if ctx is None or not ctx.info_name:
        return
    from qcarlab import __version__

    params = dict(ctx.params)
    if params.get("token"):  # a served car's secret never goes into a results file
        params["token"] = "(given)"
    metrics["invocation"] = {"command": ctx.info_name, "params": jsonable(params), "files": files_of(params),
                             "qcarlab": __version__}


def _commands() -> Any:
    """The CLI's click group with every command loaded, built once (:func:`qcarlab.cli.app.click_group`)."""
    from qcarlab.cli import load_commands
    from qcarlab.cli.app import click_group

    load_commands()
    return click_group()


def parse_command(argv: list[str]) -> tuple[str, dict[str, Any], dict[str, str]]:
    """A task's command words (after ``qcarlab``) parsed by the command's own parser: its name, its
    parameters in the command's order, and how each is written (``--speed``, ``PATH``)."""
    group = _commands()
    if not argv:
        raise InputError("empty command")
    sub = group.get_command(None, argv[0])  # type: ignore[arg-type]
    if sub is None:
        raise InputError(f"qcarlab has no command {argv[0]!r}")
    try:
        ctx = sub.make_context(argv[0], list(argv[1:]), resilient_parsing=True)
    except Exception as exc:  # noqa: BLE001 - click's (vendored) usage errors
        raise InputError(f"qcarlab {' '.join(argv)}: {exc}") from None
    params, labels = {}, {}
    for param in sub.params:
        if param.name in ctx.params:
            params[param.name] = ctx.params[param.name]
            longs = [o for o in getattr(param, "opts", []) if o.startswith("--")]
            if getattr(param, "param_type_name", "") == "option" and longs:
                labels[param.name] = longs[0]
            else:
                labels[param.name] = str(getattr(param, "metavar", None) or param.name).strip("{}[]").upper()
    return argv[0], jsonable(params), labels


def command_accepts(argv: list[str], option: str) -> bool:
    """Whether the task's command has a parameter named ``option`` (e.g. "out", "params", "use")."""
    sub = _commands().get_command(None, argv[0])  # type: ignore[arg-type]
    return sub is not None and any(p.name == option for p in sub.params)


def write_for_grader(metrics: dict[str, Any]) -> None:
    """Write the run's results to the file ``$QCARLAB_RESULTS`` names (set by ``qcarlab grade``)."""
    target = os.environ.get(RESULTS_ENV)
    if target:
        from qcarlab.record import write_json

        write_json(Path(target), metrics)


__all__ = ["RESULTS_ENV", "command_accepts", "parse_command", "record_invocation", "write_for_grader"]
