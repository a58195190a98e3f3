"""The live view and stopped runs: a WebSocket client receives scans and poses; Ctrl-C, SIGTERM and
SIGKILL during a recorded run leave a readable file."""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("foxglove")
pytest.importorskip("mcap")
websockets = pytest.importorskip("websockets")

from websockets.sync.client import connect  # noqa: E402

from qcarlab.recording import channels as C  # noqa: E402
from qcarlab.recording.reader import Recording  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def watch(url: str, topics: set[str], step, timeout: float = 60.0, extra_headers=None,
          subprotocol: str = "foxglove.sdk.v1", advertised: set[str] | None = None) -> dict[str, int]:
    """Subscribe to every advertised channel; call ``step()`` between receives until a message of
    each of ``topics`` has arrived (or ``timeout``). Returns messages received per topic; the
    advertised topics go into ``advertised``."""
    got: dict[str, int] = {}
    channels: dict[int, str] = {}
    # max_queue=None: the client's reader never stops for messages not yet received, so the
    # server's close frame is read at once (with the default 16 the scans still streaming fill
    # the queue and the close waits out its 10 s timeout)
    with connect(url, subprotocols=[subprotocol], open_timeout=30, max_queue=None) as ws:
        assert ws.subprotocol == subprotocol
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not topics <= set(got):
            step()
            try:
                msg = ws.recv(timeout=0.05)
            except TimeoutError:
                continue
            if isinstance(msg, str):
                m = json.loads(msg)
                if m.get("op") == "advertise":
                    subs = []
                    for c in m["channels"]:
                        channels[c["id"]] = c["topic"]
                        if advertised is not None:
                            advertised.add(c["topic"])
                        subs.append({"id": c["id"], "channelId": c["id"]})
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                elif m.get("op") == "status" and "Unknown channel ID" in m.get("message", ""):
                    cid = int(m["message"].rsplit(":", 1)[1])  # advertised a moment too soon: again
                    time.sleep(0.1)
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": cid, "channelId": cid}]}))
            elif msg[0] == 1:  # message data: opcode, subscription id (u32), log time (u64), payload
                _, sub, _ = struct.unpack_from("<BIQ", msg)
                topic = channels[sub]
                got[topic] = got.get(topic, 0) + 1
    return got


def test_a_websocket_client_receives_scans_and_poses():
    from qcarlab.car import open_car
    from qcarlab.recording.car import RecordingCar
    from qcarlab.recording.live import LiveView
    from qcarlab.recording.writer import Recorder

    lines = []
    view = LiveView(port=0, announce=lines.append)
    rec = Recorder(None, live=view)
    with RecordingCar(open_car("sim", world="obstacles", seed=0), rec) as car:
        rec.scene(car.inner.world or None)
        assert lines and f"ws://127.0.0.1:{view.bound_port}" in lines[0]

        def step():
            car.write(0.05, 0.1)
            car.advance(0.02)
            car.read()
            car.truth()
            car.read_lidar()

        got = watch(f"ws://127.0.0.1:{view.bound_port}", {C.LIDAR, C.POSE_TRUE, C.TF, C.READOUT}, step)
    assert {C.LIDAR, C.POSE_TRUE, C.TF, C.READOUT} <= set(got), got


@pytest.mark.parametrize("subprotocol", ["foxglove.websocket.v1", "foxglove.sdk.v1"])
def test_a_client_of_either_subprotocol_name_watches(subprotocol):
    """Was: the SDK's server answered a client offering only ``foxglove.websocket.v1`` (older
    Lichtblick, @foxglove/ws-protocol's client) with HTTP 400. Only the channels of the sensors
    the run reads are advertised (here the LIDAR: no camera channels)."""
    from qcarlab.car import open_car
    from qcarlab.recording import channels as C2
    from qcarlab.recording.car import RecordingCar
    from qcarlab.recording.live import LiveView
    from qcarlab.recording.writer import Recorder

    view = LiveView(port=0)
    car0 = open_car("sim", world="obstacles", seed=0)
    rec = Recorder(None, live=view, live_topics=C2.live_topics(car0.identity().capabilities, ("lidar",)))
    with RecordingCar(car0, rec) as car:
        def step():
            car.write(0.05, 0.0)
            car.advance(0.02)
            car.read()
            car.read_lidar()

        advertised: set[str] = set()
        got = watch(f"ws://127.0.0.1:{view.bound_port}", {C.LIDAR, C.READOUT}, step, subprotocol=subprotocol,
                    advertised=advertised)
    assert {C.LIDAR, C.READOUT} <= set(got), got
    assert C.LIDAR in advertised and not advertised & {C.COLOR, C.DEPTH, C.CALIBRATION, *C.CSI.values()}
    with pytest.raises(OSError):  # the view closed with the car: its address no longer listens
        with connect(f"ws://127.0.0.1:{view.bound_port}", subprotocols=[subprotocol], open_timeout=5):
            pass


