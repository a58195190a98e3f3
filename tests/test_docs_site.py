"""The documentation's cheap invariants, without mkdocs (issue 31): the full build is `mkdocs build --strict`.

- every page of mkdocs.yml's nav exists, and every Markdown page under docs/ is in the nav;
- every README link into docs/ resolves, and the README is short;
- every command a page marks to run (``<!-- run: qcarlab ... -->``) is a real qcarlab command
  with real options (checked against the Typer app), and every ``<!-- generate: ... -->`` names a
  generator that exists;
- every `qcarlab ...` a tutorial or how-to shows is a real command with the options it shows.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
sys.path.insert(0, str(DOCS))

import reference_gen  # noqa: E402
import runmarks  # noqa: E402


def _nav_pages() -> list[str]:
    """The nav's page paths, read from mkdocs.yml's text (its !!python tags need no YAML loader)."""
    text = (ROOT / "mkdocs.yml").read_text()
    nav = text[text.index("\nnav:"):]
    return re.findall(r"^\s*-\s+(?:[^:\n]+:\s+)?([\w./-]+\.md)\s*$", nav, flags=re.M)


def _pages() -> list[Path]:
    return sorted(p for p in DOCS.rglob("*.md"))


def test_every_nav_page_exists_and_every_page_is_in_the_nav():
    nav = _nav_pages()
    assert len(nav) >= 36, nav
    missing = [p for p in nav if not (DOCS / p).is_file()]
    assert not missing, f"in mkdocs.yml's nav but not in docs/: {missing}"
    orphans = [p.relative_to(DOCS).as_posix() for p in _pages() if p.relative_to(DOCS).as_posix() not in nav]
    assert not orphans, f"pages not in mkdocs.yml's nav: {orphans}"


def test_readme_is_short_and_its_links_into_docs_resolve():
    text = (ROOT / "README.md").read_text()
    assert 150 <= len(text.splitlines()) <= 250
    links = re.findall(r"\]\((docs/[^)#]*)(?:#[^)]*)?\)", text)
    assert len(links) >= 12
    broken = [link for link in links if not (ROOT / link).exists()]
    assert not broken, f"README links to missing docs: {broken}"


def test_every_tutorial_is_one_click_from_the_readme():
    text = (ROOT / "README.md").read_text()
    tutorials = [p.relative_to(ROOT).as_posix() for p in (DOCS / "tutorials").glob("*.md")]
    assert not [t for t in tutorials if f"]({t})" not in text]


def test_relative_links_between_pages_resolve():
    broken = []
    for page in _pages():
        text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            if not (page.parent / target.split("#")[0]).resolve().exists():
                broken.append(f"{page.relative_to(DOCS)} -> {target}")
    assert not broken, broken


def _marked_runs() -> list[tuple[str, runmarks.Run]]:
    out = []
    for page in _pages():
        out += [(page.relative_to(DOCS).as_posix(), r) for r in runmarks.find_runs(page.read_text(), str(page))]
    return out


def test_the_docs_run_commands():
    runs = _marked_runs()
    assert len(runs) >= 15
    assert not [r for _, r in runs if r.argv and r.argv[0] == "keyboard-drive"], "keyboard-drive is interactive"


@pytest.mark.parametrize("where,run", _marked_runs(), ids=lambda v: v if isinstance(v, str) else v.command)
def test_each_marked_command_is_a_real_command_with_real_options(where, run):
    name = run.argv[0]
    commands = reference_gen.click_root().commands
    assert name in commands, f"{where}: no command qcarlab {name}"
    options = reference_gen.command_options(name)
    typed = [w.split("=")[0] for w in run.argv[1:] if w.startswith("-")]
    unknown = [o for o in typed if o not in options]
    assert not unknown, f"{where}: qcarlab {name} has no option {unknown}"


def test_every_generate_marker_names_a_generator():
    bad = []
    for page in _pages():
        for m in reference_gen.MARKER.finditer(page.read_text()):
            if m.group("what") not in reference_gen.GENERATORS:
                bad.append(f"{page.relative_to(DOCS)}: {m.group(0)}")
    assert not bad, bad


def test_generated_reference_names_every_command_and_sheet():
    cli = reference_gen.cli()
    for name in reference_gen.click_root().commands:
        assert f"## `qcarlab {name}`" in cli
    sheets = reference_gen.sheets()
    for path in (ROOT / "qcarlab" / "labs").glob("*.yaml"):
        assert f"## `{path.stem}`" in sheets


def _shown_commands() -> list[tuple[str, list[str]]]:
    """Every ``qcarlab ...`` a tutorial or how-to shows in code (inline or in a block), as words."""
    out = []
    for page in _pages():
        rel = page.relative_to(DOCS).as_posix()
        if not rel.startswith(("tutorials/", "how-to/")):
            continue
        text = page.read_text()
        spans = re.findall(r"`(qcarlab [^`\n]+)`", text)
        for block in re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S):
            spans += [ln.strip() for ln in block.splitlines() if ln.strip().startswith("qcarlab ")]
        for span in spans:
            words = span.split(" #")[0].split("|")[0].split("&&")[0].split()
            if len(words) > 1 and not words[1].startswith(("-", "<", "[")):
                out.append((rel, words[1:]))
    return out


def test_the_pages_show_many_commands():
    assert len(_shown_commands()) >= 30


@pytest.mark.parametrize("where,argv", _shown_commands(), ids=lambda v: v if isinstance(v, str) else " ".join(v))
def test_each_command_a_page_shows_is_real_with_real_options(where, argv):
    """What a student copies from a page runs: the command exists and has every option shown (the
    commands themselves run at the build, or, template and grade, in test_every_point)."""
    commands = reference_gen.click_root().commands
    assert argv[0] in commands, f"{where}: no command qcarlab {argv[0]}"
    if hasattr(commands[argv[0]], "commands"):  # a group (detect, replay, ...): its subcommand's options
        return
    options = reference_gen.command_options(argv[0])
    typed = [w.split("=")[0] for w in argv[1:] if w.startswith("--") or re.fullmatch(r"-[a-zA-Z]", w)]
    unknown = [o for o in typed if o not in options]
    assert not unknown, f"{where}: qcarlab {argv[0]} has no option {unknown}"
