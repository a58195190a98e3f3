"""The car-side server on the cars' own Pythons (3.6 on a QCar 1, 3.8 on a QCar 2), as a user
runs it: it compiles, its selfcheck passes against the strict fake, it serves a dry run that the
laptop's ping, io-test, lidar-scan and keyboard-drive (Python >= 3.11) talk to, and it serves the
fake hardware of each car. Skipped where this machine has no such Python (.ci/run makes them)."""

from __future__ import annotations

import json
import re
import subprocess

import pytest
from onboard_support import SELFCHECK, SERVER, Served, fake_env, journal, need_python

from qcarlab.car.tcp import TcpCar
from qcarlab.onboard import write_server

PYTHONS = ["3.6", "3.8"]


@pytest.mark.parametrize("version", PYTHONS)
def test_it_compiles_and_answers_on_the_cars_python(version, tmp_path):
    python = need_python(version)
    written = write_server(tmp_path / "qcarlab_car_server.py")  # what a user copies to the car
    subprocess.run([python, "-m", "py_compile", str(written)], check=True, timeout=60)
    out = subprocess.run([python, str(written), "--version"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip().startswith("qcarlab-car-server")
    token = subprocess.run([python, str(written), "--new-token"], capture_output=True, text=True, timeout=60)
    assert token.returncode == 0 and len(token.stdout.strip()) >= 32
    bad = subprocess.run([python, str(written), "--port", "nope"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("version", PYTHONS)
def test_the_selfcheck_passes_on_the_cars_python(version):
    python = need_python(version, numpy=True)
    proc = subprocess.run([python, str(SELFCHECK), str(SERVER)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-2000:]
    assert re.search(r"selfcheck on Python %s\.\d+: (\d+) of \1 checks passed" % re.escape(version), proc.stdout)


@pytest.mark.parametrize("version", PYTHONS)
def test_the_laptop_talks_to_a_dry_run_on_the_cars_python(version, cli, tmp_path):
    python = need_python(version)  # the dry run needs no NumPy
    written = write_server(tmp_path / "qcarlab_car_server.py")
    with Served(python, "--dry-run", "--port", "0", "--car-type", "2", script=written) as car:
        assert "QCar 2 (dry run" in car.line
        code, out, err = cli("ping", car.uri, "--count", "3", "--interval", "0")
        assert code == 0, err
        assert "backend dry-run" in out and "3 received, 0% loss" in out and "battery 12.00 V" in out
        code, out, err = cli("io-test", "--car", car.uri, "--duration", "0.5", "--throttle", "0.1", "--json")
        assert code == 0, err
        io = json.loads(out)
        assert io["encoder_counts"] == 0 and io["battery_v"] == 12.0  # a stationary car
        code, out, err = cli("lidar-scan", "--car", car.uri, "--json")
        assert code == 0, err
        scan = json.loads(out)
        assert scan["points_with_return"] == 720 and scan["nearest_obstacle_m"] == pytest.approx(1.5)
        with TcpCar(car.host, car.port) as remote:  # the served car's parameters reach the laptop
            assert remote.params.motor_kt == 0.0047 and remote.steering_limit == 0.5
        code, out, err = car.stop()
    assert code == 0 and "the car is stopped" in out


@pytest.mark.parametrize("version", PYTHONS)
def test_keyboard_drive_against_a_dry_run_on_the_cars_python(version):
    from ptyrun import PtyRun

    python = need_python(version)
    with Served(python, "--dry-run", "--port", "0") as car:
        run = PtyRun("keyboard-drive", "--car", car.uri, "--no-map")
        run.wait_for("speed")
        run.send(b"ww", 0.3)
        run.send(b"h ", 0.2)
        run.send(b"q")
        rc = run.finish()
        assert rc == 0, run.text[-2000:]
        assert "the car is stopped" in run.text and "Traceback" not in run.text
        assert run.after == run.before


@pytest.mark.parametrize("version,car_type", [("3.6", 1), ("3.8", 2)])
def test_the_cars_python_serves_its_fake_hardware(version, car_type, tmp_path):
    python = need_python(version, numpy=True)
    log = tmp_path / "board.jsonl"
    with Served(python, "--port", "0", env=fake_env(car_type, log)) as car:
        assert f"QCar {car_type}" in car.line and "board watchdog: yes" in car.line
        with TcpCar(car.host, car.port) as remote:
            assert remote.identity().extra["car_type"] == car_type
            remote.write(0.2, 0.3, ["brake"])
            r = remote.read()
            assert r.battery_voltage == (11.8 if car_type == 1 else 15.2)
            scan = remote.read_lidar()
            assert scan.angles.size in (0, 5)
        code, out, err = car.stop()
    assert code == 0, err[-2000:]
    writes = [e for e in journal(log) if e["event"] == "write"]
    throttle = ("pwm", "0") if car_type == 1 else ("other", "11000")
    sign = -1.0 if car_type == 1 else 1.0
    assert any(w[throttle[0]].get(throttle[1]) == pytest.approx(sign * 0.2) for w in writes)
    assert writes[-1][throttle[0]][throttle[1]] == 0.0  # stopped on the way out
    assert journal(log)[-1]["event"] in ("close", "lidar_close")
