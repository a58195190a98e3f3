"""Bad input never crashes the server nor leaves the car moving (issue 5): each answer is an error
frame (or a plain HTTP 400) and/or a closed connection, with one log line; others stay served."""

from __future__ import annotations

import math
import struct
import time

import pytest

from qcarlab.wire import protocol as P
from qcarlab.wire.protocol import MsgType as M
from qcarlab.net.server import CarServer
from qcarlab.net.testing import RawClient, SyntheticCar, error_of

OFF = (0.0,) * 12


def wait_for(cond, timeout=2.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not cond():
        time.sleep(0.002)
    return cond()


@pytest.fixture
def server():
    car = SyntheticCar()
    srv = CarServer(car, "127.0.0.1", 0, watchdog=5.0, hello_timeout=0.3, io_timeout=0.3).start()
    watcher = RawClient(srv.address)  # a monitor connected throughout: it must keep being served
    watcher.hello("monitor")
    srv.watcher = watcher
    yield srv
    assert watcher.request(M.PING, b"still here").type == M.PONG
    watcher.close()
    srv.stop()


def peer(raw: RawClient) -> str:
    host, port = raw.sock.getsockname()[:2]
    return f"{host}:{port}"


def lines_about(netlog, raw_peer, word):
    return [line for line in netlog if raw_peer in line and word in line]


def controller_moving(server) -> RawClient:
    raw = RawClient(server.address)
    raw.hello("control")
    assert raw.request(M.COMMAND, P.pack_command(0.2, 0.05, OFF)).type == M.APPLIED
    assert server.car.cmd.throttle == pytest.approx(0.2)
    return raw


@pytest.mark.parametrize(
    "data,code",
    [
        (b"\x00\x01garbage-garbage-garbage", "bad_magic"),
        (P.HEADER.pack(P.MAGIC, 2, M.HELLO, 1, 0, 2) + b"{}", "bad_version"),
        (P.HEADER.pack(P.MAGIC, 1, M.HELLO, 1, 0, P.MAX_REQUEST + 1), "oversized"),
        (P.HEADER.pack(P.MAGIC, 1, M.READ, 1, 0, 0), "bad_hello"),  # the first frame must be HELLO
        (P.HEADER.pack(P.MAGIC, 1, M.HELLO, 1, 0, 5) + b"nope!", "bad_hello"),
        (P.HEADER.pack(P.MAGIC, 1, M.HELLO, 1, 0, 17) + b'{"role":"admin"} ', "bad_version"),
    ],
)
def test_bad_first_frames_get_an_error_and_a_close(server, netlog, data, code):
    with RawClient(server.address) as raw:
        who = peer(raw)
        raw.send_bytes(data)
        err = error_of(raw.recv())
        assert err["code"] == code and err["fatal"]
        assert raw.closed_by_peer()
    assert wait_for(lambda: len(lines_about(netlog, who, code)) == 1)
    assert len([line for line in netlog if who in line]) == 1  # one line, nothing else


def test_bad_role_is_refused(server):
    with RawClient(server.address) as raw:
        err = error_of(raw.request(M.HELLO, P.encode_json({"protocol": 1, "role": "admin"})))
        assert err["code"] == "bad_hello" and "role" in err["message"]
        assert raw.closed_by_peer()


def test_http_speakers_get_a_plain_http_400(server, netlog):
    with RawClient(server.address) as raw:
        who = peer(raw)
        raw.send_bytes(b"GET / HTTP/1.1\r\nHost: car\r\n\r\n")
        assert raw.closed_by_peer() is True
    with RawClient(server.address) as raw:
        raw.send_bytes(b"GET / HTTP/1.1\r\nHost: car\r\n\r\n")
        reply = b""
        raw.sock.settimeout(2.0)
        while chunk := raw.sock.recv(4096):
            reply += chunk
        assert reply.startswith(b"HTTP/1.0 400 Bad Request") and b"qcarlab" in reply
    assert wait_for(lambda: len(lines_about(netlog, who, "HTTP")) == 1)


def test_a_silent_client_is_dropped_after_the_hello_timeout(server, netlog):
    with RawClient(server.address) as raw:
        who = peer(raw)
        t0 = time.monotonic()
        err = error_of(raw.recv())
        assert err["code"] == "timeout" and 0.25 < time.monotonic() - t0 < 1.5
        assert raw.closed_by_peer()
    assert wait_for(lambda: len(lines_about(netlog, who, "no hello")) == 1)


def test_a_frame_left_half_sent_is_dropped(server):
    with RawClient(server.address) as raw:
        raw.hello("monitor")
        raw.send_bytes(P.pack_header(M.PING, 2, 0, 10) + b"abc")
        err = error_of(raw.recv())
        assert err["code"] == "timeout" and "incomplete" in err["message"]
        assert raw.closed_by_peer()


def test_out_of_order_frames_close_the_connection_and_stop_the_car(server, netlog):
    raw = controller_moving(server)
    who = peer(raw)
    raw.send(M.READ, seq=7)  # expected 3
    err = error_of(raw.recv())
    assert err["code"] == "sequence" and "expected 3" in err["message"]
    assert raw.closed_by_peer()
    assert server.car.cmd.throttle == 0.0
    assert wait_for(lambda: len(lines_about(netlog, who, "sequence")) == 1)
    raw.close()


@pytest.mark.parametrize(
    "throttle,steering,leds,field",
    [
        (math.nan, 0.0, OFF, "throttle"),
        (0.1, math.inf, OFF, "steering"),
        (0.1, 0.0, (math.nan,) + OFF[1:], "lamp"),
        (0.1, 0.0, (2.0,) + OFF[1:], "lamp"),
    ],
)
def test_non_finite_commands_are_refused_and_the_car_stops(server, netlog, throttle, steering, leds, field):
    raw = controller_moving(server)
    who = peer(raw)
    err = error_of(raw.request(M.COMMAND, P.pack_command(throttle, steering, leds)))
    assert err["code"] == "bad_value" and not err["fatal"] and field in err["message"]
    assert server.car.cmd.throttle == 0.0  # refused, and the car was stopped
    assert raw.request(M.PING, b"ok").type == M.PONG  # the connection stays
    assert wait_for(lambda: len(lines_about(netlog, who, "bad_value")) == 1)
    raw.close()


def test_a_garbled_command_payload_stops_the_car(server):
    raw = controller_moving(server)
    err = error_of(raw.request(M.COMMAND, b"\x01\x02\x03"))
    assert err["code"] == "bad_payload"
    assert server.car.cmd.throttle == 0.0
    raw.close()


@pytest.mark.parametrize(
    "mtype,payload,code",
    [
        (0x55, b"whatever", "unknown_type"),
        (M.READOUT, b"", "unknown_type"),  # a server-to-client type sent to the server
        (M.HELLO, P.encode_json({"protocol": 1}), "bad_payload"),  # a second hello
        (M.READ, b"unexpected", "bad_payload"),
        (M.PING, b"x" * 65, "bad_payload"),
        (M.ADVANCE, P.pack_scalar(0.1), "not_lockstep"),  # real-time server
        (M.GET_TRUTH, b"", "unsupported"),
    ],
)
def test_requests_that_make_no_sense_get_an_error_and_the_connection_stays(server, mtype, payload, code):
    raw = controller_moving(server)
    err = error_of(raw.request(mtype, payload))
    assert err["code"] == code and not err["fatal"]
    assert raw.request(M.PING, b"ok").type == M.PONG
    raw.close()


def test_bad_advance_values_in_lockstep():
    car = SyntheticCar(stepped=True)
    with CarServer(car, "127.0.0.1", 0) as srv, RawClient(srv.address) as raw:
        raw.hello("control")
        for dt in (math.nan, -1.0, math.inf, P.MAX_ADVANCE * 2):
            err = error_of(raw.request(M.ADVANCE, struct.pack("<d", dt)))
            assert err["code"] == "bad_value"
        assert car.time == 0.0
        assert P.unpack_scalar(raw.request(M.ADVANCE, P.pack_scalar(0.5)).payload, "t") == 0.5


def test_a_failing_backend_is_reported_and_serving_goes_on(server, netlog):
    def broken():
        raise RuntimeError("HIL board unplugged")

    server.car.read = broken
    with RawClient(server.address) as raw:
        raw.hello("monitor")
        err = error_of(raw.request(M.READ))
        assert err["code"] == "car_error" and "unplugged" in err["message"]
        assert raw.request(M.PING, b"").type == M.PONG
    del server.car.read


def test_error_logging_is_rate_limited_per_client(server, netlog):
    with RawClient(server.address) as raw:
        who = peer(raw)
        raw.hello("monitor")
        for _ in range(50):
            assert error_of(raw.request(0x66, b""))["code"] == "unknown_type"
    assert wait_for(lambda: any(who in line and "50 error frames" in line for line in netlog))
    assert len([line for line in netlog if who in line]) <= 8


def test_connect_and_close_at_once_is_harmless(server):
    for _ in range(20):
        RawClient(server.address).close()
    assert server.watcher.request(M.PING, b"").type == M.PONG


def test_hostile_hellos(server, netlog):
    nested = b"[" * 20000 + b"]" * 20000
    with RawClient(server.address) as raw:
        assert error_of(raw.request(M.HELLO, nested))["code"] == "bad_hello"
    tricky = {"protocol": 1, "role": "monitor", "client": "evil\ninfo: fake line\x1b[31m" + "x" * 500}
    with RawClient(server.address) as raw:
        who = peer(raw)
        assert raw.request(M.HELLO, P.encode_json(tricky)).type == M.WELCOME
    assert wait_for(lambda: any(who in line and "disconnected" in line for line in netlog))
    assert all("\n" not in line and "\x1b" not in line for line in netlog)
    srv = CarServer(SyntheticCar(), "127.0.0.1", 0, token="t0ken-long-enough-1234").start()
    try:
        with RawClient(srv.address) as raw:
            frame = raw.request(M.HELLO, b'{"protocol": 1, "role": "monitor", "token": "\\ud800"}')
            assert error_of(frame)["code"] == "bad_token"
    finally:
        srv.stop()
