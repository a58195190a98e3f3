"""``qcarlab onboard --write FILE`` and ``qcarlab deploy USER@HOST``: the file a user copies, the
ssh/scp commands (argument lists, no local shell; the token only on standard input), the start
command per car, errors in one line; and a deploy end to end through stand-in ssh/scp programs."""

from __future__ import annotations

import json
import os
import re
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from onboard_support import Served, car_python

import qcarlab.cli.onboard as cli_onboard
from qcarlab.car.tcp import TcpCar
from qcarlab.onboard import SERVER_FILE, server_source
from qcarlab.errors import InputError
from qcarlab.onboard.deploy import PROBE, Target, car_type_from_python


def test_onboard_write_gives_the_standalone_server(cli, tmp_path):
    code, out, err = cli("onboard", "--write", str(tmp_path / "car.py"))
    assert code == 0, err
    written = tmp_path / "car.py"
    assert written.read_text() == SERVER_FILE.read_text() and written.stat().st_mode & stat.S_IXUSR
    assert "from qcarlab" not in written.read_text() and "import qcarlab" not in written.read_text()
    code, out, err = cli("onboard", "--write", str(tmp_path / "car.py"))
    assert code == 2 and "--force" in err and len(err.strip().splitlines()) == 1
    assert cli("onboard", "--write", str(tmp_path / "car.py"), "--force")[0] == 0
    code, out, err = cli("onboard", "--write", str(tmp_path))  # a folder: the default name
    assert code == 0 and (tmp_path / "qcarlab_car_server.py").exists()
    code, out, err = cli("onboard", "--write", str(tmp_path / "no" / "such" / "x.py"))
    assert code == 2 and len(err.strip().splitlines()) == 1
    code, out, err = cli("onboard")
    assert code == 0 and str(SERVER_FILE) in out and "--dry-run" in out


class FakeRunner:
    """Stands in for subprocess.run: records the argument lists, answers like the car would."""

    def __init__(self, python="3.6.9", numpy="1.13.3", fail=None):
        self.calls = []
        self.python, self.numpy, self.fail = python, numpy, fail

    def __call__(self, argv, **kw):
        assert isinstance(argv, list) and "shell" not in kw  # no local shell, ever
        self.calls.append((argv, kw))
        if self.fail and self.fail in " ".join(argv):
            return subprocess.CompletedProcess(argv, 255, b"", b"ssh: connect to host 10.0.0.9 port 22: Connection refused\n")
        out = b""
        if "-c" in " ".join(argv) and "platform" in argv[-1]:
            out = json.dumps({"python": self.python, "numpy": self.numpy, "quanser": True, "machine": "aarch64"}).encode()
        elif argv[-1].endswith("--version"):
            out = b"qcarlab-car-server 0.1.0\n"
        elif argv[0] == "scp":
            self.copied = Path(argv[-2]).read_text()
        return subprocess.CompletedProcess(argv, 0, out, b"")


@pytest.mark.parametrize("python,car,start", [
    ("3.6.9", "QCar 1", "sudo PYTHONPATH=$PYTHONPATH python3 qcarlab_car_server.py --host 0.0.0.0 "
                        "--token-file .qcarlab_token --car-type 1"),
    ("3.8.10", "QCar 2", "python3 qcarlab_car_server.py --host 0.0.0.0 --token-file .qcarlab_token --car-type 2"),
])
def test_deploy_copies_checks_stores_the_token_and_prints_the_start_command(cli, monkeypatch, python, car, start):
    runner = FakeRunner(python=python)
    monkeypatch.setattr(cli_onboard, "runner", runner)
    monkeypatch.delenv("QCARLAB_TOKEN", raising=False)
    code, out, err = cli("deploy", "nvidia@192.168.2.15")
    assert code == 0, err
    programs = [argv[0] for argv, _ in runner.calls]
    assert programs == ["ssh", "scp", "ssh", "ssh"]
    assert runner.copied == server_source()
    assert runner.calls[1][0][-1] == "nvidia@192.168.2.15:qcarlab_car_server.py"
    token = re.search(r"export QCARLAB_TOKEN=(\S+)", out)[1]
    assert len(token) >= 32
    stdin = runner.calls[3][1]["input"]
    assert stdin == (token + "\n").encode() and "umask 077" in runner.calls[3][0][-1]
    assert not any(token in " ".join(argv) for argv, _ in runner.calls)  # never on a command line
    assert start in out and car in out and "qcarlab ping tcp://192.168.2.15:18960" in out


def test_deploy_with_the_token_from_the_environment_does_not_print_it(cli, monkeypatch):
    runner = FakeRunner(python="3.8.10")
    monkeypatch.setattr(cli_onboard, "runner", runner)
    monkeypatch.setenv("QCARLAB_TOKEN", "the-lab-token-from-env")
    code, out, err = cli("deploy", "nvidia@car2", "--port", "19000")
    assert code == 0, err
    assert runner.calls[3][1]["input"] == b"the-lab-token-from-env\n" and "the-lab-token-from-env" not in out
    assert "--port 19000" in out and "tcp://car2:19000" in out


