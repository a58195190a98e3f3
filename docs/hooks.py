"""MkDocs hooks: the pages show what the code does today, never what it did when they were written.

- ``<!-- run: qcarlab ... -->``: the command is run when the site is built (all of them at the start,
  two at a time) and its real output or figure goes on the page below the marker
  (:mod:`runmarks`). A command that fails, or no longer exits as the page says, fails the build.
- ``<!-- generate: ... -->``: reference content made from the code (:mod:`reference_gen`): the
  CLI's options, the blocks' specs, the lab sheets, the realism profiles, the exit codes.

Set ``QCARLAB_DOCS_NO_RUN=1`` to build without running the commands (a quick look at the layout:
each marker then says the output is left out).
"""

from __future__ import annotations

import logging
import os
import sys
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import reference_gen  # noqa: E402
import runmarks  # noqa: E402
from mkdocs.exceptions import PluginError  # noqa: E402

log = logging.getLogger("mkdocs.hooks.qcarlab")
_futures: dict[runmarks.Run, Future] = {}
_pool: ThreadPoolExecutor | None = None


def _skip() -> bool:
    return os.environ.get("QCARLAB_DOCS_NO_RUN", "") not in ("", "0")


def on_files(files, config):
    """Start every marked command of every page before the first page is rendered."""
    global _pool
    _futures.clear()
    if _skip():
        return files
    runs: list[runmarks.Run] = []
    for f in files.documentation_pages():
        text = Path(f.abs_src_path).read_text(encoding="utf-8")
        try:
            runs += [r for r in runmarks.find_runs(text, f.src_uri) if r not in runs]
        except ValueError as e:
            raise PluginError(str(e)) from None
    _pool = ThreadPoolExecutor(max_workers=max(1, min(2, os.cpu_count() or 1)))
    for r in runs:
        _futures[r] = _pool.submit(runmarks.execute, r)
    log.info("qcarlab docs: running %d commands of the pages", len(runs))
    return files


def _run_block(match, where: str) -> str:
    run = runmarks.parse_marker(match.group("body"), where)
    if _skip():
        return match.group(0) + f"\n\n```console\n$ {run.command}\n(output left out: QCARLAB_DOCS_NO_RUN)\n```"
    future = _futures.get(run) or (_pool or ThreadPoolExecutor(1)).submit(runmarks.execute, run)
    try:
        return match.group(0) + "\n\n" + runmarks.render(future.result())
    except Exception as e:  # the page is stale: fail the build with what went wrong
        raise PluginError(f"{where}: {e}") from None


def _generate_block(match, where: str) -> str:
    try:
        return match.group(0) + "\n\n" + reference_gen.generate(match.group("what"), match.group("arg"))
    except Exception as e:
        raise PluginError(f"{where}: <!-- generate: {match.group('what')} {match.group('arg') or ''} -->: "
                          f"{type(e).__name__}: {e}") from None


def on_page_markdown(markdown, page, config, files):
    where = page.file.src_uri
    markdown = reference_gen.MARKER.sub(lambda m: _generate_block(m, where), markdown)
    return runmarks.MARKER.sub(lambda m: _run_block(m, where), markdown)


def on_post_build(config):
    global _pool
    if _pool is not None:
        _pool.shutdown(wait=False, cancel_futures=True)
        _pool = None
