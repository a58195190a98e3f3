"""What grading writes: ``grade.json``, JUnit XML, the gradebook CSV and the class's HTML report.

- ``grade.json``: every task of every student with its criteria (expected, value, verdict, reason,
  points) and the totals.
- JUnit (``--junit FILE``, made with junitparser): one ``testsuite`` per student and sheet, one
  ``testcase`` per criterion (``classname`` = ``sheet.task``, ``student.sheet.task`` for a class,
  each part's own dots made ``_``: Jenkins reads a classname's dots as packages, so task
  ``4.1.4-pure-pursuit-block`` is ``4_1_4-pure-pursuit-block``), a ``failure`` with the reason when
  a criterion is not met, an ``error`` when the task could not run (timeout, crash, block
  missing), ``skipped`` for tasks that need a car. GitHub Actions, GitLab and Jenkins show it.
- ``gradebook.csv``: one row per student: points per task (``sheet/task`` columns), total, maximum.
- ``report.html``: one file, no external resources: a header naming the date, qcarlab's version
  and the sheets, the table of students and tasks, then per student each task's criteria, their
  figures (embedded, scaled down; each thumbnail links to the full-size PNG the grader wrote beside
  the report, ``STUDENT/SHEET/TASK/NAME.png``, or, without those files, opens the embedded full
  image in a CSS-only overlay: no JavaScript) and their ``answers.md`` (shown as text, never as
  HTML).
"""

from __future__ import annotations

import base64
import csv
import html
from collections.abc import Callable, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any
from urllib.parse import quote

from qcarlab.grading.checks import value_text


def _public(row: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in row.items() if not k.startswith("_")}


def report_dict(sheets: list[Any], students: list[dict[str, Any]], single: bool) -> dict[str, Any]:
    """grade.json: for one submission its tasks at the top level; for a class, one entry per student."""
    from qcarlab import __version__

    head = {"qcarlab": __version__,
            "sheets": [{"name": s.name, "title": s.title, "section": s.section, "path": str(s.path),
                        "lab": s.lab, "points": s.points} for s in sheets]}
    clean = [{**{k: v for k, v in st.items() if k != "tasks"}, "tasks": [_public(r) for r in st["tasks"]]}
             for st in students]
    if single:
        head.update(clean[0])
        return head
    head["students"] = clean
    return head


# --------------------------------------------------------------------------------------------
# JUnit
# --------------------------------------------------------------------------------------------
def junit_classname(*parts: str) -> str:
    """A JUnit ``classname`` of ``parts`` joined by dots, each part's own dots made ``_``: CI
    systems (Jenkins, its xunit plugin) split a classname at its dots into packages and a class, so
    ``stop-sign`` / ``5.2-task1-block`` must not become packages ``stop-sign.5`` and class
    ``2-task1-block``."""
    return ".".join(str(p).replace(".", "_") for p in parts)


def write_junit(path: str | Path, students: list[dict[str, Any]], single: bool) -> Path:
    from junitparser import Error, Failure, JUnitXml, Skipped, TestCase, TestSuite

    xml = JUnitXml("qcarlab grade")
    for st in students:
        by_sheet: dict[str, list[dict[str, Any]]] = {}
        for r in st["tasks"]:
            by_sheet.setdefault(r["sheet"], []).append(r)
        for sheet, rows in by_sheet.items():
            suite = TestSuite(sheet if single else f"{st['student']}: {sheet}")
            for r in rows:
                n = max(len(r["criteria"]), 1)
                for c in r["criteria"]:
                    case = TestCase(c["criterion"], classname=junit_classname(sheet, r["id"]) if single
                                    else junit_classname(st["student"], sheet, r["id"]),
                                    time=round((r.get("seconds") or 0.0) / n, 3))
                    got = repr(c["value"]) if c["value"] is not None else (c.get("missing") or "nothing")
                    text = f"expected {c['expected']}; got {got}; points {c['earned']:g}/{c['points']:g}"
                    if r["status"] == "skipped":
                        case.result = [Skipped(r["problem"])]
                    elif r["problem"] and not c["passed"] and c["reason"] == r["problem"]:
                        err = Error(r["problem"], "task")
                        err.text = (r.get("detail") or "")[-4000:] or text
                        case.result = [err]
                    elif not c["passed"]:
                        fail = Failure((c["reason"] or "criterion not met")
                                       + (f"; the run: {r['run_failure']}" if r.get("run_failure") else ""),
                                       "criterion")
                        fail.text = text + (f"\n{r['detail'][-4000:]}" if r.get("detail") else "")
                        case.result = [fail]
                    case.system_out = text
                    suite.add_testcase(case)
            suite.add_property("points", f"{sum(r['earned'] for r in rows):g}")
            suite.add_property("max_points", f"{sum(r['points'] for r in rows if r['status'] != 'skipped'):g}")
            xml.add_testsuite(suite)
    import os
    import tempfile

    out = Path(path)
    if out.parent != Path(""):
        out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent)
    os.close(fd)
    try:
        xml.write(tmp, pretty=True)
        os.replace(tmp, out)  # a symbolic link at ``out`` is replaced, never followed
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


