"""Inputs that ended in "internal error" (issue 30, item 5): each is one line naming what is wrong,
exit 2, and bounded work; and path-gen never writes outside --out (item 6)."""

from __future__ import annotations

import pytest


def one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "internal error" not in lines[0], err
    return lines[0]


def test_a_path_shorter_than_the_look_ahead_is_refused(cli, tmp_path):
    short = tmp_path / "short.csv"
    short.write_text("x,y\n0,0\n0,-0.11\n")
    code, out, err = cli("path-follow", short)
    assert code == 2
    assert "the path is 0.110 m long; a path to follow must be longer than" in one_error_line(err)


@pytest.mark.parametrize("args, says", [
    (("io-test", "--duration", "1e308"), "--duration must be in (0, 3600] s, got 1e+308"),
    (("io-test", "--duration", "nan"), "--duration must be in (0, 3600] s"),
    (("path-follow", "line", "--points", "1000000000"), "points must be a whole number from 2 to 100,000"),
    (("path-gen", "line", "--points", "100001"), "points must be a whole number from 2 to 100,000"),
    (("path-gen", "circle", "--step", "1e-9"), "makes more than 100,000 points"),
])
def test_absurd_sizes_are_refused_at_once(cli, args, says):
    code, out, err = cli(*args)
    assert code == 2 and says in one_error_line(err)


def test_path_gen_never_writes_outside_its_folder(cli, tmp_path):
    out = tmp_path / "paths"
    for name in ("../../escape", "sub/p", "..", "a\\b"):
        code, _, err = cli("path-gen", "circle", "--name", name, "--out", out)
        assert code == 2 and "--name must be a file name without a folder" in one_error_line(err)
    assert not any(tmp_path.parent.glob("escape*")) and not out.exists()
    code, _, err = cli("path-gen", "circle", "--name", "mine", "--out", out)
    assert code == 0 and (out / "mine.csv").is_file()


def test_an_out_folder_name_too_long_for_the_file_system_is_one_line(cli, tmp_path):
    code, out, err = cli("path-gen", "circle", "--out", tmp_path / ("a" * 300))
    assert code == 2 and "File name too long" in one_error_line(err)
