"""qcarlab's ``--help`` pages, readable at 80 columns (issue 31 item 4).

typer's own rich help puts each option in a table of six columns (long name, short name, negative
name, type, help); at 80 columns the option names are cut (``--replay-toleran…``) and the help
squeezed into a 15-character column. Here every help page is drawn in two columns instead, as
click's plain help does it: the option's names with its type, then its help, wrapped; names longer
than a third of the panel stand on their own line with the help under them. Nothing is cut at any
width from 40 columns up.

Help text: the first paragraph is the summary; in the others single line breaks are joined (as
prose), and an indented line stands on its own line as written — the examples::

    Examples:
      qcarlab path-follow circle
      qcarlab path-follow butterfly --size 2

A paragraph starting with click's ``\\b`` keeps all its lines as written.

Only ``rich`` is used (not ``typer.rich_utils``, whose import pulls in Markdown: 45 ms of the bare
``qcarlab --help``). Use :class:`Typer` for every app: its commands and groups draw help this way.
"""

from __future__ import annotations

import inspect
import os
import re
from collections import defaultdict
from typing import Any

import typer
from typer.core import TyperCommand, TyperGroup

#: the widest the names column gets, as a fraction of the panel's inner width
NAMES_SHARE = 1 / 3
#: at least this wide, whatever the terminal
NAMES_MIN = 14

_THEME = {"option": "bold cyan", "switch": "bold green", "metavar": "bold yellow", "usage": "yellow"}


def paragraphs(text: str) -> list[list[str]]:
    """A help text as paragraphs, each a list of lines to print: prose lines joined into one, an
    indented line (an example) kept as written with its indent, a ``\\b`` paragraph kept whole.
    Whatever follows a form feed (click's ``\\f``) is dropped."""
    text = inspect.cleandoc(text or "").partition("\f")[0]
    out: list[list[str]] = []
    for block in text.split("\n\n"):
        if not block.strip():
            continue
        if block.startswith("\b"):
            out.append([line.rstrip() for line in block[1:].lstrip("\n").splitlines()])
            continue
        lines: list[str] = []
        prose = False  # whether the last line is prose that the next prose line continues
        for line in block.splitlines():
            if line[:1].isspace():
                lines.append(line.rstrip())
                prose = False
            elif prose:
                lines[-1] += " " + line.strip()
            else:
                lines.append(line.strip())
                prose = True
        out.append(lines)
    return out


def summary(text: str) -> str:
    """The first paragraph of a help text as one line (a command's line in its group's list)."""
    first = paragraphs(text)
    return " ".join(first[0]) if first else ""


def split_help_record(param: Any, ctx: Any) -> tuple[str, str, str] | None:
    """(names with the type, the help, the bracketed extras: default, env var, range, required)
    from click's own help record of ``param``; None for a hidden one."""
    record = param.get_help_record(ctx)
    if record is None:
        return None
    names, text = record
    own = getattr(param, "help", None) or ""
    text = text or ""
    extra = text[len(own):] if text.startswith(own) else ""
    if not text.startswith(own):
        own = text
    return names, own.strip(), extra.strip().replace("\\[", "[")


def names_width(names: list[str], inner: int) -> int:
    """The names column: as wide as the longest names up to a third of the panel's inner width."""
    cap = max(NAMES_MIN, int(inner * NAMES_SHARE))
    fitting = [len(n) for n in names if len(n) <= cap]
    return max(fitting, default=min(cap, NAMES_MIN))


def _console():
    from rich.console import Console
    from rich.highlighter import RegexHighlighter
    from rich.theme import Theme

    class Highlighter(RegexHighlighter):
        highlights = [
            r"(^|[\s(/,])(?P<switch>-\w)(?![\w-])",
            r"(^|[\s(/,])(?P<option>--[\w][\w-]*)",
            r"(?P<metavar><[^>\s]+( [^>\s]+)?>)",
            r"(?P<usage>^Usage: )",
        ]

    width = os.environ.get("TERMINAL_WIDTH")
    return Console(theme=Theme(_THEME), highlighter=Highlighter(),
                   width=int(width) if width and width.isdigit() else None,
                   force_terminal=False if os.environ.get("_TYPER_FORCE_DISABLE_TERMINAL") else None)


def escape_non_styles(markup: str) -> str:
    """Rich markup with every bracket that is no style tag escaped, so that ``[[x0, y0], [x1, y1]]``
    or ``[default: 0.3]`` in a help text are printed, not taken for tags and dropped."""
    from rich.errors import StyleSyntaxError
    from rich.style import Style

    def keep(match: re.Match) -> str:
        if match.group(1):  # already escaped
            return match.group(0)
        tag = match.group(2).lstrip("/").strip()
        if not tag or tag.startswith("@") or tag == "link":
            return match.group(0)
        try:
            Style.parse(tag.replace("=", " ", 1))  # [link=URL] is the style "link URL"
        except StyleSyntaxError:
            return "\\" + match.group(0)
        return match.group(0)

    return _TAG.sub(keep, markup)


