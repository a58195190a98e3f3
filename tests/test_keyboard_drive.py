"""keyboard-drive (sheet 3.4): the state machine, the key decoder, the loop, and the command run
through a pseudo-terminal (keys in, panel out, terminal restored, car stopped)."""

from __future__ import annotations

import math
import os
import re
import select
import signal
import subprocess
import sys
import termios
from pathlib import Path

import numpy as np
import pytest

from qcarlab.car import open_car
from qcarlab.car.sim import SimCar
from qcarlab.errors import CarError, InputError, NotBuiltError
from qcarlab.experiments.keyboard_drive import (
    DriveConfig,
    DriveState,
    KeyDecoder,
    apply_key,
    cbreak_terminal,
    keyboard_drive,
    lamps,
    nearest_obstacle,
    world_map,
)
from qcarlab.sensors import LidarScan

from ptyrun import PtyRun

REPO = Path(__file__).resolve().parents[1]
CFG = DriveConfig(max_throttle=0.15, throttle_step=0.03, throttle_ramp=0.3, steering_step=0.1, steering_ramp=1.5)


def press(state: DriveState, *keys: str) -> DriveState:
    for k in keys:
        state = apply_key(state, k)
    return state


def run_for(state: DriveState, seconds: float, dt: float = 0.02) -> DriveState:
    for _ in range(round(seconds / dt)):
        state = apply_key(state, None, dt)
    return state


# --------------------------------------------------------------------------------------------
# the state machine
# --------------------------------------------------------------------------------------------
def test_throttle_ramps_towards_its_target():
    s = press(DriveState(CFG), "w")
    assert s.target_throttle == pytest.approx(0.03) and s.throttle == 0.0  # the key moves the target only
    s = apply_key(s, None, 0.05)
    assert s.throttle == pytest.approx(0.015)  # 0.3 duty/s for 0.05 s
    s = run_for(s, 1.0)
    assert s.throttle == pytest.approx(0.03)  # reaches the target, no overshoot
    s = press(s, "up", "up", "up", "up")  # the arrow does the same as W
    assert s.target_throttle == pytest.approx(0.15)
    before = s.throttle
    s = apply_key(s, None, 0.1)
    assert s.throttle - before == pytest.approx(0.03)  # ramp-limited, not a jump


def test_limits_hold_however_many_keys():
    s = press(DriveState(CFG), *["w"] * 20)
    assert s.target_throttle == pytest.approx(0.15)
    s = run_for(s, 2.0)
    assert s.throttle == pytest.approx(0.15)
    s = press(s, *["s"] * 40)
    assert s.target_throttle == pytest.approx(-0.15)
    s = run_for(s, 2.0)
    assert s.throttle == pytest.approx(-0.15)
    s = press(s, *["a"] * 20)
    assert s.target_steering == pytest.approx(0.5)
    s = press(s, *["right"] * 40)
    assert s.target_steering == pytest.approx(-0.5)
    s = run_for(s, 2.0)
    assert s.steering == pytest.approx(-0.5)
    # whole steps, no drift from float sums: five up and five down is exactly zero
    s = press(DriveState(CFG), *["w"] * 5, *["s"] * 5, *["a"] * 3, *["d"] * 3)
    assert s.target_throttle == 0.0 and s.target_steering == 0.0


def test_steering_ramps_left_positive_and_centres():
    s = press(DriveState(CFG), "left", "a")
    assert s.target_steering == pytest.approx(0.2)  # + = left (REP-103)
    s = apply_key(s, None, 0.1)
    assert s.steering == pytest.approx(0.15)  # 1.5 rad/s
    s = run_for(s, 1.0)
    assert s.steering == pytest.approx(0.2)
    s = press(s, "c")
    assert s.target_steering == 0.0
    s = run_for(s, 1.0)
    assert s.steering == 0.0


def test_space_brakes_at_once_and_lights_the_brake_lamp():
    s = run_for(press(DriveState(CFG), "w", "w", "w"), 1.0)
    assert s.throttle == pytest.approx(0.09)
    s = press(s, "space")
    assert s.throttle == 0.0 and s.target_throttle == 0.0 and s.braking
    assert "brake" in lamps(s)
    s = run_for(s, 0.5)
    assert s.throttle == 0.0 and "brake" in lamps(s)
    s = press(s, "w")  # driving again releases the brake
    assert not s.braking and "brake" not in lamps(s)


