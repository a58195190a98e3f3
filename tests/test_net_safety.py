"""The server's safety rules (issue 5): watchdog, dropped connection, one controller, server-side
limits, token for non-loopback binds, shutdown."""

from __future__ import annotations

import time

import pytest

from qcarlab.car.lamps import LAMP_NAMES
from qcarlab.car.tcp import TcpCar, TcpConnectError
from qcarlab.errors import CarError, InputError
from qcarlab.wire import protocol as P
from qcarlab.wire.protocol import MsgType as M
from qcarlab.net.server import CarServer, is_loopback
from qcarlab.net.testing import RawClient, SyntheticCar, error_of


def cli_error_lines(err: str) -> int:
    """Lines the CLI itself printed (an in-process test server may log lines of its own)."""
    return len([line for line in err.splitlines() if not line.startswith(("info:", "warning:"))])


def wait_for(cond, timeout=2.0, step=0.002):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(step)
    return cond()


@pytest.fixture
def served():
    servers = []

    def make(car=None, **kw):
        car = car if car is not None else SyntheticCar()
        kw.setdefault("hello_timeout", 0.5)
        server = CarServer(car, kw.pop("host", "127.0.0.1"), 0, **kw).start()
        servers.append(server)
        return server, car

    yield make
    for server in servers:
        server.stop()


def connect(server, **kw):
    """A TCP car on ``server``. (No retry on ``busy``: a controller that has just closed is gone
    for the server at once, which test_net_hardening checks; a ``busy`` here is a real one.)"""
    host, port = server.address
    return TcpCar(host, port, timeout=2.0, **kw)


def lamps_on(leds):
    return {name for name, v in zip(LAMP_NAMES, leds) if v > 0}


def test_watchdog_stops_the_car_with_hazard_lamps_in_time(served, netlog):
    server, car = served(watchdog=0.1)
    with connect(server) as ctl, connect(server, role="monitor") as mon:
        sending = time.monotonic()  # the server hears the command after this...
        ctl.write(0.2, 0.1)
        sent = time.monotonic()  # ...and before this
        assert mon.read().throttle == pytest.approx(0.2)
        assert wait_for(lambda: car.cmd.throttle == 0.0, timeout=1.0)
        stopped = time.monotonic()
        assert stopped - sending >= 0.09 and stopped - sent <= 0.1 + 0.15  # not early; not late
        r = mon.read()
        assert r.throttle == 0.0 and r.steering == 0.0
        assert {"indicator_front_left", "indicator_front_right", "indicator_rear_left", "indicator_rear_right"} <= lamps_on(r.leds)
        assert mon.status & P.STATUS_WATCHDOG
        assert wait_for(lambda: any("watchdog" in line for line in netlog))
        ctl.write(0.1, 0.0)  # a new command takes over again
        assert car.cmd.throttle == pytest.approx(0.1) and not server.tripped


def test_steady_commands_keep_the_watchdog_fed(served):
    server, car = served(watchdog=0.15)
    with connect(server) as ctl:
        for _ in range(12):
            ctl.write(0.2, 0.0)
            time.sleep(0.03)
        assert server.trips == 0 and car.cmd.throttle == pytest.approx(0.2)


def test_reads_alone_do_not_feed_the_watchdog(served):
    server, car = served(watchdog=0.08)
    with connect(server) as ctl:
        ctl.write(0.2, 0.0)
        for _ in range(20):
            ctl.read()
            time.sleep(0.01)
        assert server.trips == 1 and car.cmd.throttle == 0.0


def test_dropped_connection_stops_the_car_at_once(served, netlog):
    server, car = served(watchdog=5.0)  # long watchdog: the drop alone must stop the car
    raw = RawClient(server.address)
    raw.hello("control")
    assert raw.request(M.COMMAND, P.pack_command(0.2, 0.0, (0.0,) * 12)).type == M.APPLIED
    assert car.cmd.throttle == pytest.approx(0.2)
    t0 = time.monotonic()
    raw.close()  # no bye: a cable pulled, a laptop asleep, a crash
    assert wait_for(lambda: car.cmd.throttle == 0.0, timeout=1.0)
    assert time.monotonic() - t0 < 0.1
    assert wait_for(lambda: any("car stopped" in line for line in netlog))


