"""The server as a lab's cars need it (issue 16): each failure found by probing it from outside,
reproduced on loopback, bounded in count and time. The tight figures live in benchmarks/bench_net.py;
the bounds here are loose enough for a loaded 2-core machine and still fail the old behaviour."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from qcarlab.car.sim import SimCar
from qcarlab.car.tcp import TcpCar, TcpConnectError
from qcarlab.errors import InputError
from qcarlab.net import guard
from qcarlab.wire import protocol as P
from qcarlab.wire.protocol import MsgType as M
from qcarlab.net.server import CarServer
from qcarlab.net.testing import RawClient, SyntheticCar, error_of

OFF = (0.0,) * 12
TOKEN = "lab-car-7-0123456789abcdef"


def wait_for(cond, timeout=3.0, step=0.002):
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
        server = CarServer(car, kw.pop("host", "127.0.0.1"), 0, **kw).start()
        servers.append(server)
        return server, car

    yield make
    for server in servers:
        server.stop()


def drive(raw: RawClient, throttle: float = 0.2) -> None:
    assert raw.request(M.COMMAND, P.pack_command(throttle, 0.0, OFF)).type == M.APPLIED


# --- 1. the watchdog waits for nothing ----------------------------------------------------------------
def test_a_slow_sensor_read_does_not_delay_the_watchdog(served):
    """Was: the watchdog waited for the car lock a sensor reading held (557-754 ms for 0.25 s)."""
    server, car = served(car=SyntheticCar(sensor_delay=1.5), watchdog=0.1)
    with RawClient(server.address) as ctl, RawClient(server.address, timeout=5.0) as mon:
        ctl.hello("control")
        mon.hello("monitor")
        drive(ctl)
        mon.send(M.GET_RGBD)  # a reading that takes 1.5 s starts now; the controller falls silent
        last = time.monotonic()
        assert wait_for(lambda: car.cmd.throttle == 0.0, timeout=1.0)
        assert time.monotonic() - last < 0.1 + 0.2  # the watchdog, not the sensor, decided
        assert server.sensors.readings[M.RGBD] == 0  # the reading was still under way
        # and control is not held up by it either: a command goes through at once
        t0 = time.monotonic()
        drive(ctl, 0.1)
        assert time.monotonic() - t0 < 0.5 and car.cmd.throttle == pytest.approx(0.1)
        frame = mon.recv()
        assert frame is not None and frame.type == M.RGBD


def test_a_backend_without_its_own_sensor_path_is_read_under_the_lock(served):
    """The Car default (sensor_job reads at once) stays correct: the reading is serialised with the
    drive I/O, as a backend whose sensors share its bus needs."""
    server, car = served(car=SyntheticCar(sensor_delay=0.3, own_sensor_path=False), watchdog=5.0)
    with RawClient(server.address) as ctl, RawClient(server.address) as mon:
        ctl.hello("control")
        mon.hello("monitor")
        mon.send(M.GET_LIDAR)
        time.sleep(0.05)
        t0 = time.monotonic()
        drive(ctl)
        assert time.monotonic() - t0 > 0.15  # waited for the reading
        assert mon.recv().type == M.LIDAR


def test_the_simulators_first_lidar_read_does_not_delay_the_watchdog(served):
    """The issue's case: a monitor makes the simulator's first LIDAR read (it loads the world and
    builds the sensor) while the controller is silent. numba's kernels are made ready first, as
    ``qcarlab serve`` has them (its render process draws the sensors): in a fresh clone the LIDAR's
    first compiled scan compiles them, once per install, and LLVM holds the GIL for 0.1-0.25 s at a
    time (trips of 0.20 and 0.33 s in fresh clones under the whole suite; 0.100 s with them ready,
    at load 4). The world and the sensor stay this car's to build."""
    warm = SimCar(seed=0, on_stand=True)  # another car, another world: only the kernels are shared
    warm.warm_physics()  # numba loaded (the LIDAR scans through its kernel only then) ...
    warm.read_lidar()  # ... and the scan's kernels compiled or loaded
    car = SimCar(seed=0, realtime=True, on_stand=True)
    server, _ = served(car=car, watchdog=0.1)
    with RawClient(server.address) as ctl, RawClient(server.address, timeout=15.0) as mon:
        ctl.hello("control")
        mon.hello("monitor")
        drive(ctl)
        mon.send(M.GET_LIDAR)
        last = time.monotonic()
        with RawClient(server.address) as probe:
            probe.hello("monitor")
            assert wait_for(lambda: P.unpack_readout(probe.request(M.READ).payload)[0]["throttle"] == 0.0, timeout=2.0)
        assert time.monotonic() - last < 0.1 + 0.3
        assert server.trip_delays[0] < 0.1 + 0.15  # as the server timed it (was: + 0.3-0.5 s, the physics
        assert mon.recv().type == M.LIDAR         # switching to its compiled kernel under the drive lock)


