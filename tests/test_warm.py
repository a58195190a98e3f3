"""The warm start (qcarlab.warm): a lab command run by the warm server prints, writes and exits as a
cold one; Ctrl-C reaches it; a killed client's command is stopped; a changed install is not
served by an old server; off a terminal nothing is started unless asked."""

from __future__ import annotations

import json
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from qcarlab import warm

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the warm server is Linux only")

REPO = Path(__file__).resolve().parents[1]
CLIENT = "import sys; sys.argv[0] = 'qcarlab'; from qcarlab.warm import main; main()"


def _pids(folder: str) -> list[int]:
    """The servers started in ``folder``, from their logs ("warm in ... pid N, ...")."""
    pids = []
    for log in Path(folder).glob("*.log"):
        m = re.search(r"pid (\d+)", log.read_text(errors="replace"))
        if m:
            pids.append(int(m.group(1)))
    return pids


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ")[1][0] != "Z"
    except OSError:
        return False


def with_checkout(env: dict) -> dict:
    """``env`` with this checkout's qcarlab first on the path: every process of a test, whatever its
    folder, imports the same qcarlab (with ``pip install .`` the venv has another copy, and a
    server is one install's: a client of the other copy would not find it)."""
    return {**env, "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)}


@pytest.fixture(scope="module")
def env():
    """A private server folder (short: a socket's path has at most 107 bytes); every server
    started in it is killed at the end, whatever happened."""
    folder = tempfile.mkdtemp(prefix="qw")
    e = with_checkout({k: v for k, v in os.environ.items() if k not in ("QCARLAB_WARM", "COLUMNS", "LINES")})
    e.update(QCARLAB_WARM="1", QCARLAB_WARM_DIR=folder, TERM="xterm-256color", QCARLAB_WARM_IDLE="300")
    yield e
    _clear(folder)


def _clear(folder: str) -> None:
    """Kill every server started in ``folder`` (from their logs) and remove it."""
    for pid in _pids(folder):
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    shutil.rmtree(folder, ignore_errors=True)


def qcarlab(env: dict, *args: str, cwd: Path | None = None, timeout: float = 180) -> subprocess.CompletedProcess:
    """``qcarlab ARGS`` as the console script runs it (qcarlab.warm.main), by default in the test's
    server folder (what a command writes there goes with it; never into the checkout)."""
    return subprocess.run([sys.executable, "-c", CLIENT, *args], env=env, cwd=cwd or env["QCARLAB_WARM_DIR"],
                          capture_output=True, text=True,
                          timeout=timeout)


def cold(env: dict, *args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return qcarlab({**env, "QCARLAB_WARM": "0"}, *args, cwd=cwd)


def up(env: dict) -> dict:
    """The server of ``env``, started (``qcarlab warm``) if it is not up: its status."""
    return json.loads(subprocess.run([sys.executable, "-m", "qcarlab", "warm", "--json"], env=env, cwd=env["QCARLAB_WARM_DIR"],
                                     capture_output=True, text=True, timeout=330, check=True).stdout)


def served(env: dict) -> int:
    out = subprocess.run([sys.executable, "-m", "qcarlab", "warm", "--status", "--json"], env=env, cwd=env["QCARLAB_WARM_DIR"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    return json.loads(out.stdout)["served"]


def test_a_warm_run_prints_writes_and_exits_as_a_cold_one(env, tmp_path):
    (tmp_path / "w").mkdir()
    (tmp_path / "c").mkdir()
    first = qcarlab(env, "stop-sign", "--json", "--out", "run", cwd=tmp_path / "w")  # starts the server, waits
    n = served(env)
    again = qcarlab(env, "stop-sign", "--json", "--out", "run", cwd=tmp_path / "w")
    assert served(env) == n + 1  # the server ran it
    reference = cold(env, "stop-sign", "--json", "--out", "run", cwd=tmp_path / "c")
    assert first.returncode == again.returncode == reference.returncode == 0, first.stderr + reference.stderr
    assert first.stdout == again.stdout == reference.stdout
    m = json.loads(first.stdout)
    assert m["stopped"] is True and 0.05 <= m["stop_distance_m"] <= 0.40
    written = sorted(p.name for p in (tmp_path / "w" / "run").iterdir())  # in the client's folder
    assert written and written == sorted(p.name for p in (tmp_path / "c" / "run").iterdir())
    for name in written:
        if name.endswith((".json", ".csv")):
            assert (tmp_path / "w" / "run" / name).read_bytes() == (tmp_path / "c" / "run" / name).read_bytes(), name


def test_a_missed_goal_and_bad_input_exit_as_cold(env):
    crash = ("avoid", "--strategy", "steer", "--start", "2.5,0,0", "--duration", "5", "--json")
    w, c = qcarlab(env, *crash), cold(env, *crash)
    assert w.returncode == c.returncode == 1 and "goal missed: collision at" in w.stderr
    assert (w.stdout, w.stderr) == (c.stdout, c.stderr)
    w, c = qcarlab(env, "stop-sign", "--speed", "fast"), cold(env, "stop-sign", "--speed", "fast")
    assert w.returncode == c.returncode == 2 and w.stderr == c.stderr and len(w.stderr.strip().splitlines()) == 1


def test_ctrl_c_reaches_the_command_and_the_car_is_stopped(env):
    up(env)
    p = subprocess.Popen([sys.executable, "-c", CLIENT, "lane-follow", "--duration", "600"], env=env, cwd=env["QCARLAB_WARM_DIR"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(2.0)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=60)
    finally:
        p.kill()
    assert p.returncode == 130 and "interrupted; the car was stopped" in err


def test_a_killed_client_s_command_is_stopped(env):
    up(env)
    p = subprocess.Popen([sys.executable, "-c", CLIENT, "lane-follow", "--duration", "600"], env=env, cwd=env["QCARLAB_WARM_DIR"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(2.0)
    p.kill()
    p.wait()
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        status = json.loads(subprocess.run([sys.executable, "-m", "qcarlab", "warm", "--status", "--json"], env=env,
                                           cwd=env["QCARLAB_WARM_DIR"], capture_output=True, text=True, timeout=60).stdout)
        if status["commands_running"] == 0:
            break
        time.sleep(0.2)
    assert status["commands_running"] == 0


def on_pty(env: dict, *args: str) -> str:
    """``qcarlab ARGS`` (the console script's code) on a fresh pseudo-terminal: what it printed."""
    master, slave = os.openpty()
    p = subprocess.Popen([sys.executable, "-c", CLIENT, *args], env=env, cwd=env["QCARLAB_WARM_DIR"], stdin=slave, stdout=slave,
                         stderr=slave, start_new_session=True)
    os.close(slave)
    out = bytearray()
    try:
        drain(master, out)
    finally:
        os.close(master)
    assert p.wait(timeout=60) == 0, out.decode(errors="replace")
    return out.decode(errors="replace")


def drain(master: int, out: bytearray, timeout: float = 60, until: bytes | None = None) -> None:
    """What a pseudo-terminal's other end prints into ``out``, until it closes (or is silent for
    ``timeout`` s, or ``out`` holds ``until``)."""
    while (until is None or until not in out) and select.select([master], [], [], timeout)[0]:
        try:
            chunk = os.read(master, 65536)
        except OSError:
            break
        if not chunk:
            break
        out += chunk


def test_at_a_terminal_the_output_keeps_its_colours(env):
    auto = {k: v for k, v in env.items() if k != "QCARLAB_WARM"}  # the default: warm at a terminal
    n = up(env)["served"]
    warm_text = on_pty(auto, "path-gen", "butterfly", "--size", "2")
    assert served(env) == n + 1  # it went to the server
    cold_text = on_pty({**auto, "QCARLAB_WARM": "0"}, "path-gen", "butterfly", "--size", "2")
    # the console saw a terminal (the title in italics) in both; a warm server has imported numba,
    # whose colorama resets the terminal at exit ("\x1b[0m", invisible), as a cold lab run does
    assert "\x1b[3mpath-gen butterfly" in warm_text and "\x1b[3mpath-gen butterfly" in cold_text
    assert warm_text.removesuffix("\x1b[0m") == cold_text


@pytest.mark.parametrize("argv, says", [
    (["path-gen", "line"], "path-gen line"),
    # what a student types before a lab's first command starts it too, so that command is warm
    # (which commands: test_what_a_student_types_before_a_lab_starts_the_server_at_a_terminal)
    (["template", "stop-sign", "--out", "ws"], "ws"),
])
def test_at_a_terminal_the_first_command_runs_cold_and_then_starts_the_server(argv, says):
    folder = tempfile.mkdtemp(prefix="qw")
    try:
        e = with_checkout({k: v for k, v in os.environ.items() if k != "QCARLAB_WARM"})
        e.update(QCARLAB_WARM_DIR=folder, TERM="xterm-256color")
        assert says in on_pty(e, *argv)
        deadline = time.monotonic() + 300  # (in a fresh clone the server compiles the kernels first)
        while not list(Path(folder).glob("*.sock")) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert served(e) == 0  # up and warm, the first command not among its own
    finally:
        _clear(folder)


@pytest.fixture
def compiling():
    """A server of this install starting in a fresh folder, as :func:`qcarlab.warm.start_server`
    leaves it after an install: its lock taken (here, by this test: ``lock``, the fd) and its log
    saying it compiles the kernels. Yields (env, folder, key, lock, started): a client at a
    terminal's environment, and a list for the processes a test starts, killed at the end."""
    import fcntl

    folder = tempfile.mkdtemp(prefix="qw")
    started: list[subprocess.Popen] = []
    try:
        e = with_checkout({k: v for k, v in os.environ.items() if k != "QCARLAB_WARM"})
        e.update(QCARLAB_WARM_DIR=folder, TERM="xterm-256color")
        key = subprocess.run([sys.executable, "-c", "from qcarlab import warm; print(warm.install_key())"], env=e,
                             cwd=folder, capture_output=True, text=True, check=True).stdout.strip()
        where = warm.Place(folder, key)
        lock = os.open(where.lock, os.O_RDWR | os.O_CREAT, 0o600)
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        Path(where.log).write_text(f"{warm.COMPILING} (once after an install): key {key}\n")
        yield e, folder, key, lock, started
    finally:
        for p in started:
            p.kill()
            p.wait()
        _clear(folder)


def test_at_a_terminal_a_lab_typed_while_the_server_compiles_waits_for_it_and_says_why(compiling):
    """After an install the server compiles the kernels first (15-30 s): a simulator's lab typed
    then would compile the same kernels beside it, so it waits for the server instead, saying
    why; a command that uses no kernels (path-gen) does not wait."""
    import threading

    e, folder, key, lock, started = compiling
    t0 = time.monotonic()
    assert "waiting" not in on_pty(e, "path-gen", "line") and time.monotonic() - t0 < 30
    log = Path(warm.Place(folder, key).log)
    mine = log.read_text()
    log.write_text(mine.replace(key, key.split("-")[0] + "-older"))  # a server of a changed install
    t0 = time.monotonic()
    assert "waiting" not in on_pty(e, "io-test") and time.monotonic() - t0 < 30  # it would only say "stale"
    log.write_text(mine)

    def compiled() -> None:  # the compile done, the server takes over the lock and warms up
        time.sleep(2.0)
        started.append(subprocess.Popen([sys.executable, "-m", "qcarlab.warm", "serve", folder, key, str(lock)],
                                        env=e, cwd="/", stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL, pass_fds=(lock,), start_new_session=True))
        os.close(lock)

    handover = threading.Thread(target=compiled)
    handover.start()
    try:
        t0 = time.monotonic()
        text = on_pty(e, "io-test")
        waited = time.monotonic() - t0
    finally:
        handover.join()
    assert waited >= 2.0
    assert "qcarlab: waiting for the warm server, which compiles the simulator's kernels" in text
    assert re.search(r"\.\.\. ready after \d+ s", text) and "throttle" in text
    assert served(e) == 1  # run by the server, not cold


def test_ctrl_c_while_waiting_for_a_starting_server_runs_nothing_and_says_so(compiling):
    e, folder, _, lock, started = compiling
    master, slave = os.openpty()
    # (Ctrl-C as at a terminal: a job started in the background, as this suite may be, inherits SIGINT ignored)
    at_terminal = "import signal; signal.signal(signal.SIGINT, signal.default_int_handler); " + CLIENT
    p = subprocess.Popen([sys.executable, "-c", at_terminal, "stop-sign", "--out", "run"], env=e, cwd=folder,
                         stdin=slave, stdout=slave, stderr=slave, start_new_session=True)
    started.append(p)
    os.close(slave)
    out = bytearray()
    try:
        drain(master, out, 30, until=b"runs without it)...")
        assert b"runs without it)..." in out, out.decode(errors="replace")
        os.kill(p.pid, signal.SIGINT)
        drain(master, out, 30)
        assert p.wait(timeout=30) == 130
    finally:
        os.close(master)
        os.close(lock)
    text = out.decode(errors="replace")
    assert text.endswith("QCARLAB_WARM=0 runs without it)...\r\nstop-sign: interrupted\r\n"), text
    assert not (Path(folder) / "run").exists()  # nothing ran


def test_a_server_of_a_changed_install_gives_way(env):
    key = subprocess.run([sys.executable, "-c", "from qcarlab import warm; print(warm.install_key())"], env=env,
                         cwd=env["QCARLAB_WARM_DIR"], capture_output=True, text=True, check=True).stdout.strip()
    where = warm.Place(env["QCARLAB_WARM_DIR"], key)
    assert subprocess.run([sys.executable, "-m", "qcarlab", "warm", "--stop"], env=env, cwd=env["QCARLAB_WARM_DIR"],
                          capture_output=True, timeout=60).returncode == 0
    deadline = time.monotonic() + 10
    while os.path.exists(where.socket) and time.monotonic() < deadline:
        time.sleep(0.05)
    old = subprocess.Popen([sys.executable, "-m", "qcarlab.warm", "serve", where.folder, key.split("-")[0] + "-older"],
                           env=env, cwd="/", stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert old.stdout.readline().startswith("warm in")
        done = qcarlab(env, "path-gen", "line", "--json")
        assert done.returncode == 0 and json.loads(done.stdout)
        assert old.wait(timeout=30) == 0  # told it is stale, it left
        assert served(env) == 1  # a new server ran it
    finally:
        old.kill()


def test_off_a_terminal_nothing_starts_unless_asked(tmp_path):
    folder = tempfile.mkdtemp(prefix="qw")
    try:
        e = with_checkout({k: v for k, v in os.environ.items() if k != "QCARLAB_WARM"})
        e["QCARLAB_WARM_DIR"] = folder
        out = qcarlab(e, "path-gen", "line", "--json")
        assert out.returncode == 0 and json.loads(out.stdout)
        time.sleep(0.5)
        assert not list(Path(folder).glob("*.sock")) and not _pids(folder)
    finally:
        _clear(folder)


@pytest.mark.parametrize("argv, mode, terminal, expected", [
    (["stop-sign"], "1", False, True),
    (["stop-sign"], "", True, True),
    (["stop-sign"], "", False, False),
    (["stop-sign"], "0", True, False),
    (["grade", "x"], "1", True, False),  # student code never runs beside the user's warm server
    (["serve"], "1", True, False),
    ([], "1", True, False),
    (["--help"], "1", True, False),
])
def test_which_commands_go_warm(monkeypatch, argv, mode, terminal, expected):
    monkeypatch.setenv("QCARLAB_WARM", mode)
    monkeypatch.setattr(warm, "_at_terminal", lambda: terminal)
    assert warm.wanted(argv) is expected


@pytest.mark.parametrize("argv, mode, terminal, expected", [
    ([], "", True, True),
    (["--help"], "", True, True),
    (["-h"], "1", True, True),
    (["--version"], "", True, True),
    (["labs"], "", True, True),
    (["template", "stop-sign"], "", True, True),
    (["--help"], "", False, False),  # scripts and pipes start nothing unless asked
    (["template", "avoid"], "1", False, True),
    (["labs"], "0", True, False),
    (["grade", "stop-sign"], "", True, False),
    (["serve"], "", True, False),  # (on the car: no server it did not ask for)
    (["onboard"], "", True, False),
])
def test_what_a_student_types_before_a_lab_starts_the_server_at_a_terminal(monkeypatch, argv, mode, terminal,
                                                                             expected):
    monkeypatch.setenv("QCARLAB_WARM", mode)
    monkeypatch.setattr(warm, "_at_terminal", lambda: terminal)
    assert warm.prepares(argv) is expected
    assert not warm.wanted(argv)  # (run cold: the server is started after it)


def test_the_client_imports_nothing_heavy():
    out = subprocess.run([sys.executable, "-c", "import sys, qcarlab.warm; "
                          "print(sorted(m for m in ('numpy', 'typer', 'rich', 'cv2', 'numba') if m in sys.modules))"],
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_a_terminated_server_finishes_the_commands_it_runs(env):
    info = up(env)
    p = subprocess.Popen([sys.executable, "-c", CLIENT, "lane-follow", "--duration", "60", "--json"], env=env, cwd=env["QCARLAB_WARM_DIR"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while served(env) == info["served"] and time.monotonic() < deadline:  # until it runs
            time.sleep(0.05)
        os.kill(info["pid"], signal.SIGTERM)
        out, err = p.communicate(timeout=120)
    finally:
        p.kill()
    assert p.returncode == 0, err
    assert json.loads(out)["duration_s"] == pytest.approx(60.0)
    deadline = time.monotonic() + 10
    while _alive(info["pid"]) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(info["pid"]) and not os.path.exists(info["socket"])


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                fields = (d / "stat").read_text().rsplit(") ", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                out.append(int(d.name))
    return out


def _state(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(") ", 1)[1][0]


def test_garbage_and_silent_connections_do_not_hold_the_server_up(env):
    info = up(env)
    import socket

    silent = socket.socket(socket.AF_UNIX)
    silent.connect(info["socket"])  # says nothing
    for junk in (b"QWRM" + (2).to_bytes(4, "big") + b"[]", b"QWRM" + (4).to_bytes(4, "big") + b"null",
                 b"QWRM" + (2).to_bytes(4, "big") + b"{}", b"GET / HTTP/1.0\r\n\r\n", b"QWRM\xff\xff\xff\xff"):
        with socket.socket(socket.AF_UNIX) as s:
            s.connect(info["socket"])
            s.sendall(junk)
            s.settimeout(10)
            try:
                s.recv(64)
            except OSError:
                pass
    try:
        t0 = time.monotonic()
        done = qcarlab(env, "path-gen", "line", "--json")
        assert done.returncode == 0 and json.loads(done.stdout)
        assert time.monotonic() - t0 < 5  # not held up by the silent connection (10 s before it is dropped)
        assert _alive(info["pid"]) and served(env) == info["served"] + 1
    finally:
        silent.close()


def test_a_closed_stdin_runs_cold(env):
    n = up(env)["served"]
    done = subprocess.run(["bash", "-c", 'exec 0<&-; exec "$0" -c "$1" path-gen line --json', sys.executable, CLIENT],
                          env=env, cwd=env["QCARLAB_WARM_DIR"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and json.loads(done.stdout)
    assert served(env) == n  # not sent: its socket would have been the command's stdin


def test_ctrl_z_stops_the_command_and_fg_resumes_it(env):
    info = up(env)
    p = subprocess.Popen([sys.executable, "-c", CLIENT, "lane-follow", "--duration", "600"], env=env, cwd=env["QCARLAB_WARM_DIR"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while not _children(info["pid"]) and time.monotonic() < deadline:
            time.sleep(0.05)
        (command,) = _children(info["pid"])
        time.sleep(0.5)
        assert Path(f"/proc/{command}/comm").read_text().strip() == "qcarlab lane-fo"  # as ps -e and top show it
        p.send_signal(signal.SIGTSTP)
        deadline = time.monotonic() + 10
        while (_state(command) != "T" or _state(p.pid) != "T") and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _state(command) == "T" and _state(p.pid) == "T"
        p.send_signal(signal.SIGCONT)
        deadline = time.monotonic() + 10
        while _state(command) == "T" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _state(command) in "RS"
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=60)
        assert p.returncode == 130 and "interrupted; the car was stopped" in err
    finally:
        p.kill()


@pytest.mark.parametrize("user", [None, "2"])
def test_the_command_runs_numpy_with_one_blas_thread_unless_the_user_says(user, tmp_path):
    """numpy's OpenBLAS starts a spinning thread per core at import (some 0.1 s of CPU each, for
    2x2 matrices): the qcarlab command and ``python -m qcarlab`` set one where the user set none;
    the warm server's key treats unset and the default alike (a server started by either serves both)."""
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "QCARLAB_WARM")}
    if user:
        env["OPENBLAS_NUM_THREADS"] = user
    probe = "import os, numpy; print(os.environ.get('OPENBLAS_NUM_THREADS'), len(os.listdir('/proc/self/task')))"
    plain = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    via = "; ".join(["import os, sys", "sys.argv = ['qcarlab', 'path-gen', 'line', '--json']",  # (off a terminal: cold)
                     "from qcarlab.warm import main",
                     "import atexit; atexit.register(lambda: print(os.environ.get('OPENBLAS_NUM_THREADS'), "
                     "len(os.listdir('/proc/self/task')), file=sys.stderr))", "main()"])
    got = subprocess.run([sys.executable, "-c", via], env=env, capture_output=True, text=True, cwd=tmp_path)
    assert got.returncode == 0, got.stderr
    blas, threads = got.stderr.split()[-2:]
    assert blas == (user or "1")
    if not user and sys.platform.startswith("linux") and int(plain.stdout.split()[1]) > 1:
        assert int(threads) == 1  # numpy's import made none (where a plain import makes some: OpenBLAS, 2+ cores)
    keys = [subprocess.run([sys.executable, "-c", "from qcarlab import warm; print(warm.install_key())"],
                           env={**env, **extra}, capture_output=True, text=True, check=True).stdout
            for extra in ({}, {"OPENBLAS_NUM_THREADS": "1"})]
    assert (keys[0] == keys[1]) == (user is None)