def test_reverse_lamp_follows_the_applied_throttle():
    s = press(DriveState(CFG), "s")
    assert "reverse" not in lamps(s)  # not applied yet
    s = apply_key(s, None, 0.05)
    assert s.throttle < 0 and "reverse" in lamps(s)


def test_lamp_toggles_and_blinking_indicators():
    s = press(DriveState(CFG), "h")
    assert lamps(s) == ["headlamps"]
    s = press(s, "h")
    assert lamps(s) == []
    s = press(s, "z")  # left indicator: on in the first half of each 1/1.5 s period
    assert s.indicator == "left" and lamps(s) == ["left-indicators"]
    s = run_for(s, 0.4)
    assert lamps(s) == []
    s = run_for(s, 0.3)
    assert lamps(s) == ["left-indicators"]
    s = press(s, "x")  # right replaces left
    assert s.indicator == "right" and lamps(s) == ["right-indicators"]
    s = press(s, "x")
    assert s.indicator == "off"
    s = press(s, "e")
    assert s.indicator == "hazard" and lamps(s) == ["hazard"]
    s = press(s, ",", ".")
    assert s.indicator == "right"
    s = press(s, "e", "e")
    assert s.indicator == "off" and lamps(s) == []


def test_quit_and_interrupt_stop_the_command_and_freeze_the_state():
    s = run_for(press(DriveState(CFG), "w", "w", "a"), 1.0)
    q = press(s, "q")
    assert q.quit == "quit" and q.throttle == 0.0
    assert press(q, "w", "w").target_throttle == 0.0  # keys after quitting change nothing
    assert press(s, "Q").quit == "quit"  # Caps Lock does not matter
    assert press(s, "ctrl-c").quit == "interrupted"
    assert press(s, "ctrl-d").quit == "quit"
    assert press(s, "ctrl-z", "tab", "escape", "?").quit is None  # ignored keys
    assert press(s, "?").last_key == "?"


def test_bad_dt_and_bad_config_are_input_errors():
    with pytest.raises(InputError):
        apply_key(DriveState(CFG), None, -0.1)
    with pytest.raises(InputError):
        apply_key(DriveState(CFG), None, float("nan"))
    with pytest.raises(InputError, match="max throttle"):
        DriveConfig(max_throttle=0.0)
    with pytest.raises(InputError, match="throttle ramp"):
        DriveConfig(throttle_ramp=float("inf"))


# --------------------------------------------------------------------------------------------
# keys from a terminal
# --------------------------------------------------------------------------------------------
def test_key_decoder_letters_controls_and_arrows():
    d = KeyDecoder()
    assert d.feed(b"wA \x03\x04", 0.0) == ["w", "a", "space", "ctrl-c", "ctrl-d"]
    assert d.feed(b"\x1b[A\x1b[B\x1b[C\x1b[D", 0.0) == ["up", "down", "right", "left"]
    assert d.feed(b"\x1bOA\x1bOD", 0.0) == ["up", "left"]  # application cursor mode
    assert d.feed(b"\x1b[1;5C", 0.0) == ["right"]  # with a modifier
    assert d.feed(b"\x1b[15~q", 0.0) == ["q"]  # F5 dropped


def test_key_decoder_split_sequences_and_lone_escape():
    d = KeyDecoder(esc_timeout=0.05)
    assert d.feed(b"w\x1b", 0.0) == ["w"]
    assert d.feed(b"[", 0.01) == []
    assert d.feed(b"D", 0.02) == ["left"]
    assert d.feed(b"\x1b", 1.0) == []  # maybe the start of an arrow
    assert d.feed(b"", 1.01) == []
    assert d.feed(b"", 1.06) == ["escape"]  # no: a lone Escape
    assert d.feed(b"s", 1.07) == ["s"]


