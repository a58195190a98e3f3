"""Compiling the simulator's kernels ahead (qcarlab.precompile): a cold cache is seen as cold,
the warm server compiles when it is, and after it the labs compile nothing."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from qcarlab import warm
from qcarlab import precompile

pytest.importorskip("numba")


def _python(code: str, cache: str) -> subprocess.CompletedProcess:
    # (every process of these tests in the same folder: they import the same qcarlab, whose kernels
    # are the cache's, whether it is this checkout's or an installed copy)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=cache,
                          env={**os.environ, "NUMBA_CACHE_DIR": cache})


def test_an_empty_cache_needs_compiling(tmp_path):
    out = _python("from qcarlab import precompile; print(precompile.needs_compiling())", str(tmp_path))
    assert out.stdout.strip() == "True", out.stderr


def test_the_warm_server_compiles_only_when_the_cache_is_cold(monkeypatch):
    ran: list[tuple[list[str], dict]] = []
    monkeypatch.setattr(subprocess, "run", lambda argv, **kw: ran.append((argv, kw)))
    monkeypatch.setattr(precompile, "needs_compiling", lambda: False)
    warm._precompile("k-1")
    assert ran == []
    monkeypatch.setattr(precompile, "needs_compiling", lambda: True)
    warm._precompile("k-1")
    assert [argv for argv, _ in ran] == [[sys.executable, "-m", "qcarlab.precompile"]]
    here = str(Path(warm.__file__).resolve().parents[1])  # the folder this qcarlab is in: its kernels
    assert here in ran[0][1]["env"]["PYTHONPATH"].split(os.pathsep)
    assert ran[0][1]["timeout"] < warm.START_TIMEOUT  # (a client waits that long for a starting server)


def test_a_failed_check_leaves_the_compiling_to_the_labs(monkeypatch, capsys):
    def broken():
        raise RuntimeError("no locator available")

    monkeypatch.setattr(precompile, "needs_compiling", broken)
    warm._precompile("k-1")  # the server starts all the same
    assert "not compiled ahead" in capsys.readouterr().out


@pytest.mark.slow
def test_after_it_the_labs_compile_nothing(tmp_path):
    cache = str(tmp_path)
    done = subprocess.run([sys.executable, "-m", "qcarlab.precompile"], capture_output=True, text=True,
                          timeout=600, cwd=tmp_path, env={**os.environ, "NUMBA_CACHE_DIR": cache})
    assert done.returncode == 0 and "compiled" in done.stderr, done.stderr
    assert _python("from qcarlab import precompile; print(precompile.needs_compiling())", cache).stdout.strip() \
        == "False"
    for argv in (["stop-sign"], ["lane-follow", "--duration", "2"], ["avoid", "--world", "hallway", "--duration", "2"],
                 ["camera", "--csi"], ["lidar-scan"], ["stop-sign", "--realism", "lab"]):
        out = subprocess.run([sys.executable, "-m", "qcarlab", *argv], capture_output=True, text=True, timeout=300,
                             cwd=tmp_path, env={**os.environ, "NUMBA_CACHE_DIR": cache, "NUMBA_DEBUG_CACHE": "1"})
        assert out.returncode == 0, out.stderr
        saved = [line for line in (out.stdout + out.stderr).splitlines() if "data saved" in line]
        assert saved == [], (argv, saved)  # every kernel the lab used was in the cache
