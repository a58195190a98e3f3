"""Inputs that ended in "internal error" (issue 30, item 5): each is one line naming what is wrong,
exit 2, and bounded work; and path-gen never writes outside --out (item 6)."""

from __future__ import annotations

import pytest


def one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "internal error" not in lines[0], err
    return lines[0]


def test_a_path_shorter_than_the_look_ahead_is_refused(cli, tmp_path):
    short = tmp_path / "short.csv"
    short.write_text("x,y\n0,0\n0,-0.11\n")
    code, out, err = cli("path-follow", short)
    assert code == 2
    assert "the path is 0.110 m long; a path to follow must be longer than" in one_error_line(err)


@pytest.mark.parametrize("args, says", [
    (("io-test", "--duration", "1e308"), "--duration must be in (0, 3600] s, got 1e+308"),
    (("io-test", "--duration", "nan"), "--duration must be in (0, 3600] s"),
    (("path-follow", "line", "--points", "1000000000"), "points must be a whole number from 2 to 100,000"),
    (("path-gen", "line", "--points", "100001"), "points must be a whole number from 2 to 100,000"),
    (("path-gen", "circle", "--step", "1e-9"), "makes more than 100,000 points"),
])
def test_absurd_sizes_are_refused_at_once(cli, args, says):
    code, out, err = cli(*args)
    assert code == 2 and says in one_error_line(err)


def test_path_gen_never_writes_outside_its_folder(cli, tmp_path):
    out = tmp_path / "paths"
    for name in ("../../escape", "sub/p", "..", "a\\b"):
        code, _, err = cli("path-gen", "circle", "--name", name, "--out", out)
        assert code == 2 and "--name must be a file name without a folder" in one_error_line(err)
    assert not any(tmp_path.parent.glob("escape*")) and not out.exists()
    code, _, err = cli("path-gen", "circle", "--name", "mine", "--out", out)
    assert code == 0 and (out / "mine.csv").is_file()


def test_an_out_folder_name_too_long_for_the_file_system_is_one_line(cli, tmp_path):
    code, out, err = cli("path-gen", "circle", "--out", tmp_path / ("a" * 300))
    assert code == 2 and "File name too long" in one_error_line(err)


def test_a_parameter_file_not_utf8_or_nested_thousands_deep_is_one_line(cli, tmp_path):
    utf16 = tmp_path / "p16.yaml"
    utf16.write_bytes("lab:\n  kp: 0.5\n".encode("utf-16"))
    deep = tmp_path / "deep.yaml"
    deep.write_text("lab: " + "[" * 3000 + "]" * 3000 + "\n")
    code, _, err = cli("stop-sign", "--params", utf16)
    assert code == 2 and "p16.yaml: the parameter file is not UTF-8 text" in one_error_line(err)
    code, _, err = cli("stop-sign", "--params", deep)
    assert code == 2 and "deep.yaml: nested too deep to read" in one_error_line(err)


def test_a_template_where_it_cannot_be_written_and_a_path_of_huge_numbers(cli, tmp_path):
    code, _, err = cli("template", "stop-sign", "--out", "/proc/qcarlab-not-here")
    assert code == 2 and "cannot write the workspace there" in one_error_line(err)
    huge = tmp_path / "huge.csv"
    huge.write_text("x,y\n0,0\n1e308,-1e308\n")
    code, _, err = cli("path-follow", huge)
    assert code == 2 and "huge.csv point 2: (1e+308, -1e+308) m is beyond +-10,000 m" in one_error_line(err)


def test_a_ros_map_whose_header_claims_a_huge_image_is_refused_before_decoding(cli, tmp_path):
    (tmp_path / "map.pgm").write_bytes(b"P5\n100000 100000\n255\n" + b"\x00" * 64)
    (tmp_path / "map.yaml").write_text("image: map.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 0\n"
                                       "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
    code, _, err = cli("lidar-scan", "--world", tmp_path / "map.yaml")
    assert code == 2 and "100000 x 100000 px, over the 50 megapixels" in one_error_line(err)


@pytest.mark.parametrize("command", [("stop-sign", "--car"), ("io-test", "--car"), ("ping",), ("grade", "stop-sign", "--car")])
def test_car_addresses_are_checked_alike_by_every_command(cli, command):
    for address, says in (("tcp://[::1", "unclosed '[' in the address"),
                          ("tcp://::1:18960", "IPv6 addresses go in brackets"),
                          ("tcp://", "expected tcp://HOST:PORT")):
        code, _, err = cli(*command, address)
        assert code == 2 and says in one_error_line(err), (command, address, err)


def test_a_damaged_image_or_video_is_our_one_line_without_opencvs_noise(tmp_path):
    """Run as a user runs it (a fresh process: OpenCV and ffmpeg write to the real stderr)."""
    import os
    import struct
    import subprocess
    import sys
    import zlib

    ihdr = struct.pack(">IIBBBBB", 64, 48, 8, 2, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    (tmp_path / "bad.png").write_bytes(png + b"garbage" * 20)
    (tmp_path / "bad.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + b"junk" * 100)
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENCV_")}
    for name, says in (("bad.png", "cannot read this image"), ("bad.mp4", "cannot open this video")):
        done = subprocess.run([sys.executable, "-m", "qcarlab", "detect", "lanes", str(tmp_path / name)],
                              capture_output=True, text=True, env=env, timeout=120)
        assert done.returncode == 2 and says in one_error_line(done.stderr), done.stderr


def test_replay_info_of_a_recording_cut_before_its_first_message_says_so(cli, tmp_path):
    pytest.importorskip("mcap")
    rec = tmp_path / "r.mcap"
    code, _, err = cli("io-test", "--duration", "0.5", "--record", rec)
    assert code == 0, err
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(rec.read_bytes()[:100])
    code, out, err = cli("replay", "info", cut)
    assert code == 2 and "cut.mcap: the recording was cut off before its first message" in one_error_line(err)


def test_results_and_log_have_the_modes_of_the_figures_beside_them(cli, tmp_path):
    import stat

    out = tmp_path / "run"
    code, _, err = cli("io-test", "--duration", "0.5", "--out", out)
    assert code == 0, err
    modes = {f.name: stat.S_IMODE(f.stat().st_mode) for f in out.iterdir()}
    assert modes["results.json"] == modes["log.csv"] and modes["results.json"] & 0o044 == 0o044, modes


def test_a_run_killed_before_saving_never_leaves_an_earlier_runs_results_looking_like_its_own(cli, tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "runs" / "drive"
    code, _, err = cli("io-test", "--on-floor", "--throttle", "0.1", "--duration", "0.5", "--out", out)
    assert code == 0 and not (out / "run-in-progress.txt").exists(), err
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.Popen([sys.executable, "-m", "qcarlab", "io-test", "--on-floor", "--throttle", "0.1",
                             "--duration", "60", "--realtime", "--out", str(out)], env=env, cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while not (out / "run-in-progress.txt").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    marker = (out / "run-in-progress.txt").read_text()
    assert "io-test" in marker and "has not saved its results" in marker
    sheet = tmp_path / "sheet.yaml"
    sheet.write_text("title: t\nlab: io-test\ntasks:\n  - id: drive\n    command: qcarlab io-test --on-floor "
                     "--throttle 0.1 --duration 0.5\n    criteria:\n      mean_speed_mps: {min: 0.0}\n")
    code, stdout, err = cli("grade", sheet, "--results", tmp_path / "runs", "--json")
    import json

    problem = json.loads(stdout)["tasks"][0]["problem"]
    assert code == 1 and "a run started there after these results and did not save its own" in problem