def test_one_controller_many_read_only_monitors(served):
    server, car = served()
    ctl = connect(server)
    with pytest.raises(TcpConnectError) as busy:
        connect(server)
    assert busy.value.kind == "busy" and "controlled by" in str(busy.value)
    monitors = [connect(server, role="monitor") for _ in range(3)]
    ctl.write(0.15, 0.0)
    assert all(m.read().throttle == pytest.approx(0.15) for m in monitors)
    with pytest.raises(CarError, match="monitor"):
        monitors[0].write(0.3, 0.0)
    with RawClient(server.address) as raw:  # a monitor that sends commands anyway
        raw.hello("monitor")
        for mtype, payload in ((M.COMMAND, P.pack_command(0.3, 0.0, (0.0,) * 12)), (M.STOP, b""), (M.ADVANCE, P.pack_scalar(1.0))):
            err = error_of(raw.request(mtype, payload))
            assert err["code"] == "read_only" and not err["fatal"]
        assert raw.request(M.PING, b"x").type == M.PONG  # still connected
    assert car.cmd.throttle == pytest.approx(0.15)  # nobody but the controller moved it
    ctl.close()
    with connect(server) as second:  # the role is free again
        second.write(0.05, 0.0)
    for m in monitors:
        m.close()


def test_throttle_limit_is_enforced_by_the_server(served):
    server, car = served(car=SyntheticCar(throttle_limit=0.2))
    with RawClient(server.address) as raw:  # a client that ignores every limit
        raw.hello("control")
        thr, ste, _ = P.unpack_applied(raw.request(M.COMMAND, P.pack_command(0.9, 2.0, (0.0,) * 12)).payload)
        assert (thr, ste) == (0.2, pytest.approx(0.5))  # the car's steering limit, +-0.5 rad
        thr, _, _ = P.unpack_applied(raw.request(M.COMMAND, P.pack_command(-5.0, 0.0, (0.0,) * 12)).payload)
        assert thr == -0.2 and car.cmd.throttle == -0.2
    assert wait_for(lambda: server.controller is None)  # the server has seen the raw client go
    with connect(server, throttle_limit=0.3) as ctl:
        assert ctl.throttle_limit == 0.2  # the client adopts the stricter server limit
        assert ctl.write(0.3, 0.0).throttle == 0.2


def test_non_loopback_bind_needs_a_token(served):
    car = SyntheticCar()
    with pytest.raises(InputError, match="without a token"):
        CarServer(car, "0.0.0.0", 0).start()
    server, _ = served(car=car, host="0.0.0.0", token="s3cret-token-0123456789")
    port = server.address[1]
    with pytest.raises(TcpConnectError) as missing:
        TcpCar("127.0.0.1", port, timeout=2.0)
    assert missing.value.kind == "token"
    with pytest.raises(TcpConnectError) as wrong:
        TcpCar("127.0.0.1", port, token="guess", timeout=2.0)
    assert wrong.value.kind == "token" and "QCARLAB_TOKEN" in str(wrong.value)
    with TcpCar("127.0.0.1", port, token="s3cret-token-0123456789", timeout=2.0) as ok:
        ok.write(0.1, 0.0)


def test_token_from_the_environment(served, monkeypatch):
    server, _ = served(token="from-env-123-abcdefgh")
    monkeypatch.setenv("QCARLAB_TOKEN", "from-env-123-abcdefgh")
    with connect(server, role="monitor") as mon:
        assert mon.ping() > 0


def test_serve_cli_refuses_non_loopback_without_token(cli, monkeypatch):
    monkeypatch.delenv("QCARLAB_TOKEN", raising=False)
    code, out, err = cli("serve", "--host", "0.0.0.0", "--port", "0")
    assert code == 2
    assert cli_error_lines(err) == 1 and "without a token" in err and "Traceback" not in err


@pytest.mark.parametrize("host,loop", [("127.0.0.1", True), ("127.5.0.1", True), ("localhost", True), ("::1", True),
                                       ("0.0.0.0", False), ("", False), ("192.168.2.15", False)])
def test_is_loopback(host, loop):
    assert is_loopback(host) is loop


def test_stopping_the_server_says_bye_and_stops_the_car(netlog):
    car = SyntheticCar()
    server = CarServer(car, "127.0.0.1", 0).start()
    raw = RawClient(server.address)
    raw.hello("control")
    raw.request(M.COMMAND, P.pack_command(0.2, 0.0, (0.0,) * 12))
    t0 = time.monotonic()
    server.stop()
    assert time.monotonic() - t0 < 2.0
    frame = raw.recv()
    assert frame is not None and frame.type == M.BYE
    assert car.cmd.throttle == 0.0
    raw.close()


def test_too_many_clients_get_an_error_and_the_rest_keep_working(served):
    server, _ = served(max_clients=3)  # two monitors, and one slot kept for a controller
    a, b = connect(server, role="monitor"), connect(server, role="monitor")
    with pytest.raises(TcpConnectError) as full:
        connect(server, role="monitor")
    assert full.value.kind == "full" and "kept for a controller" in str(full.value)
    with connect(server) as ctl:  # the reserved slot
        ctl.write(0.1, 0.0)
    assert a.ping() > 0 and b.ping() > 0
    a.close()
    b.close()
