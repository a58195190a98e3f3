"""The reference pages' content, generated from the code when the documentation is built.

A page asks for a piece with a marker that ``docs/hooks.py`` replaces::

    <!-- generate: cli -->                 every command's usage and options (from the Typer app)
    <!-- generate: blocks -->              every lab's blocks (their BlockSpec: signature, units, section)
    <!-- generate: sheets -->              every lab sheet: tasks, criteria, points (from its YAML)
    <!-- generate: sheet stop-sign -->     one sheet
    <!-- generate: template stop-sign -->  the files `qcarlab template` writes for a lab's blocks to fill
    <!-- generate: questions stop-sign --> the sheet's questions that answers.md asks
    <!-- generate: realism -->             the realism profiles' values, units and sources
    <!-- generate: exit-codes -->          the error classes and their exit codes
    <!-- generate: include PATH -->        a Markdown file of the project (PATH from the root)

Each function returns Markdown; none needs mkdocs.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

MARKER = re.compile(r"<!-- generate: (?P<what>[\w-]+)(?: (?P<arg>[^>]*?))? -->")
ROOT = Path(__file__).resolve().parent.parent


def _cell(text: object) -> str:
    """Text safe inside a Markdown table cell."""
    return " ".join(str(text).split()).replace("|", "\\|")


def click_root():
    """The CLI as click sees it, every command loaded."""
    import typer

    from qcarlab.cli import app, load_commands

    load_commands()
    return typer.main.get_command(app)


def command_options(name: str) -> set[str]:
    """Every option name (``--speed``, ``-n``) the command ``name`` accepts; KeyError when no such command."""
    cmd = click_root().commands[name]
    names = {"--help"}
    for p in cmd.params:
        names.update(getattr(p, "opts", ()))
        names.update(getattr(p, "secondary_opts", ()))
    return names


def cli() -> str:
    """Every command: its help's first paragraph, usage, arguments and options (from the CLI itself)."""
    root = click_root()
    out = ["Every command below is `qcarlab COMMAND [OPTIONS]`; `qcarlab COMMAND --help` prints the same.", ""]
    for name, cmd in root.commands.items():
        ctx = cmd.context_class(cmd, info_name=name, parent=root.context_class(root, info_name="qcarlab"))
        help_text = (cmd.help or "").strip()
        paragraphs = help_text.split("\n\n")
        out += [f"## `qcarlab {name}`", "", " ".join(paragraphs[0].split()), ""]
        for extra in paragraphs[1:]:
            if extra.strip().startswith("Examples:"):
                examples = [e.strip() for e in extra.strip()[len("Examples:"):].replace("\n", " ").split("|")]
                out += ["Examples:", "", "```"] + [e for e in examples if e] + ["```", ""]
            else:
                out += [" ".join(extra.split()), ""]
        out += ["```", cmd.get_usage(ctx), "```", "", "| argument or option | what it does |", "|---|---|"]
        for p in cmd.params:
            if getattr(p, "hidden", False):
                continue
            if p.param_type_name == "argument":
                out.append(f"| `{p.name.upper()}` | {_cell(getattr(p, 'help', '') or '')} |")
                continue
            record = p.get_help_record(ctx)
            if record:
                out.append(f"| `{_cell(record[0])}` | {_cell(record[1])} |")
        out.append("")
    return "\n".join(out)


def blocks() -> str:
    """Every lab's blocks, from their specs (the same rows as ``qcarlab blocks LAB``)."""
    from qcarlab.experiments.labs import LABS, block_rows

    out = ["Each lab is the sheet's block diagram; any block can be replaced by yours "
           "(`--use FILE.py`, `--block NAME=FILE.py:FUNCTION`). **fill**: the sheet asks you to write it "
           "(`qcarlab template` makes its file). Units: SI; body frame x forward, y left; angles + = left.", ""]
    for lab in LABS:
        out += [f"## `{lab.command}`: sheet {lab.section}, {lab.title}", "",
                "| block | signature | units | sheet | what it does |", "|---|---|---|---|---|"]
        for r in block_rows(lab):
            tags = (" **fill**" if r["in_template"] else "") + (" (class)" if r["stateful"] else "")
            out.append(f"| `{r['name']}`{tags} | `{_cell(r['signature'])}` | {_cell(r['units'])} | "
                       f"{_cell(r['section'])} | {_cell(r['what'])} |")
        out.append("")
    return "\n".join(out)


