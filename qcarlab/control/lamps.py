"""The ``indicatorAndLamps`` block of the lane example (block 10): which lamps the car shows.

Pure: numbers in, lamp names out (``qcarlab.car.lamps.parse_lamps`` turns them into the 12 LED
values; control/ does not import the car).
"""

from __future__ import annotations

__all__ = ["INDICATOR_STEERING", "indicator_and_lamps"]

INDICATOR_STEERING = 0.3  # rad: the indicators blink beyond this much steering


def indicator_and_lamps(steering: float, v_ref: float, threshold: float = INDICATOR_STEERING) -> tuple[str, ...]:
    """Lamps for a steering command (rad, + = left) and a speed reference (m/s)::

        v_ref = 0                -> brake
        v_ref < 0                -> reverse (the red rear lamps)
        steering >  threshold    -> left indicators
        steering < -threshold    -> right indicators

    Returns lamp names (``brake``, ``reverse``, ``left-indicators``, ``right-indicators``).
    """
    out = []
    if v_ref == 0.0:
        out.append("brake")
    elif v_ref < 0.0:
        out.append("reverse")
    if steering > threshold:
        out.append("left-indicators")
    elif steering < -threshold:
        out.append("right-indicators")
    return tuple(out)
