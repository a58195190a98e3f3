"""``qcarlab ping`` (sheet 3.1): statistics and identity when the car answers (exit 0), one clear
line and exit 1 for refused / timed out / wrong protocol / wrong token, exit 2 for a bad URI."""

from __future__ import annotations

import json
import socket
import threading

import pytest

from qcarlab.cli.net import _stats, normalise_uri
from qcarlab.wire import protocol as P
from qcarlab.net.server import CarServer
from qcarlab.net.testing import SyntheticCar


@pytest.fixture
def server():
    srv = CarServer(SyntheticCar(), "127.0.0.1", 0, token=None).start()
    yield srv
    srv.stop()


class FakePeer:
    """A TCP listener that answers every connection with fixed bytes (or nothing at all)."""

    def __init__(self, answer: bytes | None):
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.answer = answer
        self.conns: list[socket.socket] = []
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.conns.append(conn)
            if self.answer is not None:
                try:
                    conn.recv(1024)
                    conn.sendall(self.answer)
                except OSError:
                    pass

    def close(self):
        self.sock.close()
        for c in self.conns:
            c.close()


def one_line(err: str) -> str:
    """The CLI's own error line (the in-process test server may log lines of its own)."""
    mine = [line for line in err.splitlines() if not line.startswith(("info:", "warning:"))]
    assert len(mine) == 1 and "Traceback" not in err, err
    return mine[0]


def test_ping_a_served_car(cli, server):
    code, out, err = cli("ping", server.uri, "--count", "4", "--interval", "0")
    assert code == 0, err
    assert "synthetic" in out and "protocol v1" in out and "battery 12.00 V" in out
    assert "4 sent, 4 received, 0% loss" in out and "rtt min/avg/max/jitter" in out


def test_ping_json(cli, server):
    code, out, err = cli("ping", server.uri, "-c", "3", "-i", "0.01", "--json")
    assert code == 0, err
    res = json.loads(out)
    assert res["reachable"] is True and res["protocol"] == 1 and res["backend"] == "synthetic"
    assert res["sent"] == 3 and res["received"] == 3 and res["loss"] == 0.0
    assert res["battery_v"] == 12.0 and len(res["samples_ms"]) == 3
    rtt = res["rtt_ms"]
    assert 0 < rtt["min"] <= rtt["avg"] <= rtt["max"] < 1000 and rtt["jitter"] >= 0


def test_ping_accepts_quansers_tcpip_form_and_bare_hosts(cli, server):
    port = server.address[1]
    assert cli("ping", f"tcpip://127.0.0.1:{port}", "-c", "1")[0] == 0
    assert cli("ping", f"127.0.0.1:{port}", "-c", "1")[0] == 0
    assert normalise_uri("192.168.2.15") == ("192.168.2.15", P.DEFAULT_PORT)


def test_refused(cli):
    probe = socket.create_server(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # nothing listens there now
    code, out, err = cli("ping", f"tcp://127.0.0.1:{port}", "-c", "1")
    assert code == 1 and "connection refused" in one_line(err)


def test_timed_out(cli):
    silent = FakePeer(answer=None)  # accepts, never says a word
    try:
        code, out, err = cli("ping", f"tcp://127.0.0.1:{silent.port}", "-c", "1", "--timeout", "0.3")
    finally:
        silent.close()
    assert code == 1 and "timed out" in one_line(err)


def test_wrong_protocol(cli):
    web = FakePeer(answer=b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\nhi")
    try:
        code, out, err = cli("ping", f"tcp://127.0.0.1:{web.port}", "-c", "1", "--timeout", "1")
    finally:
        web.close()
    assert code == 1 and "wrong protocol" in one_line(err) and "HTTP" in err


def test_wrong_protocol_version(cli):
    future = FakePeer(answer=P.HEADER.pack(P.MAGIC, 2, P.MsgType.WELCOME, 1, 1, 0))
    try:
        code, out, err = cli("ping", f"tcp://127.0.0.1:{future.port}", "-c", "1", "--timeout", "1")
    finally:
        future.close()
    assert code == 1 and "wrong protocol version" in one_line(err)


def test_wrong_token(cli, monkeypatch):
    monkeypatch.delenv("QCARLAB_TOKEN", raising=False)
    srv = CarServer(SyntheticCar(), "127.0.0.1", 0, token="the-real-one-0123456789").start()
    try:
        code, out, err = cli("ping", srv.uri, "-c", "1", "--token", "a-guess")
        assert code == 1 and "wrong token" in one_line(err)
        code, out, err = cli("ping", srv.uri, "-c", "1")
        assert code == 1 and "wrong token" in err
        code, out, err = cli("ping", srv.uri, "-c", "1", "--token", "the-real-one-0123456789")
        assert code == 0, err
    finally:
        srv.stop()


def test_json_failure_says_why(cli):
    probe = socket.create_server(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    code, out, err = cli("ping", f"tcp://127.0.0.1:{port}", "-c", "1", "--json")
    assert code == 1
    res = json.loads(out)
    assert res["reachable"] is False and res["reason"] == "refused"


@pytest.mark.parametrize("uri", ["sim", "ftp://car:1", "tcp://car:99999", "tcp://car"])
def test_bad_uri_is_exit_2(cli, uri):
    code, out, err = cli("ping", uri, "-c", "1")
    assert code == 2 and "error" in one_line(err)


def test_lockstep_server_before_any_readout_still_answers(cli):
    srv = CarServer(SyntheticCar(stepped=True), "127.0.0.1", 0).start()
    try:
        code, out, err = cli("ping", srv.uri, "-c", "2", "-i", "0")
    finally:
        srv.stop()
    assert code == 0 and "battery unknown" in out and "lock-step" in out


def test_stats():
    s = _stats([0.001, 0.003, 0.002])
    assert s["min"] == pytest.approx(1.0) and s["max"] == pytest.approx(3.0) and s["avg"] == pytest.approx(2.0)
    assert s["jitter"] == pytest.approx(1.5)  # mean |difference| of consecutive samples
    assert _stats([])["avg"] is None


def test_the_server_listens_only_once_it_can_answer(cli, monkeypatch):
    """While the car gets ready (sensors, compiled physics) nothing listens: a client is refused at
    once rather than left waiting in the backlog, and the first one after start() is answered."""
    import time

    from qcarlab.car.sim import SimCar

    car = SimCar()
    slow = car.prepare_sensors

    def prepare() -> None:
        time.sleep(1.0)
        slow()

    monkeypatch.setattr(car, "prepare_sensors", prepare)
    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    server = CarServer(car, "127.0.0.1", port, prepare=True)
    started = threading.Thread(target=server.start)
    started.start()
    try:
        time.sleep(0.3)  # bound, still preparing
        with pytest.raises(ConnectionRefusedError):
            socket.create_connection(("127.0.0.1", port), timeout=2).close()
        started.join(30)
        code, out, err = cli("ping", f"tcp://127.0.0.1:{port}", "--count", "2")
        assert code == 0, err
    finally:
        started.join(30)
        server.stop()
