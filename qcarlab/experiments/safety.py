"""Did the run stay safe? Collisions with the world and leaving it, from the simulator's truth.

The geometry is the simulator's (:mod:`qcarlab.sim.contact`: the exact distance between the car's
footprint and every solid and ball; :class:`Clearance` is imported from there).
:class:`WorldWatch` wraps any lab model: before each tick it ends the run (a goal missed) when the
car touches a solid or leaves the world's bounds (:class:`~qcarlab.sim.contact.Contact`, which
skips the full check while the car cannot have reached the nearest solid), and says so in a line.
"""

from __future__ import annotations

from typing import Any

from qcarlab.constants import QCarParams
from qcarlab.experiments.loop import STOP
from qcarlab.sim.contact import Clearance, Contact

__all__ = ["Clearance", "WorldWatch"]


class WorldWatch:
    """Ends a run when the car collides with the world or leaves it (simulated cars in a local world)."""

    def __init__(self, world: Any, params: QCarParams, truth):
        self.world, self.truth = world, truth
        self.contact = Contact(world, params)
        self.clearance = self.contact.clearance
        self.event: dict[str, Any] | None = None

    @property
    def min_clearance(self) -> float:
        """The smallest clearance (m) a full check found so far."""
        return self.contact.min_clearance

    @classmethod
    def for_car(cls, car: Any, world: Any) -> WorldWatch | None:
        if world is None or car.truth() is None:
            return None
        return cls(world, car.params, car.truth)

    def check(self, t: float) -> dict[str, Any] | None:
        """The collision or exit at this tick, or None (``t`` is the run's time, for the report)."""
        tr = self.truth()
        hit = self.contact.check(tr.x, tr.y, tr.yaw, tr.t)
        if hit is None:
            return None
        if hit.kind == "left_world":
            self.event = {"kind": "left_world", "what": f"the car left the world at ({tr.x:.2f}, {tr.y:.2f}) m, "
                          f"t = {t:.2f} s", "t": t, "x": tr.x, "y": tr.y, "yaw": tr.yaw}
            return self.event
        where = hit.obstacle
        at = f" near ({where[0]:.2f}, {where[1]:.2f})" if where else ""
        self.event = {"kind": "collision", "what": f"collision at ({tr.x:.2f}, {tr.y:.2f}) m{at}, t = {t:.2f} s",
                      "t": t, "x": tr.x, "y": tr.y, "yaw": tr.yaw, "obstacle": list(where) if where else None}
        return self.event

    def wrap(self, model: Any) -> _Watched:
        return _Watched(model, self)


class _Watched:
    """A lab model whose run ends (STOP) at the first collision or exit."""

    def __init__(self, model: Any, watch: WorldWatch):
        self.model, self.watch = model, watch

    def start(self, car: Any, dt: float) -> None:
        start = getattr(self.model, "start", None)
        if callable(start):
            start(car, dt)

    def step(self, t: float, readout: Any, dt: float) -> Any:
        if self.watch.event is not None or self.watch.check(t) is not None:
            return STOP
        return self.model.step(t, readout, dt)
