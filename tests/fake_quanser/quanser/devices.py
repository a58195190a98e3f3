"""Strict fake of ``quanser.devices`` (RPLIDAR, RangingMeasurements, enums, DeviceError).

``RPLIDAR.read`` follows the real wrapper: it returns the number of measurements (0 when there
is nothing new) and raises DeviceError for errors; older wrappers raise -34 (would block) instead
of returning 0, so the script can do both: ``scan``, ``none`` (0) and ``block`` (DeviceError -34).
"""

import numpy as np

from quanser import _fake
from quanser._fake import STATE
from quanser.common import GenericError


class DeviceError(GenericError):
    pass


class RangingDistance(object):
    SHORT = 0
    MEDIUM = 1
    LONG = 2


class RangingMeasurementMode(object):
    NORMAL = 0
    INTERPOLATED = 1


class RangingMeasurements(object):
    def __init__(self, num_measurements):
        n = int(num_measurements)
        self.distance = np.zeros(n, dtype=np.float64)
        self.distance_sigma = np.zeros(n, dtype=np.float64)
        self.heading = np.zeros(n, dtype=np.float64)
        self.quality = np.zeros(n, dtype=np.uint8)
        self.length = 0


class RPLIDAR(object):
    def __init__(self):
        self._open = False

    def open(self, uri, ranging_distance):
        if "lidar" not in STATE.sensors:
            raise DeviceError(_fake.SERIAL_PORT, "no LIDAR answers")
        if uri != STATE.board["lidar_url"]:
            STATE.event("lidar_open_refused", uri=uri)
            raise DeviceError(_fake.SERIAL_PORT, "nothing on {!r}".format(uri))
        if ranging_distance not in (RangingDistance.SHORT, RangingDistance.MEDIUM, RangingDistance.LONG):
            raise DeviceError(_fake.INVALID_ARGUMENT, "ranging distance")
        self._open = True
        STATE.event("lidar_open", uri=uri)

    def read(self, mode, max_interpolated_distance, max_interpolated_angle, measurements):
        if not self._open:
            raise DeviceError(_fake.NOT_OPEN, "lidar")
        if mode not in (RangingMeasurementMode.NORMAL, RangingMeasurementMode.INTERPOLATED):
            raise DeviceError(_fake.INVALID_ARGUMENT, "mode")
        if not isinstance(measurements, RangingMeasurements):
            raise DeviceError(_fake.INVALID_ARGUMENT, "measurements must be RangingMeasurements")
        script = STATE.lidar_script or ["scan"]
        step = script[STATE.lidar_reads % len(script)]
        STATE.lidar_reads += 1
        if step == "block":
            raise DeviceError(_fake.WOULD_BLOCK)
        if step == "none":
            return 0
        headings, distances, qualities = _fake.lidar_scan()
        n = len(headings)
        if measurements.heading.size < n:
            raise DeviceError(_fake.BUFFER_TOO_SMALL)
        measurements.heading[:n] = headings
        measurements.distance[:n] = distances
        measurements.quality[:n] = qualities
        measurements.length = n
        return n

    def close(self):
        self._open = False
        STATE.event("lidar_close")
