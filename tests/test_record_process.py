"""The recorder in a process of its own (qcarlab.recording.process): the same file as in the lab's
process, images through a ring of shared memory that never drops a frame, one-line errors, and the
choice of when to use it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("foxglove")
mcap_reader = pytest.importorskip("mcap.reader")

from qcarlab.car import open_car  # noqa: E402
from qcarlab.errors import InputError, QcarlabError  # noqa: E402
from qcarlab.recording import channels as C  # noqa: E402
from qcarlab.recording import process as P  # noqa: E402
from qcarlab.recording.car import RecordingCar  # noqa: E402
from qcarlab.recording.reader import Recording  # noqa: E402
from qcarlab.recording.writer import Recorder  # noqa: E402
from qcarlab.sensors import CSIFrames  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
T0 = 1_800_000_000_000_000_000

needs_child = pytest.mark.skipif(not P.RecorderProcess.available(), reason="no memfd_create or one core")


def messages(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    out: dict[str, list[tuple[int, bytes]]] = {}
    with open(path, "rb") as f:
        for _, channel, msg in mcap_reader.make_reader(f).iter_messages(log_time_order=False):
            out.setdefault(channel.topic, []).append((msg.log_time, bytes(msg.data)))
    return out


def drive(rec, world: str, seconds: float, csi: bool = False) -> None:
    """A short drive through every kind of call: readouts, commands, truth, values, LIDAR, RGBD (and CSI)."""
    from qcarlab.sim.world import load_world

    w = load_world(world)
    with RecordingCar(open_car("sim", world=w, seed=3), rec) as car:
        rec.scene(w, np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 0.0]]))
        k = 0
        while car.time < seconds:
            r = car.read()
            car.write(0.08, 0.1 * np.sin(r.t))
            car.truth()
            rec.log_values(r.t, {"v_ref": 0.3, "state": "go" if k % 50 else "turn", "cte": 0.01 * k})
            if k % 10 == 0:
                car.read_lidar()
            if k % 3 == 0:
                car.read_rgbd()
            if csi and k % 25 == 0:
                car.read_csi()
            car.advance(0.01)
            k += 1


@needs_child
@pytest.mark.parametrize("profile", ["compact", "exact"])
def test_the_child_writes_the_same_messages_as_the_lab_process(profile, tmp_path):
    a, b = tmp_path / "here.mcap", tmp_path / "child.mcap"
    drive(Recorder(a, profile=profile, t0_ns=T0), "track", 1.2, csi=True)
    child = P.RecorderProcess(b, profile=profile, t0_ns=T0)
    drive(child, "track", 1.2, csi=True)
    here, there = messages(a), messages(b)
    assert set(here) == set(there) and {C.LIDAR, C.COLOR, C.DEPTH, C.SCENE, C.READOUT, C.CSI["front"]} <= set(here)
    for topic in here:
        assert here[topic] == there[topic], topic  # same times, same bytes
    assert child.counts == {t: len(m) for t, m in there.items()}
    assert Recording(b).complete


@needs_child
def test_a_ring_smaller_than_the_run_makes_the_lab_wait_never_drop(monkeypatch, tmp_path):
    monkeypatch.setattr(P, "RING_BYTES", 2 * 640 * 480 * 7 + 4096)  # two frames with depth, five without
    rec = P.RecorderProcess(tmp_path / "small.mcap")
    waits = []
    wait_for = P.RecorderProcess._wait_for
    monkeypatch.setattr(P.RecorderProcess, "_wait_for", lambda self, n: (waits.append(n), wait_for(self, n)))
    with RecordingCar(open_car("sim", world="track", seed=0), rec) as car:
        for _ in range(40):
            car.advance(1 / 30)
            car.read()
            car.read_rgbd()
    assert waits  # the ring was full at times ...
    assert Recording(tmp_path / "small.mcap").info()["topics"][C.COLOR]["count"] == 40  # ... and no frame was lost


@needs_child
def test_a_dead_child_is_one_line_error_not_a_hang(tmp_path):
    rec = P.RecorderProcess(tmp_path / "run.mcap")
    rec.metadata("x", {"a": "1"})
    rec.flush()
    rec._proc.kill()
    rec._proc.wait()
    frame = np.zeros((480, 640, 3), np.uint8)
    with pytest.raises(QcarlabError, match=r"--record .*run\.mcap: .*recording process"):
        for k in range(200):  # the ring fills or a write finds the pipe closed
            rec.csi(CSIFrames(k * 0.1, frame, frame, frame, frame))
    rec.close()  # safe after the failure


@needs_child
def test_bad_input_is_refused_in_the_lab_process(tmp_path):
    with pytest.raises(InputError, match="is a folder"):
        P.RecorderProcess(tmp_path)
    with pytest.raises(InputError, match="does not exist"):
        P.RecorderProcess(tmp_path / "no" / "run.mcap")
    with pytest.raises(InputError, match="profile"):
        P.RecorderProcess(tmp_path / "a.mcap", profile="lossy")
    rec = P.RecorderProcess(tmp_path / "a.mcap")
    with pytest.raises(InputError, match="BGR uint8"):
        rec.rgbd(type("F", (), {"t": 0.0, "color": np.zeros((4, 4), np.float32), "depth": np.zeros((4, 4))})())
    rec.close()
    assert Recording(tmp_path / "a.mcap").complete


def test_open_recorder_keeps_a_live_view_one_core_or_the_switch_in_the_lab_process(monkeypatch, tmp_path):
    monkeypatch.setattr(P.os, "sched_getaffinity", lambda pid: {0})
    rec = P.open_recorder(tmp_path / "one.mcap")
    assert isinstance(rec, Recorder)
    rec.close()
    monkeypatch.undo()
    monkeypatch.setenv("QCARLAB_RECORD_PROCESS", "0")
    rec = P.open_recorder(tmp_path / "off.mcap")
    assert isinstance(rec, Recorder)
    rec.close()


@needs_child
def test_a_prestarted_child_is_taken_by_the_next_recorder_or_discarded(tmp_path):
    P.prestart()
    spare = P._spare
    assert spare is not None
    rec = P.open_recorder(tmp_path / "run.mcap")
    assert isinstance(rec, P.RecorderProcess) and rec._proc is spare.proc and P._spare is None
    rec.close()
    P.prestart()
    proc = P._spare.proc
    P.discard_spare()
    assert proc.returncode is not None and P._spare is None


@needs_child
def test_the_cli_records_through_the_child_and_says_so(tmp_path):
    f = tmp_path / "run.mcap"
    env = dict(os.environ, QCARLAB_RECORD_PROCESS="1")
    t = time.monotonic()
    out = subprocess.run([sys.executable, "-m", "qcarlab", "stop-sign", "--record", str(f), "--out", str(tmp_path / "o")],
                         cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    assert f"to {f}" in out.stdout and time.monotonic() - t < 300
    rec = Recording(f)
    assert rec.complete and rec.metadata["qcarlab"]["argv"][:1] == ["stop-sign"]  # the lab's command line
    assert rec.info()["topics"][C.COLOR]["count"] > 30


def test_a_world_goes_to_the_child_as_its_shapes_not_its_rasters():
    import pickle

    from qcarlab.sim.world import load_world

    world = load_world("track")
    car = open_car("sim", world=world, seed=0)
    first = car.read_rgbd().color
    assert world._cache  # the sensors' rasters, tens of MB
    data = pickle.dumps(world)
    assert len(data) < 100_000
    again = open_car("sim", world=pickle.loads(data), seed=0)
    assert np.array_equal(again.read_rgbd().color, first)  # the same world, rasters built again


@needs_child
def test_a_batch_cut_short_by_ctrl_c_is_finished_before_the_next(monkeypatch, tmp_path):
    """Ctrl-C while the pipe is full: the next batch starts where the cut one stopped."""
    rec = P.RecorderProcess(tmp_path / "run.mcap")
    real_write, calls = os.write, []

    def write(fd, data):  # the third write takes half (a full pipe), the fourth is interrupted
        calls.append(len(data))
        if len(calls) == 3:
            return real_write(fd, bytes(data[: len(data) // 2]))
        if len(calls) == 4:
            raise KeyboardInterrupt  # (as os.write does when Ctrl-C comes while it waits: nothing written)
        return real_write(fd, data)

    monkeypatch.setattr(P.os, "write", write)
    done = []
    with pytest.raises(KeyboardInterrupt):
        for k in range(5):
            rec.log_values(k, {"k": k})
            rec.flush()
            done.append(k)
    for k in range(5, 8):
        rec.log_values(k, {"k": k})
    rec.close()  # no error: the child read every batch whole
    assert Recording(tmp_path / "run.mcap").complete
    ks = [json.loads(data)["k"] for _, data in messages(tmp_path / "run.mcap")[C.LAB]]
    cut = len(done)  # the value whose flush was interrupted: its batch was the one cut in half
    assert cut < 4 and ks == [*range(cut + 1), 5, 6, 7]  # every value once, in order; none lost
