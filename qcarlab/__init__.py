"""qcarlab: the QCar self-driving lab in Python: a real car over TCP or a built-in simulator.

    import qcarlab
    with qcarlab.open_car("sim", seed=1) as car:
        car.write(0.1, 0.0)
        car.advance(2.0)
        print(car.read().encoder_counts)
"""

import os as _os

# No image qcarlab decodes may be larger than this (a 30,000 x 30,000 px PNG of a few kB would take
# gigabytes): qcarlab.media.check_image_size reads the size from the header first, and OpenCV
# itself refuses larger images (its own setting, read at its first decode).
MAX_IMAGE_PIXELS = 50_000_000
_os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(MAX_IMAGE_PIXELS))
# A damaged image or video is one line of ours ("cannot read this image"), not OpenCV's and
# ffmpeg's own warnings besides it (read when OpenCV loads; qcarlab.media also sets OpenCV's level).
_os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
_os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET

__version__ = "0.1.0"
__all__ = ["open_car", "__version__"]


def __getattr__(name: str):
    """``qcarlab.open_car`` is imported on first use: the ``qcarlab`` command's first step
    (:mod:`qcarlab.warm`) imports this package and must not pay for numpy and the simulator."""
    if name == "open_car":
        from qcarlab.car import open_car

        return open_car
    raise AttributeError(f"module 'qcarlab' has no attribute {name!r}")
