"""The simulator's public contact API: SimCar.contact() and qcarlab.sim.contact.Contact (issue 29,
item 5: ending a gymnasium episode on a collision without reaching into the simulator)."""

from __future__ import annotations

import math

import pytest

from qcarlab import open_car
from qcarlab.sim.contact import Clearance, Contact, ContactEvent
from qcarlab.sim.world import load_world, world_from_dict


def test_a_car_driven_into_a_wall_reports_the_collision():
    with open_car("sim", world="hallway", seed=1) as car:
        assert car.contact() is None  # the start is free
        car.write(0.3, 0.0)
        hit = None
        for _ in range(400):
            car.advance(0.02)
            hit = car.contact()
            if hit is not None:
                break
        assert isinstance(hit, ContactEvent) and hit.kind == "collision"
        assert hit.y < -5.5 and hit.obstacle is not None and 2.0 < hit.t < 5.0
        assert math.isclose(hit.t, car.time)


def test_a_car_leaving_its_world_reports_it():
    world = world_from_dict({"name": "open", "floor": {"size": [2.0, 2.0], "origin": [-1.0, -1.0]},
                             "start": [0.0, 0.0, 0.0]})
    with open_car("sim", world=world) as car:
        car.write(0.2, 0.0)
        hit = None
        while hit is None and car.time < 10.0:
            car.advance(0.05)
            hit = car.contact()
        assert hit is not None and hit.kind == "left_world" and hit.x > 1.0


@pytest.mark.parametrize("world", ["hallway", "obstacles", "track", "stop-sign"])
def test_contact_agrees_with_the_clearance_at_every_pose(world):
    """The skip between full checks never hides a contact the exact clearance finds (balls too)."""
    import numpy as np

    w = load_world(world)
    contact, clearance = Contact(w), Clearance(w, w.params)
    x0, y0, x1, y1 = w.bounds
    rng = np.random.default_rng(0)
    x, y, yaw = w.start
    for k in range(3000):  # a random walk of small moves, as a car's poses follow each other
        x = min(max(x + rng.normal(0.0, 0.03), x0 - 0.1), x1 + 0.1)
        y = min(max(y + rng.normal(0.0, 0.03), y0 - 0.1), y1 + 0.1)
        yaw += rng.normal(0.0, 0.05)
        t = k * 0.02
        hit = contact.check(x, y, yaw, t)
        inside = x0 <= x <= x1 and y0 <= y <= y1
        if not inside:
            assert hit is not None and hit.kind == "left_world"
        else:
            assert (hit is not None) == (clearance(x, y, yaw, t)[0] <= 0.0), (k, x, y, yaw)
