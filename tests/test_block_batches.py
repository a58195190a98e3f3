"""Two student blocks of a tick in one round trip (issue 28), and the watchdog that guards them.

A graded run calls the student's blocks in the student's own process (:mod:`qcarlab.sandbox`);
path following's steering and speed controller go there together (:func:`qcarlab.blocks.together`).
These tests check that the batch changes nothing a student or a grade sees: the same run, each
block checked and named as before, the second block not called after the first fails, a block
that does not return stopped and named; and that the watchdog, now armed lazily, still fires.
"""

from __future__ import annotations

import json
import os
import signal
import textwrap
import time
from pathlib import Path

import pytest

from qcarlab import blocks
from qcarlab.blocks import BlockSpec, StudentBlock, StudentBlockError, together
from qcarlab.errors import InputError
from qcarlab.sandbox.client import BlockHost, HostPlan

STEER = BlockSpec("steer", "steer(x) -> steering", "", "", "", returns="steering")
SPEED = BlockSpec("speed", "speed(x) -> throttle", "", "", "", returns="throttle")

FILE = """
import time

log = []

def nap(x):
    if isinstance(x, str) and x.startswith("nap"):  # "nap0.3": sleep 0.3 s, then return 0
        time.sleep(float(x[3:]))
        return True
    return False

def steer(x):
    log.append(("steer", x))
    if nap(x):
        return 0.0
    if x == "raise":
        raise ValueError("no steering today")
    if x == "deep":  # a value the codec refuses (nested too deep)
        v = []
        for _ in range(10000):
            v = [v]
        return v
    if x == "hang":
        while True:
            pass
    return 0.1 * x

def speed(x):
    log.append(("speed", x))
    if nap(x):
        return 0.0
    if x == "hang":
        while True:
            time.sleep(0.001)
    return 0.01 * x

def calls():
    return list(log)
"""


@pytest.fixture
def host(tmp_path):
    """The student's process (unconfined: the batch, not the jail, is under test) with FILE loaded."""
    sub = tmp_path / "submission"
    sub.mkdir()
    (sub / "student.py").write_text(FILE)
    h = BlockHost.start(HostPlan(tmp_path, sub, tmp_path / "out.txt", tmp_path / "err.txt", sandbox=False))
    try:
        yield h, h.load(sub / "student.py")
    finally:
        h.close()
        blocks._watchdog.stop()


def pair(found: dict) -> tuple[StudentBlock, StudentBlock]:
    a = StudentBlock(STEER, found["steer"], "student.py:steer", Path("student.py")).start()
    b = StudentBlock(SPEED, found["speed"], "student.py:speed", Path("student.py")).start()
    return a, b


def counting(host: BlockHost) -> list:
    """Every request the trusted side sends to the student's process, from now on."""
    sent, send = [], host.channel.send

    def spy(msg):
        sent.append(msg[0])
        return send(msg)

    host.channel.send = spy
    return sent


def test_two_blocks_go_in_one_round_trip_with_the_values_of_two_calls(host):
    h, found = host
    a, b = pair(found)
    sent = counting(h)
    assert together(a, (2.0,), b, (3.0,)) == pytest.approx((0.2, 0.03))
    assert sent == ["calls"]
    assert found["calls"]() == [("steer", 2.0), ("speed", 3.0)]  # in that order, once each
    assert a.calls == b.calls == 1 and a.total_s > 0.0 and b.total_s > 0.0
    # out of range: checked as a single call is, and named
    with pytest.raises(StudentBlockError, match=r"block speed returned 3 \(duty fraction\), out of range"):
        together(a, (1.0,), b, (300.0,))


def test_a_first_block_that_raises_is_named_and_the_second_is_not_called(host):
    h, found = host
    a, b = pair(found)
    with pytest.raises(Exception) as exc:
        together(a, ("raise",), b, (1.0,))
    assert "steer" in str(exc.value) and "ValueError" in str(exc.value) and "no steering today" in str(exc.value)
    assert found["calls"]() == [("steer", "raise")]
    assert b.calls == 0


def test_a_value_that_cannot_be_sent_back_names_its_block(host):
    h, found = host
    a, b = pair(found)
    with pytest.raises(Exception) as exc:
        together(a, ("deep",), b, (1.0,))
    assert "block steer" in str(exc.value) and "cannot be passed back" in str(exc.value)
    assert b.calls == 0  # (the student's process ran it: only a first block that raises stops the second)
    assert found["calls"]() == [("steer", "deep"), ("speed", 1.0)]


