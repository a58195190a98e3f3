"""The grader's own rules of trust (issue 26), on any machine: the grader's failures are retried and
never scored, results need their invocation record, ``--sandbox required`` refuses without a
sandbox, images are size-checked before decoding, outputs never follow a planted link."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import pytest

from qcarlab.errors import InputError
from qcarlab.grading import runner
from qcarlab.grading.grader import Options, Planned, grade, summary
from qcarlab.grading.sheet import MetricCriterion, Sheet, Task


class Commands:
    def parse(self, argv):
        from qcarlab.cli.invocation import parse_command

        return parse_command(argv)

    def accepts(self, argv, option):
        from qcarlab.cli.invocation import command_accepts

        return command_accepts(argv, option)


def planned() -> Planned:
    task = Task("run", command="qcarlab stop-sign", uses=(), criteria=[MetricCriterion("stopped", min=1)])
    return Planned("ann", Sheet("s", Path("s.yaml"), "s", "5.2", "stop-sign", [task]), task, None)


def test_a_task_the_grader_failed_is_run_again_and_never_scored(monkeypatch):
    calls = []

    def attempt(job, warm, cpu):
        calls.append(warm)
        return {"status": "infrastructure", "reason": "the task's process was killed from outside (SIGKILL)",
                "seconds": 0.5}

    monkeypatch.setattr(runner, "_attempt", attempt)
    job = runner.Job(("ann", "s", "run"), "scenario", {"timeout": 5, "memory_mb": 512, "output_mb": 1})
    outcome = runner.execute(job, warm="zygote")
    assert calls == ["zygote", None]  # once more, cold
    assert outcome["status"] == "infrastructure" and outcome["reason"].startswith("not graded: the grader failed twice")
    row = grade(planned(), outcome, Commands())
    assert row["status"] == "error" and row["earned"] == 0 and row["problem"].startswith("not graded")
    totals = summary([row])
    assert totals == {"passed": 0, "total": 0, "skipped": 0, "errors": 1, "points": 0, "max_points": 0}

    answers = iter([{"status": "infrastructure", "reason": "zygote gone", "seconds": 0.1},
                    {"status": "ok", "reason": None, "seconds": 1.0, "results": {}}])
    monkeypatch.setattr(runner, "_attempt", lambda job, warm, cpu: next(answers))
    assert runner.execute(job)["status"] == "ok"


def test_a_killed_task_process_is_the_graders_failure_not_out_of_memory(tmp_path):
    job = runner.Job(("ann", "s", "run"), "scenario", {"timeout": 5, "memory_mb": 512, "output_mb": 1},
                     argv=["stop-sign", "--block", "stop_sign=submission/s.py:stop_sign"])
    for name in ("stdout.txt", "stderr.txt"):
        (tmp_path / name).write_text("")
    outcome = runner._classify(job, runner.Limits(5, 512, 1), -9, False, tmp_path, tmp_path / "results.json",
                               tmp_path / "stdout.txt", tmp_path / "stderr.txt")
    assert outcome["status"] == "infrastructure" and "memory" not in outcome["reason"]
    assert outcome["reason"] == "the task's process was killed from outside (SIGKILL)"


def test_results_without_their_invocation_record_are_refused():
    outcome = {"status": "ok", "reason": None, "seconds": 1.0, "results": {"stopped": 1, "stop_distance_m": 0.2}}
    row = grade(planned(), outcome, Commands())
    assert row["status"] == "failed" and row["earned"] == 0
    assert row["problem"].startswith("the results do not record the command that made them")


def test_sandbox_required_refuses_where_there_is_none(cli, tmp_path, monkeypatch):
    from qcarlab.sandbox import jail

    monkeypatch.setattr(jail, "_probed", ["the sandbox needs Linux (this is plan9)"])
    code, out, err = cli("grade", "stop-sign", "--submission", tmp_path, "--sandbox", "required")
    assert code == 2
    assert "--sandbox required: the sandbox needs Linux (this is plan9)" in err
    assert len([ln for ln in err.splitlines() if ln.strip()]) == 1
    code, out, err = cli("grade", "stop-sign", "--sandbox", "maybe")
    assert code == 2 and "--sandbox must be required, auto or off" in err


def png_header(width: int, height: int) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    return b"\x89PNG\r\n\x1a\n" + chunk + b"\x00" * 64


def test_an_image_is_size_checked_before_it_is_decoded(tmp_path):
    from qcarlab.grading.report import thumbnail
    from qcarlab.media import check_image_size, image_size, read_image

    bomb = png_header(30_000, 30_000)
    assert image_size(bomb) == (30_000, 30_000)
    with pytest.raises(InputError, match="30000 x 30000 px, over the 50 megapixels"):
        check_image_size(bomb, "x.png")
    assert thumbnail(bomb) == ("image/png", bomb)  # shown as it is, never decoded
    (tmp_path / "bomb.png").write_bytes(bomb)
    with pytest.raises(InputError, match="bomb.png: the image is 30000 x 30000 px"):
        read_image(tmp_path / "bomb.png")
    (tmp_path / "map.pgm").write_bytes(b"P5\n# a map\n100000 100000\n255\n" + b"\x00" * 16)
    assert image_size((tmp_path / "map.pgm").read_bytes()) == (100_000, 100_000)
    import cv2
    import numpy as np

    ok, jpg = cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8))
    assert ok and image_size(jpg.tobytes()) == (64, 48)


def test_outputs_replace_a_planted_link_and_never_write_through_it(tmp_path):
    from qcarlab.record import inner_folder, write_bytes

    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "grades"
    out.mkdir()
    (out / "gradebook.csv").symlink_to(victim)
    (out / "alice").symlink_to(tmp_path)  # a folder link on the way
    write_bytes(out / "gradebook.csv", b"student,total\n")
    folder = inner_folder(out, "alice", "stop-sign")
    write_bytes(folder / "grade.json", json.dumps({}).encode())
    assert victim.read_text() == "precious"
    assert not (out / "gradebook.csv").is_symlink() and (out / "gradebook.csv").read_bytes() == b"student,total\n"
    assert not (out / "alice").is_symlink() and not (tmp_path / "stop-sign").exists()


def test_options_default_to_auto():
    assert Options().sandbox == "auto" and runner.Job(("a", "b", "c"), "block", {}).sandbox == "auto"


def test_a_block_in_the_students_process_fails_as_one_run_here_would(tmp_path):
    """The same one-line messages whether the block raised in this process or in the student's:
    NotImplementedError (not filled in), sys.exit, an exception with the student's own lines."""
    import os

    from qcarlab.blocks import StudentBlock, StudentBlockError
    from qcarlab.experiments.labs import find_lab
    from qcarlab.sandbox.client import BlockHost, HostPlan

    if not hasattr(os, "fork"):
        pytest.skip("the student's process is forked")
    spec = {b.name: b for b in find_lab("stop-sign").blocks}["stop_sign"]
    src = tmp_path / "submission"
    src.mkdir()
    (src / "stop_sign.py").write_text(
        "import sys\n\ndef stop_sign(d, v):\n    if d > 1:\n        raise NotImplementedError('far')\n"
        "    if d < 0:\n        sys.exit(3)\n    return 1 / 0\n")
    local_ns: dict = {}
    exec(compile((src / "stop_sign.py").read_text(), str(src / "stop_sign.py"), "exec"), local_ns)
    host = BlockHost.start(HostPlan(tmp_path, src, tmp_path / "o.txt", tmp_path / "e.txt", sandbox=False))
    try:
        remote = host.load(src / "stop_sign.py")["stop_sign"]
        said = []
        for target in (local_ns["stop_sign"], remote):
            block = StudentBlock(spec, target, "stop_sign.py:stop_sign", src / "stop_sign.py").start()
            got = []
            for d in (2.0, -1.0, 0.5):
                with pytest.raises((InputError, StudentBlockError)) as exc:
                    block(d, 0.5)
                got.append(str(exc.value))
            said.append(got)
    finally:
        host.close()
    assert said[0] == said[1]
    assert "stop_sign is not filled in yet" in said[0][0] and "called sys.exit(3)" in said[0][1]
    assert "stop_sign.py:8 in stop_sign" in said[0][2] and said[0][2].endswith("raised ZeroDivisionError: division by zero")
