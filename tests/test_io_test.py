"""``qcarlab io-test`` as a user runs it (lab sheet 3.3), and the Car API's command checks."""

from __future__ import annotations

import csv
import json
import logging

import pytest

import qcarlab
from qcarlab.car.lamps import LAMP_NAMES, parse_lamps
from qcarlab.errors import InputError


def test_on_floor_encoder_speed_matches_truth(cli_json):
    res = cli_json("io-test", "--on-floor", "--throttle", "0.1", "--duration", "2")
    assert res["mean_speed_mps"] > 0.2
    assert res["mean_speed_mps"] == pytest.approx(res["truth"]["mean_speed_mps"], rel=0.02)
    assert res["distance_m"] == pytest.approx(res["truth"]["distance_m"], rel=0.02)
    for key in ("encoder_counts", "motor_current_a", "battery_v", "leds_on"):
        assert key in res
    assert 10.0 < res["battery_v"] < 12.6


def test_same_seed_prints_identical_json(cli):
    args = ("io-test", "--on-floor", "--throttle", "0.1", "--duration", "2", "--seed", "5", "--json")
    first, second = cli(*args), cli(*args)
    assert first[0] == 0 and first[1] == second[1]
    other = cli(*args[:-2], "--seed", "6", "--json")
    assert other[1] != first[1]  # the seed really drives the noise


def test_on_stand_encoder_counts_but_car_stays(cli_json):
    res = cli_json("io-test", "--throttle", "0.1", "--duration", "1")  # --on-stand is the default
    assert res["on_stand"] is True
    assert res["encoder_counts"] > 10_000 and res["mean_speed_mps"] > 0.5
    assert res["truth"]["distance_m"] == 0.0 and res["truth"]["mean_speed_mps"] == 0.0


def test_lamps_are_reported(cli_json):
    res = cli_json("io-test", "--leds", "brake,headlamps,user2", "--duration", "0.2")
    assert res["leds_on"] == ["brake", "headlamp_left", "headlamp_right", "user2"]


def test_out_writes_results_and_log(cli, tmp_path):
    code, out, err = cli("io-test", "--on-floor", "--duration", "0.5", "--out", tmp_path / "run")
    assert code == 0, err
    results = json.loads((tmp_path / "run" / "results.json").read_text())
    rows = list(csv.DictReader((tmp_path / "run" / "log.csv").open()))
    assert len(rows) == 50  # 0.5 s at 100 Hz
    assert float(rows[-1]["encoder_counts"]) <= results["encoder_counts"]
    assert "mean speed" in out  # the human summary


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--throttle", "nan"), "throttle must be a finite number"),
        (("--steering", "inf"), "steering must be a finite number"),
        (("--leds", "brake,fog"), "unknown lamp 'fog'"),
        (("--duration", "-1"), "--duration must be in (0, 3600] s"),
        (("--throttle", "abc"), "--throttle"),
        (("--car", "udp://x"), "expected 'sim' or 'tcp://HOST:PORT'"),
        (("--rate", "0"), "--rate"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(cli, args, message):
    code, out, err = cli("io-test", *args)
    assert code == 2
    assert message in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert out == ""


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("rolling_resistance: [1,\n", "line 2"),
        ("mass: heavy\n", "'mass' must be a finite number"),
        ("wheelbase_typo: 1\n", "unknown parameter 'wheelbase_typo'"),
        ("- 1\n- 2\n", "expected a mapping"),
    ],
)
def test_malformed_parameter_file(cli, tmp_path, text, message):
    path = tmp_path / "car.yaml"
    path.write_text(text)
    code, _, err = cli("io-test", "--params", path)
    assert code == 2 and message in err and str(path) in err
    assert len(err.strip().splitlines()) == 1


def test_parameter_file_changes_the_car(cli_json, tmp_path):
    path = tmp_path / "weak_battery.yaml"
    path.write_text("battery_soc0: 0.05\n")
    res = cli_json("io-test", "--params", path, "--duration", "0.2")
    assert res["battery_v"] < 10.6 and res["battery_low"] is True


def test_help_lists_every_subcommand(cli):
    code, out, _ = cli("--help")
    assert code == 0
    for name in ("ping", "io-test", "keyboard-drive", "lidar-scan", "camera", "path-gen", "path-follow",
                 "stop-sign", "lane-follow", "avoid", "serve", "grade"):
        assert name in out


def test_commands_are_clamped_and_reported_once(caplog):
    with caplog.at_level(logging.WARNING, logger="qcarlab"):  # conftest: the logger propagates in a test
        with qcarlab.open_car("sim") as car:
            assert car.write(0.9, -2.0).throttle == 0.3
            assert car.write(0.9, -2.0).steering == pytest.approx(-0.5)  # the servo's +-0.5 rad
            assert car.write(-0.5, 0.0).throttle == -0.3
    messages = [r.getMessage() for r in caplog.records]
    assert sum("throttle" in m for m in messages) == 1
    assert sum("steering" in m for m in messages) == 1


def test_non_finite_commands_are_refused_and_car_keeps_last_safe_command():
    with qcarlab.open_car("sim") as car:
        car.write(0.1, 0.0)
        with pytest.raises(InputError):
            car.write(float("nan"), 0.0)
        assert car.read().throttle == 0.1


def test_leaving_the_with_block_stops_the_car():
    car = qcarlab.open_car("sim")
    with car:
        car.write(0.2, 0.1)
        car.advance(1.0)
    assert car.read().throttle == 0.0 and car.read().steering == 0.0


def test_lamp_parsing():
    assert parse_lamps("hazard") == parse_lamps(["left-indicators", "right-indicators"])
    assert sum(parse_lamps("all")) == len(LAMP_NAMES)
    assert parse_lamps({"brake": 0.5})[0] == 0.5
    with pytest.raises(InputError):
        parse_lamps({"brake": 2.0})


def test_an_out_that_is_a_file_is_refused_before_the_run(cli, tmp_path):
    blocker = tmp_path / "results"
    blocker.write_text("not a folder")
    code, out, err = cli("io-test", "--duration", "30", "--out", blocker)
    assert code == 2 and "is not a folder" in err and out == ""
    assert blocker.read_text() == "not a folder"  # nothing lost