@pytest.mark.parametrize("stuck", ["steer", "speed"])
def test_a_block_that_does_not_return_in_a_batch_is_the_one_named(host, stuck, monkeypatch):
    h, found = host
    a, b = pair(found)
    monkeypatch.setenv("QCARLAB_BLOCK_TIMEOUT_S", "0.5")
    a.start(), b.start()
    args = (("hang",), (1.0,)) if stuck == "steer" else ((1.0,), ("hang",))
    t0 = time.monotonic()
    with pytest.raises(Exception) as exc:
        together(a, args[0], b, args[1])
    assert 0.45 < time.monotonic() - t0 < 10.0
    assert f"block {stuck} " in str(exc.value) and "has not returned after 0.5 s" in str(exc.value)
    assert h.wait(5.0) is not None  # its process was ended


def test_each_block_of_a_batch_has_the_whole_time_limit(host, monkeypatch):
    """Two blocks that each take 0.6 of the limit: neither is stopped (one deadline for the pair
    would stop the second); a second that then does not return is stopped and named."""
    h, found = host
    monkeypatch.setenv("QCARLAB_BLOCK_TIMEOUT_S", "0.5")
    a, b = pair(found)
    assert a.watched
    assert together(a, ("nap0.3",), b, ("nap0.3",)) == (0.0, 0.0)
    t0 = time.monotonic()
    with pytest.raises(StudentBlockError, match="block speed .*has not returned after 0.5 s"):
        together(a, ("nap0.3",), b, ("hang",))
    assert 0.75 < time.monotonic() - t0 < 10.0  # 0.3 s for steer, then at least speed's own 0.5 s


def test_the_sandboxed_path_follow_run_is_the_in_process_one(cli, tmp_path):
    """A student's pure pursuit and speed controller, in their own process (one round trip a tick)
    and in this one: the same run to the last digit."""
    assert cli("template", "path-follow", "--out", tmp_path)[0] == 0
    (tmp_path / "pure_pursuit.py").write_text(textwrap.dedent("""
        import math

        def pure_pursuit(pose, target, lookahead, wheelbase):
            x, y, yaw = pose
            alpha = math.atan2(target[1] - y, target[0] - x) - yaw
            return math.atan2(2 * wheelbase * math.sin(alpha), lookahead)
    """))
    (tmp_path / "speed_controller.py").write_text(textwrap.dedent("""
        class speed_controller:
            def reset(self):
                self.integral = 0.0

            def __call__(self, v_ref, v_measured, dt):
                e = v_ref - v_measured
                self.integral += 2.0 * e * dt
                return max(-0.3, min(0.3, 0.1 * v_ref + 0.5 * e + self.integral))
    """))
    argv = ("path-follow", "circle", "--use", tmp_path, "--json")
    code, out, err = cli(*argv)
    assert code == 0, err
    here = json.loads(out)
    h = BlockHost.start(HostPlan(tmp_path, tmp_path, tmp_path / "o.txt", tmp_path / "e.txt", sandbox=False))
    sent = counting(h)
    blocks.load_with(h.load)
    try:
        code, out, err = cli(*argv)
    finally:
        blocks.load_with(None)
        h.close()
    assert code == 0, err
    there = json.loads(out)
    ticks = there["student_blocks"]["pure_pursuit"]["calls"]
    assert ticks > 100 and there["student_blocks"]["speed_controller"]["calls"] >= ticks
    assert sent.count("calls") >= ticks - 1 and sent.count("call") < ticks // 10  # one round trip a tick
    for m in (here, there):
        m.pop("student_blocks")
        m.pop("wall_s", None)
    assert there == here


def _hang():
    while True:
        pass


def _quick():
    return 0.0


def test_the_lazy_watchdog_still_stops_a_block_after_an_earlier_calls_alarm(monkeypatch):
    """An alarm set for a quick call is left running; a stuck call after it is stopped at its own
    deadline (not the quick call's), and a forked child's first stuck call is stopped too."""
    blocks.unwatch()
    monkeypatch.setattr(blocks._watchdog, "lazy", True)  # as in a graded task (load_with a student's process)
    monkeypatch.setenv("QCARLAB_BLOCK_TIMEOUT_S", "0.4")
    spec = BlockSpec("hang", "hang() -> any", "", "", "")
    quick = StudentBlock(spec, _quick, "t.py:_quick", Path(__file__)).start()
    stuck = StudentBlock(spec, _hang, "t.py:_hang", Path(__file__)).start()
    pid = 0
    try:
        assert quick.watched
        quick()
        assert blocks._watchdog.pending  # left set
        time.sleep(0.25)
        t0 = time.monotonic()
        with pytest.raises(StudentBlockError, match="has not returned after 0.4 s"):
            stuck()
        assert 0.35 < time.monotonic() - t0 < 5.0  # its own 0.4 s, not what was left of the quick call's
        quick()
        t0 = time.monotonic()
        pid = os.fork()
        if pid == 0:  # the child has no alarm set, whatever the parent's watchdog thought
            code = 3
            try:
                stuck()
            except StudentBlockError:
                code = 0 if 0.35 < time.monotonic() - t0 < 5.0 else 5
            except BaseException:  # noqa: BLE001
                code = 4
            os._exit(code)
        status = None
        for _ in range(2000):  # 20 s at most (a child that hangs is killed, not waited for forever)
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                pid = 0
                break
            time.sleep(0.01)
        assert pid == 0, "the forked child's stuck block was not stopped"
        assert os.waitstatus_to_exitcode(status) == 0
    finally:
        if pid:
            os.kill(pid, 9)
            os.waitpid(pid, 0)
        blocks.unwatch()
    assert not blocks._watchdog.pending


