"""The grader's HTML report: a header with the date, qcarlab's version and the sheets; every
figure opens full size, by a link to the file beside the report or, without one, in a CSS-only
overlay (no JavaScript) (issue 29)."""

from __future__ import annotations

import base64
import re
from datetime import datetime, timezone

import cv2
import numpy as np

from qcarlab import __version__
from qcarlab.grading.report import figure_href, write_html


def _student() -> dict:
    row = {"sheet": "stop-sign", "id": "5.2-task2-run", "status": "passed", "earned": 4, "points": 4,
           "problem": None, "criteria": [{"criterion": "stopped", "expected": "true", "value": True, "passed": True,
                                          "reason": None, "earned": 4, "points": 4}]}
    return {"student": "ana maria", "points": 4, "max_points": 4, "tasks": [row]}


def _png(w: int = 1200, h: int = 800) -> bytes:
    img = np.full((h, w, 3), 255, np.uint8)
    cv2.circle(img, (w // 2, h // 2), 100, (0, 0, 200), -1)
    return cv2.imencode(".png", img)[1].tobytes()


def test_header_names_the_date_the_version_and_the_sheets(tmp_path):
    when = datetime(2026, 12, 3, 14, 5, tzinfo=timezone.utc)
    page = write_html(tmp_path / "report.html", "grades", [_student()], {}, {},
                      sheets=["5.2 Stop sign (stop-sign)"], when=when).read_text()
    assert "<dt>date</dt><dd>2026-12-03 14:05 UTC</dd>" in page
    assert f"<dt>qcarlab</dt><dd>{__version__}</dd>" in page
    assert "<dt>sheets</dt><dd>5.2 Stop sign (stop-sign)</dd>" in page


def test_thumbnails_link_to_the_full_size_files(tmp_path):
    figs = {("ana maria", "stop-sign", "5.2-task2-run"): {"detection.png": _png(), "speed.png": _png(700, 450)}}
    page = write_html(tmp_path / "report.html", "grades", [_student()], figs, {}, href=figure_href).read_text()
    links = re.findall(r"<a href='([^']+)' target='_blank'", page)
    assert links == ["ana%20maria/stop-sign/5.2-task2-run/detection.png", "ana%20maria/stop-sign/5.2-task2-run/speed.png"]
    assert page.count("src='data:image/jpeg;base64,") == 2  # the thumbnails stay embedded, scaled down
    assert figure_href("x", "s", "t", "a.png", single=True) == "s/t/a.png"


def test_without_the_files_a_click_shows_the_embedded_full_image(tmp_path):
    png = _png()
    figs = {("ana maria", "stop-sign", "5.2-task2-run"): {"detection.png": png}}
    page = write_html(tmp_path / "report.html", "grades", [_student()], figs, {}).read_text()
    assert "<a href='#fig-1'>" in page and "id='fig-1'" in page and "<script" not in page
    full = re.search(r"id='fig-1'[^>]*><img [^>]*src='data:image/png;base64,([^']+)'", page)
    assert full and base64.b64decode(full.group(1)) == png  # the full-size figure itself
    assert ".big:target" in page  # shown by CSS alone