def test_a_server_that_prepares_its_simulator_has_the_lidars_compiled_scan_ready(served):
    """``prepare`` (as ``qcarlab serve`` has it) compiles or loads the LIDAR's kernels before the
    server listens: a fresh install's first LIDAR read would compile them under the GIL the
    watchdog needs."""
    from qcarlab.sim import _kernels, lidar

    car = SimCar(seed=0, on_stand=True)
    served(car=car, watchdog=0.1, prepare=True)
    if lidar.load_compiled() is not None:  # (numba installed)
        assert _kernels.lidar_scan_edges.signatures
    first = car.read_lidar()
    again = SimCar(seed=0, on_stand=True).read_lidar()  # prepare drew no noise: the same first scan
    assert np.array_equal(first.ranges, again.ranges)


# --- 2. deadlines per handshake and per frame ----------------------------------------------------------
def trickle(raw: RawClient, data: bytes, every: float, until_closed_within: float) -> tuple[bool, float]:
    """Send ``data`` a byte at a time; (closed by the server, seconds it took)."""
    t0 = time.monotonic()
    for byte in data:
        try:
            raw.send_bytes(bytes([byte]))
        except OSError:
            return True, time.monotonic() - t0
        time.sleep(every)
        if time.monotonic() - t0 > until_closed_within:
            break
    return raw.closed_by_peer(1.0), time.monotonic() - t0


def test_a_hello_sent_a_byte_at_a_time_is_cut_off_at_the_hello_deadline(served, netlog):
    """Was: a HELLO sent a byte a second was accepted after 35 s (the timeout was per recv)."""
    server, _ = served(hello_timeout=0.5)
    hello = P.pack_header(M.HELLO, 1, 0, 40) + P.encode_json({"protocol": 1, "role": "monitor", "client": "x"}).ljust(40)
    with RawClient(server.address) as raw:
        closed, took = trickle(raw, hello, every=0.05, until_closed_within=3.0)
    assert closed and took < 0.5 + 0.8  # 56 bytes at 50 ms would take 2.8 s
    assert wait_for(lambda: any("no complete HELLO" in line for line in netlog))


def test_a_frame_sent_a_byte_at_a_time_is_cut_off_at_the_frame_deadline(served):
    """Was: a frame sent a byte every 4 s stayed open past 48 s (docs: 5 s)."""
    server, car = served(io_timeout=0.5, watchdog=5.0)
    with RawClient(server.address) as raw:
        raw.hello("control")
        drive(raw)
        frame = P.pack_header(M.COMMAND, 3, 0, P.COMMAND.size) + P.pack_command(0.3, 0.0, OFF)
        closed, took = trickle(raw, frame, every=0.05, until_closed_within=4.0)
    assert closed and took < 0.5 + 0.8  # 132 bytes at 50 ms would take 6.6 s
    assert car.cmd.throttle == 0.0  # the controller was dropped: the car stopped


def test_an_idle_client_that_said_hello_may_stay(served):
    server, _ = served(io_timeout=0.3)
    with RawClient(server.address) as raw:
        raw.hello("monitor")
        time.sleep(0.8)
        assert raw.request(M.PING, b"still").type == M.PONG


