"""Built-in paths (the sheet's exact matrices), path geometry, path files and the path plot."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qcarlab import paths
from qcarlab.constants import DEFAULT_PARAMS
from qcarlab.errors import InputError

FREQ = 2 * math.pi / 30
TS = 0.033


# ---- the sheet's matrices (section 4.2.1) ------------------------------------------------------
def test_line_is_the_sheets_p1_exactly():
    p1 = paths.line(3, 4)
    assert p1.dtype == float and p1.shape == (4, 2)
    assert np.array_equal(p1, [[0, 0], [0, -1], [0, -2], [0, -3]])
    assert not np.signbit(p1[:, 0]).any()  # no -0.0
    assert np.array_equal(paths.line(), p1)  # the defaults are the sheet's
    assert np.allclose(paths.line(2, 5)[:, 1], [0, -0.5, -1, -1.5, -2])


def test_circle_is_64_rows_from_the_start_pose_turning_left():
    p2 = paths.circle()
    assert p2.shape == (64, 2)
    assert np.array_equal(p2[0], [0, 0]) and np.array_equal(p2[1], [0, 0])  # start point + theta=0
    centre = np.array([1.5, 0.0])  # on the car's left when heading -Y
    assert np.allclose(np.hypot(*(p2 - centre).T), 1.5)
    ang = np.unwrap(np.arctan2(p2[1:, 1] - centre[1], p2[1:, 0] - centre[0]))
    assert np.allclose(np.diff(ang), 0.1)  # counter-clockwise, 0.1 rad apart (rows 1..63)
    assert p2[2, 1] < 0 and abs(p2[2, 0]) < 0.01  # leaves the start along -Y
    assert paths.curvature(p2)[2:-1].min() > 0  # a left turn everywhere
    assert np.allclose(p2[-1], [1.5 * (1 - math.cos(6.2)), -1.5 * math.sin(6.2)])


def test_butterfly_is_the_sheets_p3():
    p3 = paths.butterfly(4, 4)
    assert p3.shape == (911, 2)
    assert np.array_equal(p3[0], [0, 0]) and np.array_equal(p3[1], [0, 0])
    for k in (1, 100, 454, 909):  # row k+1 is t = k * Ts
        t = k * TS
        assert p3[k + 1] == pytest.approx([4 * math.sin(FREQ * t), -4 * math.sin(2 * FREQ * t)], abs=1e-12)
    assert p3[-1] == pytest.approx([4 * math.sin(FREQ * 29.997), -4 * math.sin(2 * FREQ * 29.997)])
    # width/height are the sheet's wingWidth/wingHeight (amplitudes): x and y span [-4, 4]
    assert paths.summary(p3)["bbox"] == pytest.approx([-4, -4, 4, 4], abs=1e-4)
    p4 = paths.butterfly(2, 3)
    assert p4[1:, 0] == pytest.approx(p3[1:, 0] / 2) and p4[1:, 1] == pytest.approx(p3[1:, 1] * 3 / 4)


# ---- geometry ------------------------------------------------------------------------------------
def test_tight_spots_of_the_sheets_paths():
    rmin = DEFAULT_PARAMS.min_turning_radius
    assert rmin == pytest.approx(0.256 / math.tan(0.5), abs=1e-9)  # 0.469 m: the servo takes +-0.5 rad
    s4 = paths.summary(paths.butterfly(2, 2), rmin)
    assert len(s4["tight_spots"]) == 4
    for spot in s4["tight_spots"]:
        assert 0.2 < spot["radius_m"] < rmin
        assert abs(abs(spot["y"]) - 2) < 0.01 and abs(abs(spot["x"]) - math.sqrt(2)) < 0.1
    assert sorted(s["turn"] for s in s4["tight_spots"]) == ["left", "left", "right", "right"]
    assert s4["tightest_radius_m"] == pytest.approx(0.2388, abs=2e-3)
    s3 = paths.summary(paths.butterfly(4, 4))
    assert s3["tight_spots"] == [] and s3["tightest_radius_m"] > rmin
    s2 = paths.summary(paths.circle())
    assert s2["tight_spots"] == [] and s2["tightest_radius_m"] == pytest.approx(1.5)
    s1 = paths.summary(paths.line())
    assert s1 == {"points": 4, "length_m": 3.0, "bbox": [0.0, -3.0, 0.0, 0.0],
                  "tightest_radius_m": None, "tight_spots": []}


def test_curvature_signed_and_robust_to_duplicates():
    theta = np.linspace(0, math.pi, 20)
    arc = np.column_stack([2 * np.cos(theta), 2 * np.sin(theta)])  # CCW, radius 2
    k = paths.curvature(arc)
    assert k[0] == 0 and k[-1] == 0 and np.allclose(k[1:-1], 0.5)
    assert np.allclose(paths.curvature(arc[::-1])[1:-1], -0.5)  # clockwise: negative
    dup = np.repeat(arc, [1, 1, 3] + [1] * 17, axis=0)  # vertex 2 three times
    kd = paths.curvature(dup)
    assert np.isfinite(kd).all() and np.allclose(kd[2:5], 0.5) and len(kd) == 22
    assert np.array_equal(paths.curvature([[0, 0], [1, 0], [2, 0]]), [0, 0, 0])
    assert paths.path_length(dup) == pytest.approx(paths.path_length(arc))


def test_builtin_by_name_and_bad_options():
    assert np.array_equal(paths.builtin("butterfly", width=2, height=2), paths.butterfly(2, 2))
    assert np.array_equal(paths.builtin("circle", radius=None), paths.circle())
    assert set(paths.BUILTIN) == {"line", "circle", "butterfly"}
    bad = [
        (("spiral",), {}, "unknown path 'spiral'"),
        (("line",), {"radius": 1}, "unknown option 'radius'"),
        (("line",), {"points": 1}, "points"),
        (("line",), {"points": 2.5}, "points"),
        (("line",), {"length": -3}, "length must be a positive number"),
        (("circle",), {"radius": 0}, "radius"),
        (("circle",), {"step": 4}, "step"),
        (("butterfly",), {"width": float("nan")}, "width"),
        (("butterfly",), {"height": "big"}, "height"),
    ]
    for args, kwargs, text in bad:
        with pytest.raises(InputError, match=text):
            paths.builtin(*args, **kwargs)


# ---- files ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["csv", "npy", "yaml"])
def test_write_read_round_trip_bit_exact(tmp_path, fmt):
    p = paths.butterfly(2, 2)
    out = paths.write_path(p, tmp_path / f"sub/p4.{fmt}")
    back = paths.read_path(out)
    assert np.array_equal(back, p[1:])  # the repeated start point is dropped on reading


def test_csv_header_and_explicit_format(tmp_path):
    out = paths.write_path(paths.line(), tmp_path / "p1.csv")
    assert out.read_text().splitlines()[:3] == ["x,y", "0.0,0.0", "0.0,-1.0"]
    f = tmp_path / "noheader.csv"
    f.write_text("# my path\n0,0\n\n1.5, 2\n")
    assert np.array_equal(paths.read_path(f), [[0, 0], [1.5, 2]])
    y = tmp_path / "m.yaml"
    y.write_text("path:\n  - [0, 0]\n  - [1, 0]\n  - ['2e-1', 1]\n")
    assert np.allclose(paths.read_path(y), [[0, 0], [1, 0], [0.2, 1]])
    paths.write_path(paths.line(), tmp_path / "as_npy.dat", fmt="npy")
    assert np.load(tmp_path / "as_npy.dat").shape == (4, 2)
    with pytest.raises(InputError, match="unknown path format"):
        paths.write_path(paths.line(), tmp_path / "x.csv", fmt="xls")


BAD_FILES = [
    ("empty.csv", "", "empty.csv: the file is empty"),
    ("blank.csv", "  \n\n", "blank.csv: the file is empty"),
    ("header.csv", "x,y\n", "header.csv: no points"),
    ("p.csv", "x,y\n0,0\nabc,1\n", "p.csv line 3: 'abc' is not a number"),
    ("cols.csv", "x,y\n0,0\n1,2,3\n", "cols.csv line 3: expected two numbers x,y, got 3 values"),
    ("one.csv", "0\n1\n", "one.csv line 1: expected two numbers x,y, got 1 values"),
    ("badhdr.csv", "east,north\n0,0\n1,1\n", "badhdr.csv line 1: 'east' is not a number"),
    ("nan.csv", "x,y\n0,0\nnan,1\n", "nan.csv line 3: 'nan' is not a finite number"),
    ("inf.csv", "x,y\n0,0\n1,-inf\n", "inf.csv line 3: '-inf' is not a finite number"),
    ("single.csv", "x,y\n1,2\n", "single.csv: a path needs at least 2 points, got 1"),
    ("same.csv", "x,y\n1,2\n1,2\n1,2\n", "same.csv: the path has zero length"),
    ("p.txt2", "0,0\n1,1\n", "unknown path file type '.txt2'"),
    ("list.yaml", "path: 3\n", "list.yaml: expected a list of [x, y] pairs"),
    ("nokey.yaml", "points: [[0, 0], [1, 1]]\n", "nokey.yaml: a mapping needs the key 'path'"),
    ("pair.yaml", "- [0, 0]\n- [1, 2, 3]\n", "pair.yaml point 2: expected a pair [x, y]"),
    ("word.yaml", "- [0, 0]\n- [abc, 2]\n", "word.yaml point 2: 'abc' is not a number"),
    ("bool.yaml", "- [0, 0]\n- [true, 2]\n", "bool.yaml point 2: True is not a number"),
    ("nanv.yaml", "- [0, 0]\n- [.nan, 2]\n", "nanv.yaml point 2: nan is not a finite number"),
    ("syntax.yaml", "- [0, 0\n- [1, 2]\n", "syntax.yaml line"),
    ("one.yaml", "- [0, 0]\n", "one.yaml: a path needs at least 2 points, got 1"),
    ("empty.yaml", "", "empty.yaml: the file is empty"),
]


@pytest.mark.parametrize(("name", "text", "message"), BAD_FILES, ids=[b[0] for b in BAD_FILES])
def test_read_path_bad_text_files(tmp_path, name, text, message):
    f = tmp_path / name
    f.write_text(text)
    with pytest.raises(InputError) as info:
        paths.read_path(f)
    msg = str(info.value)
    assert "\n" not in msg and message in msg


def test_read_path_bad_npy_and_missing(tmp_path):
    cases = []
    np.save(tmp_path / "shape.npy", np.zeros((3, 3)))
    cases.append(("shape.npy", "expected an array of shape (N, 2), got (3, 3)"))
    np.save(tmp_path / "nan.npy", np.array([[0, 0], [np.nan, 1]]))
    cases.append(("nan.npy", "nan.npy point 2: not a finite number"))
    np.save(tmp_path / "one.npy", np.array([[0.0, 1.0]]))
    cases.append(("one.npy", "a path needs at least 2 points, got 1"))
    np.save(tmp_path / "text.npy", np.array([["a", "b"], ["c", "d"]]))
    cases.append(("text.npy", "expected a numeric array"))
    (tmp_path / "junk.npy").write_bytes(b"not numpy at all")
    cases.append(("junk.npy", "junk.npy: not a readable .npy array"))
    (tmp_path / "empty.npy").write_bytes(b"")
    cases.append(("empty.npy", "empty.npy: the file is empty"))
    cases.append(("missing.csv", "missing.csv: no such file"))
    (tmp_path / "dir.csv").mkdir()
    cases.append(("dir.csv", "is a directory"))
    for name, message in cases:
        with pytest.raises(InputError) as info:
            paths.read_path(tmp_path / name)
        assert "\n" not in str(info.value) and message in str(info.value), name


def test_read_path_drops_consecutive_duplicates(tmp_path):
    f = tmp_path / "dups.csv"
    f.write_text("x,y\n0,0\n0,0\n1,0\n1,0\n1,1\n0,0\n")
    assert np.array_equal(paths.read_path(f), [[0, 0], [1, 0], [1, 1], [0, 0]])


# ---- plot ----------------------------------------------------------------------------------------
def test_plot_path_writes_a_png(tmp_path):
    from qcarlab.plots import plot_path

    p4 = paths.butterfly(2, 2)
    out = plot_path(p4, tmp_path / "fig" / "p4.png", "p4", paths.summary(p4)["tight_spots"])
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000