def test_cbreak_terminal_restores_the_settings():
    master, slave = os.openpty()
    try:
        before = termios.tcgetattr(slave)
        with cbreak_terminal(slave):
            mode = termios.tcgetattr(slave)
            assert not mode[3] & termios.ICANON and not mode[3] & termios.ECHO and not mode[3] & termios.ISIG
        assert termios.tcgetattr(slave) == before
        with pytest.raises(RuntimeError):
            with cbreak_terminal(slave):
                raise RuntimeError("boom")
        assert termios.tcgetattr(slave) == before
    finally:
        os.close(master)
        os.close(slave)


# --------------------------------------------------------------------------------------------
# the loop (in-process)
# --------------------------------------------------------------------------------------------
def scripted(script: list[tuple[float, list[str]]]):
    """keys(t): the keys of every script entry whose time has come, each once."""
    pending = list(script)

    def keys(t: float) -> list[str]:
        out = []
        while pending and pending[0][0] <= t:
            out += pending.pop(0)[1]
        return out

    return keys


def test_loop_drives_a_stepped_simulator_and_stops_it():
    car = open_car("sim", world="studio", seed=1)  # stepped: the loop advances it by dt per tick
    frames = []
    cfg = DriveConfig(max_throttle=0.15, throttle_ramp=3.0, steering_ramp=5.0)
    summary = keyboard_drive(
        car, cfg, keys=scripted([(0.0, ["w"] * 5 + ["a"]), (0.3, ["space"]), (0.35, ["q"])]),
        on_frame=frames.append, rate=100.0,
    )
    assert summary.reason == "quit" and summary.ticks >= 10  # late ticks on a busy machine are dropped, not burst
    assert summary.distance_m > 0.02 and summary.truth_distance_m > 0.02
    assert summary.heading_change_rad > 0.0  # steered left
    assert summary.keys == 8
    assert car.read().throttle == 0.0  # stopped
    assert max(f.state.throttle for f in frames) <= 0.15
    assert any("brake" in f.lamps for f in frames)
    assert all(isinstance(f.lidar, (tuple, str)) for f in frames)
    assert "drove" in summary.line() and "the car is stopped" in summary.line()


class _NoLidarCar(SimCar):
    def read_lidar(self):
        raise NotBuiltError("no LIDAR here")


class _DroppingCar(SimCar):
    """A car whose connection drops after some commands: every later call fails."""

    def __init__(self, *args, drop_after: int = 10, **kw):
        super().__init__(*args, **kw)
        self.calls = 0
        self.drop_after = drop_after
        self.stop_tried = False

    def _apply(self, cmd):
        self.calls += 1
        if self.calls > self.drop_after:
            raise CarError("tcp://car:1: the connection to the car was lost")
        super()._apply(cmd)

    def stop(self):
        self.stop_tried = True
        super().stop()


def test_loop_shows_na_without_lidar_and_ends_at_end_of_input():
    car = _NoLidarCar(seed=0)
    frames = []
    calls = iter([["w"], [], [], None])
    summary = keyboard_drive(car, CFG, keys=lambda t: next(calls), on_frame=frames.append, rate=200.0)
    assert summary.reason == "terminal closed"
    assert frames and all(f.lidar == "n/a" for f in frames)


def test_loop_lost_connection_raises_car_error_after_trying_to_stop():
    car = _DroppingCar(seed=0, drop_after=5)
    with pytest.raises(CarError, match="lost"):
        keyboard_drive(car, CFG, keys=lambda t: ["w"], rate=200.0)
    assert car.stop_tried


def test_loop_ends_on_sigint_and_restores_the_handler():
    car = _NoLidarCar(seed=0)
    before = signal.getsignal(signal.SIGINT)
    sent = []

    def keys(t: float) -> list[str]:
        if t > 0.05 and not sent:
            sent.append(t)
            os.kill(os.getpid(), signal.SIGINT)  # as `kill -INT` would: no KeyboardInterrupt
        return ["w"]

    summary = keyboard_drive(car, CFG, keys=keys, rate=200.0)
    assert summary.reason == "interrupted" and summary.signal == signal.SIGINT
    assert signal.getsignal(signal.SIGINT) is before
    assert car.read().throttle == 0.0