# --- 3. connections that never say hello, the controller's slot, the log ----------------------------------
def test_connections_without_hello_cannot_lock_a_token_server_out(served):
    """Was: sixteen slow connections without a token held every slot (too_many_clients for everyone)."""
    server, _ = served(token=TOKEN, max_pending=4, max_clients=4)
    squatters = []
    for _ in range(16):  # each sends half a hello and stalls
        raw = RawClient(server.address)
        raw.send_bytes(P.pack_header(M.HELLO, 1, 0, 50) + b'{"protocol": 1,')
        squatters.append(raw)
    try:
        with TcpCar(*server.address, token=TOKEN, timeout=3.0) as ctl:
            ctl.write(0.1, 0.0)
        with TcpCar(*server.address, token=TOKEN, role="monitor", timeout=3.0) as mon:
            assert mon.ping() > 0
        assert server.evicted >= 12
    finally:
        for raw in squatters:
            raw.close()


def test_reconnecting_sockets_that_never_say_hello_neither_refuse_clients_nor_flood_the_log(served, netlog):
    """Was: sixteen reconnecting silent sockets got a real client refused 100 of 100 times and wrote
    147,553 log lines in 20 s."""
    server, _ = served(max_pending=8, hello_timeout=0.3)
    stop = threading.Event()
    opened = [0]

    def squat():
        while not stop.is_set():
            try:
                s = socket.create_connection(server.address, timeout=1.0)
                opened[0] += 1
                time.sleep(0.01)
                s.close()
            except OSError:
                pass

    threads = [threading.Thread(target=squat, daemon=True) for _ in range(16)]
    for t in threads:
        t.start()
    try:
        time.sleep(0.3)
        ok = 0
        for _ in range(20):
            try:
                with TcpCar(*server.address, role="monitor", timeout=3.0, connect_timeout=3.0) as mon:
                    mon.ping()
                    ok += 1
            except TcpConnectError:
                pass
    finally:
        stop.set()
        for t in threads:
            t.join(5)
    assert ok == 20
    assert opened[0] > 100
    assert len([line for line in netlog if "no hello" in line or "refused" in line]) <= 10


def test_refusals_are_counted_not_logged_one_by_one(netlog):
    clock = [0.0]
    refusals = guard.RefusalLog(__import__("logging").getLogger("qcarlab.net"), interval=10.0, clock=lambda: clock[0])
    for i in range(500):
        refusals.refused("busy", "%s refused: busy", f"10.0.0.{i % 250}:5000")
    refusals.refused("bad_token", "%s refused: bad token", "10.0.0.9:1")
    assert netlog == ["10.0.0.0:5000 refused: busy", "10.0.0.9:1 refused: bad token"]
    clock[0] = 10.5
    refusals.flush()
    assert len(netlog) == 3 and "refused 499 more connections in the last 10 s (busy 499)" in netlog[2]
    refusals.flush()
    assert len(netlog) == 3  # nothing new: no line


def test_monitors_cannot_take_the_controllers_slot(served):
    """Was: 16 idle monitors locked the controller out (no reserved slot)."""
    server, car = served(max_clients=4)
    monitors = [TcpCar(*server.address, role="monitor", timeout=2.0) for _ in range(3)]
    try:
        with pytest.raises(TcpConnectError) as full:
            TcpCar(*server.address, role="monitor", timeout=2.0)
        assert full.value.kind == "full"
        with TcpCar(*server.address, timeout=2.0) as ctl:
            ctl.write(0.1, 0.0)
            assert car.cmd.throttle == pytest.approx(0.1)
    finally:
        for m in monitors:
            m.close()


