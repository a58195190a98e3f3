"""The bugs a new user hit (issue 11, item 5): each test fails on the old behaviour."""

from __future__ import annotations

import io
import json
import logging
import time

import numpy as np
import pytest

from qcarlab.car.sim import SimCar
from qcarlab.car.tcp import TcpCar
from qcarlab.experiments.io_test import io_test
from qcarlab.net.server import CarServer


# --- a lock-step server keeps the car's state between clients -------------------------------
def test_each_controlling_client_of_a_lockstep_server_starts_from_the_start_state():
    """The same io-test drove 0.81, 1.69, then 2.00 m: each client went on from the last one."""
    server = CarServer(SimCar(seed=3), "127.0.0.1", 0, watchdog=5.0).start()
    runs = []
    try:
        for _ in range(3):
            with TcpCar(*server.address, timeout=5.0) as car:
                t0, tr0 = car.time, car.truth()
                r = io_test(car, 0.15, 0.1, None, duration=1.0, rate=100.0)
                runs.append((t0, (tr0.x, tr0.y, tr0.yaw, tr0.distance), r.metrics))
    finally:
        server.stop()
    for t0, pose, metrics in runs:
        assert t0 == 0.0 and pose == pytest.approx((0.0, 0.0, -np.pi / 2, 0.0))
    assert json.dumps(runs[1][2], sort_keys=True) == json.dumps(runs[0][2], sort_keys=True)
    assert json.dumps(runs[2][2], sort_keys=True) == json.dumps(runs[0][2], sort_keys=True)


# --- the real-time watchdog trips at the start of every client ------------------------------
def test_the_realtime_watchdog_guards_from_the_first_command_not_from_the_hello(caplog):
    car = SimCar(seed=0, realtime=True)
    server = CarServer(car, "127.0.0.1", 0, watchdog=0.05).start()
    try:
        with caplog.at_level(logging.WARNING, logger="qcarlab"):
            with TcpCar(*server.address, timeout=5.0) as remote:
                time.sleep(0.3)  # a client busy with its first (slow) sensor frame before it drives
                r = remote.read()
                assert server.trips == 0 and not remote.status & 1
                remote.write(0.05, 0.0)
                time.sleep(0.3)  # then silent: now the watchdog stops the car
                remote.read()
                assert server.trips == 1 and remote.status & 1
        assert r.throttle == 0.0
        warned = [rec.getMessage() for rec in caplog.records if "watchdog stopped the car" in rec.getMessage()]
        assert len(warned) == 1  # the client says so once, after it had driven
    finally:
        server.stop()
        car.close()


def test_keyboard_drive_prints_a_warning_on_its_own_line_above_the_panel():
    """It came out as 'starting the car...warning: ...' on one line."""
    from rich.console import Console
    from rich.live import Live
    from rich.text import Text

    from qcarlab.cli.drive import _log_above
    from tests.ptyrun import ANSI

    buf = io.StringIO()
    console = Console(file=buf, force_terminal=True, width=80)
    with Live(Text("starting the car..."), console=console, auto_refresh=False, transient=True) as live, \
            _log_above(live):
        logging.getLogger("qcarlab").warning("tcp://car:1: the server's watchdog stopped the car")
    text = ANSI.sub("", buf.getvalue()).replace("\r", "\n")
    assert "starting the car...warning" not in text
    assert "\nwarning: tcp://car:1: the server's watchdog stopped the car\n" in text


# --- lane-follow --laps 1 stopped at the default 30 s with 0.62 laps --------------------------
@pytest.mark.slow
def test_lane_follow_laps_sets_the_time_the_laps_need(cli_json):
    m = cli_json("lane-follow", "--laps", "1")
    assert m["laps"] == pytest.approx(1.0, abs=0.02) and m["duration_s"] > 30.0 and m["goal_reached"]


# --- lidar-scan --out drew cloud.png's map 0.25 m off ----------------------------------------
def test_the_map_under_the_point_cloud_is_where_the_world_is(cli, tmp_path, monkeypatch):
    from qcarlab import plots

    seen = {}
    real = plots.plot_cloud

    def spy(cloud, poses, file, background=None, extent=None):
        seen.update(cloud=cloud, background=background, extent=extent)
        return real(cloud, poses, file, background, extent)

    monkeypatch.setattr(plots, "plot_cloud", spy)
    code, out, err = cli("lidar-scan", "--world", "obstacles", "--out", tmp_path / "s")
    assert code == 0, err
    img, (x0, x1, y0, y1) = seen["background"], seen["extent"]
    h, w = img.shape[:2]
    assert (x1 - x0) * h == pytest.approx((y1 - y0) * w)  # square pixels
    # the box ahead of the car (0, -1.2), 0.40 x 0.30 m, brown: under its centre the map must be brown
    col = int((0.0 - x0) / (x1 - x0) * w)
    row = int((y1 - (-1.2)) / (y1 - y0) * h)
    b, g, r = (int(v) for v in img[row, col])
    assert r > g > b and r - b > 40, (b, g, r)
    # and the LIDAR's returns off that box lie on its face (y = -1.05), seen on the same map
    near = seen["cloud"][np.hypot(seen["cloud"][:, 0], seen["cloud"][:, 1] + 1.05) < 0.1]
    assert len(near) and abs(float(np.median(near[:, 1])) + 1.05) < 0.02


