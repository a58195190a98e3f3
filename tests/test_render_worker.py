"""A served real-time simulator draws its frames in a worker process: the same frames the car would
have drawn itself, with its realism profile's effects (the worker once built an ideal car)."""

from __future__ import annotations

import numpy as np
import pytest

from qcarlab.car.sim import SimCar
from qcarlab.net.render_worker import RenderWorker

pytestmark = pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs fork")

POSE, T, YAW_RATE = (1.0, 0.0, -1.5707963), 0.5, 1.2


def own_frame(realism, kind):
    car = SimCar(seed=3, world="track", realism=realism)
    car.lidar_beams = None
    return car.draw_frame(kind, POSE, T, YAW_RATE)


@pytest.mark.parametrize("realism", ["lab", "ideal"])
def test_the_worker_draws_the_cars_own_frames_with_its_realism(realism):
    car = SimCar(seed=3, world="track", realism=realism)
    worker = RenderWorker(car.sensor_recipe(), kinds=("rgbd", "lidar"))
    try:
        color, depth = worker.draw("rgbd", POSE, T, YAW_RATE)
        angles, ranges = worker.draw("lidar", POSE, T, YAW_RATE)
    finally:
        worker.close()
    want = own_frame(realism, "rgbd")
    np.testing.assert_array_equal(color, want.color)
    np.testing.assert_array_equal(depth, want.depth)
    np.testing.assert_array_equal(ranges, own_frame(realism, "lidar").ranges)
    if realism == "lab":  # the profile's exposure, blur and dropouts are in the worker's frames
        ideal = own_frame("ideal", "rgbd")
        assert not np.array_equal(color, ideal.color)
        assert np.count_nonzero(ranges == 0.0) > np.count_nonzero(own_frame("ideal", "lidar").ranges == 0.0)