# --- 4. a frozen controller --------------------------------------------------------------------------
def test_a_frozen_controller_loses_control_to_the_next_one(served, netlog):
    """Was: a laptop that slept or left the Wi-Fi held the car forever (busy for everyone else)."""
    server, car = served(watchdog=0.05, controller_timeout=0.3)
    frozen = RawClient(server.address)
    frozen.hello("control")
    froze = time.monotonic()  # before its last command: the server last heard it no earlier than this
    drive(frozen)  # from now on it sends nothing and reads nothing
    with pytest.raises(TcpConnectError) as busy:
        TcpCar(*server.address, timeout=2.0)
    assert busy.value.kind == "busy" and "silent for 0.3 s" in str(busy.value)
    took = None
    deadline = froze + 3.0
    while time.monotonic() < deadline:
        try:
            ctl = TcpCar(*server.address, timeout=2.0)
        except TcpConnectError as exc:
            assert exc.kind == "busy"
            time.sleep(0.01)
            continue
        took = time.monotonic() - froze
        break
    assert took is not None and 0.3 <= took < 0.3 + 1.5  # not before its silence; then soon (load 8: 1.5 s)
    assert car.cmd.throttle == 0.0 and server.takeovers == 1
    with ctl:
        ctl.write(0.15, 0.0)
        assert car.cmd.throttle == pytest.approx(0.15)
        err = error_of(frozen.recv())  # the laptop wakes up: it is told, and disconnected
        assert err["code"] == "control_lost" and err["fatal"]
        assert frozen.closed_by_peer()
        assert car.cmd.throttle == pytest.approx(0.15)  # its leaving does not stop the new controller's car
    frozen.close()
    assert wait_for(lambda: any("control passed to" in line for line in netlog))


def test_a_controller_that_froze_before_its_first_command_loses_control_too(served):
    """The watchdog is armed by the first command; a controller that never sent one (the car stands
    stopped) and falls silent is taken over all the same."""
    server, car = served(watchdog=0.05, controller_timeout=0.3)
    with RawClient(server.address) as frozen:
        froze = time.monotonic()  # before the hello: the server last heard it no earlier than this
        frozen.hello("control")
        with pytest.raises(TcpConnectError) as busy:
            TcpCar(*server.address, timeout=2.0)
        assert busy.value.kind == "busy"
        while True:
            try:
                ctl = TcpCar(*server.address, timeout=2.0)
                break
            except TcpConnectError as exc:
                assert exc.kind == "busy" and time.monotonic() - froze < 3.0
                time.sleep(0.01)
        assert time.monotonic() - froze >= 0.3
        with ctl:
            ctl.write(0.1, 0.0)
            assert car.cmd.throttle == pytest.approx(0.1)
        assert error_of(frozen.recv())["code"] == "control_lost"


def test_the_watchdog_is_armed_at_once_by_the_first_command(served):
    server, car = served(watchdog=0.05)
    with RawClient(server.address) as ctl:
        ctl.hello("control")
        time.sleep(0.3)  # unarmed: no trip, the car stands stopped
        assert server.trips == 0
        drive(ctl)
        assert wait_for(lambda: car.cmd.throttle == 0.0, timeout=1.0)
        assert server.trips == 1
        assert server.trip_delays[-1] < 0.05 + 0.04  # as the server timed it: not a 0.1 s idle wait late


def test_a_controller_that_keeps_talking_keeps_control(served):
    """Stopped by the watchdog but still reading (a parked car being watched): not stale."""
    server, car = served(watchdog=0.05, controller_timeout=0.2)
    with RawClient(server.address) as ctl:
        ctl.hello("control")
        drive(ctl)
        for _ in range(40):  # 0.4 s of reads, no command
            assert ctl.request(M.READ).type == M.READOUT
            time.sleep(0.01)
        assert server.tripped
        with pytest.raises(TcpConnectError) as busy:
            TcpCar(*server.address, timeout=2.0)
        assert busy.value.kind == "busy"
        drive(ctl, 0.1)  # and it drives again
        assert car.cmd.throttle == pytest.approx(0.1)


def test_a_controller_that_has_just_closed_is_not_busy(served):
    """A client that closes and reconnects at once gets control (was: busy, now and then)."""
    server, car = served()
    for i in range(30):
        raw = RawClient(server.address)
        raw.hello("control")
        drive(raw, 0.01 * (i % 3 + 1))
        raw.close()
    with TcpCar(*server.address, timeout=2.0) as ctl:
        ctl.write(0.1, 0.0)


