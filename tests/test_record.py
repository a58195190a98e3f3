"""--record: every driving command writes an MCAP that the mcap reader opens, with Foxglove's schemas."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("foxglove")
pytest.importorskip("mcap")

from mcap.reader import make_reader  # noqa: E402

from qcarlab.recording import channels as C  # noqa: E402
from qcarlab.recording.reader import Recording, open_recording  # noqa: E402


def summary_of(path):
    with open(path, "rb") as f:
        s = make_reader(f).get_summary()
    topics = {c.topic: s.schemas[c.schema_id].name for c in s.channels.values()}
    return topics, s.statistics


LABS = {
    "io-test": (["io-test", "--duration", "0.5", "--on-floor"], {C.READOUT: "qcarlab.Readout"}),
    "lidar-scan": (["lidar-scan", "--scans", "3", "--world", "obstacles"], {C.LIDAR: "foxglove.LaserScan"}),
    "camera": (["camera", "--rgbd", "--csi"], {C.COLOR: "foxglove.CompressedImage", C.DEPTH: "foxglove.RawImage",
                                               C.CSI["front"]: "foxglove.CompressedImage",
                                               C.CALIBRATION: "foxglove.CameraCalibration"}),
    "path-follow": (["path-follow", "circle", "--max-time", "1"], {C.SCENE: "foxglove.SceneUpdate"}),
    "stop-sign": (["stop-sign", "--max-time", "1"], {C.COLOR: "foxglove.CompressedImage"}),
    "lane-follow": (["lane-follow", "--duration", "1"], {C.DEPTH: "foxglove.RawImage"}),
    "avoid": (["avoid", "--duration", "1"], {C.LIDAR: "foxglove.LaserScan"}),
}


@pytest.mark.parametrize("lab", sorted(LABS))
def test_each_lab_records_an_mcap_with_foxglove_schemas(lab, cli, tmp_path):
    args, expected = LABS[lab]
    f = tmp_path / f"{lab}.mcap"
    extra = ["--out", str(tmp_path / "cam")] if lab == "camera" else []
    code, out, err = cli(*args, *extra, "--record", f)
    # a one-second run of path-follow or stop-sign ends before its goal (exit 1): it still records
    assert code == 0 or (code == 1 and "goal missed" in err), err
    assert f"to {f}" in out  # the line naming the recording
    topics, stats = summary_of(f)
    for topic, schema in expected.items():
        assert topics.get(topic) == schema, (topic, topics)
    # every simulated run has the poses and transforms, and its world (or path) as a scene
    assert topics[C.TF] == "foxglove.FrameTransforms"
    assert topics[C.POSE_TRUE] == "foxglove.PoseInFrame"
    if lab != "io-test":  # on its stand, with no world to show
        assert topics[C.SCENE] == "foxglove.SceneUpdate"
    assert stats.message_count > 10


def test_recorded_values_read_back_exactly(tmp_path):
    """Readouts, commands and scans read back bit for bit; depth (exact) as float32 metres."""
    from qcarlab.car import open_car
    from qcarlab.recording.car import RecordingCar
    from qcarlab.recording.writer import Recorder

    f = tmp_path / "r.mcap"
    seen = {"readouts": [], "scans": [], "frames": [], "cmds": []}
    with RecordingCar(open_car("sim", world="obstacles", seed=3), Recorder(f, profile="exact")) as car:
        for k in range(30):
            seen["cmds"].append(car.write(0.1, 0.05 * math.sin(k), leds=["headlamps"]))
            seen["readouts"].append(car.read())
            if k % 10 == 0:
                seen["scans"].append(car.read_lidar())
                seen["frames"].append(car.read_rgbd())
            car.advance(0.01)
        car.recorder.log_values(car.time, {"v_ref": np.float64(0.3), "state": "go", "nan": math.nan})
    tape = Recording(f).tape()
    assert [r.to_dict() for r in tape.readouts] == [r.to_dict() for r in seen["readouts"]]
    assert [c for _, c, stop in tape.commands if not stop] == seen["cmds"]
    for a, b in zip(tape.scans, seen["scans"]):
        assert a.t == b.t and np.array_equal(a.angles, b.angles) and np.array_equal(a.ranges, b.ranges)
    frames = [load() for _, load in tape.rgbd()]
    assert [fr.t for fr in frames] == [fr.t for fr in seen["frames"]]
    for a, b in zip(frames, seen["frames"]):
        assert np.array_equal(a.color, b.color) and a.depth.dtype == np.float32 and np.array_equal(a.depth, b.depth)
    assert tape.lab[-1]["v_ref"] == 0.3 and tape.lab[-1]["state"] == "go" and tape.lab[-1]["nan"] is None
    assert tape.params == car.params and tape.throttle_limit == car.throttle_limit


def test_compact_profile_is_jpeg_colour_and_millimetre_depth_every_15th_frame(tmp_path):
    from qcarlab.car import open_car
    from qcarlab.recording.car import RecordingCar
    from qcarlab.recording.writer import Recorder

    f = tmp_path / "c.mcap"
    frames = []
    with RecordingCar(open_car("sim", world="track", seed=0), Recorder(f)) as car:
        for _ in range(31):
            frames.append(car.read_rgbd())
            car.advance(0.034)  # one frame per step (30 fps)
    rec = Recording(f)
    counts = {t: e["count"] for t, e in rec.info()["topics"].items()}
    assert counts[C.COLOR] == 31 and counts[C.DEPTH] == 3  # frames 0, 15, 30
    got = [load() for _, load in rec.tape().rgbd()]
    assert len(got) == 31
    # JPEG colour: close, not equal; depth: the nearest millimetre of frame 15, held to frame 29
    assert np.abs(got[5].color.astype(int) - frames[5].color).mean() < 3.0
    assert np.abs(got[15].depth - frames[15].depth).max() <= 0.0005 + 1e-6
    assert np.array_equal(got[29].depth, got[15].depth)


def test_replay_info_lists_topics_counts_and_rates(cli, tmp_path):
    f = tmp_path / "a.mcap"
    assert cli("avoid", "--duration", "2", "--record", f)[0] == 0
    code, out, err = cli("replay", "info", f, "--json")
    assert code == 0, err
    info = json.loads(out)
    assert info["complete"] and info["world"] == "obstacles" and info["profile"] == "compact"
    lidar = info["topics"][C.LIDAR]
    assert lidar["schema"] == "foxglove.LaserScan" and lidar["count"] == 20
    assert lidar["rate_hz"] == pytest.approx(10.0, rel=0.01)
    assert info["topics"][C.READOUT]["rate_hz"] == pytest.approx(100.0, rel=0.01)
    assert 1.9 < info["duration_s"] < 2.1
    code, out, _ = cli("replay", "info", f)
    assert code == 0 and "/qcar/lidar" in out and "foxglove.LaserScan" in out


def test_recording_over_tcp(cli, tmp_path):
    """--record works on a served car too: the readouts and scans come over the wire."""
    from qcarlab.car import open_car
    from qcarlab.net.server import CarServer

    with open_car("sim", world="obstacles", seed=0) as served:
        server = CarServer(served, "127.0.0.1", 0, lockstep=True)
        server.start()
        try:
            import threading

            thread = threading.Thread(target=server.serve_forever, daemon=True)
            thread.start()
            f = tmp_path / "tcp.mcap"
            code, out, err = cli("avoid", "--duration", "1", "--car", server.uri, "--record", f)
            assert code == 0, err
        finally:
            server.stop()
    counts = {t: e["count"] for t, e in Recording(f).info()["topics"].items()}
    assert counts[C.READOUT] == 100 and counts[C.LIDAR] == 10 and counts[C.COMMAND] >= 100


@pytest.mark.parametrize("args, message", [
    (["--record", "/no/such/folder/x.mcap"], "does not exist"),
    (["--record-exact"], "--record-exact needs --record"),
    (["--topics", "scan=/scan"], "--topics maps a rosbag2"),
    (["--car", "replay:/no/such.mcap"], "no such file"),
    (["--car", "replay:"], "expected replay:FILE"),
    (["--live-port", "http:x"], "--live-port"),
])
def test_bad_recording_options_give_one_line_and_exit_2(args, message, cli):
    code, out, err = cli("avoid", "--duration", "0.5", *args)
    assert code == 2
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_not_an_mcap_is_refused(cli, tmp_path):
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"hello")
    code, _, err = cli("replay", "info", bad)
    assert code == 2 and "not an MCAP file" in err


def test_without_the_extra_one_line_says_what_to_install(cli, tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "foxglove", None)  # as if foxglove-sdk were not installed
    code, _, err = cli("avoid", "--duration", "0.5", "--record", tmp_path / "x.mcap")
    assert code == 2
    assert "pip install 'qcarlab[record]'" in err and len(err.strip().splitlines()) == 1


def test_open_recording_refuses_a_folder_that_is_not_a_bag(tmp_path):
    from qcarlab.errors import InputError

    with pytest.raises(InputError, match="not a rosbag2"):
        open_recording(tmp_path)


def _messages(path):
    """Every message of a recording in file order: (topic, log time from the first, data)."""
    with open(path, "rb") as f:
        msgs = [(ch.topic, m.log_time, m.data) for _, ch, m in make_reader(f).iter_messages(log_time_order=False)]
    t0 = msgs[0][1]
    return [(topic, t - t0, data) for topic, t, data in msgs]


def _record_camera_drive(path, **frames_opts):
    from qcarlab.car import open_car
    from qcarlab.recording import writer
    from qcarlab.recording.car import RecordingCar
    from qcarlab.recording.writer import Recorder

    old = writer._Frames.THREADED
    writer._Frames.THREADED = frames_opts.get("threaded", old)
    try:
        with RecordingCar(open_car("sim", world="track", seed=0), Recorder(path)) as car:
            for k in range(100):  # 1 s: 100 ticks, 30 RGBD frames, a CSI set every 10th tick
                car.write(0.1, 0.02)
                car.read()
                car.truth()
                car.read_rgbd()
                if k % 10 == 0:
                    car.read_csi()
                car.recorder.log_values(car.time, {"k": k})
                car.advance(0.01)
    finally:
        writer._Frames.THREADED = old


def test_images_encoded_on_the_encoder_thread_make_the_same_file_as_in_the_callers(tmp_path):
    """JPEG colour and millimetre depth encoded meanwhile on a thread of their own: the same
    messages, in the same order, at the same times, as encoding them in the caller's thread."""
    _record_camera_drive(tmp_path / "t.mcap", threaded=True)
    _record_camera_drive(tmp_path / "i.mcap", threaded=False)
    threaded, inline = _messages(tmp_path / "t.mcap"), _messages(tmp_path / "i.mcap")
    topics = {t for t, _, _ in threaded}
    assert {C.COLOR, C.DEPTH, C.CSI["front"], C.READOUT, C.LAB} <= topics
    assert [(t, lt) for t, lt, _ in threaded] == [(t, lt) for t, lt, _ in inline]
    images = {C.COLOR, C.DEPTH, *C.CSI.values()}

    def same(msgs):  # the images past their timestamp (field 1: the two recordings' clocks differ), the ticks
        return [d[2 + d[1]:] if t in images else d for t, _, d in msgs
                if t in images or t in (C.READOUT, C.COMMAND, C.TRUTH, C.LAB)]

    assert same(threaded) == same(inline)
    assert sum(t == C.COLOR for t, _, _ in threaded) == 30 and sum(t == C.DEPTH for t, _, _ in threaded) == 2


