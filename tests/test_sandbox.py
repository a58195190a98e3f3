"""The grade is the student's: every attack a cheating student tried on ``qcarlab grade`` (issue 26)
fails to change a grade or an output, and no student can hurt a classmate.

Each attack is a submission that tries it and otherwise behaves like an honest block that never
stops at the sign (or a correct one, where the attack is on a classmate); the test checks that the
grade is exactly what that honest code deserves, that the classmates' grades did not move, and
that nothing outside the student's sandbox changed. They need the sandbox (Linux, root, namespaces:
CI has them) and skip elsewhere, saying why.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

from qcarlab.sandbox.jail import BASE_UID, probe

from tests.grading_submissions import correct_submission, write_block

WHY = probe()
pytestmark = pytest.mark.skipif(WHY is not None, reason=f"no sandbox here: {WHY}")

NEVER_STOPS = "def stop_sign(distance_to_sign, desired_speed):\n    return desired_speed\n"
HONEST = "def stop_sign(distance_to_sign, desired_speed):\n    return 0.0 if 0.05 < distance_to_sign < 0.40 else desired_speed\n"
SHEET = """\
title: sandbox
lab: stop-sign
tasks:
  - id: block
    block: stop_sign
    cases:
      - {args: [0.30, 0.5], expect: 0.0}
      - {args: [0.02, 0.5], expect: 0.5}
  - id: run
    command: qcarlab stop-sign
    uses: [stop_sign]
    criteria:
      stopped: {min: 1}
      stop_distance_m: {min: 0.05, max: 0.40}
"""


def student(root: Path, name: str, source: str) -> Path:
    folder = correct_submission(root / name, ("stop-sign",)) / "stop-sign"
    write_block(folder, "stop_sign.py", source)
    return folder


def grade_class(cli, tmp_path: Path, students: dict[str, str], *extra: str) -> dict[str, dict]:
    sheet = tmp_path / "private" / "sheet.yaml"  # the instructor's private sheet
    sheet.parent.mkdir(exist_ok=True)
    sheet.write_text(SHEET)
    root = tmp_path / "class"
    for name, source in students.items():
        student(root, name, source)
    done = installed("grade", sheet, "--class", root, "--out", tmp_path / "grades", "--jobs", "2",
                     "--sandbox", "required", "--timeout", "60", "--memory", "1024", "--json", *extra, cwd=tmp_path)
    assert done.returncode in (0, 1), done.stderr
    report = json.loads(done.stdout)
    assert report["sandbox"]["sandboxed"] is True
    return {s["student"]: {t["id"]: t for t in s["tasks"]} | {"_entry": s} for s in report["students"]}


def installed(*args: object, cwd: Path) -> subprocess.CompletedProcess:
    """``qcarlab ARGS`` as an instructor's CI runs it: the installed qcarlab (in CI a non-editable
    install), from a folder that is not the checkout."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run([sys.executable, "-m", "qcarlab", *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


def installed_file(module: str, cwd: Path) -> Path:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return Path(subprocess.run([sys.executable, "-c", f"import {module} as m; print(m.__file__)"], cwd=cwd, env=env,
                               capture_output=True, text=True, check=True).stdout.strip())


def attack(body: str, **paths: Path) -> str:
    """A block file that runs ``body`` when it is loaded (with the paths it aims at), then never stops."""
    head = "".join(f"{k.upper()} = {str(v)!r}\n" for k, v in paths.items())
    return "import os, sys, json, glob, signal, time\n" + head + textwrap.dedent(body) + "\n" + NEVER_STOPS


def student_processes() -> set[int]:
    """The pids of the processes running as a student's user (of this test or, under xdist, of
    another worker's grading)."""
    out = subprocess.run(["ps", "-eo", "uid=,pid="], capture_output=True, text=True).stdout.split()
    return {int(p) for u, p in zip(out[::2], out[1::2]) if u.isdigit() and int(u) >= BASE_UID}


def no_student_processes_left(wait: float = 20.0) -> bool:
    """No process that ran as a student's user when the grader finished is still running ``wait``
    s later (another xdist worker's tasks end within their limits, a few seconds; an escaped
    daemon of this test's would live a minute); True as soon as they have all gone."""
    import time

    left, deadline = student_processes(), time.monotonic() + wait
    while left and time.monotonic() < deadline:
        time.sleep(0.2)
        left &= student_processes()
    return not left


def deserved(grades: dict) -> None:
    """What a block that never stops deserves: 1 of 2 cases, a run that does not stop."""
    assert [c["passed"] for c in grades["block"]["criteria"]] == [False, True], json.dumps(grades["block"])
    assert grades["run"]["status"] == "failed"
    assert grades["run"]["criteria"][0]["value"] == 0  # stopped = 0: the simulator ran, untouched


