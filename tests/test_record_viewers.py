"""A free viewer opens qcarlab's recordings (issue 29, item 2): Rerun's own MCAP reader (the Python
SDK's ``rerun.chunk.McapReader``, the loader behind ``rerun run.mcap``) reads every message of a
recording and turns the Foxglove schemas into what Rerun draws. Skipped when rerun-sdk is not
installed (``pip install 'qcarlab[view]'``)."""

from __future__ import annotations

import pytest

pytest.importorskip("foxglove")
pytest.importorskip("mcap")
rerun_chunk = pytest.importorskip("rerun.chunk")
if not hasattr(rerun_chunk, "McapReader"):
    pytest.skip("this rerun-sdk has no MCAP reader (rerun-sdk >= 0.41 has)", allow_module_level=True)

from qcarlab.recording import channels as C  # noqa: E402
from qcarlab.recording.reader import Recording  # noqa: E402

# what Rerun makes of each Foxglove schema qcarlab writes (its archetypes), and of qcarlab's own
# protobuf messages (decoded from the descriptors the file carries)
EXPECTED = {
    C.COLOR: "EncodedImage:blob",  # foxglove.CompressedImage (JPEG)
    C.DEPTH: "Image:buffer",  # foxglove.RawImage 16UC1
    C.CALIBRATION: "Pinhole:image_from_camera",  # foxglove.CameraCalibration
    C.TF: "Transform3D:translation",  # foxglove.FrameTransforms
    C.POSE_TRUE: "InstancePoses3D:translations",  # foxglove.PoseInFrame
    C.POSE_ESTIMATE: "InstancePoses3D:translations",
    C.LIDAR: "foxglove.LaserScan:message",  # (a structured message: Rerun 0.41 does not draw scans)
    C.READOUT: "qcarlab.Readout:message",
    C.COMMAND: "qcarlab.Command:message",
    C.TRUTH: "qcarlab.Truth:message",
}


def test_rerun_reads_every_message_of_a_recording(tmp_path):
    from qcarlab.car import open_car
    from qcarlab.recording.car import RecordingCar
    from qcarlab.recording.writer import Recorder

    f = tmp_path / "drive.mcap"
    with RecordingCar(open_car("sim", world="obstacles", seed=0), Recorder(f)) as car:
        for _ in range(40):  # 0.4 s: LIDAR scans, RGBD frames (one with depth), poses, readouts
            car.read()
            car.truth()
            car.read_lidar()
            car.read_rgbd()
            car.write(0.1, 0.05)
            car.advance(0.01)
    rows: dict[str, int] = {}
    columns: dict[str, set[str]] = {}
    for chunk in rerun_chunk.McapReader(f).stream():
        if chunk.is_static:  # the channels' and the file's descriptions
            continue
        path = chunk.entity_path
        rows[path] = rows.get(path, 0) + chunk.num_rows
        columns.setdefault(path, set()).update(chunk.to_record_batch().schema.names)
    ours = {topic: entry["count"] for topic, entry in Recording(f).info()["topics"].items()}
    # every message, on every topic (a /tf message holds several transforms: a row each in Rerun)
    assert set(rows) == set(ours) and rows[C.TF] >= ours[C.TF]
    assert {k: v for k, v in rows.items() if k != C.TF} == {k: v for k, v in ours.items() if k != C.TF}
    for topic, column in EXPECTED.items():
        assert column in columns[topic], (topic, sorted(columns[topic]))
