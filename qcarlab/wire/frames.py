"""Sensor frame types used on both ends of the wire.

``qcarlab.sensors`` defines the frozen dataclasses ``LidarScan(t, angles, ranges)``,
``RGBDFrame(t, color, depth)`` and ``CSIFrames(t, right, rear, left, front)``; until it exists
(or if it fails to import) look-alike dataclasses with the same fields stand in, so the network
code and the on-car driver never depend on the simulator's sensors being built.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from qcarlab.wire.protocol import FRAME_FIELDS, MsgType


@dataclass(frozen=True)
class _LidarScan:
    t: float
    angles: np.ndarray
    ranges: np.ndarray


@dataclass(frozen=True)
class _RGBDFrame:
    t: float
    color: np.ndarray
    depth: np.ndarray


@dataclass(frozen=True)
class _CSIFrames:
    t: float
    right: np.ndarray
    rear: np.ndarray
    left: np.ndarray
    front: np.ndarray


_FALLBACK = {MsgType.LIDAR: _LidarScan, MsgType.RGBD: _RGBDFrame, MsgType.CSI: _CSIFrames}
_NAMES = {MsgType.LIDAR: "LidarScan", MsgType.RGBD: "RGBDFrame", MsgType.CSI: "CSIFrames"}


def frame_class(kind: int) -> type:
    """The dataclass for a sensor frame message type (qcarlab.sensors' when available)."""
    try:
        import qcarlab.sensors as sensors  # noqa: PLC0415  (written alongside; optional here)

        cls = getattr(sensors, _NAMES[kind], None)
        if cls is not None:
            return cls
    except Exception:  # not built yet, or mid-edit: the stand-in has the same fields
        pass
    return _FALLBACK[kind]


def make_frame(kind: int, t: float, arrays: list[np.ndarray]) -> Any:
    """Build the sensor frame object for ``kind`` from its time and arrays (in FRAME_FIELDS order)."""
    fields = FRAME_FIELDS[kind]
    values = dict(zip(fields, arrays))
    cls = frame_class(kind)
    try:
        return cls(t=t, **values)
    except Exception:  # a stricter qcarlab.sensors class refusing, e.g., a read-only array
        return _FALLBACK[kind](t=t, **values)


def frame_arrays(kind: int, frame: Any, default_t: float) -> tuple[float, list[np.ndarray]]:
    """The time and arrays of a sensor frame object, for sending."""
    t = getattr(frame, "t", None)
    t = default_t if t is None else float(t)
    return t, [np.asarray(getattr(frame, name)) for name in FRAME_FIELDS[kind]]
