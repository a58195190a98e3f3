"""The lab sheets travel with the package: a non-editable install finds them from any folder."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_a_non_editable_install_grades_from_any_folder(tmp_path):
    target = tmp_path / "site"
    done = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", str(REPO), "--target",
                           str(target)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (target / "qcarlab" / "labs" / "path-following.yaml").is_file()
    env = {**os.environ, "PYTHONPATH": str(target)}  # the installed copy first, not the checkout
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    def qcarlab(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "qcarlab", *args], cwd=elsewhere, env=env, capture_output=True,
                              text=True, timeout=600)

    where = subprocess.run([sys.executable, "-c", "import qcarlab; print(qcarlab.__file__)"], cwd=elsewhere,
                           env=env, capture_output=True, text=True)
    assert where.stdout.strip().startswith(str(target)), where
    listed = qcarlab("labs", "--json")
    assert listed.returncode == 0, listed.stderr
    paths = [Path(r["path"]) for r in json.loads(listed.stdout)["sheets"]]
    assert len(paths) >= 9 and all(str(p).startswith(str(target)) for p in paths)
    graded = qcarlab("grade", "path-following", "--task", "p1-line", "--json")
    assert graded.returncode == 0, graded.stderr
    assert json.loads(graded.stdout)["tasks"][0]["passed"] is True
