"""Strict fake of ``quanser.multimedia`` (Video3D, VideoCapture, enums, MediaError)."""

import numpy as np

from quanser import _fake
from quanser._fake import STATE
from quanser.common import GenericError


class MediaError(GenericError):
    pass


class Video3DStreamType(object):
    DEPTH = 0
    COLOR = 1
    INFRARED = 2


class ImageFormat(object):
    COL_MAJOR_PLANAR_RGB = 0
    COL_MAJOR_GREYSCALE = 1
    ROW_MAJOR_INTERLEAVED_RGB = 2
    ROW_MAJOR_GREYSCALE = 3
    ROW_MAJOR_INTERLEAVED_BGR = 4


class ImageDataType(object):
    UINT8 = 0
    UINT16 = 1
    UINT32 = 2
    SINGLE = 3
    DOUBLE = 4


D435_COLOR = {(640, 480), (1280, 720), (1920, 1080), (960, 540), (424, 240)}
D435_DEPTH = {(640, 480), (1280, 720), (848, 480), (480, 270), (424, 240)}
CSI_MODES = {(820, 410), (1640, 820), (3280, 2464), (1280, 720)}


class _Frame(object):
    def __init__(self, stream):
        self.stream = stream
        self.released = False

    def get_data(self, buf):
        s = self.stream
        shape = (s.h, s.w, 3) if s.kind == Video3DStreamType.COLOR else (s.h, s.w, 1)
        if not isinstance(buf, np.ndarray) or buf.dtype != np.uint8 or buf.size != s.w * s.h * shape[2]:
            raise MediaError(_fake.INVALID_BUFFER, "get_data buffer")
        buf[...] = 7 if s.kind == Video3DStreamType.COLOR else 3

    def get_meters(self, buf):
        s = self.stream
        if s.kind != Video3DStreamType.DEPTH:
            raise MediaError(_fake.INVALID_ARGUMENT, "get_meters on a colour stream")
        if not isinstance(buf, np.ndarray) or buf.dtype != np.float32 or buf.size != s.w * s.h:
            raise MediaError(_fake.INVALID_BUFFER, "get_meters buffer")
        buf[...] = 1.5

    def get_timestamp(self):
        return 0.0

    def release(self):
        self.released = True


class _Stream(object):
    def __init__(self, video, kind, w, h):
        self.video, self.kind, self.w, self.h = video, kind, w, h
        self.reads = 0

    def get_frame(self):
        if not self.video.streaming:
            raise MediaError(_fake.NOT_OPEN, "not streaming")
        self.reads += 1
        return None if self.reads == 1 else _Frame(self)  # the first poll has nothing yet

    def close(self):
        pass


class Video3D(object):
    def __init__(self, device_id):
        if "rgbd" not in STATE.sensors:
            raise MediaError(_fake.NOT_OPEN, "no RealSense found")
        if device_id != "0":
            raise MediaError(_fake.INVALID_ARGUMENT, "device {!r}".format(device_id))
        self.streaming = False
        self.streams = []

    def stream_open(self, kind, index, fps, w, h, fmt, dtype):
        if self.streaming:
            raise MediaError(_fake.INVALID_ARGUMENT, "open streams before start_streaming")
        if index != 0 or fps not in (6.0, 15.0, 30.0, 60.0, 90.0):
            raise MediaError(_fake.INVALID_ARGUMENT, "stream index/fps")
        if kind == Video3DStreamType.COLOR:
            if (w, h) not in D435_COLOR or fmt != ImageFormat.ROW_MAJOR_INTERLEAVED_BGR or dtype != ImageDataType.UINT8:
                raise MediaError(_fake.INVALID_ARGUMENT, "colour mode {}x{} fmt {} dtype {}".format(w, h, fmt, dtype))
        elif kind == Video3DStreamType.DEPTH:
            if (w, h) not in D435_DEPTH or fmt != ImageFormat.ROW_MAJOR_GREYSCALE or dtype not in (ImageDataType.UINT8, ImageDataType.UINT16):
                raise MediaError(_fake.INVALID_ARGUMENT, "depth mode {}x{} fmt {} dtype {}".format(w, h, fmt, dtype))
        else:
            raise MediaError(_fake.INVALID_ARGUMENT, "stream type")
        stream = _Stream(self, kind, w, h)
        self.streams.append(stream)
        return stream

    def start_streaming(self):
        self.streaming = True

    def stop_streaming(self):
        self.streaming = False

    def close(self):
        self.streaming = False


class VideoCapture(object):
    def __init__(self, url, fps, w, h, fmt, dtype, attributes, num_attributes):
        if "csi" not in STATE.sensors:
            raise MediaError(_fake.NOT_OPEN, "no CSI cameras")
        prefix = "video://localhost:"
        if not url.startswith(prefix) or not url[len(prefix):].isdigit() or int(url[len(prefix):]) not in STATE.board["csi_ids"]:
            raise MediaError(_fake.INVALID_ARGUMENT, "camera url {!r}".format(url))
        if (w, h) not in CSI_MODES or fmt != ImageFormat.ROW_MAJOR_INTERLEAVED_BGR or dtype != ImageDataType.UINT8:
            raise MediaError(_fake.INVALID_ARGUMENT, "CSI mode")
        if (attributes is None) != (num_attributes == 0):
            raise MediaError(_fake.INVALID_ARGUMENT, "attributes")
        self.cam = int(url[len(prefix):])
        self.w, self.h = w, h
        self.started = False

    def start(self):
        self.started = True

    def read(self, buf):
        """Fills ``buf`` with 10 + 40 * camera id and returns True, or False (no new frame) as scripted."""
        if not self.started:
            raise MediaError(_fake.NOT_OPEN, "capture not started")
        if not isinstance(buf, np.ndarray) or buf.dtype != np.uint8 or buf.shape != (self.h, self.w, 3):
            raise MediaError(_fake.INVALID_BUFFER, "capture buffer")
        script = STATE.camera_script or [True]
        ok = script[STATE.camera_reads % len(script)]
        STATE.camera_reads += 1
        if ok:
            buf[...] = 10 + 40 * self.cam
        return bool(ok)

    def stop(self):
        self.started = False

    def close(self):
        self.started = False
