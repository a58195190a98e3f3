"""The simulator's precomputed rasters kept on disk, and the referee's compiled collision check."""

from __future__ import annotations

import numpy as np
import pytest

from qcarlab.sim import raster
from qcarlab.sim.world import load_world


def test_a_cached_floor_is_the_drawn_one_and_a_damaged_file_is_drawn_again(tmp_path, monkeypatch):
    monkeypatch.setenv(raster.CACHE_ENV, str(tmp_path))
    drawn = raster.floor_runs(load_world("stop-sign"), 200.0)
    files = list(tmp_path.glob("floor_runs-*"))
    assert len(files) == 1 and files[0].is_dir()
    loaded = raster.floor_runs(load_world("stop-sign"), 200.0)  # a new world object: from the disk
    for name in ("texels", "levels", "squares"):
        assert np.array_equal(getattr(drawn, name), getattr(loaded, name))
    assert (drawn.x0, drawn.y1, drawn.ppm) == (loaded.x0, loaded.y1, loaded.ppm)
    other = raster.floor_runs(load_world("track"), 200.0)  # another floor: another file
    assert len(list(tmp_path.glob("floor_runs-*"))) == 2 and other.texels.shape != drawn.texels.shape
    (files[0] / "texels.npy").write_bytes(b"not an npy")
    again = raster.floor_runs(load_world("stop-sign"), 200.0)
    assert np.array_equal(again.texels, drawn.texels)
    assert np.array_equal(np.load(files[0] / "texels.npy"), drawn.texels)  # written again whole
    (files[0] / "levels.npy").unlink()
    assert np.array_equal(raster.floor_runs(load_world("stop-sign"), 200.0).levels, drawn.levels)
    assert (files[0] / "levels.npy").exists()


def test_the_cache_can_be_switched_off(tmp_path, monkeypatch):
    monkeypatch.setenv(raster.CACHE_ENV, "off")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    raster.floor_runs(load_world("stop-sign"), 200.0)
    assert not list(tmp_path.rglob("*.npy"))


def test_a_cached_raster_is_the_built_one(tmp_path, monkeypatch):
    import dataclasses

    monkeypatch.setenv(raster.CACHE_ENV, str(tmp_path))
    for world in ("hallway", "obstacles"):
        built = raster.build_raster(load_world(world), z=0.2)
        loaded = raster.build_raster(load_world(world), z=0.2)
        for f in dataclasses.fields(raster.Raster):
            a, b = getattr(built, f.name), getattr(loaded, f.name)
            assert type(a) is type(b) and np.array_equal(a, b) and getattr(a, "dtype", None) == getattr(b, "dtype", None), f.name
    assert len(list(tmp_path.glob("raster-*"))) == 2


def test_a_cameras_noise_tiles_from_the_disk_are_the_drawn_ones_and_leave_the_generator_as_drawing_does(
        tmp_path, monkeypatch):
    """The tiles as ``rng.normal`` and the float32 standard normals drew them (the formula before the
    cache), the same whether drawn or read back, and the generator left where the draws leave it
    (the frames' noise windows come from it next); another seed, another entry."""
    from qcarlab.sim import camera

    monkeypatch.setenv(raster.CACHE_ENV, str(tmp_path))
    shape = (100 + camera._NOISE_PAD, 80 + camera._NOISE_PAD)
    for seed in (3, 3, 4):
        ref = np.random.default_rng(seed)
        ref.random(5)
        tile = np.clip(np.rint(ref.normal(0.0, camera.COLOR_NOISE_SD, shape + (3,))), -127, 127).astype(np.int8)
        depth = np.clip(np.rint(ref.standard_normal(shape, dtype=np.float32) / camera.DEPTH_TILE_STEP), -127,
                        127).astype(np.int8)
        rng = np.random.default_rng(seed)
        rng.random(5)
        noise = camera._Noise(rng, 100, 80, camera.COLOR_NOISE_SD, True)
        assert np.array_equal(noise.tile, tile.reshape(shape[0], -1)) and np.array_equal(noise.depth, depth)
        assert rng.random(4).tolist() == ref.random(4).tolist()
    assert len(list(tmp_path.glob("noise-*"))) == 2
    # a damaged entry's generator state: the tiles drawn again, the generator as drawing leaves it
    for entry in tmp_path.glob("noise-*"):
        np.save(entry / "after.npy", np.asarray("not json"), allow_pickle=False)
    rng, ref = np.random.default_rng(3), np.random.default_rng(3)
    rng.random(5)
    ref.random(5)
    tile = np.clip(np.rint(ref.normal(0.0, camera.COLOR_NOISE_SD, shape + (3,))), -127, 127).astype(np.int8)
    ref.standard_normal(shape, dtype=np.float32)
    noise = camera._Noise(rng, 100, 80, camera.COLOR_NOISE_SD, True)
    assert np.array_equal(noise.tile, tile.reshape(shape[0], -1)) and rng.random() == ref.random()
    # noise entries are kept in a pool of their own: many seeds never push a floor or raster out
    monkeypatch.setattr(raster, "OWN_POOL", {"noise": 2})
    monkeypatch.setattr(raster, "KEEP", 1)
    raster.build_raster(load_world("hallway"), z=0.2)
    for seed in (5, 6, 7):
        camera._Noise(np.random.default_rng(seed), 20, 10, camera.COLOR_NOISE_SD, False)
    assert len(list(tmp_path.glob("noise-*"))) == 2 and len(list(tmp_path.glob("raster-*"))) == 1


