"""The LIDAR's numpy edge scan and the referee's PathClearance give the compiled / array numbers, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from qcarlab.constants import DEFAULT_PARAMS
from qcarlab.sim import lidar as lidar_mod
from qcarlab.sim.contact import Clearance, PathClearance
from qcarlab.sim.edge_scan import shape_tables
from qcarlab.sim.lidar import Lidar
from qcarlab.sim.raster import build_raster
from qcarlab.sim.world import load_world

WORLDS = ["hallway", "obstacles", "stop-sign", "studio", "track"]


@pytest.mark.parametrize("name", WORLDS)
def test_shape_tables_are_the_rasters(name):
    w = load_world(name)
    r, s = build_raster(w, z=DEFAULT_PARAMS.lidar_z), shape_tables(w, DEFAULT_PARAMS.lidar_z)
    for f in ("kinds", "poly_start", "poly_count", "verts", "circles"):
        assert np.array_equal(getattr(r, f), getattr(s, f)) and getattr(r, f).dtype == getattr(s, f).dtype, f


@pytest.mark.parametrize("name", ["hallway", "obstacles"])
@pytest.mark.parametrize("fov", [None, 4.7])
def test_numpy_scan_is_the_kernels(name, fov, monkeypatch):
    w = load_world(name)
    lid = Lidar(w, fov=fov, beams=None if fov is None else 1080)
    rng = np.random.default_rng(5)
    x0, y0, x1, y1 = w.bounds
    for k in range(60):
        pose, t = (rng.uniform(x0, x1), rng.uniform(y0, y1), rng.uniform(-4, 4)), rng.uniform(0, 40)
        noise = rng.normal(0, 0.005, lid.beams) if k % 2 else lid._no_noise
        for near_mode in (-1, 0, 1):
            monkeypatch.setattr(lidar_mod, "COMPILED", True)
            a = lid._cast(pose, t, noise, near_mode)
            monkeypatch.setattr(lidar_mod, "COMPILED", False)
            b = lid._cast(pose, t, noise, near_mode)
            assert np.array_equal(a, b), (pose, t, near_mode)


@pytest.mark.parametrize("name", WORLDS)
def test_path_clearance_is_clearance(name):
    w = load_world(name)
    full, path = Clearance(w, DEFAULT_PARAMS), PathClearance(w, DEFAULT_PARAMS)
    rng = np.random.default_rng(3)
    x0, y0, x1, y1 = w.bounds
    for _ in range(8):
        x, y, yaw, t = rng.uniform(x0, x1), rng.uniform(y0, y1), rng.uniform(-4, 4), rng.uniform(0, 30)
        step = rng.choice([0.001, 0.005, 0.03, 0.2])
        for i in range(150):
            x, y, yaw, t = x + rng.normal(0, step), y + rng.normal(0, step), yaw + rng.normal(0, step), t + 0.01
            assert full(x, y, yaw, t, balls=i % 7 != 0) == path(x, y, yaw, t, balls=i % 7 != 0)
