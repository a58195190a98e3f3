"""Record, replay and watch: MCAP recordings that open in Foxglove, a recording as a car, a live view.

    from qcarlab.recording import Recorder, RecordingCar
    with RecordingCar(qcarlab.open_car("sim"), Recorder("run.mcap")) as car:
        ...                                   # every read, write, scan and frame is recorded

- :mod:`~qcarlab.recording.channels`: the topics, frames and message conversions (Foxglove's
  well-known schemas for scans, images, poses, transforms and the scene; JSON for readouts,
  commands and the lab's values);
- :mod:`~qcarlab.recording.writer`: :class:`Recorder`, writing an MCAP file incrementally and/or
  streaming to the live view;
- :mod:`~qcarlab.recording.process`: :class:`RecorderProcess`, the same Recorder in a process of
  its own (what ``--record`` uses where it can: :func:`open_recorder`);
- :mod:`~qcarlab.recording.car`: :class:`RecordingCar`, the decorator that records any car;
- :mod:`~qcarlab.recording.reader`: reading a recording back (``qcarlab replay info``);
- :mod:`~qcarlab.recording.rosbag`: reading a rosbag2 from a real QCar's ROS 2 stack;
- :mod:`~qcarlab.recording.live`: the Foxglove WebSocket live view.

The heavy libraries (foxglove-sdk, mcap, rosbags) are the ``record`` extra; without them a command
asking for a recording says ``pip install 'qcarlab[record]'`` in one line.
"""

from __future__ import annotations

from qcarlab.errors import NotBuiltError

EXTRA_HINT = "pip install 'qcarlab[record]'"


def require(what: str, module: str = "foxglove") -> None:
    """Import ``module`` or raise one clear line naming the extra that provides it."""
    try:
        __import__(module)
    except ImportError:
        raise NotBuiltError(f"{what} needs the recording libraries: {EXTRA_HINT}") from None


__all__ = ["EXTRA_HINT", "require"]
