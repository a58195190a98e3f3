"""The floor's rasters are drawn once per machine: cached on disk, keyed by what draws them."""

from __future__ import annotations

import numpy as np

from qcarlab.sim import raster
from qcarlab.sim.world import load_world


def test_a_cached_floor_is_the_drawn_one_and_a_damaged_file_is_drawn_again(tmp_path, monkeypatch):
    monkeypatch.setenv(raster.CACHE_ENV, str(tmp_path))
    drawn = raster.floor_runs(load_world("stop-sign"), 200.0)
    files = list(tmp_path.glob("floor_runs-*.npz"))
    assert len(files) == 1
    loaded = raster.floor_runs(load_world("stop-sign"), 200.0)  # a new world object: from the disk
    for name in ("texels", "levels", "squares"):
        assert np.array_equal(getattr(drawn, name), getattr(loaded, name))
    assert (drawn.x0, drawn.y1, drawn.ppm) == (loaded.x0, loaded.y1, loaded.ppm)
    other = raster.floor_runs(load_world("track"), 200.0)  # another floor: another file
    assert len(list(tmp_path.glob("floor_runs-*.npz"))) == 2 and other.texels.shape != drawn.texels.shape
    files[0].write_bytes(b"not an npz")
    again = raster.floor_runs(load_world("stop-sign"), 200.0)
    assert np.array_equal(again.texels, drawn.texels)


def test_the_cache_can_be_switched_off(tmp_path, monkeypatch):
    monkeypatch.setenv(raster.CACHE_ENV, "off")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    raster.floor_runs(load_world("stop-sign"), 200.0)
    assert not list(tmp_path.rglob("*.npz"))


def test_a_cached_raster_is_the_built_one(tmp_path, monkeypatch):
    import dataclasses

    monkeypatch.setenv(raster.CACHE_ENV, str(tmp_path))
    for world in ("hallway", "obstacles"):
        built = raster.build_raster(load_world(world), z=0.2)
        loaded = raster.build_raster(load_world(world), z=0.2)
        for f in dataclasses.fields(raster.Raster):
            a, b = getattr(built, f.name), getattr(loaded, f.name)
            assert type(a) is type(b) and np.array_equal(a, b) and getattr(a, "dtype", None) == getattr(b, "dtype", None), f.name
    assert len(list(tmp_path.glob("raster-*.npz"))) == 2