def test_nearest_obstacle_and_world_map():
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ranges = np.array([0.0, 2.0, 1.5, 0.0, 0.7, 3.0, 0.0, 0.0])
    rng, bearing = nearest_obstacle(LidarScan(0.0, angles, ranges))
    assert rng == 0.7 and abs(bearing) == pytest.approx(math.pi)  # behind
    assert nearest_obstacle(LidarScan(0.0, angles, np.zeros(8))) == "none"

    from qcarlab.sim.world import load_world

    world = load_world("studio")
    grid = world_map(world, cols=40, rows=16)
    assert grid.cols <= 40 and grid.rows <= 16 and grid.rgb.dtype == np.uint8
    assert grid.solid[0].any() and grid.solid[-1].any()  # the room's walls, top and bottom
    assert grid.pixel_of(*world.start[:2]) is not None
    assert grid.pixel_of(1e3, 0.0) is None


# --------------------------------------------------------------------------------------------
# the command, through a pseudo-terminal
# --------------------------------------------------------------------------------------------
SUMMARY = re.compile(r"drove ([0-9.]+) m in ([0-9.]+) s .*heading change ([+-][0-9]+) deg; the car is stopped")


def test_drive_the_simulator_through_a_pty():
    run = PtyRun("keyboard-drive", "--car", "sim", "--world", "studio")
    run.wait_for("speed")  # the live panel is up: keys are read now
    mode = termios.tcgetattr(run.slave)
    assert not mode[3] & termios.ICANON and not mode[3] & termios.ECHO  # keys, not lines
    run.send(b"wwwww", 0.5)
    run.send(b"\x1b[D\x1b[D", 0.3)  # left arrow twice
    run.send(b"h ", 0.1)  # headlamps, brake
    run.send(b"q")
    rc = run.finish()
    text = run.text
    assert rc == 0, text[-2000:]
    assert run.after == run.before  # the terminal is as it was
    m = SUMMARY.search(text)
    assert m, text[-2000:]
    assert float(m.group(1)) > 0.05  # it drove
    assert int(m.group(3)) > 0  # and turned left
    assert "nearest" in text and "battery" in text  # the panel showed the readings
    assert "Traceback" not in text


def test_ctrl_c_stops_and_restores_the_terminal():
    run = PtyRun("keyboard-drive", "--world", "track", "--no-map")
    run.wait_for("speed")
    run.send(b"ww", 0.05)
    run.send(b"\x03")  # a key, not a signal: the terminal's ISIG is off while driving
    rc = run.finish()
    assert rc == 130, run.text[-2000:]
    assert run.after == run.before
    assert "the car is stopped" in run.text
    assert "Traceback" not in run.text


def test_lost_connection_restores_the_terminal_and_says_so():
    server = subprocess.Popen(
        [sys.executable, "-m", "qcarlab", "serve", "--backend", "sim", "--on-floor", "--port", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
    )
    try:
        ready, _, _ = select.select([server.stdout], [], [], 30.0)  # a start under load, not a timing
        assert ready, "the server did not start"
        line = server.stdout.readline()
        uri = re.search(r"tcp://[0-9.]+:[0-9]+", line)
        assert uri, line
        run = PtyRun("keyboard-drive", "--car", uri.group(0))
        run.wait_for("speed")
        run.send(b"www", 0.2)
        server.kill()  # the connection drops under the driver
        rc = run.finish()
    finally:
        if server.poll() is None:
            server.kill()
        server.wait(5)
        server.stdout.close()
    text = run.text
    assert rc == 1, text[-2000:]
    assert run.after == run.before
    errors = [ln for ln in text.splitlines() if "error:" in ln]
    assert len(errors) == 1 and "keyboard-drive" in errors[0] and uri.group(0) in errors[0], text[-2000:]
    assert "Traceback" not in text


def test_refuses_without_a_tty():
    proc = subprocess.run(
        [sys.executable, "-m", "qcarlab", "keyboard-drive"],
        stdin=subprocess.DEVNULL, capture_output=True, text=True, cwd=REPO, timeout=20,
    )
    assert proc.returncode == 2
    assert proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "keyboard-drive needs an interactive terminal" in lines[0]


def test_help_teaches_the_keys(cli):
    code, out, _ = cli("keyboard-drive", "--help")
    assert code == 0
    for word in ("Space", "brake", "headlamps", "indicator", "hazard", "Ctrl-C", "--max-throttle", "--ramp"):
        assert word in out