def test_a_controller_that_never_reads_its_replies_is_dropped_and_the_car_stopped(served, netlog):
    """Was: never noticed."""
    server, car = served(watchdog=0.1, io_timeout=0.5)
    raw = RawClient(server.address)
    raw.hello("control")
    raw.sock.settimeout(None)  # whole frames only: the send blocks until the server reads or closes
    guard_timer = threading.Timer(10.0, raw.close)  # bound the test if the server never gives up
    guard_timer.start()
    command = P.pack_command(0.2, 0.0, OFF, P.FLAG_READ_BACK)
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < 10.0:
            raw.send(M.COMMAND, command)
    except OSError:
        pass  # the server stopped reading, then closed
    guard_timer.cancel()
    try:
        assert wait_for(lambda: not server.sessions, timeout=5.0)
        assert car.cmd.throttle == 0.0
        assert time.monotonic() - t0 < 10.0
        assert wait_for(lambda: any("not reading its replies" in line for line in netlog))
    finally:
        raw.close()


# --- 5. camera monitors and the controller ----------------------------------------------------------------
def test_monitors_get_sensor_frames_at_the_servers_rate_and_share_them(served):
    """Was: each monitor's frame was read for it, as often as it asked (flat out: the controller
    missed 2,634 of 3,000 ticks)."""
    server, car = served(monitor_rate=10.0, watchdog=5.0)
    counts = []
    stop = threading.Event()

    def watch():
        n = 0
        with TcpCar(*server.address, role="monitor", timeout=5.0) as mon:
            while not stop.is_set():
                mon.read_rgbd()
                n += 1
        counts.append(n)

    threads = [threading.Thread(target=watch) for _ in range(4)]
    with TcpCar(*server.address, timeout=5.0) as ctl:
        for t in threads:
            t.start()
        t0 = time.monotonic()
        commands = 0
        while time.monotonic() - t0 < 1.0:
            ctl.write(0.1, 0.0)
            commands += 1
            time.sleep(0.005)
        stop.set()
        for t in threads:
            t.join(5)
        elapsed = time.monotonic() - t0
        assert ctl.read_rgbd().color.shape == (480, 640, 3)  # the controller is not paced
    assert len(counts) == 4
    assert all(2 <= n <= 10.0 * elapsed + 3 for n in counts), counts  # at most the rate, flat out
    assert server.sensors.readings[M.RGBD] <= 10.0 * elapsed + 4  # shared: one reading serves them all
    assert commands >= 20 and server.trips == 0  # the controller was never held up for long


def test_monitor_pacing_never_touches_the_controller(served):
    server, car = served(monitor_rate=2.0)
    with TcpCar(*server.address, timeout=5.0) as ctl:
        t0 = time.monotonic()
        for _ in range(10):
            ctl.read_lidar()
        assert time.monotonic() - t0 < 1.0  # ten frames in well under the monitors' 5 s


# --- 7. loopback, tokens ---------------------------------------------------------------------------------
def test_localhost_mapped_elsewhere_is_not_trusted(monkeypatch):
    """Was: "localhost" was trusted by name; a hosts file mapping it elsewhere opened the car to a network."""
    real = socket.getaddrinfo

    def hosts_file(host, *args, **kw):
        return real("0.0.0.0" if host == "localhost" else host, *args, **kw)

    monkeypatch.setattr(socket, "getaddrinfo", hosts_file)
    from qcarlab.net.server import is_loopback

    assert not is_loopback("localhost")
    with pytest.raises(InputError, match="without a token"):
        CarServer(SyntheticCar(), "localhost", 0).start()
    server = CarServer(SyntheticCar(), "localhost", 0, token=TOKEN).start()
    try:
        assert server.address[0] == "0.0.0.0" and not server.loopback
    finally:
        server.stop()


def test_serve_cli_decides_loopback_by_address(cli, monkeypatch):
    real = socket.getaddrinfo
    monkeypatch.setattr(socket, "getaddrinfo", lambda host, *a, **k: real("0.0.0.0" if host == "localhost" else host, *a, **k))
    monkeypatch.delenv("QCARLAB_TOKEN", raising=False)
    code, out, err = cli("serve", "--host", "localhost", "--port", "0")
    assert code == 2 and "without a token" in err and "Traceback" not in err