# --------------------------------------------------------------------------------------------
# the gradebook
# --------------------------------------------------------------------------------------------
def columns(students: list[dict[str, Any]]) -> list[str]:
    cols: list[str] = []
    for st in students:
        for r in st["tasks"]:
            key = f"{r['sheet']}/{r['id']}"
            if key not in cols:
                cols.append(key)
    return cols


def write_gradebook(path: str | Path, students: list[dict[str, Any]]) -> Path:
    """student, points per task, total, max_points, sandboxed (skipped tasks are empty; a task the
    grader failed to run says "not graded")."""
    cols = columns(students)
    from qcarlab.record import atomic_file

    out = Path(path)
    with atomic_file(out, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["student", *cols, "total", "max_points", "sandboxed"])
        for st in students:
            got = {f"{r['sheet']}/{r['id']}": r for r in st["tasks"]}
            cells = []
            for c in cols:
                r = got.get(c)
                cells.append("" if r is None or r["status"] == "skipped" else
                             "not graded" if r["status"] == "error" else f"{r['earned']:g}")
            w.writerow([st["student"], *cells, f"{st['points']:g}", f"{st['max_points']:g}",
                        "yes" if st.get("sandboxed", True) else "no"])
    return out


# --------------------------------------------------------------------------------------------
# the HTML report
# --------------------------------------------------------------------------------------------
_CSS = """
body{font-family:system-ui,sans-serif;margin:2em;color:#222}
table{border-collapse:collapse;margin:1em 0}
td,th{border:1px solid #ccc;padding:.25em .5em;text-align:left;vertical-align:top;font-size:90%}
th{background:#f3f3f3} .pass{background:#e3f6e3} .fail{background:#fbe3e3} .skip{background:#eee;color:#777}
.figs img{max-width:360px;margin:.25em;border:1px solid #ddd} pre{background:#f7f7f7;padding:1em;white-space:pre-wrap}
.figs a{display:inline-block;text-decoration:none} .figs figure{display:inline-block;margin:.25em}
.figs figcaption{font-size:80%;color:#555}
.big{display:none} .big:target{display:flex;position:fixed;inset:0;background:rgba(0,0,0,.85);z-index:9;
 align-items:center;justify-content:center} .big img{max-width:98vw;max-height:98vh;background:#fff}
h2{border-top:2px solid #ddd;padding-top:1em} .small{color:#666;font-size:85%}
.head{color:#444;margin-top:-.5em} .head dt{font-weight:bold;display:inline} .head dd{display:inline;margin:0 1.5em 0 .3em}
"""


def figure_href(student: str, sheet: str, task: str, name: str, single: bool = False) -> str:
    """Where the grader writes a task's figure, relative to ``report.html`` in the same OUT folder
    (``STUDENT/SHEET/TASK/NAME``, each part URL-quoted), for the report's links."""
    parts = (sheet, task, Path(name).name) if single else (student, sheet, task, Path(name).name)
    return "/".join(quote(str(p), safe="") for p in parts)


def thumbnail(png: bytes, width: int = 480) -> tuple[str, bytes]:
    """A figure scaled to ``width`` px as JPEG (mime, bytes); the PNG itself when it cannot be read
    or its header says it is over :data:`qcarlab.MAX_IMAGE_PIXELS` (it is then never decoded)."""
    try:
        import cv2
        import numpy as np

        from qcarlab import MAX_IMAGE_PIXELS
        from qcarlab.media import image_size

        size = image_size(png)
        if size is None or size[0] * size[1] > MAX_IMAGE_PIXELS:  # never decoded: shown as it is
            return "image/png", png
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            return "image/png", png
        if img.shape[1] > width:
            img = cv2.resize(img, (width, int(img.shape[0] * width / img.shape[1])), interpolation=cv2.INTER_AREA)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
        return ("image/jpeg", buf.tobytes()) if ok else ("image/png", png)
    except Exception:  # noqa: BLE001 - a figure that cannot be scaled is shown as it is
        return "image/png", png


def _cls(r: dict[str, Any]) -> str:
    return {"passed": "pass", "skipped": "skip"}.get(r["status"], "fail")