def test_deploy_dry_run_runs_nothing_and_hides_the_token(cli, monkeypatch):
    runner = FakeRunner()
    monkeypatch.setattr(cli_onboard, "runner", runner)
    code, out, err = cli("deploy", "nvidia@192.168.2.15", "--dry-run", "--token", "x" * 20)
    assert code == 0 and runner.calls == []
    assert out.count("ssh ") >= 3 and "scp " in out and "< <token>" in out and "x" * 20 not in out


def test_deploy_errors_are_one_line(cli, monkeypatch):
    monkeypatch.setattr(cli_onboard, "runner", FakeRunner(fail="ssh"))
    code, out, err = cli("deploy", "nvidia@10.0.0.9")
    assert code == 1 and "probe the car's Python failed: ssh: connect to host" in err
    assert len(err.strip().splitlines()) == 1
    for bad in ("192.168.2.15", "nvidia@", "nvidia@host;rm -rf ~", "-oProxyCommand=x@h", "nvidia@-oX"):
        code, out, err = cli("deploy", "--", bad)
        assert code == 2 and len(err.strip().splitlines()) == 1, bad
    with pytest.raises(InputError):
        Target.parse("-ox@h")
    code, out, err = cli("deploy", "nvidia@car", "--token", "short")
    assert code == 2 and "16 or more" in err
    monkeypatch.setattr(cli_onboard, "runner", FakeRunner(python="2.7.17"))
    code, out, err = cli("deploy", "nvidia@car")
    assert code == 1 and "needs 3.6 or newer" in err


def test_the_car_type_follows_the_cars_python():
    assert (car_type_from_python("3.6.9"), car_type_from_python("3.8.10"), car_type_from_python("3.10.1")) == (1, 2, None)
    assert "'" not in PROBE  # it travels inside single quotes


# --- end to end, through stand-in ssh and scp ------------------------------------------------------
STAND_IN = '''#!{python}
"""A stand-in for {name}: the "car" is the folder $FAKE_CAR_HOME on this machine."""
import os, shutil, subprocess, sys
args = sys.argv[1:]
i = 0
while i < len(args) and args[i].startswith("-"):
    i += 2 if args[i] in ("-o", "-p", "-i", "-l", "-F", "-P") else 1
home = os.environ["FAKE_CAR_HOME"]
if "{name}" == "scp":
    src, dest = args[i], args[i + 1]
    shutil.copy(src, os.path.join(home, dest.split(":", 1)[1]))
    sys.exit(0)
command = " ".join(args[i + 1:])  # as sshd does: the words joined, run by the login shell
env = dict(os.environ, HOME=home, PATH=os.environ["FAKE_CAR_PATH"])
sys.exit(subprocess.call(["/bin/sh", "-c", command], cwd=home, env=env))
'''


def test_deploy_end_to_end_then_the_car_serves_with_the_stored_token(cli, monkeypatch, tmp_path):
    car_py = car_python("3.8")
    if car_py is None:
        pytest.skip("Python 3.8 is not on this machine")
    bin_dir, car_bin, home = tmp_path / "bin", tmp_path / "car-bin", tmp_path / "home"
    for d in (bin_dir, car_bin, home):
        d.mkdir()
    for name in ("ssh", "scp"):
        p = bin_dir / name
        p.write_text(STAND_IN.format(python=sys.executable, name=name))
        p.chmod(0o755)
    (car_bin / "python3").symlink_to(car_py)  # the "car" runs Python 3.8, as a QCar 2
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("FAKE_CAR_HOME", str(home))
    monkeypatch.setenv("FAKE_CAR_PATH", f"{car_bin}{os.pathsep}/usr/bin{os.pathsep}/bin")
    monkeypatch.delenv("QCARLAB_TOKEN", raising=False)
    code, out, err = cli("deploy", "nvidia@127.0.0.1")
    assert code == 0, err
    assert (home / "qcarlab_car_server.py").read_text() == server_source()
    token_file = home / ".qcarlab_token"
    assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
    token = re.search(r"export QCARLAB_TOKEN=(\S+)", out)[1]
    assert token_file.read_text().strip() == token
    assert "QCar 2" in out and "Python 3.8." in out
    start = re.search(r"^  (python3 qcarlab_car_server.py .*)$", out, re.M)[1].split()
    assert start[:2] == ["python3", "qcarlab_car_server.py"]
    # the printed command, as typed on the car (with --dry-run: no hardware here)
    with Served(car_py, *start[2:], "--dry-run", "--port", "0", script=home / start[1], cwd=home) as srv:
        assert "token required" in srv.line
        with TcpCar("127.0.0.1", srv.port, token=token, role="monitor") as car:
            assert car.read().battery_voltage == 12.0
        code, out, err = srv.stop()
    assert code == 0