def test_a_frame_the_lab_draws_on_is_recorded_as_it_was_read(tmp_path):
    """The encoder works from a copy: a lab that paints over its frame right after reading it
    (while the JPEG is still being encoded) does not change what was recorded."""
    from qcarlab.car import open_car
    from qcarlab.recording.car import RecordingCar
    from qcarlab.recording.writer import Recorder

    from qcarlab.recording import writer

    f = tmp_path / "d.mcap"
    seen = []
    old, writer._Frames.THREADED = writer._Frames.THREADED, True  # (whatever the machine's load)
    try:
        with RecordingCar(open_car("sim", world="track", seed=0), Recorder(f)) as car:
            for _ in range(10):
                frame = car.read_rgbd()
                seen.append((frame.color.copy(), frame.depth.copy()))
                frame.color[:] = 0  # painted over at once
                frame.depth[:] = 0
                car.advance(0.034)
    finally:
        writer._Frames.THREADED = old
    got = [load() for _, load in Recording(f).tape().rgbd()]
    assert len(got) == 10
    for g, (color, depth) in zip(got, seen):
        assert np.abs(g.color.astype(int) - color).mean() < 3.0
    assert np.abs(got[0].depth - seen[0][1]).max() <= 0.0005 + 1e-6


@pytest.mark.parametrize("cores, load, threaded", [(2, 1.2, True), (2, 2.5, False), (1, 0.1, False), (4, 3.5, True)])
def test_images_go_to_the_encoder_thread_only_with_a_core_to_spare(cores, load, threaded, monkeypatch):
    from qcarlab.recording import writer

    monkeypatch.setattr(writer, "_cores", lambda: cores)
    monkeypatch.setattr(writer.os, "getloadavg", lambda: (load, load, load))
    frames = writer._Frames()
    try:
        assert frames._threaded() is threaded
        job = frames.color(None, C.COLOR, np.zeros((48, 64, 3), np.uint8), 0, C.CAMERA_FRAME, False)
        assert (job.encoder is not None) is threaded and job.result() is not None
    finally:
        frames.close()


def test_a_csv_log_keeps_every_float_to_the_last_bit(tmp_path):
    """Logs are read back by students' scripts and by qcarlab replay: each float is its shortest
    repr, so it reads back as the same float (nan, inf, -0.0 and subnormals too)."""
    import csv

    from qcarlab.record import write_csv

    rng = np.random.default_rng(3)
    a = np.concatenate((rng.normal(size=500) * 10.0 ** rng.integers(-30, 30, 500),
                        [np.nan, np.inf, -np.inf, -0.0, 5e-324, 0.1]))
    path = write_csv(tmp_path / "log.csv", {"t": a, "n": np.arange(len(a)), "label": ["a,b"] * len(a)})
    rows = list(csv.reader(path.open(encoding="utf-8")))
    assert rows[0] == ["t", "n", "label"]
    back = np.array([float(r[0]) for r in rows[1:]])
    assert np.array_equal(back, a, equal_nan=True) and np.signbit(back[-3]) and rows[-1][2] == "a,b"
    assert [int(r[1]) for r in rows[1:]] == list(range(len(a)))