def test_a_client_offering_neither_name_is_refused():
    from qcarlab.recording.live import LiveView
    from qcarlab.recording.writer import Recorder

    rec = Recorder(None, live=LiveView(port=0))
    try:
        with pytest.raises(websockets.InvalidStatus):
            with connect(f"ws://127.0.0.1:{rec.live.bound_port}", subprotocols=["other"], open_timeout=30):
                pass
    finally:
        rec.close()


def test_a_non_loopback_live_view_needs_the_token():
    from qcarlab.errors import InputError
    from qcarlab.recording.live import LiveView

    with pytest.raises(InputError, match="without a token"):
        LiveView("0.0.0.0", 0)


def test_the_token_proxy_lets_in_only_a_client_with_the_token():
    from qcarlab.car import open_car
    from qcarlab.recording.car import RecordingCar
    from qcarlab.recording.live import LiveView
    from qcarlab.recording.writer import Recorder

    view = LiveView("0.0.0.0", 0, token="s3cret")  # a proxy in front of the SDK's loopback server
    rec = Recorder(None, live=view)
    with RecordingCar(open_car("sim", world="obstacles", seed=0), rec) as car:
        port = view.bound_port
        with pytest.raises(websockets.InvalidStatus):
            with connect(f"ws://127.0.0.1:{port}/?token=wrong", subprotocols=["foxglove.sdk.v1"], open_timeout=30):
                pass

        def step():
            car.advance(0.02)
            car.read()
            car.read_lidar()

        got = watch(f"ws://127.0.0.1:{port}/?token=s3cret", {C.LIDAR}, step)
    assert got.get(C.LIDAR, 0) >= 1


def test_lab_command_with_live_streams_while_it_drives(tmp_path):
    """`qcarlab avoid --live` (real time) announces the address on stderr; a client gets scans."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "qcarlab", "avoid", "--duration", "60", "--realtime", "--live", "--live-port", "0"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = ""
        deadline = time.monotonic() + 60
        while "ws://" not in line and time.monotonic() < deadline:
            line = proc.stderr.readline()
        assert "ws://127.0.0.1:" in line, line
        url = line[line.index("ws://"):].split()[0]
        advertised: set[str] = set()
        got = watch(url, {C.LIDAR, C.POSE_TRUE}, lambda: None, advertised=advertised)
        assert {C.LIDAR, C.POSE_TRUE} <= set(got), got
        # avoid reads the LIDAR only: no camera channel advertised that would never send
        assert not advertised & {C.COLOR, C.DEPTH, C.CALIBRATION, *C.CSI.values()}, advertised
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(60)
    assert proc.returncode == 130


def _start_recording(tmp_path: Path, child: bool = True) -> tuple[subprocess.Popen, Path]:
    """A recorded lane-follow under way; ``child=False``: the recorder in the lab's process."""
    f = tmp_path / "run.mcap"
    env = dict(os.environ, QCARLAB_RECORD_PROCESS="1" if child else "0")
    proc = subprocess.Popen(
        [sys.executable, "-m", "qcarlab", "lane-follow", "--duration", "120", "--realtime", "--record", str(f)],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:  # wait until chunks are on disk: the run is under way
        if f.exists() and f.stat().st_size > 1_500_000:
            return proc, f
        if proc.poll() is not None:
            break
        time.sleep(0.1)
    proc.kill()
    pytest.fail(f"the recorded run did not get going: {proc.stderr.read() if proc.stderr else ''}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_or_sigterm_leaves_a_complete_readable_file(sig, tmp_path):
    proc, f = _start_recording(tmp_path)
    proc.send_signal(sig)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == 130, err  # Ctrl-C's exit code, after the car was stopped and the file closed
    rec = Recording(f)
    assert rec.complete  # the summary was written on the way out
    tape = rec.tape()
    assert len(tape.readouts) > 10 and tape.commands[-1][2]  # ends with the stop
    assert Recording(f).info()["topics"][C.COLOR]["count"] > 5


def test_sigkill_loses_at_most_the_last_chunk(tmp_path):
    """The recorder in the lab's process (a live view, one core): the file ends at its last chunk."""
    proc, f = _start_recording(tmp_path, child=False)
    size = f.stat().st_size
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(30)
    rec = Recording(f)
    assert not rec.complete
    info = rec.info()
    assert info["topics"][C.READOUT]["count"] > 10 and info["topics"][C.COLOR]["count"] > 5
    assert len(rec.tape().readouts) == info["topics"][C.READOUT]["count"]
    assert f.stat().st_size >= size


def test_sigkill_of_the_lab_leaves_a_complete_file_when_the_recorder_has_a_process(tmp_path):
    """The recorder's own process sees the lab's pipe end and closes the file with its summary."""
    proc, f = _start_recording(tmp_path, child=True)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(30)
    deadline = time.monotonic() + 30
    while not Recording(f).complete and time.monotonic() < deadline:
        time.sleep(0.1)
    rec = Recording(f)
    assert rec.complete
    info = rec.info()
    assert info["topics"][C.READOUT]["count"] > 10 and info["topics"][C.COLOR]["count"] > 5
    assert len(rec.tape().readouts) == info["topics"][C.READOUT]["count"]