def honest(grades: dict) -> None:
    assert grades["block"]["passed"] and grades["run"]["passed"], json.dumps(
        {k: {"problem": t.get("problem"), "reasons": [c.get("reason") for c in t.get("criteria") or []]}
         for k, t in grades.items() if k != "_entry"})  # (what failed, in full: pytest cuts a long dict short)


def test_forging_the_results_patching_qcarlab_and_reading_the_sheets_change_nothing(cli, tmp_path):
    outputs = tmp_path / "grades"
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(4)
    accepted: list[object] = []
    threading.Thread(target=lambda: accepted.append(server.accept()), daemon=True).start()
    PORT = server.getsockname()[1]  # noqa: N806
    forger = attack("""
        for path in [os.environ.get("QCARLAB_RESULTS") or "/nonexistent", *glob.glob("/tmp/qcarlab-grade-*/results.json"),
                     *glob.glob("/tmp/qcarlab-grade-*/cases.jsonl")]:
            try:
                open(path, "w").write(json.dumps({"stopped": 1, "stop_distance_m": 0.2, "value": 0.0}))
            except OSError:
                pass
        import qcarlab.grading.checks as checks, qcarlab.record as record, qcarlab.sim.vehicle as vehicle
        checks.check_metric = lambda *a, **k: None                  # the scoring
        record.write_json = lambda *a, **k: None                     # the results writer
        for m in (checks, record, vehicle):                          # the installed package, for the next run
            try:
                open(m.__file__, "a").write("\\nraise SystemExit('pwned')\\n")
            except OSError:
                pass
        LEAKS = []
        for secret in (SHEET, CLASSMATE, OUT):
            try:
                os.listdir(secret) if os.path.isdir(secret) else open(secret).read()
                LEAKS.append(secret)
            except OSError:
                pass
        try:  # (its own /tmp is writable: the real folder must stay untouched, checked outside)
            os.makedirs(OUT + "/planted", exist_ok=True)
        except OSError:
            pass
        try:
            __import__("socket").create_connection(("127.0.0.1", int(PORT)), timeout=1)
            LEAKS.append("network")
        except OSError:
            pass
        if LEAKS:
            print("LEAKED", LEAKS)
            raise SystemExit(0)  # a leak is loud: the test sees it
    """, sheet=tmp_path / "private" / "sheet.yaml", classmate=tmp_path / "class" / "alice" / "stop-sign" / "stop_sign.py",
        out=outputs, port=PORT)
    modules = {m: installed_file(m, tmp_path) for m in ("qcarlab.grading.checks", "qcarlab.record",
                                                          "qcarlab.sim.vehicle")}
    before = {m: f.read_bytes() for m, f in modules.items()}
    by = grade_class(cli, tmp_path, {"alice": HONEST, "mallory": forger})
    honest(by["alice"])
    deserved(by["mallory"])
    assert "LEAKED" not in (by["mallory"]["block"].get("student_output") or "")
    assert not accepted
    assert {m: f.read_bytes() for m, f in modules.items()} == before  # the installed qcarlab, untouched
    assert not (outputs / "planted").exists()
    server.close()


def test_hurting_classmates_fails_killing_daemons_memory_and_disk(cli, tmp_path):
    """Kill every process in sight, leave a daemon to rewrite the gradebook later, plant a
    matplotlibrc, fill memory with forked children and the disk with files: the classmates are
    graded as if alone, the grader finishes, nothing is left running or written."""
    outputs = tmp_path / "grades"
    killer = attack("""
        for pid in range(1, 1 << 16):
            if pid != os.getpid():
                try:
                    os.kill(pid, signal.SIGKILL)
                except OSError:
                    pass
        if os.fork() == 0:  # a daemon that outlives the task and rewrites the outputs
            os.setsid()
            for _ in range(600):  # a minute: longer than no_student_processes_left waits
                time.sleep(0.1)
                for name in ("grade.json", "gradebook.csv", "report.html"):
                    try:
                        open(os.path.join(OUT, name), "w").write("pwned")
                    except OSError:
                        pass
            os._exit(0)
        os.makedirs(os.path.expanduser("~/.config/matplotlib"), exist_ok=True)
        open(os.path.expanduser("~/.config/matplotlib/matplotlibrc"), "w").write("figure.dpi: 2000\\n")
        open("matplotlibrc", "w").write("figure.dpi: 2000\\n")
    """, out=outputs)
    hog = attack("""
        def grow():
            keep = []
            while True:
                keep.append(bytearray(50 * 2**20))
        for _ in range(6):  # six children of 300+ MB each: far over 1024 MB together
            if os.fork() == 0:
                try:
                    grow()
                finally:
                    os._exit(0)
        try:
            with open("/tmp/fill", "wb") as f:  # then a disk full of files
                while True:
                    f.write(b"x" * 2**20)
        except OSError:
            pass
    """)
    by = grade_class(cli, tmp_path, {"alice": HONEST, "bob": HONEST, "mallory": killer, "trudy": hog})
    honest(by["alice"])
    honest(by["bob"])
    deserved(by["mallory"])
    assert by["trudy"]["run"]["status"] == "failed" and by["trudy"]["block"]["status"] == "failed"
    assert no_student_processes_left()
    import time

    time.sleep(1.5)  # the daemon would have written by now
    assert json.loads((outputs / "grade.json").read_text())["students"]
    assert "pwned" not in (outputs / "gradebook.csv").read_text()


