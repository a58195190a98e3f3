"""The car server: exposes any :class:`~qcarlab.car.base.Car` over the qcarlab protocol.

    from qcarlab.car.sim import SimCar
    from qcarlab.net.server import CarServer

    with SimCar(seed=1, realtime=True) as car, CarServer(car, "127.0.0.1", 18960) as server:
        server.serve_forever()          # Ctrl-C (KeyboardInterrupt) ends it; the car is stopped

One thread per connection (blocking sockets, TCP_NODELAY), one lock around the car. Safety:

- **one controller**: the first client that says hello as ``control`` drives; others may connect
  as ``monitor`` (read-only); a second controller is refused (``busy``); in lock-step each new
  controller starts from the car's start state (``reset()``: start pose, at rest, time 0, noise
  re-seeded), so the same client run twice gets the same numbers;
- **watchdog**: no command from the controller for ``watchdog`` seconds -> throttle 0, wheels
  straight, hazard and brake lamps (in lock-step mode any frame from the controller counts, since
  simulated time only moves when the controller says so); armed by the controller's first
  ``COMMAND`` or ``STOP``: before it the car stands stopped anyway, and a client that reads its
  first (slow) sensor frame before driving is not stopped for it;
- **dropped connection**: when the controller leaves (bye, close, reset, protocol error) the car is
  stopped before its socket is closed;
- **limits**: every command goes through ``Car.write``: non-finite values are refused (the car is
  stopped), throttle and steering are clamped to the car's limits whatever the client sends;
- **token**: binding anything but loopback needs a token; a hello without it is refused;
- **bad input**: malformed, oversized or out-of-order frames, unknown types, silent clients and
  HTTP speakers get an error frame (or a plain HTTP 400) and/or are disconnected, with one log
  line; the server keeps serving everyone else.
"""

from __future__ import annotations

import errno
import hmac
import ipaddress
import logging
import math
import select
import socket
import threading
import time
from dataclasses import fields as dc_fields
from typing import Any

from qcarlab.car.base import Car, Readout
from qcarlab.car.lamps import parse_lamps
from qcarlab.errors import CarError, InputError, NotBuiltError, QcarlabError
from qcarlab.net import protocol as P
from qcarlab.net.frames import frame_arrays
from qcarlab.net.protocol import MsgType as M

log = logging.getLogger("qcarlab.net")

LOOPBACK_NAMES = ("localhost", "ip6-localhost", "ip6-loopback")
WATCHDOG_LAMPS = parse_lamps(["hazard", "brake"])
CONTROL_ONLY = frozenset({M.COMMAND, M.STOP, M.ADVANCE})
SENSOR_CALLS = {M.GET_LIDAR: (M.LIDAR, "read_lidar", "lidar"),
                M.GET_RGBD: (M.RGBD, "read_rgbd", "rgbd"),
                M.GET_CSI: (M.CSI, "read_csi", "csi")}
MAX_LOGGED_ERRORS = 5  # per connection; further ones are counted and summed up at disconnect


def is_loopback(host: str) -> bool:
    """True when every address ``host`` names is a loopback address (127.0.0.0/8, ::1)."""
    if not host:
        return False
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]").split("%")[0]).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except OSError:
        return False
    return bool(infos) and all(ipaddress.ip_address(i[4][0].split("%")[0]).is_loopback for i in infos)