def test_a_lowered_limit_is_kept_though_an_alarm_for_the_higher_one_is_set(monkeypatch):
    """An alarm left set by a call under a 30 s limit does not let a stuck call under a 0.4 s limit
    run on to it."""
    blocks.unwatch()
    monkeypatch.setattr(blocks._watchdog, "lazy", True)
    spec = BlockSpec("hang", "hang() -> any", "", "", "")
    monkeypatch.setenv("QCARLAB_BLOCK_TIMEOUT_S", "30")
    quick = StudentBlock(spec, _quick, "t.py:_quick", Path(__file__)).start()
    try:
        quick()
        assert blocks._watchdog.pending
        monkeypatch.setenv("QCARLAB_BLOCK_TIMEOUT_S", "0.4")
        stuck = StudentBlock(spec, _hang, "t.py:_hang", Path(__file__)).start()
        t0 = time.monotonic()
        with pytest.raises(StudentBlockError, match="has not returned after 0.4 s"):
            stuck()
        assert time.monotonic() - t0 < 10.0
    finally:
        blocks.unwatch()


def test_in_process_blocks_leave_no_alarm_set_between_calls(monkeypatch, tmp_path):
    """A lab run with the student's blocks in its own process (on a car, a HIL read in C beside
    them): each call cancels its alarm, so no SIGALRM fires while no block overruns; only blocks
    run in the student's process (a graded task) leave it set."""
    blocks.unwatch()
    blocks.load_with(None)
    assert not blocks._watchdog.lazy
    spec = BlockSpec("quick", "quick() -> any", "", "", "")
    quick = StudentBlock(spec, _quick, "t.py:_quick", Path(__file__)).start()
    try:
        for _ in range(3):
            quick()
            assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0) and not blocks._watchdog.pending
        blocks.load_with(lambda path: {})  # as a graded task does
        assert blocks._watchdog.lazy
        quick()
        assert signal.getitimer(signal.ITIMER_REAL)[0] > 0.0  # left set: a call costs no system call
    finally:
        blocks.load_with(None)
        blocks.unwatch()
    assert not blocks._watchdog.lazy


EXITS_71 = "import os\n\ndef steer(x):\n    os._exit(71)\n"


@pytest.mark.parametrize("where", ["call", "load"])
def test_a_student_exit_with_the_sandboxs_failure_code_is_the_students(tmp_path, where):
    """os._exit(71), the code the sandbox's set-up exits with, from the student's code: their block's
    death (scored), not a grader fault (rerun, never scored)."""
    sub = tmp_path / "submission"
    sub.mkdir()
    (sub / "student.py").write_text(EXITS_71 if where == "call" else "import os\nos._exit(71)\n")
    h = BlockHost.start(HostPlan(tmp_path, sub, tmp_path / "out.txt", tmp_path / "err.txt", sandbox=False))
    try:
        if where == "load":
            with pytest.raises(InputError, match="exited with code 71"):
                h.load(sub / "student.py")
        else:
            steer = StudentBlock(STEER, h.load(sub / "student.py")["steer"], "student.py:steer",
                                 Path("student.py")).start()
            with pytest.raises(StudentBlockError, match="block steer .*exited with code 71"):
                steer(1.0)
    finally:
        h.close()
        blocks.unwatch()


def test_a_process_that_fails_before_it_is_ready_is_the_sandboxs_fault(tmp_path, monkeypatch):
    from qcarlab.sandbox import client

    def broken(plan):
        raise OSError("no limits today")

    monkeypatch.setattr(client, "_rlimits", broken)  # (in the forked student side)
    sub = tmp_path / "submission"
    sub.mkdir()
    (sub / "student.py").write_text(EXITS_71)
    h = BlockHost.start(HostPlan(tmp_path, sub, tmp_path / "out.txt", tmp_path / "err.txt", sandbox=False))
    try:
        with pytest.raises(client.SandboxFailed, match="no limits today"):
            h.load(sub / "student.py")
    finally:
        h.close()