@pytest.mark.parametrize("token", ["x", "s3cret", "fifteen-chars-x"])
def test_short_tokens_are_refused_with_a_hint(token, cli, monkeypatch):
    with pytest.raises(InputError, match="at least 16 characters.*--new-token"):
        CarServer(SyntheticCar(), "127.0.0.1", 0, token=token)
    monkeypatch.setenv("QCARLAB_TOKEN", token)
    code, out, err = cli("serve", "--port", "0")
    assert code == 2 and "--new-token" in err


def test_new_token_prints_a_usable_token(cli, served):
    code, out, err = cli("serve", "--new-token")
    token = out.strip()
    assert code == 0 and len(token) >= 32 and token.isprintable() and " " not in token
    server, _ = served(token=token)
    with TcpCar(*server.address, token=token, role="monitor") as mon:
        assert mon.ping() > 0


def test_wrong_tokens_slow_down_per_address(served):
    """Was: no limit on guesses (about 1,950 per second)."""
    server, _ = served(token=TOKEN)
    t0 = time.monotonic()
    waits = []
    for i in range(6):
        with RawClient(server.address) as raw:
            err = error_of(raw.hello("monitor", token=f"guess-number-{i:04d}-xxxx"))
            assert err["code"] == "bad_token"
            waits.append(err.get("retry_after_s") or 0.0)
    assert waits[:3] == [0.0, 0.0, 0.0] and waits[3] == pytest.approx(0.5)
    # during the wait even the right token is not compared
    with pytest.raises(TcpConnectError) as slow:
        TcpCar(*server.address, token=TOKEN, role="monitor")
    assert slow.value.kind == "token" and "try again in" in str(slow.value)
    attempts = 0
    while True:  # a client that retries: it gets in once its wait is over, not before
        attempts += 1
        try:
            with TcpCar(*server.address, token=TOKEN, role="monitor") as mon:
                assert mon.ping() > 0
            break
        except TcpConnectError:
            time.sleep(0.05)
        assert time.monotonic() - t0 < 10.0
    assert server.tokens.failures("127.0.0.1") == 0  # the right token clears the address


def test_the_slow_down_schedule():
    clock = [100.0]
    g = guard.TokenGuard(clock=lambda: clock[0])
    assert [g.failed("a") for _ in range(8)] == [0.0, 0.0, 0.0, 0.5, 1.0, 2.0, 4.0, 8.0]
    assert g.wait_s("a") == 8.0 and g.wait_s("b") == 0.0  # per address
    for _ in range(10):
        g.failed("a")
    assert g.wait_s("a") == guard.MAX_S
    clock[0] += guard.FORGET_S + 1
    assert g.wait_s("a") == 0.0 and g.failures("a") == 0


def test_token_comparison_hides_length_and_value():
    assert guard.token_matches(TOKEN, TOKEN)
    assert not guard.token_matches(TOKEN[:-1], TOKEN) and not guard.token_matches(None, TOKEN)
    assert not guard.token_matches("\ud800", TOKEN)


# --- 8. small ones -------------------------------------------------------------------------------------
@pytest.mark.parametrize("uri", ["tcp://[::1", "[::1", "tcp://::1:18960", "tcp://[]:5", "tcp://car park:5"])
def test_ping_with_a_malformed_uri_is_bad_input(cli, uri):
    """Was: `qcarlab ping 'tcp://[::1'` exited 1 with "unknown host ':'"."""
    code, out, err = cli("ping", uri, "-c", "1")
    assert code == 2 and "error" in err and "unknown host" not in err


def test_ping_over_ipv6_loopback(cli):
    if not socket.has_ipv6:
        pytest.skip("no IPv6 here")
    try:
        server = CarServer(SyntheticCar(), "::1", 0).start()
    except Exception:
        pytest.skip("no IPv6 loopback here")
    try:
        code, out, err = cli("ping", f"tcp://[::1]:{server.address[1]}", "-c", "1")
        assert code == 0, err
    finally:
        server.stop()


