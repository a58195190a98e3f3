"""What a scan's beam angles alone give, made once: a LIDAR's angles are one read-only array, the
same every scan, so their cosines and sines (and the like) need not be recomputed each scan.
Pure: numpy in, numbers out; the same numbers as computing them anew (element by element)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["cos_sin", "derived"]

_KEPT: dict[tuple[int, str], tuple[np.ndarray, Any]] = {}  # (id(angles), name) -> (angles, value)


def derived(angles: np.ndarray, name: str, make: Callable[[np.ndarray], Any]) -> Any:
    """``make(angles)``, kept under ``name`` for an ``angles`` array that owns its numbers and is
    read-only (they cannot change under it: a LIDAR's), made anew for any other array."""
    if angles.base is not None or angles.flags.writeable:
        return make(angles)
    key = (id(angles), name)
    hit = _KEPT.get(key)
    if hit is not None and hit[0] is angles:  # (the array itself is kept: its id is not reused)
        return hit[1]
    value = make(angles)
    if len(_KEPT) >= 32:
        _KEPT.clear()
    _KEPT[key] = (angles, value)
    return value


def cos_sin(angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(cos(angles), sin(angles))`` of a float64 array (see :func:`derived`)."""
    return derived(angles, "cos_sin", _cos_sin)


def _cos_sin(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.cos(a), np.sin(a)
