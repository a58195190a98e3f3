"""What every lab model shares: its blocks looked up by their sheet names, the student's in place.

A lab model is the sheet's block diagram in code. Its class lists the blocks (``BLOCKS``, in the
sheet's order, each a :class:`~qcarlab.blocks.BlockSpec`), builds the reference blocks bound to the
run's parameters (``reference_blocks``), and its ``step(t, readout, dt)`` calls them as
``self.<sheet_name>(...)`` and returns a :class:`~qcarlab.experiments.loop.Step` (the command and
the values to log). ``blocks={"stop_sign": my_fn}`` replaces any of them::

    lab = StopSignLab(cfg, params, blocks={"stop_sign": my_stop_sign})
    log = run_loop(car, lab, duration=20.0)
    lab.block_report()     # which blocks were the student's, and how long they took
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from qcarlab.blocks import BlockSpec, StudentBlock, as_block
from qcarlab.errors import InputError


#: Blocks several labs share (each lab may restate the sheet section with dataclasses.replace).
BASIC_SPEED_ESTIMATION = BlockSpec(
    "basic_speed_estimation", "basic_speed_estimation(counts_per_s) -> speed", "counts/s -> m/s",
    "3.3; lane example block 9", "Car speed from the motor encoder's rate.", "speed")
SPEED_CONTROLLER = BlockSpec(
    "speed_controller", "speed_controller(v_ref, v_measured, dt) -> throttle", "m/s, m/s, s -> duty fraction",
    "4.2.3, Figure 43; lane example block 7",
    "Feed-forward PI from the desired speed to the throttle (a class: it integrates).", "throttle", stateful=True)
INDICATOR_AND_LAMPS = BlockSpec(
    "indicator_and_lamps", "indicator_and_lamps(steering, v_ref) -> lamp names",
    "rad, m/s -> names (brake, reverse, left-indicators, right-indicators)", "lane example block 8",
    "Brake lamp at v_ref = 0, reverse lamps backing up, indicators in turns.")
TURN_SPEED_HANDLING = BlockSpec(
    "turn_speed_handling", "turn_speed_handling(desired_speed, steering) -> speed", "m/s, rad -> m/s",
    "lane example block 6", "Slow down in turns: v cos(delta)^8, within 0.5..1 of v.", "speed")


class LabModel:
    """Base class: installs the blocks; subclasses define ``BLOCKS``, ``reference_blocks`` and ``step``."""

    lab: ClassVar[str] = ""
    BLOCKS: ClassVar[tuple[BlockSpec, ...]] = ()

    def __init__(self, blocks: Mapping[str, Any] | None = None) -> None:
        specs = self.specs()
        self.student: dict[str, StudentBlock] = {}
        reference = self.reference_blocks()
        missing = set(specs) - set(reference)
        if missing:  # a programming error in the package, not the student's
            raise RuntimeError(f"{type(self).__name__}: no reference for {sorted(missing)}")
        for name, fn in reference.items():
            setattr(self, name, fn)
        for name, value in (blocks or {}).items():
            if name not in specs:
                raise InputError(f"{self.lab} has no block {name!r} (its blocks: {', '.join(specs)})")
            block = as_block(specs[name], value)
            self.student[name] = block
            setattr(self, name, block)

    @classmethod
    def specs(cls) -> dict[str, BlockSpec]:
        return {s.name: s for s in cls.BLOCKS}

    def reference_blocks(self) -> dict[str, Any]:
        raise NotImplementedError

    def start(self, car: Any, dt: float) -> None:
        """Called by the loop before the first tick: reset stateful blocks, set the tick budget."""
        for spec in self.BLOCKS:
            block = getattr(self, spec.name)
            if isinstance(block, StudentBlock):
                block.start()
                block.budget_s = None if car.stepped else dt
            elif spec.stateful and callable(getattr(block, "reset", None)):
                block.reset()

    def block_report(self) -> dict[str, dict[str, Any]]:
        """The student's blocks of this run: source file, calls, worst and mean time, over budget."""
        return {name: block.timing() for name, block in self.student.items()}


def finish(metrics: dict, log: Any, lab: LabModel, watch: Any, goal: bool, goal_text: str) -> None:
    """The parts of ``metrics`` every lab run has: the goal, why it was missed, the student's
    blocks and their timing, the loop's overruns, and whether Ctrl-C cut the run short."""
    reasons = []
    if watch is not None and watch.event is not None:
        reasons.append(watch.event["what"])
        metrics[watch.event["kind"]] = watch.event
    if log.interrupted:
        reasons.append("interrupted (Ctrl-C)")
    elif not goal and not reasons:
        reasons.append(goal_text)
    metrics["goal_reached"] = not reasons
    metrics["failure"] = "; ".join(reasons) if reasons else None
    metrics["interrupted"] = log.interrupted
    metrics["student_blocks"] = lab.block_report()
    metrics["loop"] = {"ticks": log.ticks, "overruns": log.overruns, "worst_tick_s": log.worst_tick_s}