class CarServer:
    """Serve ``car`` on ``host:port`` (port 0 picks a free port; see :attr:`address`)."""

    def __init__(
        self,
        car: Car,
        host: str = "127.0.0.1",
        port: int = P.DEFAULT_PORT,
        *,
        token: str | None = None,
        watchdog: float = 0.25,
        lockstep: bool | None = None,
        max_clients: int = 16,
        hello_timeout: float = 2.0,
        io_timeout: float = 5.0,
    ):
        if not (isinstance(port, int) and 0 <= port < 65536):
            raise InputError(f"--port must be in 0-65535, got {port!r}")
        if not (math.isfinite(watchdog) and 0.01 <= watchdog <= 60.0):
            raise InputError(f"--watchdog must be between 0.01 and 60 s, got {watchdog}")
        if token is not None and (not token or len(token) > 256 or not token.isprintable()):
            raise InputError("--token must be 1-256 printable characters")
        if not 1 <= max_clients <= 1024:
            raise InputError(f"max clients must be in 1-1024, got {max_clients}")
        self.car = car
        self.host = host
        self.port = port
        self.token = token or None
        self.watchdog = float(watchdog)
        self.lockstep = bool(car.stepped) if lockstep is None else bool(lockstep)
        if self.lockstep and not car.stepped:
            raise InputError("lock-step serving needs a stepped car (the simulator without --realtime)")
        if not self.lockstep and car.stepped:
            raise InputError("a stepped simulator can only be served in lock-step (its time moves only on advance)")
        self.max_clients = max_clients
        self.hello_timeout = hello_timeout
        self.io_timeout = io_timeout

        self.car_lock = threading.RLock()
        self.state_lock = threading.Lock()
        self.controller: _Session | None = None
        self.sessions: set[_Session] = set()
        self.last_feed = time.monotonic()
        self.tripped = False
        self.armed = False  # the watchdog guards from the controller's first command on
        self.trips = 0
        self.cache: dict[int, Any] = {}  # lock-step: the controller's last readout and frames
        self.stopping = False
        self._stop_evt = threading.Event()
        self._listener: socket.socket | None = None
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._threads: list[threading.Thread] = []
        self._started = False
        self._bound_port: int | None = None
        self.welcome_base = self._welcome_base()

    # --- identity ---------------------------------------------------------------------------------
    def _welcome_base(self) -> dict[str, Any]:
        ident = self.car.identity()
        caps = [c for c in ident.capabilities if c != "lockstep"]  # the backend says what it has
        if self.lockstep:
            caps.append("lockstep")
        params = {f.name: getattr(self.car.params, f.name) for f in dc_fields(self.car.params)}
        from qcarlab import __version__

        return {
            "protocol": P.VERSION,
            "server": f"qcarlab {__version__}",
            "identity": {"name": ident.name, "backend": ident.backend, "capabilities": caps, "extra": ident.extra},
            "lockstep": self.lockstep,
            "watchdog_s": self.watchdog,
            "throttle_limit": self.car.throttle_limit,
            "steering_limit": self.car.steering_limit,
            "max_request": P.MAX_REQUEST,
            "params": params,
        }

    @property
    def capabilities(self) -> list[str]:
        return list(self.welcome_base["identity"]["capabilities"])

    # --- lifecycle --------------------------------------------------------------------------------
    @property
    def address(self) -> tuple[str, int]:
        """(host, port) actually bound (the port is the real one when 0 was asked)."""
        return self.host, self._bound_port if self._bound_port is not None else self.port

    @property
    def uri(self) -> str:
        host, port = self.address
        return f"tcp://{'[' + host + ']' if ':' in host else host}:{port}"

    def start(self) -> CarServer:
        """Bind, listen and start serving in background threads; returns self."""
        if self._started:
            return self
        if not is_loopback(self.host) and not self.token:
            shown = self.host or "all interfaces"
            raise InputError(
                f"refusing to serve on {shown} without a token: anyone on that network could drive the car; "
                "pass --token SECRET (or set QCARLAB_TOKEN), or bind to 127.0.0.1"
            )
        self._listener = self._bind()
        self._bound_port = self._listener.getsockname()[1]
        self._wake_r, self._wake_w = socket.socketpair()
        self._started = True
        self._spawn(self._accept_loop, "qcarlab-accept")
        self._spawn(self._watchdog_loop, "qcarlab-watchdog")
        return self

    def _bind(self) -> socket.socket:
        where = f"{self.host or '*'}:{self.port}"
        try:
            infos = socket.getaddrinfo(self.host or None, self.port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
            family = infos[0][0]
            return socket.create_server((self.host, self.port), family=family, backlog=64)
        except socket.gaierror:
            raise InputError(f"--host {self.host!r}: unknown host name") from None
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise CarError(f"cannot listen on {where}: the port is in use (another qcarlab serve?); pick another --port") from None
            if exc.errno in (errno.EACCES, errno.EPERM):
                raise CarError(f"cannot listen on {where}: permission denied (ports below 1024 need privileges)") from None
            if exc.errno == errno.EADDRNOTAVAIL:
                raise InputError(f"--host {self.host!r}: this machine has no such address") from None
            raise CarError(f"cannot listen on {where}: {exc.strerror or exc}") from None

    def _spawn(self, target: Any, name: str, *args: Any) -> threading.Thread:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        self._threads.append(thread)
        thread.start()
        return thread

    def serve_forever(self) -> None:
        """Serve until :meth:`stop` is called (from another thread or a signal handler)."""
        self.start()
        while not self._stop_evt.wait(0.2):
            pass

    def request_stop(self) -> None:
        """Make :meth:`serve_forever` return (safe from a signal handler); then call :meth:`stop`."""
        self._stop_evt.set()

    def stop(self) -> None:
        """Stop serving: the car is stopped, every client is told bye and disconnected."""
        if self.stopping:
            return
        self.stopping = True
        self._stop_evt.set()
        if self._wake_w is not None:
            try:
                self._wake_w.send(b"x")
            except OSError:
                pass
        with self.state_lock:
            sessions = list(self.sessions)
        for s in sessions:
            s.interrupt()
        for thread in list(self._threads):
            if thread is not threading.current_thread():
                thread.join(timeout=3.0)
        for s in sessions:
            s.close_socket()
        for sock in (self._listener, self._wake_r, self._wake_w):
            if sock is not None:
                try:
                    sock.close()
                except OSError:
                    pass
        self.safe_stop("server stopping")

    def __enter__(self) -> CarServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- the car ----------------------------------------------------------------------------------
    def safe_stop(self, why: str) -> bool:
        """Stop the car; a failing backend is logged, never raised."""
        try:
            with self.car_lock:
                self.car.stop()
            return True
        except Exception as exc:  # the backend failed to stop: say so loudly
            log.error("could not stop the car (%s): %s", why, exc)
            return False

    def feed(self) -> None:
        self.last_feed = time.monotonic()
        self.tripped = False

    def status(self, session: _Session | None) -> int:
        bits = 0
        if self.tripped:
            bits |= P.STATUS_WATCHDOG
        if self.controller is not None:
            bits |= P.STATUS_CONTROLLED
        if self.lockstep:
            bits |= P.STATUS_LOCKSTEP
        return bits

    def _watchdog_loop(self) -> None:
        next_tick = time.monotonic()
        while not self._stop_evt.wait(0.005):
            if not self.lockstep and time.monotonic() >= next_tick:
                # keep a real-time simulator's physics current, so that a request after a long
                # idle spell does not have to catch up on hours of steps at once
                next_tick = time.monotonic() + 0.1
                try:
                    with self.car_lock:
                        self.car.time
                except Exception:
                    pass
            ctl = self.controller
            if ctl is None or self.tripped or not self.armed:
                continue
            if time.monotonic() - self.last_feed <= self.watchdog:
                continue
            with self.car_lock:  # re-check under the lock: a command may have just arrived
                if self.controller is not ctl or self.tripped or time.monotonic() - self.last_feed <= self.watchdog:
                    continue
                try:
                    self.car.write(0.0, 0.0, WATCHDOG_LAMPS)
                except Exception as exc:
                    log.error("watchdog could not stop the car: %s", exc)
                    self.safe_stop("watchdog")
                self.tripped = True
                self.trips += 1
            log.warning(
                "watchdog: no command from %s for %.3g s; car stopped (throttle 0, hazard lamps)", ctl.peer, self.watchdog
            )

    # --- connections ------------------------------------------------------------------------------
    def _accept_loop(self) -> None:
        assert self._listener is not None and self._wake_r is not None
        while not self.stopping:
            try:
                ready, _, _ = select.select([self._listener, self._wake_r], [], [], 1.0)
            except (OSError, ValueError):
                break
            if self.stopping:
                break
            if self._listener not in ready:
                continue
            try:
                sock, addr = self._listener.accept()
            except OSError:
                continue
            peer = _peer_name(addr)
            with self.state_lock:
                full = len(self.sessions) >= self.max_clients
            if full:
                try:
                    sock.settimeout(0.5)
                    P.send_frame(sock, M.ERROR, 1, 0, P.error_payload(
                        "too_many_clients", f"the server already has {self.max_clients} clients; try again later"))
                except OSError:
                    pass
                sock.close()
                log.warning("%s refused: already %d clients (too_many_clients)", peer, self.max_clients)
                continue
            try:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
            except OSError:
                pass
            session = _Session(self, sock, peer)
            with self.state_lock:
                self.sessions.add(session)
            session.thread = self._spawn(session.run, f"qcarlab-client-{peer}")
            self._threads = [t for t in self._threads if t.is_alive() or t is session.thread]


def _one_line(text: str) -> str:
    """Text for a log line: one line, printable, not too long."""
    flat = " ".join(str(text).split())
    flat = "".join(ch if ch.isprintable() else "?" for ch in flat)
    return flat if len(flat) <= 300 else flat[:297] + "..."


def _peer_name(addr: Any) -> str:
    if isinstance(addr, tuple) and len(addr) >= 2:
        host = addr[0]
        return f"[{host}]:{addr[1]}" if ":" in host else f"{host}:{addr[1]}"
    return str(addr)


class _End(Exception):
    """End this connection; ``reason`` goes into the disconnect log line."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


class _Session:
    """One client connection, served by its own thread."""

    def __init__(self, server: CarServer, sock: socket.socket, peer: str):
        self.server = server
        self.car = server.car
        self.sock = sock
        self.peer = peer
        self.role: str | None = None
        self.client = "?"
        self.rx_seq = 0
        self.tx_seq = 0
        self.errors = 0
        self.thread: threading.Thread | None = None
        self.bye_ref: int | None = None
        self.reader = P.FrameReader(sock, P.MAX_REQUEST, bufsize=P.MAX_REQUEST + P.HEADER_SIZE + 4096)
        self.handlers = {
            M.COMMAND: self._command,
            M.STOP: self._stop,
            M.READ: self._read,
            M.GET_TRUTH: self._truth,
            M.GET_TIME: self._time,
            M.ADVANCE: self._advance,
            M.GET_LIDAR: self._sensor,
            M.GET_RGBD: self._sensor,
            M.GET_CSI: self._sensor,
            M.PING: self._ping,
        }

    @property
    def is_controller(self) -> bool:
        return self.server.controller is self

    # --- sending ----------------------------------------------------------------------------------
    def send(self, mtype: int, ref: int, *parts: Any) -> None:
        self.tx_seq += 1
        P.send_frame(self.sock, mtype, self.tx_seq, ref, *parts)

    def error(self, code: str, message: str, ref: int) -> None:
        """Answer an error frame; non-fatal ones are logged here (one line, rate limited)."""
        try:
            self.send(M.ERROR, ref, P.error_payload(code, message))
        except OSError:
            pass
        if code in P.FATAL_CODES or code in ("unsupported", "no_data", "not_lockstep"):
            return
        self.errors += 1
        if self.errors <= MAX_LOGGED_ERRORS:
            log.warning("%s (%s): %s: %s", self.peer, self.role or "no hello", code, _one_line(message))
            if self.errors == MAX_LOGGED_ERRORS:
                log.warning("%s: further errors from this client are counted, not logged", self.peer)

    def fatal(self, code: str, message: str, ref: int = 0) -> _End:
        try:
            self.send(M.ERROR, ref, P.error_payload(code, message))
        except OSError:
            pass
        return _End(f"{code}: {message}")

    # --- the connection's life --------------------------------------------------------------------
    def interrupt(self) -> None:
        """Wake the thread blocked in recv (server shutdown)."""
        try:
            self.sock.shutdown(socket.SHUT_RD)
        except OSError:
            pass

    def close_socket(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass

    def run(self) -> None:
        reason = "closed"
        try:
            reason = self._loop()
        except _End as end:
            reason = end.reason
        except OSError as exc:
            reason = f"connection error: {exc.strerror or exc}"
        except Exception as exc:  # never let one client take the server down
            reason = f"internal error: {type(exc).__name__}: {exc}"
        finally:
            self._finish(reason)

    def _finish(self, reason: str) -> None:
        server = self.server
        stopped = ""
        if server.controller is self:
            ok = server.safe_stop(f"{self.peer} left")
            with server.state_lock:
                server.controller = None
                server.tripped = False
                server.armed = False
            stopped = "; car stopped" if ok else "; STOPPING THE CAR FAILED"
        if self.errors > MAX_LOGGED_ERRORS:
            reason += f"; {self.errors} error frames in all"
        line = "%s (%s) disconnected: %s%s"
        args = (self.peer, self.role or "no hello", _one_line(reason), stopped)
        if self.role is None or reason.startswith(("internal", "connection error")) or "STOPPING" in stopped:
            log.warning(line, *args)
        else:
            log.info(line, *args)
        if self.bye_ref is not None:
            try:
                self.send(M.BYE, self.bye_ref)
            except OSError:
                pass
        self.close_socket()
        with server.state_lock:
            server.sessions.discard(self)

    def _loop(self) -> str:
        server = self.server
        deadline = time.monotonic() + server.hello_timeout
        self.sock.settimeout(server.hello_timeout)
        while True:
            try:
                if self.role is None:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise TimeoutError
                    self.sock.settimeout(left)
                frame = self.reader.read_frame()
            except TimeoutError:
                if self.role is None:
                    if P.looks_like_http(self.reader.peek()):
                        return self._http()
                    raise self.fatal("timeout", f"no hello within {server.hello_timeout:g} s") from None
                if self.reader.mid_frame:
                    raise self.fatal("timeout", f"incomplete frame: nothing more for {server.io_timeout:g} s") from None
                if server.stopping:
                    return "server stopping"
                continue  # an idle client may stay
            except P.IncompleteFrame:
                return "closed in the middle of a frame"
            except P.ProtocolError as exc:
                if exc.code == "bad_magic" and self.rx_seq == 0 and P.looks_like_http(self.reader.peek()):
                    return self._http()
                raise self.fatal(exc.code, exc.message) from None
            if frame is None:
                if server.stopping:
                    try:
                        self.send(M.BYE, 0, P.encode_json({"reason": "server stopping"}))
                    except OSError:
                        pass
                    return "server stopping"
                return "closed by the client"
            expected = self.rx_seq + 1
            if frame.seq != expected:
                raise self.fatal("sequence", f"frame seq {frame.seq} out of order (expected {expected})", frame.seq)
            self.rx_seq = frame.seq
            if self.role is None:
                self._hello(frame)
                continue
            if frame.type == M.BYE:
                self.bye_ref = frame.seq  # answered once the car is stopped and the line logged
                return "said bye"
            self._dispatch(frame)

    def _http(self) -> str:
        try:
            self.sock.sendall(P.HTTP_REPLY)
        except OSError:
            pass
        return "spoke HTTP; answered 400 and closed"

    # --- hello ------------------------------------------------------------------------------------
    def _hello(self, frame: P.Frame) -> None:
        server = self.server
        if frame.type != M.HELLO:
            raise self.fatal("bad_hello", f"the first frame must be HELLO, got {frame.name}", frame.seq)
        try:
            msg = P.decode_json(frame.payload, "hello")
        except P.ProtocolError as exc:
            raise self.fatal("bad_hello", exc.message, frame.seq) from None
        proto = msg.get("protocol")
        if proto != P.VERSION:
            raise self.fatal(
                "bad_version", f"client speaks protocol {proto!r}; this server speaks version {P.VERSION}", frame.seq
            )
        role = msg.get("role", "control")
        if role not in ("control", "monitor"):
            raise self.fatal("bad_hello", f"role must be 'control' or 'monitor', got {role!r}", frame.seq)
        client = msg.get("client")
        if isinstance(client, str):  # free text going into a log line: printable, short
            self.client = "".join(ch if ch.isprintable() else "?" for ch in client[:64])
        if server.token is not None:
            given = msg.get("token")
            if not isinstance(given, str) or not hmac.compare_digest(
                given.encode("utf-8", "surrogatepass"), server.token.encode("utf-8")
            ):
                raise self.fatal("bad_token", "wrong or missing token", frame.seq)
        if role == "control":
            with server.state_lock:
                holder = server.controller
                if holder is None:
                    server.controller = self
                    server.feed()
                    server.armed = False
            if holder is not None:
                raise self.fatal(
                    "busy", f"the car is controlled by {holder.peer}; connect as a monitor to watch", frame.seq
                )
            reset = getattr(self.car, "reset", None)
            if server.lockstep and callable(reset):  # a new run: from the start state, not the last client's
                with server.car_lock:
                    reset()
                    server.cache.clear()
        self.role = role
        welcome = dict(server.welcome_base, role=role)
        self.sock.settimeout(server.io_timeout)
        log.info("%s connected as %s (%s)", self.peer, role, self.client)
        self.send(M.WELCOME, frame.seq, P.encode_json(welcome))

    # --- requests ---------------------------------------------------------------------------------
    def _dispatch(self, frame: P.Frame) -> None:
        server = self.server
        mtype = frame.type
        controller = server.controller is self
        if controller and server.lockstep:
            server.feed()
        handler = self.handlers.get(mtype)
        if handler is None:
            if mtype == M.HELLO:
                self.error("bad_payload", "HELLO was already received on this connection", frame.seq)
            else:
                self.error("unknown_type", f"unknown or unexpected message type {frame.name}", frame.seq)
            return
        if mtype in CONTROL_ONLY and not controller:
            self.error("read_only", f"{frame.name} needs the control role; this connection is a monitor", frame.seq)
            return
        try:
            handler(frame)
        except P.ProtocolError as exc:
            if mtype == M.COMMAND:
                server.safe_stop("bad command")
            self.error(exc.code, exc.message, frame.seq)
        except NotBuiltError as exc:
            self.error("unsupported", str(exc), frame.seq)
        except InputError as exc:
            if mtype == M.COMMAND:
                server.safe_stop("bad command")
            self.error("bad_value", str(exc), frame.seq)
        except (QcarlabError, Exception) as exc:  # a failing backend: report, keep serving
            if mtype == M.COMMAND:
                server.safe_stop("command failed")
            self.error("car_error", f"{type(exc).__name__}: {exc}", frame.seq)

    def _command(self, frame: P.Frame) -> None:
        server = self.server
        throttle, steering, leds, flags = P.unpack_command(frame.payload)
        with server.car_lock:
            server.feed()
            server.armed = True
            cmd = self.car.write(throttle, steering, leds)
            readout = self.car.read() if flags & P.FLAG_READ_BACK else None
        if readout is not None:
            if server.lockstep:
                server.cache[M.READOUT] = readout
            self.send(M.READOUT, frame.seq, P.pack_readout(readout, server.status(self)))
        else:
            self.send(M.APPLIED, frame.seq, P.pack_applied(cmd.throttle, cmd.steering, cmd.leds))

    def _stop(self, frame: P.Frame) -> None:
        server = self.server
        _expect_empty(frame)
        with server.car_lock:
            server.feed()
            server.armed = True
            self.car.stop()
        self.send(M.OK, frame.seq)

    def _read(self, frame: P.Frame) -> None:
        server = self.server
        _expect_empty(frame)
        status = server.status(self)
        if server.lockstep and server.controller is not self:
            readout: Readout | None = server.cache.get(M.READOUT)
            if readout is None:
                self.error("no_data", "lock-step: no readout yet (monitors see the controller's last readout)", frame.seq)
                return
            status |= P.STATUS_CACHED
        else:
            with server.car_lock:
                readout = self.car.read()
            if server.lockstep:
                server.cache[M.READOUT] = readout
        self.send(M.READOUT, frame.seq, P.pack_readout(readout, status))

    def _truth(self, frame: P.Frame) -> None:
        _expect_empty(frame)
        with self.server.car_lock:
            truth = self.car.truth()
        if truth is None:
            self.error("unsupported", "this car has no ground truth (only simulated cars do)", frame.seq)
            return
        self.send(M.TRUTH, frame.seq, P.pack_truth(truth))

    def _time(self, frame: P.Frame) -> None:
        _expect_empty(frame)
        with self.server.car_lock:
            t = self.car.time
        self.send(M.TIME, frame.seq, P.pack_scalar(t))

    def _advance(self, frame: P.Frame) -> None:
        server = self.server
        dt = P.unpack_scalar(frame.payload, "advance")
        if not server.lockstep:
            self.error("not_lockstep", "ADVANCE needs a lock-step server (qcarlab serve --lockstep); time runs by itself here", frame.seq)
            return
        if not (math.isfinite(dt) and 0.0 <= dt <= P.MAX_ADVANCE):
            raise InputError(f"advance: dt must be a number of seconds in [0, {P.MAX_ADVANCE:g}], got {dt!r}")
        with server.car_lock:
            self.car.advance(dt)
            t = self.car.time
        self.send(M.TIME, frame.seq, P.pack_scalar(t))

    def _sensor(self, frame: P.Frame) -> None:
        server = self.server
        _expect_empty(frame)
        reply, method, cap = SENSOR_CALLS[frame.type]
        if cap not in server.capabilities:
            self.error("unsupported", f"this car has no {cap} sensor", frame.seq)
            return
        if server.lockstep and server.controller is not self:
            parts = server.cache.get(reply)
            if parts is None:
                self.error("no_data", f"lock-step: no {cap} frame yet (monitors see the controller's last one)", frame.seq)
                return
        else:
            with server.car_lock:
                obj = getattr(self.car, method)()
                t_now = self.car.time
            t, arrays = frame_arrays(reply, obj, t_now)
            parts = P.pack_arrays(t, arrays)
            if server.lockstep:
                server.cache[reply] = parts
        self.send(reply, frame.seq, *parts)

    def _ping(self, frame: P.Frame) -> None:
        if len(frame.payload) > P.MAX_PING:
            raise P.ProtocolError("bad_payload", f"ping payload is at most {P.MAX_PING} bytes, got {len(frame.payload)}")
        self.send(M.PONG, frame.seq, frame.payload)


def _expect_empty(frame: P.Frame) -> None:
    if len(frame.payload):
        raise P.ProtocolError("bad_payload", f"{frame.name} takes no payload, got {len(frame.payload)} bytes")