def test_a_command_with_reserved_flag_bits_is_refused_and_the_car_stopped(served):
    """Was: accepted."""
    server, car = served(watchdog=5.0)
    with RawClient(server.address) as raw:
        raw.hello("control")
        drive(raw)
        err = error_of(raw.request(M.COMMAND, P.pack_command(0.3, 0.0, OFF, 0x4)))
        assert err["code"] == "bad_value" and "reserved" in err["message"] and not err["fatal"]
        assert car.cmd.throttle == 0.0
        reply = raw.request(M.COMMAND, P.pack_command(0.1, 0.0, OFF, P.FLAG_READ_BACK))
        assert reply.type == M.READOUT  # bit 0 is defined


def test_welcome_states_the_servers_limits(served):
    server, _ = served(watchdog=0.2, monitor_rate=5.0, max_clients=8)
    with TcpCar(*server.address, role="monitor") as mon:
        w = mon.welcome
    assert w["watchdog_s"] == 0.2 and w["controller_timeout_s"] == pytest.approx(0.8)
    assert w["monitor_rate_hz"] == 5.0 and w["max_clients"] == 8
    assert w["hello_timeout_s"] == 2.0 and w["frame_timeout_s"] == 5.0


# --- the simulator's frames are drawn in a process of their own ------------------------------------------
def test_a_served_simulator_draws_its_frames_in_a_process_of_its_own(served, netlog):
    """Drawing holds the interpreter lock in places; in its own process it cannot hold up the
    controller's or the watchdog's thread. Same seed, same frames as drawn in-process."""
    import numpy as np

    from qcarlab.car.sim import START_POSE

    car = SimCar(seed=5, realtime=True, on_stand=True)
    server, _ = served(car=car, render_process=True)
    assert server.worker is not None and server.worker.proc.is_alive()
    with TcpCar(*server.address, role="monitor", timeout=10.0) as mon:
        # the render process's first frame compiles numba's camera kernels in a fresh clone (some
        # 30 s on a slow 2-core host, beside the other workers): this bound catches a hang only
        mon.frame_timeout = 180.0
        scan, rgbd = mon.read_lidar(), mon.read_rgbd()
        assert not car._sensors  # the server's own process never built a sensor
        ref = SimCar(seed=5)
        assert np.array_equal(ref.draw_frame("lidar", START_POSE, scan.t).ranges, scan.ranges)
        ref_rgbd = ref.draw_frame("rgbd", START_POSE, rgbd.t)
        assert np.array_equal(ref_rgbd.color, rgbd.color) and np.array_equal(ref_rgbd.depth, rgbd.depth)
        server.worker.proc.kill()  # the worker dies: frames keep coming, drawn in the server's process
        server.worker.proc.join(5)
        time.sleep(0.15)
        assert mon.read_lidar().ranges.shape == scan.ranges.shape
        assert wait_for(lambda: any("own process from now on" in line for line in netlog))


def test_a_monitors_requests_are_rate_limited(served):
    """A monitor flooding the server gets its replies more slowly, never an error: its requests
    cannot take the server's (and the car computer's) CPU time from the controller."""
    from qcarlab.net.server import MONITOR_BURST, MONITOR_REQUESTS_PER_S

    server, _ = served()
    with RawClient(server.address) as raw:
        raw.hello("monitor")
        t0 = time.monotonic()
        n = 0
        while time.monotonic() - t0 < 0.5:
            assert raw.request(M.PING, b"x").type == M.PONG
            n += 1
        took = time.monotonic() - t0
    assert n <= MONITOR_REQUESTS_PER_S * took + MONITOR_BURST + 5


def test_tuning_a_serving_process_can_be_undone():
    """serve tunes its process (switch interval, priorities) and gives the settings back when it
    stops, so that an in-process caller (a test, a notebook) is left as it was."""
    import sys

    from qcarlab.net.server import process_settings, restore_process, tune_process

    saved = process_settings()
    try:
        tune_process()
        assert sys.getswitchinterval() <= 0.0005
    finally:
        restore_process(saved)
    assert process_settings() == saved