def test_the_compiled_collision_check_gives_the_numpy_ones_numbers():
    """Clearance runs numba's kernel once numba is loaded (the sensors load it), else numpy: the
    same distances and pieces, bit for bit, on random poses in every kind of world."""
    import sys

    pytest.importorskip("numba")
    from qcarlab.constants import DEFAULT_PARAMS
    from qcarlab.experiments.safety import Clearance

    rng = np.random.default_rng(7)
    for name in ("hallway", "obstacles", "track", "stop-sign"):
        world = load_world(name)
        check = Clearance(world, DEFAULT_PARAMS)
        x0, y0, x1, y1 = world.bounds
        poses = np.column_stack((rng.uniform(x0, x1, 400), rng.uniform(y0, y1, 400), rng.uniform(-4, 4, 400)))
        fast = [check(x, y, yaw, 1.0) for x, y, yaw in poses]
        numba_module = sys.modules.pop("numba")
        try:
            slow = [check(x, y, yaw, 1.0) for x, y, yaw in poses]
        finally:
            sys.modules["numba"] = numba_module
        assert fast == slow, name
        assert any(d == 0.0 for d, _ in fast) and any(d > 0.1 for d, _ in fast)


def test_a_student_at_a_terminal_is_told_once_why_the_first_run_compiles(monkeypatch, caplog):
    """numba's first compilation after an install takes 10-30 s: at a terminal one line says so,
    once a process; with stderr captured or redirected (tests, CI, the grader) nothing is said."""
    import io
    import logging

    from qcarlab.sim import _kernels

    assert _kernels.COMPILE_NOTICE is not None  # numba is a dependency: the notice is always registered

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    with caplog.at_level(logging.INFO, logger="qcarlab.sim"):
        monkeypatch.setattr("sys.stderr", io.StringIO())
        quiet = type(_kernels.COMPILE_NOTICE)()
        quiet.on_start(None)
        monkeypatch.setattr("sys.stderr", Terminal())
        told = type(_kernels.COMPILE_NOTICE)()
        told.on_start(None)
        told.on_start(None)
    said = [r.getMessage() for r in caplog.records if "compiling" in r.getMessage()]
    assert len(said) == 1 and "once after an install" in said[0]


def test_rows_of_a_lazily_drawn_frame_read_negative_bounds_as_a_slice_does():
    """RowFrame.color_rows/depth_rows(a, b): negative bounds count from the bottom, as numpy's
    slices, and every row returned is drawn (equal to the whole frame's)."""
    from qcarlab.constants import DEFAULT_PARAMS
    from qcarlab.sim.camera import RGBDCamera

    pose = (0.5, 0.3, 0.2)
    whole = RGBDCamera("hallway", DEFAULT_PARAMS, np.random.default_rng(3)).render(pose, 1.0)
    rows = RGBDCamera("hallway", DEFAULT_PARAMS, np.random.default_rng(3)).render_rows(pose, 1.0)
    assert np.array_equal(rows.depth_rows(400, -1), whole.depth[400:-1])
    assert np.array_equal(rows.color_rows(-40, 480), whole.color[-40:])
