"""Every ``qcarlab ... --help`` reads at 80 columns (issue 31 item 4): no line wider than the
terminal, nothing cut with "…", every option name in full, every example on a line of its own."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
import typer.main
from typer.testing import CliRunner

from qcarlab import cli
from qcarlab.cli import helpfmt

cli.load_commands()
ROOT = typer.main.get_command(cli.app)
ENV = {"COLUMNS": "80", "TERM": "dumb", "NO_COLOR": "1", "TERMINAL_WIDTH": None}


def _walk(command, path):
    yield path, command
    for name in getattr(command, "list_commands", lambda ctx: [])(None):
        yield from _walk(command.get_command(None, name), [*path, name])


COMMANDS = list(_walk(ROOT, []))


def _help(path: list[str]) -> str:
    done = CliRunner().invoke(cli.app, [*path, "--help"], env=ENV, prog_name="qcarlab")
    assert done.exit_code == 0, done.output
    return done.output


def _examples(command) -> list[str]:
    """The indented lines of a help text: the examples (and key tables), each to be printed whole."""
    return [line.strip() for para in helpfmt.paragraphs(command.help or "") for line in para
            if line[:1].isspace()]


@pytest.mark.parametrize("path,command", COMMANDS, ids=[" ".join(p) or "qcarlab" for p, _ in COMMANDS])
def test_help_fits_80_columns(path, command):
    out = _help(path)
    wide = [line for line in out.splitlines() if len(line) > 80]
    assert not wide, f"qcarlab {' '.join(path)} --help: {len(wide)} lines over 80 columns:\n" + "\n".join(wide)
    assert "…" not in out, out
    for param in command.params:
        if getattr(param, "hidden", False):
            continue
        for name in [*param.opts, *param.secondary_opts]:
            if name.startswith("-"):
                assert re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", out), f"{name} cut or missing:\n{out}"
    lines = {line.strip(" │") for line in out.splitlines()}
    for example in _examples(command):
        plain = re.sub(r"\[/?[a-z ]+\]", "", example)  # the keys' [b]...[/b]
        assert plain in lines, f"{example!r} is not on a line of its own:\n{out}"
    if "Example" in (command.help or ""):
        assert _examples(command), "examples go one per indented line (see qcarlab.cli.helpfmt)"
        assert " | qcarlab" not in (command.help or ""), "examples go one per indented line"


@pytest.mark.parametrize("path,command", COMMANDS[:1] + [c for c in COMMANDS if c[0] == ["path-follow"]],
                         ids=["qcarlab", "path-follow"])
def test_help_fits_narrow_and_wide_terminals(path, command):
    for width in ("50", "200"):
        done = CliRunner().invoke(cli.app, [*path, "--help"], env={**ENV, "COLUMNS": width}, prog_name="qcarlab")
        assert done.exit_code == 0
        assert max(len(line) for line in done.output.splitlines()) <= int(width)
        assert "…" not in done.output
        assert "--replay-tolerance" in done.output or not path


def test_paragraphs_join_prose_and_keep_indented_lines():
    text = """Summary line
    goes on.

    Examples:
      qcarlab a --x 1
      qcarlab b
    Prose after
    them.

    \bkept
    as is"""
    assert helpfmt.paragraphs(text) == [["Summary line goes on."],
                                        ["Examples:", "  qcarlab a --x 1", "  qcarlab b", "Prose after them."],
                                        ["kept", "as is"]]
    assert helpfmt.summary("One\ntwo.\n\nThree.") == "One two."


def test_brackets_that_are_no_style_are_printed():
    assert helpfmt.escape_non_styles("[b]sim[/b] [[x0, y0]] [default: 1]") == r"[b]sim[/b] [\[x0, y0]] \[default: 1]"


def test_the_bare_help_fits_80_columns_too():
    """The quick path (the index's stand-ins, qcarlab.cli.app._list_commands) in its own process."""
    env = {**os.environ, "COLUMNS": "80", "TERM": "dumb"}
    env.pop("TERMINAL_WIDTH", None)
    done = subprocess.run([sys.executable, "-m", "qcarlab", "--help"], capture_output=True, text=True, env=env,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert max(len(line) for line in done.stdout.splitlines()) <= 80
    assert "…" not in done.stdout and "keyboard-drive" in done.stdout
    assert "  qcarlab io-test --on-floor --throttle 0.1 --duration 2" in done.stdout


# -- qcarlab grade's table: wrapped at 80 columns, never cut -----------------------------------------

def _criterion(text, value, passed=True, reason=""):
    return {"criterion": text, "value": value, "passed": passed, "reason": reason, "earned": 1 if passed else 0,
            "points": 1}


def _student(name="mylab"):
    tasks = [
        {"id": "5.2-task1-block", "sheet": "stop-sign", "status": "skipped", "problem":
         "a block task grades a student's block: give --submission DIR", "points": 1, "criteria": []},
        {"id": "5.2-task1-stopsign", "sheet": "stop-sign", "status": "passed", "problem": None, "points": 2,
         "criteria": [_criterion("stopped >= 1", 1), _criterion("0.05 <= measured_distance_m <= 0.4", 0.3299)]},
        {"id": "4.2.3-speed-controller-block", "sheet": "path-following", "status": "failed", "problem": None,
         "points": 2, "criteria": [
             _criterion("2 s 0.1 m/s too slow: still pushing, within the limit >= 0.01 and <= 0.3", 0.5, False,
                        "0.5 > 0.3 (the controller overshoots: check the integral term's sign)"),
             _criterion("about to touch: stop or back up >= [any, -0.5] and <= [0, 0.5]", None, False, "no value")]},
    ]
    return {"student": name, "passed": 1, "total": 3, "points": 3, "max_points": 5, "skipped": 1, "tasks": tasks}


def _columns(out: str) -> list[str]:
    """Each table column's cells run together, without spaces (a wrapped cell's lines joined)."""
    rows = [line.split("│")[1:-1] for line in out.splitlines() if line.startswith("│")]
    return ["".join(r[i].replace(" ", "") for r in rows) for i in range(len(rows[0]))]


@pytest.mark.parametrize("width", [80, 60])
def test_the_grade_table_wraps_its_cells_at_the_width(monkeypatch, width):
    import io
    from types import SimpleNamespace

    from rich.console import Console

    from qcarlab.cli import grade

    student = _student()
    for single, students in ((True, [student]), (False, [student, _student("a-long-student-folder-name-2026")])):
        monkeypatch.setattr(grade, "stdout", Console(width=width, file=io.StringIO(), highlight=False))
        grade._print([SimpleNamespace(title="Stop sign detection and stopping (RGBD camera)")], students, single)
        out = grade.stdout.file.getvalue()
        assert max(len(line) for line in out.splitlines()) <= width, out
        assert "…" not in out, out
        columns = _columns(out)
        if single:
            for t in student["tasks"]:
                assert t["id"] in columns[0], out
                for c in t["criteria"]:
                    assert c["criterion"].replace(" ", "") in columns[1], out  # brackets too: no markup
        else:
            assert "a-long-student-folder-name-2026" in columns[0], out
