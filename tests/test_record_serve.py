"""A recorded car behind the server (``qcarlab serve --live``): its sensors are read off the drive
lock (or drawn in the render process) as the bare car's are, so a silent controller is still
stopped on time; the frames it serves are the ones recorded; a Foxglove client of ``serve --live``
receives scans and poses while a TCP client drives. Loopback only, bounded in time."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("foxglove")
pytest.importorskip("mcap")
pytest.importorskip("websockets")

from qcarlab.car.sim import SimCar  # noqa: E402
from qcarlab.car.tcp import TcpCar  # noqa: E402
from qcarlab.net.server import CarServer  # noqa: E402
from qcarlab.net.testing import RawClient, SyntheticCar  # noqa: E402
from qcarlab.recording import channels as C  # noqa: E402
from qcarlab.recording.car import RecordingCar  # noqa: E402
from qcarlab.recording.reader import Recording  # noqa: E402
from qcarlab.recording.writer import Recorder  # noqa: E402
from qcarlab.wire import protocol as P  # noqa: E402
from qcarlab.wire.protocol import MsgType as M  # noqa: E402

from tests.test_record_live import watch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OFF = (0.0,) * 12


def wait_for(cond, timeout=3.0, step=0.002):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(step)
    return cond()


def drive(raw: RawClient, throttle: float = 0.2) -> None:
    assert raw.request(M.COMMAND, P.pack_command(throttle, 0.0, OFF)).type == M.APPLIED


@pytest.fixture
def served():
    made = []

    def make(car, **kw):
        server = CarServer(car, "127.0.0.1", 0, **kw).start()
        made.append((server, car))
        return server

    yield make
    for server, car in made:
        server.stop()
        car.close()


def test_a_recorded_cars_slow_sensor_read_does_not_delay_the_watchdog(served, tmp_path):
    """Was: RecordingCar had the Car default sensor_job, reading the frame under the drive lock:
    a 1.5 s reading kept the watchdog waiting for 1.5 s."""
    inner = SyntheticCar(sensor_delay=1.5)
    car = RecordingCar(inner, Recorder(tmp_path / "served.mcap"))
    server = served(car, watchdog=0.1)
    with RawClient(server.address) as ctl, RawClient(server.address, timeout=5.0) as mon:
        ctl.hello("control")
        mon.hello("monitor")
        drive(ctl)
        mon.send(M.GET_RGBD)  # a reading that takes 1.5 s starts now; the controller falls silent
        last = time.monotonic()
        assert wait_for(lambda: inner.cmd.throttle == 0.0, timeout=1.0)
        assert time.monotonic() - last < 0.1 + 0.2  # the watchdog, not the sensor, decided
        assert server.sensors.readings[M.RGBD] == 0  # the reading was still under way
        t0 = time.monotonic()
        drive(ctl, 0.1)  # and a command goes through at once
        assert time.monotonic() - t0 < 0.5 and inner.cmd.throttle == pytest.approx(0.1)
        assert mon.recv().type == M.RGBD
    server.stop()
    car.close()
    info = Recording(tmp_path / "served.mcap").info()["topics"]
    assert info[C.COLOR]["count"] == 1  # the frame served was recorded, once
    assert info[C.COMMAND]["count"] >= 3  # the commands, the watchdog's stop among them


def test_frames_drawn_in_the_render_process_are_the_ones_recorded(served, tmp_path):
    """A recorded real-time simulator still draws its frames in a process of its own; each frame a
    client gets is recorded (exact profile: the very pixels)."""
    f = tmp_path / "served.mcap"
    inner = SimCar(seed=3, realtime=True, on_stand=True)
    car = RecordingCar(inner, Recorder(f, profile="exact"), follow_truth=True)
    server = served(car, render_process=True, prepare=True)
    assert server.worker is not None
    with TcpCar(*server.address, role="monitor", timeout=10.0) as mon:
        scan, rgbd = mon.read_lidar(), mon.read_rgbd()
        mon.read()
    assert not inner._sensors  # the server's own process never built a sensor: the worker drew them
    server.stop()
    car.close()
    tape = Recording(f).tape()
    assert len(tape.scans) == 1 and np.array_equal(tape.scans[0].ranges, scan.ranges)
    assert np.array_equal(tape.scans[0].angles, scan.angles) and tape.scans[0].t == scan.t
    frames = list(tape.rgbd())
    assert len(frames) == 1
    got = frames[0][1]()
    assert np.array_equal(got.color, rgbd.color) and np.array_equal(got.depth, rgbd.depth)


def test_a_silent_controller_under_serve_live_is_stopped_in_time(served):
    """serve --live's car and server, as the command builds them: a monitor's first RGBD read while
    the controller is silent. Was: no render process and no prepared sensors behind the recording
    wrapper, so that read built the world and the camera under the drive lock (0.5 s and more)."""
    from qcarlab.cli.recording import live_car

    car = live_car(SimCar(seed=0, realtime=True, on_stand=True), True, "127.0.0.1:0", None)
    server = served(car, watchdog=0.1, prepare=True, render_process=True)
    assert server.worker is not None  # the frames are drawn in a process of their own, as without --live
    with RawClient(server.address) as ctl, RawClient(server.address, timeout=15.0) as mon:
        ctl.hello("control")
        mon.hello("monitor")
        drive(ctl)
        mon.send(M.GET_RGBD)
        last = time.monotonic()
        with RawClient(server.address) as probe:
            probe.hello("monitor")
            assert wait_for(lambda: P.unpack_readout(probe.request(M.READ).payload)[0]["throttle"] == 0.0, timeout=2.0)
        assert time.monotonic() - last < 0.1 + 0.3
        assert server.trip_delays[0] < 0.1 + 0.1  # as the server timed it
        assert mon.recv().type == M.RGBD


def test_serve_live_streams_scans_and_poses_to_a_foxglove_client():
    """`qcarlab serve --live` on loopback: a TCP client drives and reads the LIDAR; a Foxglove
    WebSocket client receives the scans, the true pose (the client never asks for it) and the
    transforms. SIGINT stops it with the car stopped."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "qcarlab", "serve", "--port", "0", "--watchdog", "1", "--live", "--live-port", "0"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    err_lines: list[str] = []
    try:
        url, uri = None, None
        deadline = time.monotonic() + 120
        while (url is None or uri is None) and time.monotonic() < deadline and proc.poll() is None:
            if url is None:
                line = proc.stderr.readline()
                err_lines.append(line)
                if "ws://" in line:
                    url = line[line.index("ws://"):].split()[0]
            else:
                line = proc.stdout.readline()
                if "tcp://" in line:
                    uri = line[line.index("tcp://"):].split()[0]
        assert url and url.startswith("ws://127.0.0.1:"), "".join(err_lines)
        assert uri and uri.startswith("tcp://127.0.0.1:"), "".join(err_lines)
        threading.Thread(target=lambda: [err_lines.append(x) for x in proc.stderr], daemon=True).start()
        host, port = uri[len("tcp://"):].rsplit(":", 1)
        with TcpCar(host, int(port), timeout=15.0) as ctl:
            ctl.read_lidar()  # the first frame may take a while (the render process warming up)

            def step():
                ctl.write(0.1, 0.2)
                ctl.read()
                ctl.read_lidar()

            got = watch(url, {C.LIDAR, C.POSE_TRUE, C.TF, C.READOUT, C.COMMAND}, step, timeout=60.0)
        # (the true pose logged at the start went out before anyone subscribed: these were logged
        # as the car drove, though the client never asked for the truth)
        assert {C.LIDAR, C.POSE_TRUE, C.TF, C.READOUT, C.COMMAND} <= set(got), got
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        out = proc.communicate(timeout=60)[0]
    assert proc.returncode == 0, "".join(err_lines)
    assert "the car is stopped" in out
