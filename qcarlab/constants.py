"""The QCar's facts, in one place, in SI units.

Every number the simulator, the controllers and the driver use comes from :class:`QCarParams`.
The defaults are the Quanser QCar 1's (lab sheet section 2 and DESIGN.md section 3);
:data:`QCAR2_PARAMS` are a QCar 2's. Where Quanser's own documents give a figure, it is used and
its source is written beside it ("[hw1]" = the QCar 1 hardware/user manual, pages as quoted in
qcarlab issue 15; "[qcar.py]" = Quanser_Academic_Resources pal/products/qcar.py). A YAML file
can override any field::

    # my_car.yaml
    battery_soc0: 0.5        # start half charged
    rolling_resistance: 0.03

and ``load_params("my_car.yaml")`` returns the merged parameters (unknown keys and non-numeric
values are refused with the file and field named).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

from qcarlab.errors import InputError


@dataclass(frozen=True, slots=True)
class QCarParams:
    """Physical parameters of the car and its sensors (SI units)."""

    # geometry
    wheelbase: float = 0.256  # L, m; axles at +-L/2 from the centre
    track: float = 0.170  # m
    length: float = 0.425  # m
    width: float = 0.192  # m
    height: float = 0.182  # m (QCar 2: 0.2 m, [hw2])
    mass: float = 2.7  # kg
    wheel_radius: float = 0.033  # m
    # steering servo
    max_steering: float = 0.5  # rad at the wheels: the servo takes +-0.5 rad ([hw1] p.11; was 0.5236)
    steering_tau: float = 0.16  # s, first-order servo lag
    # drive train
    encoder_cpr: float = 2880.0  # counts per motor revolution (720 lines, 4x quadrature)
    gear_ratio: float = (13 * 19) / (70 * 37)  # motor rev -> wheel rev, 0.09537
    motor_resistance: float = 0.47  # ohm (QCar 2: 0.4, [hw2])
    motor_kt: float = 0.0027  # N m / A (QCar 2: 0.0047, [hw2])
    motor_kb: float = 0.0027  # V s / rad (QCar 2: 0.0047, [hw2])
    drivetrain_inertia: float = 4.0e-6  # kg m^2 at the motor shaft (rotor, gears, wheels)
    motor_friction: float = 2.0e-4  # N m Coulomb friction at the motor shaft (on the stand too)
    motor_damping: float = 2.0e-7  # N m s / rad viscous friction at the motor shaft
    rolling_resistance: float = 0.016  # C_rr on the floor (force = C_rr m g)
    # throttle
    throttle_limit: float = 0.3  # PWM duty-cycle fraction
    # battery: 3S LiPo, 3300 mAh
    battery_cells: int = 3
    battery_capacity_ah: float = 3.3
    battery_resistance: float = 0.06  # ohm, internal
    battery_soc0: float = 0.9  # state of charge at power-on, 0..1
    idle_current: float = 1.5  # A drawn by the computer and sensors (2 h 11 min stationary)
    battery_low_v: float = 10.5
    battery_shutdown_v: float = 10.0
    # IMU noise (standard deviations) and gyro bias
    gyro_noise: float = 0.002  # rad/s
    gyro_bias_sd: float = 0.001  # rad/s, drawn once per run
    accel_noise: float = 0.02  # m/s^2
    current_noise: float = 0.01  # A
    voltage_noise: float = 0.005  # V
    # sensor mounts (body frame: x forward, y left, z up, from the car's centre on the floor)
    lidar_x: float = -0.0108  # m, RPLidar A2 on the roof, just behind the centre ([hw1]; was 0)
    lidar_z: float = 0.186  # m ([hw1]; was 0.20)
    lidar_beams: int = 800  # samples per turn at 10 Hz
    lidar_rate: float = 10.0  # Hz
    lidar_min_range: float = 0.15  # m
    lidar_max_range: float = 18.0  # m ([hw1]; Quanser's QCar lidar code keeps maxDistance = 18.0; the lab
    # sheet's spec table says 12 m; was 12)
    lidar_noise: float = 0.005  # m, range noise standard deviation
    rgbd_x: float = 0.0822  # m, Intel D435 at the front ([hw1]; was 0.19)
    rgbd_z: float = 0.1582  # m ([hw1]; was 0.14)
    rgbd_pitch: float = 0.0  # rad, + = looking down
    rgbd_width: int = 640
    rgbd_height: int = 480
    # the D435's colour field of view is 69.4 x 42.5 deg at 16:9; at 640x480 (4:3) with square
    # pixels the simulator takes the focal length from the vertical FOV (f = 616 px, ~55 deg across)
    rgbd_hfov: float = math.radians(69.4)  # at 16:9; informational
    rgbd_vfov: float = math.radians(42.5)  # sets the focal length
    rgbd_rate: float = 30.0  # Hz
    rgbd_max_depth: float = 10.0  # m; beyond reads 0 (no data)
    # the four 160 deg CSI cameras: front and rear on the car's axis, left and right at +-csi_side_y
    csi_front_x: float = 0.193  # m ([hw1]; was 0.10)
    csi_rear_x: float = -0.165  # m ([hw1]; was -0.10)
    csi_side_y: float = 0.10  # m: NOT from Quanser (the material read gives no side offset)
    csi_z: float = 0.0953  # m ([hw1]; was 0.16)
    csi_width: int = 820
    csi_height: int = 410
    csi_fov: float = math.radians(160.0)
    csi_rate: float = 30.0  # Hz
    # simulation
    physics_dt: float = 0.002  # s, the simulator's internal step (QUARC's 500 Hz)
    gravity: float = 9.81

    @property
    def speed_per_count(self) -> float:
        """Metres of travel per encoder count: 1/cpr * gear * 2 pi r (6.866e-6 m)."""
        return self.gear_ratio * 2.0 * math.pi * self.wheel_radius / self.encoder_cpr

    @property
    def min_turning_radius(self) -> float:
        """Tightest turn of the rear axle, L / tan(delta_max) (0.469 m)."""
        return self.wheelbase / math.tan(self.max_steering)


DEFAULT_PARAMS = QCarParams()
QCAR1_PARAMS = DEFAULT_PARAMS
# a QCar 2 ([hw2] = the QCar 2 user manual's specification, as quoted in qcarlab issue 15): the
# geometry, gearing and sensors we could not find differing are the QCar 1's
QCAR2_PARAMS = replace(DEFAULT_PARAMS, height=0.2, motor_resistance=0.4, motor_kt=0.0047, motor_kb=0.0047)

_INT_FIELDS = {f.name for f in fields(QCarParams) if f.type in ("int", int)}
_SIGNED_FIELDS = {"rgbd_pitch", "battery_soc0", "lidar_x", "csi_rear_x"}
_FIELD_NAMES = [f.name for f in fields(QCarParams)]


def csi_mounts(p: QCarParams) -> dict[str, tuple[float, float, float, float]]:
    """Where the four CSI cameras sit on the car: name -> (x, y, z, yaw) in the body frame (m, rad)."""
    return {
        "right": (0.0, -p.csi_side_y, p.csi_z, -math.pi / 2.0),
        "rear": (p.csi_rear_x, 0.0, p.csi_z, math.pi),
        "left": (0.0, p.csi_side_y, p.csi_z, math.pi / 2.0),
        "front": (p.csi_front_x, 0.0, p.csi_z, 0.0),
    }


def params_from_mapping(data: Any, source: str = "parameters") -> QCarParams:
    """Merge a mapping of field -> number over the defaults, refusing unknown or bad fields."""
    if data is None:
        return DEFAULT_PARAMS
    if not isinstance(data, dict):
        raise InputError(f"{source}: expected a mapping of parameter: value, got {type(data).__name__}")
    changes: dict[str, float | int] = {}
    for key, value in data.items():
        if key not in _FIELD_NAMES:
            raise InputError(f"{source}: unknown parameter '{key}' (known: {', '.join(_FIELD_NAMES)})")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InputError(f"{source}: parameter '{key}' must be a finite number, got {value!r}")
        if value <= 0 and key not in _SIGNED_FIELDS:
            raise InputError(f"{source}: parameter '{key}' must be positive, got {value!r}")
        changes[key] = int(value) if key in _INT_FIELDS else float(value)
    if "battery_soc0" in changes and not 0.0 <= changes["battery_soc0"] <= 1.0:
        raise InputError(f"{source}: parameter 'battery_soc0' must be in [0, 1]")
    return replace(DEFAULT_PARAMS, **changes)


def load_params(path: str | Path | None) -> QCarParams:
    """Read a YAML parameter file (see the module docstring); ``None`` gives the defaults."""
    if path is None:
        return DEFAULT_PARAMS
    from qcarlab.yamlio import load_yaml

    data = load_yaml(path, "parameter file")
    if isinstance(data, dict):  # a lab's tunables live beside the car's, in a ``lab:`` section
        data = {k: v for k, v in data.items() if k != "lab"}
    return params_from_mapping(data, str(Path(path)))