# --- bad --start, --rate and --world: one clear line, exit 2 ----------------------------------
@pytest.mark.parametrize("args, says", [
    (("avoid", "--start", "50,50,0", "--duration", "1"), "outside the world 'obstacles'"),
    (("lane-follow", "--start", "9,0,0", "--duration", "1"), "outside the world 'track'"),
    (("stop-sign", "--start", "-2.0,-3,0"), "inside an obstacle (or a wall)"),
    (("avoid", "--world", "."), "is a folder"),
    (("lidar-scan", "--world", "/"), "is a folder"),
    (("avoid", "--rate", "5000", "--duration", "1"), "--rate must be between 1 and 2000 Hz"),
    (("io-test", "--rate", "0.5"), "--rate must be between 1 and 2000 Hz"),
])
def test_bad_start_rate_and_world_say_so_in_one_line_and_exit_2(cli, args, says):
    code, out, err = cli(*args)
    assert code == 2 and says in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_the_rate_option_documents_the_range_it_accepts(cli):
    code, out, err = cli("avoid", "--help")
    assert "1-2000" in " ".join(out.split())


# --- --token on the lab commands, and qcarlab --version ---------------------------------------
def test_lab_commands_take_the_token_of_a_served_car(cli, monkeypatch):
    monkeypatch.delenv("QCARLAB_TOKEN", raising=False)
    server = CarServer(SimCar(seed=1), "127.0.0.1", 0, token="s3cret-token-of-16+", watchdog=5.0).start()
    try:
        code, out, err = cli("io-test", "--car", server.uri, "--duration", "0.2", "--json")
        assert code == 1 and "wrong token" in err and "--token" in err
        code, out, err = cli("io-test", "--car", server.uri, "--token", "s3cret-token-of-16+", "--duration", "0.2", "--json")
        assert code == 0, err
        code, out, err = cli("avoid", "--car", server.uri, "--token", "s3cret-token-of-16+", "--duration", "0.2", "--json")
        assert code == 0, err
    finally:
        server.stop()


def test_version(cli):
    from qcarlab import __version__

    code, out, err = cli("--version")
    assert code == 0 and out.strip() == f"qcarlab {__version__}"


# --- camera without --out wrote into the current folder; CSI views carry their names ---------
def test_camera_without_out_writes_nothing_and_the_views_name_their_camera(cli, tmp_path, monkeypatch):
    import cv2

    monkeypatch.chdir(tmp_path)
    code, out, err = cli("camera", "--rgbd", "--csi")
    assert code == 0 and list(tmp_path.iterdir()) == [] and "--out" in out
    code, out, err = cli("camera", "--csi", "--out", tmp_path / "o")
    assert code == 0
    pano = cv2.imread(str(tmp_path / "o" / "panorama.png"))
    views = {n: cv2.imread(str(tmp_path / "o" / f"csi_{n}.png")) for n in ("right", "rear", "left", "front")}
    w = views["right"].shape[1]
    for k, (name, img) in enumerate(views.items()):
        band = img[:20]
        assert (band < 30).mean() > 0.8 and (band > 200).any(), name  # a black band with white letters
        assert np.array_equal(pano[:, k * w:(k + 1) * w], img)  # the panorama in the sheet's order, labelled
    assert not np.array_equal(views["right"][:20], views["rear"][:20])  # different names


# --- the depth image read the sign's white letters as 6.39 m ------------------------------------
def test_the_depth_camera_reads_the_stop_signs_letters_at_the_signs_distance():
    import cv2

    import qcarlab

    with qcarlab.open_car("sim", world="stop-sign", start=(0.0, -1.8, -np.pi / 2)) as car:
        f = car.read_rgbd()
    c, d = f.color.astype(int), f.depth
    red = ((c[:, :, 2] > 150) & (c[:, :, 1] < 80)).astype(np.uint8)
    inside = np.zeros(red.shape, np.uint8)
    cv2.fillConvexPoly(inside, cv2.convexHull(cv2.findNonZero(red)), 1)
    inside = cv2.erode(inside, np.ones((9, 9), np.uint8)) > 0  # the plate, letters and all
    white = inside & (c.min(axis=2) > 170)
    assert white.sum() > 200  # the letters are there
    plate = float(np.median(d[inside]))
    assert 0.4 < plate < 0.7 and np.abs(d[inside] - plate).max() < 0.02  # the camera 13 cm behind the bumper
