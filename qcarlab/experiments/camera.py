"""Explore the cameras (lab sheets 3.6 and 3.7): grab RGBD and CSI frames and describe them."""

from __future__ import annotations

import numpy as np

from qcarlab.car.base import Car
from qcarlab.experiments.result import Result


def depth_stats(depth: np.ndarray) -> dict[str, float | None]:
    """Statistics of the valid (non-zero) depth pixels, metres, and the valid fraction."""
    valid = depth[depth > 0]
    if valid.size == 0:
        return {"valid_fraction": 0.0, "min_m": None, "median_m": None, "max_m": None}
    return {"valid_fraction": float(valid.size / depth.size), "min_m": float(valid.min()),
            "median_m": float(np.median(valid)), "max_m": float(valid.max())}


def grab(car: Car, rgbd: bool = True, csi: bool = False, settle: float = 0.0) -> Result:
    """Read one RGBD pair and/or one set of the four CSI views (after ``settle`` seconds)."""
    if settle > 0:
        car.advance(settle)
    metrics: dict = {"experiment": "camera"}
    data: dict = {}
    p = car.params
    if rgbd:
        frame = car.read_rgbd()
        h, w = frame.color.shape[:2]
        metrics["rgbd"] = {"t": frame.t, "color_size": [w, h], "depth_size": list(frame.depth.shape[::-1]),
                           "rate_hz": p.rgbd_rate, "depth": depth_stats(frame.depth),
                           "center_depth_m": float(frame.depth[h // 2, w // 2])}
        data["rgbd"] = frame
    if csi:
        frames = car.read_csi()
        metrics["csi"] = {"t": frames.t, "rate_hz": p.csi_rate,
                          "views": {name: list(img.shape[1::-1]) for name, img in
                                    zip(("right", "rear", "left", "front"), frames.as_list())}}
        data["csi"] = frames
    return Result("camera", metrics, data=data)
