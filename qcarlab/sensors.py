"""What the car's exteroceptive sensors return: the same types from the simulator and the real car.

Conventions (DESIGN.md section 2):

- :class:`LidarScan`: ``angles`` in the body frame (REP-103: x forward, y left), radians
  counter-clockwise from forward, ``ranges`` in metres, ``0`` where the beam had no return
  (nothing within range, or closer than the device's minimum range).
- :class:`RGBDFrame`: ``color`` BGR ``uint8`` (H, W, 3); ``depth`` ``float32`` metres (H, W),
  aligned pixel for pixel to ``color``, ``0`` = no data. Depth is the z-depth along the camera's
  optical axis (as the Intel D435 reports it), not the distance along the pixel's ray.
- :class:`CSIFrames`: the four wide-angle views, BGR ``uint8``, in the lab sheet's order
  right, rear, left, front.
- :class:`CameraIntrinsics`: the pinhole model, pixels with u to the right and v down::

      u = cx + fx * X / Z        v = cy + fy * Y / Z

  with (X, Y, Z) in the optical frame (X right, Y down, Z forward along the optical axis).

Every readout carries ``t``, the time (s since the car was opened) at which it was taken.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from qcarlab.beams import cos_sin


@dataclass(frozen=True, slots=True)
class LidarScan:
    """One LIDAR turn: ``angles`` (rad, body frame, CCW from forward) and ``ranges`` (m, 0 = none)."""

    t: float
    angles: np.ndarray  # (n,) float64
    ranges: np.ndarray  # (n,) float64

    @property
    def valid(self) -> np.ndarray:
        """Boolean mask of the beams that have a return."""
        return self.ranges > 0.0

    def points(self) -> np.ndarray:
        """The returns as (m, 2) body-frame points (x forward, y left) of the LIDAR, no-returns dropped."""
        ok = self.valid
        cos_a, sin_a = cos_sin(self.angles)
        r = self.ranges[ok]
        return np.column_stack((r * cos_a[ok], r * sin_a[ok]))


@dataclass(frozen=True, slots=True)
class RGBDFrame:
    """An aligned colour/depth pair: ``color`` BGR uint8 (H, W, 3), ``depth`` float32 m (H, W), 0 = none."""

    t: float
    color: np.ndarray
    depth: np.ndarray


@dataclass(frozen=True, slots=True)
class CSIFrames:
    """The four CSI wide-angle views, BGR uint8, in the sheet's order right, rear, left, front."""

    t: float
    right: np.ndarray
    rear: np.ndarray
    left: np.ndarray
    front: np.ndarray

    def as_list(self) -> list[np.ndarray]:
        """The views as [right, rear, left, front] (the order of the sheet's 360 panorama)."""
        return [self.right, self.rear, self.left, self.front]


@dataclass(frozen=True, slots=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels (u right, v down); ``width`` x ``height`` image."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_fov(cls, width: int, height: int, hfov: float, vfov: float | None = None) -> CameraIntrinsics:
        """Intrinsics of an ideal pinhole with the principal point at the image centre.

        ``hfov``/``vfov`` are the full fields of view in radians; without ``vfov`` the pixels are
        square. The centre column (u = cx = (width - 1) / 2) looks along the optical axis.
        """
        fx = (width / 2.0) / math.tan(hfov / 2.0)
        fy = fx if vfov is None else (height / 2.0) / math.tan(vfov / 2.0)
        return cls(fx=fx, fy=fy, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, width=int(width), height=int(height))

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project (n, 3) optical-frame points (X right, Y down, Z forward) to (n, 2) pixels (u, v)."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        return np.column_stack((self.cx + self.fx * p[:, 0] / p[:, 2], self.cy + self.fy * p[:, 1] / p[:, 2]))