def test_a_symlink_to_a_classmates_file_is_refused_in_one_line(cli, tmp_path):
    root = tmp_path / "class"
    alice = student(root, "alice", HONEST)
    mallory = correct_submission(root / "mallory", ("stop-sign",)) / "stop-sign"
    (mallory / "stop_sign.py").unlink()
    (mallory / "stop_sign.py").symlink_to(alice / "stop_sign.py")
    sheet = tmp_path / "sheet.yaml"
    sheet.write_text(SHEET)
    code, out, err = cli("grade", sheet, "--class", root, "--task", "block", "--out", tmp_path / "g", "--json")
    entry = {s["student"]: s for s in json.loads(out)["students"]}
    assert entry["alice"]["passed"] == 1 and entry["mallory"]["passed"] == 0
    assert entry["mallory"]["submission_problems"] == ["stop_sign.py: a symbolic link, refused (hand in the file itself)"]


def test_a_graded_block_may_not_import_qcarlabs_own(cli, tmp_path):
    sub = correct_submission(tmp_path / "s", ("stop-sign",)) / "stop-sign"
    write_block(sub, "stop_sign.py", "from qcarlab.control.stop_sign import stop_sign  # noqa\n")
    sheet = tmp_path / "sheet.yaml"
    sheet.write_text(SHEET)
    code, out, err = cli("grade", sheet, "--submission", sub, "--task", "block", "--json")
    assert code == 1
    problem = json.loads(out)["tasks"][0]["problem"]
    assert problem.startswith("stop_sign.py line 1: imports qcarlab's own stop_sign; a graded block must be your code")
    code, out, err = cli("stop-sign", "--use", sub / "stop_sign.py", "--json")  # a run of one's own: allowed
    assert code in (0, 1) and json.loads(out)["student_blocks"]["stop_sign"]["calls"] > 0


def test_the_students_process_sees_only_its_arguments(tmp_path):
    """Straight through the API: the student's process is another user, PID 1's child in its own
    namespace, without network, with a read-only view and nothing of the grader's environment."""
    from qcarlab.sandbox.client import BlockHost, HostPlan

    sub = tmp_path / "submission"
    sub.mkdir()
    (sub / "probe.py").write_text(textwrap.dedent("""
        import os
        def probe():
            writable = []
            for d in ("/usr", "/etc", os.path.dirname(__import__("qcarlab").__file__), os.path.dirname(__file__)):
                try:
                    open(os.path.join(d, "x"), "w")
                    writable.append(d)
                except OSError:
                    pass
            return {"uid": os.getuid(), "pids": sorted(int(p) for p in os.listdir("/proc") if p.isdigit()),
                    "env": sorted(os.environ), "writable": writable, "home": os.path.expanduser("~"),
                    "root": sorted(os.listdir("/"))}
    """))
    host = BlockHost.start(HostPlan(tmp_path, sub, tmp_path / "o.txt", tmp_path / "e.txt", memory_mb=512))
    try:
        seen = host.load(sub / "probe.py")["probe"]()
    finally:
        host.close()
    assert seen["uid"] >= BASE_UID
    assert seen["pids"] == [1, 2]  # the namespace's init and itself
    assert not any(v.startswith("QCARLAB") for v in seen["env"])
    assert seen["writable"] == []
    assert seen["home"] == "/home/student"
    assert "sys" not in seen["root"] and tmp_path.name not in str(seen["root"])


def test_values_from_the_student_are_decoded_never_unpickled():
    import numpy as np

    from qcarlab.perception.lane import LineFit
    from qcarlab.sandbox import codec

    value = (1.5, [np.arange(6, dtype=np.uint8).reshape(2, 3)], {"a": None}, LineFit(0.5, 3.0, 10, (1, 2)))
    back = codec.decode(codec.encode(value))
    assert back[0] == 1.5 and back[1][0].tolist() == [[0, 1, 2], [3, 4, 5]] and back[2] == {"a": None}
    assert back[3] == LineFit(0.5, 3.0, 10, (1, 2))
    import pickle

    for bad in (pickle.dumps(os.system), b"A\x03|O8\x01" + b"\x00" * 16, b"L\xff\xff\xff\xff", b"Z"):
        with pytest.raises(codec.CodecError):
            codec.decode(bad)