_TAG = re.compile(r"(\\?)\[([^\[\]]*)\]")


def _text(console, markup: str, style: str = ""):
    """A help text line: rich markup (the house mode), highlighted; plain when the markup is bad."""
    from rich.errors import MarkupError
    from rich.text import Text

    try:
        text = Text.from_markup(escape_non_styles(markup), style=style)
    except MarkupError:
        text = Text(markup, style=style)
    return console.highlighter(text)


def _two_columns(console, rows: list[tuple[str, Any]], inner: int, name_style: str = ""):
    """Rows of (names, help renderable): aligned, the long names on a line of their own."""
    from rich.console import Group
    from rich.padding import Padding
    from rich.table import Table
    from rich.text import Text

    width = names_width([n for n, _ in rows], inner)
    parts = []
    for names, help_ in rows:
        label = console.highlighter(Text(names, style=name_style))
        if len(names) <= width:
            grid = Table.grid(padding=(0, 2), expand=True)
            grid.add_column(width=width, no_wrap=True)
            grid.add_column(ratio=1, overflow="fold")
            grid.add_row(label, help_)
            parts.append(grid)
        else:
            parts.append(label)
            parts.append(Padding(help_, (0, 0, 0, width + 2)))
    return Group(*parts)


def _panel(console, title: str, body):
    from rich.panel import Panel

    return Panel(body, border_style="dim", title=title, title_align="left")


def _param_help(console, own: str, extra: str):
    from rich.text import Text

    text = Text()
    lines = [" ".join(p) for p in paragraphs(own)]
    if lines:
        text.append_text(_text(console, "\n".join(lines)))
    if extra:
        text.append(("  " if lines else "") + extra, style="dim")
    return text


def render(command: Any, ctx: Any) -> None:
    """Print ``command``'s help page (usage, help text, arguments, options, subcommands)."""
    from rich.console import Group
    from rich.padding import Padding
    from rich.text import Text

    console = _console()
    inner = max(20, console.width - 4)  # a panel's border and padding
    console.print(Padding(console.highlighter(Text(command.get_usage(ctx).rstrip())), 1), style="bold")
    if command.help:
        lines: list[Any] = []
        for i, para in enumerate(paragraphs(command.help)):
            if i:
                lines.append(Text(""))
            lines.append(_text(console, "\n".join(para), style="" if i == 0 else "dim"))
        console.print(Padding(Group(*lines), (0, 1, 1, 1)))

    panels: dict[str, list[tuple[str, Any]]] = defaultdict(list)
    for kind, default in (("argument", "Arguments"), ("option", "Options")):
        for param in command.get_params(ctx):
            if param.param_type_name != kind:
                continue
            record = split_help_record(param, ctx)
            if record is None:
                continue
            names, own, extra = record
            title = getattr(param, "rich_help_panel", None) or default
            panels[title].append((names, _param_help(console, own, extra)))
    for title, rows in panels.items():
        console.print(_panel(console, title, _two_columns(console, rows, inner)))

    if isinstance(command, TyperGroup):
        groups: dict[str, list[tuple[str, Any]]] = defaultdict(list)
        for name in command.list_commands(ctx):
            sub = command.get_command(ctx, name)
            if sub is None or sub.hidden:
                continue
            title = getattr(sub, "rich_help_panel", None) or "Commands"
            groups[title].append((name, _text(console, summary(sub.short_help or sub.help or ""))))
        for title, rows in groups.items():
            console.print(_panel(console, title, _two_columns(console, rows, inner, name_style="bold cyan")))
    if command.epilog:
        text = "\n\n".join("\n".join(p) for p in paragraphs(command.epilog))
        console.print(Padding(_text(console, text), 1))


class HelpCommand(TyperCommand):
    """A typer command whose ``--help`` is :func:`render`'s."""

    def format_help(self, ctx, formatter) -> None:
        render(self, ctx)


class HelpGroup(TyperGroup):
    """A typer group whose ``--help`` is :func:`render`'s."""

    def format_help(self, ctx, formatter) -> None:
        render(self, ctx)


class Typer(typer.Typer):
    """``typer.Typer`` whose groups and commands draw their help with :func:`render`."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("cls", HelpGroup)
        super().__init__(*args, **kwargs)

    def command(self, *args: Any, cls: Any = None, **kwargs: Any):
        return super().command(*args, cls=cls or HelpCommand, **kwargs)