def write_html(path: str | Path, title: str, students: list[dict[str, Any]], figures: dict[tuple, dict[str, bytes]],
               answers: dict[str, list[tuple[str, str]]], sheets: Sequence[str] = (),
               href: Callable[[str, str, str, str], str | None] | None = None,
               when: datetime | None = None) -> Path:
    """The class report; ``figures[(student, sheet, task)]`` are PNG bytes by name, ``answers[student]``
    each sheet's ``answers.md`` as (sheet, text). The header names ``when`` (default now), qcarlab's
    version and ``sheets``. ``href(student, sheet, task, name)`` is the full-size figure's address
    relative to the report (:func:`figure_href` where the grader wrote the files); without it, or
    where it gives None, a thumbnail opens the embedded full image in an overlay (CSS ``:target``)."""
    from qcarlab import __version__

    e = html.escape
    cols = columns(students)
    stamp = (when or datetime.now().astimezone()).strftime("%Y-%m-%d %H:%M %Z").strip()
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{e(title)}</title><style>{_CSS}</style>"
             f"<meta name='generator' content='qcarlab {e(__version__)}'></head><body><h1>{e(title)}</h1>",
             f"<dl class='head'><dt>date</dt><dd>{e(stamp)}</dd><dt>qcarlab</dt><dd>{e(__version__)}</dd>"
             + (f"<dt>sheets</dt><dd>{e('; '.join(sheets))}</dd>" if sheets else "") + "</dl>",
             "<p class='small'>click a figure to see it full size</p>" if figures and any(figures.values()) else "",
             "<table><tr><th>student</th>"]
    parts += [f"<th>{e(c)}</th>" for c in cols] + ["<th>total</th></tr>"]
    for st in students:
        got = {f"{r['sheet']}/{r['id']}": r for r in st["tasks"]}
        parts.append(f"<tr><td><a href='#s-{e(st['student'])}'>{e(st['student'])}</a></td>")
        for c in cols:
            r = got.get(c)
            if r is None:
                parts.append("<td></td>")
            else:
                shown = {"skipped": "skipped", "error": "not graded"}.get(r["status"], f"{r['earned']:g}/{r['points']:g}")
                parts.append(f"<td class='{_cls(r)}' title='{e(r['problem'] or '')}'>{shown}</td>")
        parts.append(f"<td><b>{st['points']:g}</b>/{st['max_points']:g}</td></tr>")
    parts.append("</table>")
    n_big = 0
    for st in students:
        parts.append(f"<h2 id='s-{e(st['student'])}'>{e(st['student'])}: {st['points']:g} of "
                     f"{st['max_points']:g} points</h2>")
        if not st.get("sandboxed", True):
            parts.append("<p><b>not sandboxed</b>: this student's code ran without the sandbox; see each task</p>")
        if st.get("submission_problems"):
            parts.append("<p class='small'>" + "<br>".join(e(x) for x in st["submission_problems"]) + "</p>")
        for r in st["tasks"]:
            parts.append(f"<h3 class='{_cls(r)}'>{e(r['sheet'])} / {e(r['id'])}: {r['status']} "
                         f"({r['earned']:g}/{r['points']:g})</h3>")
            if r.get("command"):
                parts.append(f"<p class='small'><code>{e(r['command'])}</code></p>")
            if r["problem"]:
                parts.append(f"<p><b>{e(r['problem'])}</b></p>")
            if r.get("run_failure"):
                parts.append(f"<p>the run failed: <b>{e(r['run_failure'])}</b></p>")
            if r.get("detail"):
                parts.append(f"<pre>{e(r['detail'])}</pre>")
            if r.get("student_output"):
                parts.append(f"<p class='small'>your code printed:</p><pre>{e(r['student_output'])}</pre>")
            parts.append("<table><tr><th>criterion</th><th>value</th><th>result</th><th>points</th></tr>")
            for c in r["criteria"]:
                shown = value_text(c)
                verdict = "pass" if c["passed"] else ("skipped" if r["status"] == "skipped" else
                                                      "FAIL: " + (c["reason"] or ""))
                parts.append(f"<tr class='{'pass' if c['passed'] else _cls(r)}'><td>{e(c['criterion'])}</td>"
                             f"<td>{e(shown[:200])}</td><td>{e(verdict)}</td>"
                             f"<td>{c['earned']:g}/{c['points']:g}</td></tr>")
            parts.append("</table>")
            figs = figures.get((st["student"], r["sheet"], r["id"])) or {}
            if figs:
                parts.append("<div class='figs'>")
                for name, png in sorted(figs.items()):
                    mime, data = thumbnail(png)
                    thumb = (f"<img alt='{e(name)}' title='{e(name)}: click for full size' "
                             f"src='data:{mime};base64,{base64.b64encode(data).decode()}'>")
                    target = href(st["student"], r["sheet"], r["id"], name) if href is not None else None
                    if target is not None:
                        parts.append(f"<figure><a href='{e(target)}' target='_blank' rel='noopener'>{thumb}</a>"
                                     f"<figcaption>{e(name)}</figcaption></figure>")
                    else:  # the full image embedded, shown over the page while the URL's fragment names it
                        n_big += 1
                        big = f"fig-{n_big}"
                        parts.append(f"<figure><a href='#{big}'>{thumb}</a><figcaption>{e(name)}</figcaption></figure>"
                                     f"<a class='big' id='{big}' href='#_' title='close'><img alt='{e(name)}' "
                                     f"src='data:image/png;base64,{base64.b64encode(png).decode()}'></a>")
                parts.append("</div>")
        given = answers.get(st["student"]) or []
        if not given:
            parts.append("<h3>answers.md</h3><p class='small'>(none)</p>")
        for sheet, text in given:
            parts.append(f"<h3>answers.md ({e(sheet)})</h3><pre>{e(text)}</pre>")
    parts.append("</body></html>")
    out = Path(path)
    from qcarlab.record import write_bytes

    write_bytes(out, "".join(parts).encode("utf-8"))
    return out


__all__ = ["figure_href", "junit_classname", "report_dict", "thumbnail", "write_gradebook", "write_html", "write_junit"]