def _sheet_md(path: Path, level: str = "##") -> list[str]:
    from qcarlab.grading.sheet import load_sheet

    s = load_sheet(path)
    out = [f"{level} `{s.name}`: {s.section} {s.title} ({s.points:g} points)", ""]
    if s.lab:
        out += [f"Lab: `qcarlab {s.lab}` (`qcarlab template {s.lab} --out DIR` makes the workspace). "
                f"Grade yourself: `qcarlab grade {s.name} --submission DIR`.", ""]
    else:
        out += [f"No blocks to fill: its tasks run on your car (`qcarlab grade {s.name} --car tcp://CAR:18960`) "
                f"or on saved runs (`--results DIR`).", ""]
    out += ["| task | what | graded by | criteria (points) |", "|---|---|---|---|"]
    for t in s.tasks:
        how = f"block `{t.block}`" if t.block else f"`{_cell(t.command)}`"
        if t.uses and not t.block:
            how += "<br>uses " + ", ".join(f"`{u}`" for u in t.uses)
        crit = "<br>".join(f"{_cell(c.describe())} ({c.points:g})" for c in t.criteria)
        out.append(f"| `{t.id}` | {_cell(t.text)} | {how} | {crit} |")
    out.append("")
    return out


def sheets() -> str:
    """Every shipped lab sheet: tasks, criteria, points."""
    from qcarlab.grading.sheet import shipped_sheets

    out = ["The lab sheets shipped with qcarlab (`qcarlab/labs/*.yaml`; `qcarlab labs` lists them, "
           "`qcarlab labs NAME` shows one). A criterion is worth 1 point unless its sheet says otherwise.", ""]
    for path in shipped_sheets():
        out += _sheet_md(path)
    return "\n".join(out)


def sheet(name: str) -> str:
    """One shipped sheet, as a section of a tutorial."""
    from qcarlab.grading.sheet import find_sheet

    return "\n".join(_sheet_md(find_sheet(name), level="###"))


def template(lab_name: str) -> str:
    """The block files and params.yaml that ``qcarlab template LAB`` writes, as the student gets them."""
    from qcarlab.experiments.labs import block_file, find_lab, params_file

    lab = find_lab(lab_name)
    out = []
    for spec in lab.to_fill:
        out += [f"`{spec.name}.py`:", "", "```python", block_file(spec, lab).rstrip(), "```", ""]
    out += ["`params.yaml`:", "", "```yaml", params_file(lab).rstrip(), "```", ""]
    return "\n".join(out)


def questions(lab_name: str) -> str:
    """The sheet's questions, as ``answers.md`` asks them."""
    from qcarlab.experiments.labs import find_lab

    return "\n".join(f"{i}. {q}" for i, q in enumerate(find_lab(lab_name).questions, 1))


def realism() -> str:
    """Each shipped realism profile: every imperfection's value, unit and source."""
    import yaml

    out = []
    for path in sorted((ROOT / "qcarlab" / "realism").glob("*.yaml")):
        data = yaml.safe_load(path.read_text())
        out += [f"## `--realism {data.get('name', path.stem)}`", "", _cell(data.get("description", "")), "",
                "| imperfection | value | unit | source |", "|---|---|---|---|"]
        for key, entry in data.items():
            if isinstance(entry, dict) and "value" in entry:
                out.append(f"| `{key}` | {entry['value']:g} | {_cell(entry.get('unit', ''))} | "
                           f"{_cell(entry.get('source', ''))} |")
        out.append("")
    return "\n".join(out)


def exit_codes() -> str:
    """The error classes the CLI maps to exit codes (from ``qcarlab.errors``)."""
    import inspect

    from qcarlab import errors

    out = ["| exit code | error class | when |", "|---|---|---|"]
    for name, cls in inspect.getmembers(errors, inspect.isclass):
        if issubclass(cls, errors.QcarlabError) and cls.__module__ == errors.__name__:
            out.append(f"| {cls.exit_code} | `{name}` | {_cell((cls.__doc__ or '').strip())} |")
    return "\n".join(out)


def include(path: str) -> str:
    """A Markdown file of the project, its first heading dropped (the page has its own)."""
    text = (ROOT / path).read_text()
    return re.sub(r"\A# .*\n", "", text)


GENERATORS = {"cli": cli, "blocks": blocks, "sheets": sheets, "sheet": sheet, "template": template,
              "questions": questions, "realism": realism, "exit-codes": exit_codes, "include": include}


def generate(what: str, arg: str | None) -> str:
    """The Markdown for one ``<!-- generate: WHAT ARG -->`` marker; KeyError for an unknown WHAT."""
    fn = GENERATORS[what]
    return fn(*shlex.split(arg)) if arg else fn()


__all__ = ["GENERATORS", "MARKER", "command_options", "generate"]
