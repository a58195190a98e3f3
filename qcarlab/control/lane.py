"""Lane-following control blocks (lab sheet 5.3, the lane example's blue part): steering from the
fitted lane line, and the adaptive cruise control in front of an obstacle.

- :func:`steering_calculation`: where the fitted line is vs where it should be, as pure pursuit
  on the floor (equation below).
- :func:`automated_driving`: the ``automatedDriving`` block: full desired speed when the road is
  clear, slower as an obstacle nears, 0 at the stop distance.
- ``turn_speed_handling``, ``speed_controller`` (:class:`~qcarlab.control.speed.SpeedController`)
  and ``basic_speed_estimation`` live in :mod:`qcarlab.control.speed`.

No I/O, no car: numbers in, numbers out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from qcarlab.constants import DEFAULT_PARAMS, QCarParams

__all__ = ["CRAWL_SPEED", "LOOKAHEAD", "LaneCamera", "automated_driving", "line_offset", "steering_calculation",
           "user_inputs"]

LOOKAHEAD = 0.5  # m ahead of the camera where the fitted line is read (image row ~412)
LANE_HALF_WIDTH = 0.2  # m: lane centre to its lines (0.4 m lanes)
CRAWL_SPEED = 0.05  # m/s: the slowest automated_driving asks for before the stop distance


def rgbd_focal_px(p: QCarParams = DEFAULT_PARAMS) -> float:
    """The RGBD colour camera's focal length in pixels, f = (H / 2) / tan(vfov / 2): about 617 px
    at 480 rows and 42.5 deg, what the simulator renders with."""
    return (p.rgbd_height / 2.0) / math.tan(p.rgbd_vfov / 2.0)


@dataclass(frozen=True)
class LaneCamera:
    """What the steering needs of the RGBD camera: focal length ``f`` and principal point
    (``cx``, ``cy``) in pixels, height ``h`` above the floor (m, level camera), distance
    ``to_rear_axle`` from the rear axle forward to the camera (m) and the wheelbase (m)."""

    f: float = rgbd_focal_px()
    cx: float = DEFAULT_PARAMS.rgbd_width / 2.0
    cy: float = DEFAULT_PARAMS.rgbd_height / 2.0
    h: float = DEFAULT_PARAMS.rgbd_z
    to_rear_axle: float = DEFAULT_PARAMS.rgbd_x + DEFAULT_PARAMS.wheelbase / 2.0
    wheelbase: float = DEFAULT_PARAMS.wheelbase
    max_steering: float = DEFAULT_PARAMS.max_steering

    @classmethod
    def from_params(cls, p: QCarParams) -> LaneCamera:
        return cls(rgbd_focal_px(p), p.rgbd_width / 2.0, p.rgbd_height / 2.0, p.rgbd_z, p.rgbd_x + p.wheelbase / 2.0,
                   p.wheelbase, p.max_steering)


def line_offset(lane: str, source: str, half_width: float = LANE_HALF_WIDTH) -> float:
    """Where the tracked line lies from the lane centre, m, + = left. Right lane: the yellow centre
    line is ``half_width`` to the left (+), the white edge line to the right (-); left lane: mirrored."""
    sign = 1.0 if lane == "right" else -1.0
    return sign * half_width if source == "yellow" else -sign * half_width


def steering_calculation(fit, offset: float, cam: LaneCamera = LaneCamera(), lookahead: float = LOOKAHEAD) -> float:
    """Steering angle (rad, + = left) that brings the car onto the lane centre.

    ``fit`` has ``slope`` and ``intercept`` of the line ``u = slope v + intercept`` in the image
    (:func:`qcarlab.perception.lane.linear_poly_fit`); ``offset`` is where that line should be from
    the lane centre (m, + = left, :func:`line_offset`). With a level camera at height ``h`` a floor
    point ``X`` m ahead and ``Y`` m to the left is seen at ``v = cy + f h / X``, ``u = cx - f Y / X``.

        v_L   = cy + f h / L_a                    # the row of the look-ahead distance L_a (0.5 m),
                                                  # clamped to the rows the line was seen on (the
                                                  # curve's line is only seen near: L_a shrinks)
        u_L   = slope v_L + intercept             # where the line is on that row
        u_nom = cx - f offset / L_a               # where it should be (car on the lane centre)
        y     = -(u_L - u_nom) L_a / f            # lateral error of the lane centre there, m, + = left
        x     = L_a + d_cam                       # ahead of the rear axle (d_cam = camera to rear axle)
        delta = clip(atan(2 L y / (x^2 + y^2)), +-30 deg)   # pure pursuit onto that point

    The line right of where it should be (``u_L > u_nom``) means the car has drifted left: steer
    right (negative). None for ``fit`` (no line): 0.
    """
    if fit is None:
        return 0.0
    la = float(lookahead)
    v_l = cam.cy + cam.f * cam.h / la
    rows = getattr(fit, "rows", None)
    if rows is not None and rows[0] > cam.cy:  # read the line where it was seen, not beyond
        v_l = min(max(v_l, float(rows[0])), float(rows[1]))
        la = cam.f * cam.h / (v_l - cam.cy)
    u_l = fit.slope * v_l + fit.intercept
    u_nom = cam.cx - cam.f * offset / la
    y = -(u_l - u_nom) * la / cam.f
    x = la + cam.to_rear_axle
    delta = math.atan2(2.0 * cam.wheelbase * y, x * x + y * y)
    return max(-cam.max_steering, min(cam.max_steering, delta))


def automated_driving(desired_speed: float, obstacle_distance: float, stop_distance: float = 0.6,
                      nominal_distance: float | None = None, crawl: float = CRAWL_SPEED) -> float:
    """The ``automatedDriving`` block: speed command (m/s) from the obstacle distance (m).

        d <= 0 (nothing seen)          -> desired_speed
        d <= stop_distance             -> 0
        stop < d < nominal             -> max(desired * (d - stop) / (nominal - stop), min(crawl, desired))
        d >= nominal                   -> desired_speed

    ``nominal_distance`` (the sheet's nominal tracking distance) defaults to 2 x stop_distance.
    The ``crawl`` floor (5 cm/s) makes the car reach the stop distance: the ramp alone slows it
    in proportion to the gap left, so the gap only halves every few seconds and the command never
    gets to 0 (a car 1 cm from its stop distance was still asked for 2 mm/s after 10 s).
    """
    d = float(obstacle_distance)
    if not math.isfinite(d) or d <= 0.0:
        return desired_speed
    nominal = 2.0 * stop_distance if nominal_distance is None else float(nominal_distance)
    if d <= stop_distance:
        return 0.0
    if d >= nominal or nominal <= stop_distance:
        return desired_speed
    ramp = desired_speed * (d - stop_distance) / (nominal - stop_distance)
    return max(ramp, min(float(crawl), desired_speed))


def user_inputs(speed_selector: float, stop_offset: float, distance_to_lane: float, max_speed: float = 0.3,
                min_stop_distance: float = 0.6) -> tuple[float, float, float]:
    """The lane example's ``userInputs`` sliders (block 10): ``(desired_speed m/s, stop_distance m,
    lane_gain)`` from three percentages and the model's section-1 constants::

        desired_speed = max_speed * speed_selector / 100               (Speed Selector, 0..100 %)
        stop_distance = min_stop_distance * (1 + stop_offset / 100)    (Stopping Distance Offset:
                                                                        0 % -> 0.6 m, 100 % -> 1.2 m)
        lane_gain     = distance_to_lane / 100                         (Distance To Lane: 0 % follows
                                                                        the line itself, 100 % the
                                                                        lane's centre)

    ``lane_gain`` scales :func:`line_offset`, where the tracked line should be seen from the car.
    """
    for name, value in (("speed_selector", speed_selector), ("stop_offset", stop_offset),
                        ("distance_to_lane", distance_to_lane)):
        if not (math.isfinite(value) and 0.0 <= value <= 100.0):
            raise ValueError(f"{name} must be a percentage in 0..100, got {value}")
    return (max_speed * speed_selector / 100.0, min_stop_distance * (1.0 + stop_offset / 100.0),
            distance_to_lane / 100.0)
