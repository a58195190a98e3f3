"""docs/lessons.md is what the commands print today (issue 27: each lesson's table made by the
command itself): regenerated in-process and compared line for line."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_the_lessons_page_is_what_the_commands_print(cli):
    spec = importlib.util.spec_from_file_location("lessons_page", DOCS / "lessons.py")
    lessons = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(lessons)

    def run(argv):
        code, out, err = cli(*argv, "--json")
        assert code in (0, 1), err
        return code, json.loads(out)

    fresh = lessons.page(run).splitlines()
    page = (DOCS / "lessons.md").read_text(encoding="utf-8").splitlines()
    stale = [(i + 1, a, b) for i, (a, b) in enumerate(zip(page, fresh)) if a != b]
    assert len(page) == len(fresh) and not stale, (
        f"docs/lessons.md is stale (run python docs/lessons.py); first differences: {stale[:3]}")
    text = "\n".join(fresh)
    assert "| 0.5 | 3.8 |" in text and "missed: the car did not reach the end of the path" in text
    assert "exit 1: never found the yellow line" in text
