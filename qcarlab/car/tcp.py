"""The TCP car: a :class:`Car` served by ``qcarlab serve`` (a simulator elsewhere, or the real QCar).

    import qcarlab
    with qcarlab.open_car("tcp://192.168.2.15:18960") as car:    # role="monitor" to only watch
        car.write(0.1, 0.0, leds=["headlamps"])
        car.advance(0.01)        # lock-step server: steps its simulator; otherwise sleeps here
        print(car.read().battery_voltage)

Every call is one request and one reply (see ``docs/protocol.md``). A lock-step server makes the
car ``stepped``: runs over TCP then give the same numbers as in-process with the same seed. The
server's own limits (throttle, watchdog) always apply; its parameters are used unless you pass
your own. Connection failures raise :class:`TcpConnectError` (a :class:`CarError`) whose
``kind`` is one of ``refused``, ``timeout``, ``unreachable``, ``protocol``, ``token``, ``busy``,
``full``, ``lost``.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
from typing import Any

from qcarlab.car.base import Car, Command, Identity, Readout, Truth
from qcarlab.constants import DEFAULT_PARAMS, QCarParams, params_from_mapping
from qcarlab.errors import CarError, InputError, NotBuiltError
from qcarlab.wire import interrupts
from qcarlab.wire import protocol as P
from qcarlab.wire.frames import make_frame
from qcarlab.wire.protocol import MsgType as M

log = logging.getLogger("qcarlab")

TOKEN_ENV = "QCARLAB_TOKEN"
_get_ident = threading.get_ident
_new_tuple = tuple.__new__  # a Readout from its ten values without the Python-level _make
_READOUT, _APPLIED = (int(M.READOUT),), (int(M.APPLIED),)  # every tick's replies (plain ints: no enum lookups)


class TcpConnectError(CarError):
    """The car could not be reached or refused us; ``kind`` says why (for ``ping``)."""

    def __init__(self, message: str, kind: str):
        super().__init__(message)
        self.kind = kind


class TcpCar(Car):
    """A car behind a qcarlab server at ``host:port``."""

    frame_timeout = 15.0  # s to wait for a sensor frame (the first one may be built on demand)
    spin = 0.0001  # s to look for a reply before sleeping on it (a loopback reply comes within tens of us)

    def __init__(
        self,
        host: str,
        port: int,
        params: QCarParams = DEFAULT_PARAMS,
        throttle_limit: float | None = None,
        *,
        role: str = "control",
        token: str | None = None,
        timeout: float = 5.0,
        connect_timeout: float = 3.0,
        on_stand: bool | None = None,
        client: str = "qcarlab",
        tls: Any = None,
        tls_ca: str | None = None,
        **_sim_only: Any,  # world, seed, ... are the server's business
    ):
        super().__init__(params, throttle_limit)
        if role not in ("control", "monitor"):
            raise InputError(f"role must be 'control' or 'monitor', got {role!r}")
        for name, value in (("timeout", timeout), ("connect timeout", connect_timeout)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InputError(f"{name} must be a positive number of seconds, got {value!r}")
        self.host, self.port = host, int(port)
        # tls: True (tcps://: the server's certificate checked against tls_ca, QCARLAB_TLS_CA or the
        # system's authorities) or an ssl.SSLContext of the caller's; None/False: plain TCP
        if tls is True or (tls is None and tls_ca is not None):
            from qcarlab.wire.tls import client_context

            tls = client_context(tls_ca)
        self._tls = tls or None
        scheme = "tcps" if self._tls is not None else "tcp"
        self.uri = f"{scheme}://{'[' + host + ']' if ':' in host else host}:{self.port}"
        self.role = role
        self.timeout = float(timeout)
        self.status = 0
        self._lock = threading.RLock()
        self._seq = 0
        self._rx = 0
        self._owed = 0  # the last request whose reply an interruption left unread (0: none)
        self._sock: socket.socket | None = None
        self._waiter: P.Waiter | None = None
        self._reader: P.FrameReader | None = None
        self._writer: P.FrameWriter | None = None
        self._warned_trip = False
        self._commanded = False  # a watchdog trip before our first command stopped nothing of ours
        if token is None:
            token = os.environ.get(TOKEN_ENV) or None
        self.welcome = self._connect(token, float(connect_timeout), client)
        ident = self.welcome.get("identity") or {}
        self._caps = set(ident.get("capabilities") or [])
        self._lockstep = bool(self.welcome.get("lockstep"))
        self.protocol = int(self.welcome.get("protocol", P.VERSION))
        if params is DEFAULT_PARAMS and isinstance(self.welcome.get("params"), dict):
            try:  # the served car's facts, unless the caller brought their own
                self.params = params_from_mapping(self.welcome["params"], f"{self.uri} parameters")
                self.steering_limit = self.params.max_steering
            except InputError:
                pass
        limit = self.welcome.get("throttle_limit")
        if isinstance(limit, (int, float)) and 0 < limit < self.throttle_limit:
            self.throttle_limit = float(limit)
        remote_on_stand = (ident.get("extra") or {}).get("on_stand")
        if on_stand is not None and remote_on_stand is not None and bool(remote_on_stand) != bool(on_stand):
            where, asked = ("on its stand", "on the floor") if remote_on_stand else ("on the floor", "on its stand")
            flag = "--on-floor" if remote_on_stand else "--on-stand"
            log.warning("the car at %s is %s, not %s: the server decides (qcarlab serve %s)", self.uri, where, asked, flag)

    # --- connection -------------------------------------------------------------------------------
    def _connect(self, token: str | None, connect_timeout: float, client: str) -> dict[str, Any]:
        uri = self.uri
        try:
            sock = socket.create_connection((self.host, self.port), timeout=connect_timeout)
        except ConnectionRefusedError:
            raise TcpConnectError(
                f"{uri}: connection refused: nothing listens there (is `qcarlab serve` running on that machine and port?)",
                "refused",
            ) from None
        except socket.gaierror:
            raise TcpConnectError(f"{uri}: unknown host '{self.host}'", "unreachable") from None
        except TimeoutError:
            raise TcpConnectError(
                f"{uri}: timed out after {connect_timeout:g} s connecting (is the car on, and on this network?)", "timeout"
            ) from None
        except OSError as exc:
            raise TcpConnectError(f"{uri}: cannot connect: {exc.strerror or exc}", "unreachable") from None
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError:
            pass
        sock.settimeout(0.0)  # non-blocking: waits go through the waiter, bounded by self.timeout
        if self._tls is not None:
            sock = self._start_tls(sock)
        self._sock = sock
        self._waiter = P.Waiter(sock)
        self._reader = P.FrameReader(sock, P.MAX_REPLY, waiter=self._waiter)
        self._reader.recv_timeout = self.timeout
        self._writer = P.FrameWriter(sock, self._waiter, self.timeout)
        hello = {"protocol": P.VERSION, "role": self.role, "client": client}
        if token:
            hello["token"] = token
        try:
            self._seq = 1
            self._writer.send(M.HELLO, 1, 0, P.encode_json(hello))
            frame = self._reader.read_frame()
        except TimeoutError:
            self._drop()
            raise TcpConnectError(
                f"{uri}: connected, but no answer to hello within {self.timeout:g} s (timed out; is it a qcarlab server?)",
                "timeout",
            ) from None
        except P.ProtocolError as exc:
            seen = self._reader.peek()[:40]
            self._drop()
            if exc.code == "bad_version":
                raise TcpConnectError(f"{uri}: wrong protocol version: {exc.message}; update qcarlab on one side", "protocol") from None
            if exc.code == "incomplete":
                raise TcpConnectError(f"{uri}: the server closed the connection during the hello (wrong protocol?)", "protocol") from None
            raise TcpConnectError(
                f"{uri}: wrong protocol: that server does not speak the qcarlab protocol (it answered {seen!r})", "protocol"
            ) from None
        except OSError as exc:
            self._drop()
            hint = "" if self._tls is not None else "; a server started with --tls-cert needs tcps://"
            raise TcpConnectError(f"{uri}: connection lost during the hello ({exc.strerror or exc}){hint}", "protocol") from None
        if frame is None:
            self._drop()
            hint = "" if self._tls is not None else " (a server started with --tls-cert needs tcps://)"
            raise TcpConnectError(f"{uri}: the server closed the connection without answering the hello{hint}", "protocol")
        self._rx = frame.seq
        if frame.type == M.ERROR:
            self._drop()
            err = _error_fields(frame)
            code, message = err["code"], err["message"]
            if code == "bad_token":
                if err.get("retry_after_s"):
                    raise TcpConnectError(f"{uri}: wrong token: {message} (set {TOKEN_ENV} to the server's token)", "token")
                raise TcpConnectError(
                    f"{uri}: wrong token: the server refused it (pass --token or set {TOKEN_ENV} to the server's token)",
                    "token",
                )
            if code == "busy":
                raise TcpConnectError(f"{uri}: busy: {message}", "busy")
            if code == "too_many_clients":
                raise TcpConnectError(f"{uri}: the server is full: {message}", "full")
            if code == "bad_version":
                raise TcpConnectError(f"{uri}: wrong protocol version: {message}", "protocol")
            raise TcpConnectError(f"{uri}: the server refused the connection: {code}: {message}", "protocol")
        if frame.type != M.WELCOME:
            self._drop()
            raise TcpConnectError(f"{uri}: wrong protocol: expected WELCOME, got {frame.name}", "protocol")
        try:
            return P.decode_json(frame.payload, "welcome")
        except P.ProtocolError as exc:
            self._drop()
            raise TcpConnectError(f"{uri}: wrong protocol: {exc.message}", "protocol") from None

    def _start_tls(self, sock: socket.socket) -> Any:
        """The TLS handshake (tcps://), within the reply timeout; a refusal in one line."""
        import ssl

        from qcarlab.wire.tls import CA_ENV, TLSSocket

        uri = self.uri
        try:
            tsock = TLSSocket(self._tls.wrap_socket(sock, server_hostname=self.host, do_handshake_on_connect=False))
            tsock.handshake(time.monotonic() + self.timeout, P.Waiter(tsock))
            return tsock
        except ssl.SSLCertVerificationError as exc:
            sock.close()
            raise TcpConnectError(f"{uri}: the server's certificate is not trusted ({exc.verify_message}); set {CA_ENV} "
                                  "to the server's certificate (PEM) if it is self-signed", "tls") from None
        except TimeoutError:
            sock.close()
            raise TcpConnectError(f"{uri}: no TLS handshake within {self.timeout:g} s (is the server started with "
                                  "--tls-cert? a plain server is tcp://)", "tls") from None
        except (ssl.SSLError, OSError) as exc:
            sock.close()
            why = getattr(exc, "reason", None) or getattr(exc, "strerror", None) or exc
            raise TcpConnectError(f"{uri}: TLS handshake failed ({why}): is the server started with --tls-cert? "
                                  "(a plain server is tcp://)", "tls") from None

    def _drop(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            try:
                sock.close()
            except OSError:
                pass

    @property
    def connected(self) -> bool:
        return self._sock is not None

    def _request(
        self, mtype: int, *parts: Any, expect: tuple[int, ...], timeout: float | None = None,
        keep_on_timeout: bool = False, framed: Any = None, values: tuple[Any, ...] = (),
    ) -> P.Frame:
        """Send one request, return its reply; error frames become exceptions.

        ``parts`` are the payload's bytes; or ``framed`` (:func:`P.framed` of a payload's struct)
        and the payload's ``values``, packed with the header straight into the writer's buffer.
        ``timeout`` overrides the connection's reply timeout for this request. On a timeout the
        connection is dropped (a reply may still be in flight), unless ``keep_on_timeout``: then
        TimeoutError is raised and a late reply is skipped later (pings)."""
        with self._lock:
            reader, writer = self._reader, self._writer
            if self._sock is None or reader is None or writer is None:
                raise TcpConnectError(f"{self.uri}: not connected (the connection was closed)", "lost")
            sending = sent = False
            seq = self._seq + 1
            hold = _get_ident() == interrupts.MAIN  # Ctrl-C/SIGTERM (the CLI's handler) wait for the reply
            if hold:
                interrupts.depth += 1
            try:
                self._seq = seq
                if timeout is not None:
                    reader.recv_timeout = timeout
                sending = True
                if framed is None:
                    writer.send(mtype, seq, 0, *parts)
                else:
                    writer.send_struct(framed, mtype, seq, 0, values)
                sent = True
                reader.spin(self.spin)
                while True:
                    frame = reader.read_frame()
                    if frame is None:
                        self._drop()
                        raise TcpConnectError(f"{self.uri}: the server closed the connection", "lost")
                    rx = self._rx + 1
                    if frame.seq != rx and not (self._owed and frame.seq > rx):
                        self._drop()
                        raise TcpConnectError(f"{self.uri}: reply out of order (seq {frame.seq}, expected {rx})",
                                              "protocol")
                    self._rx = frame.seq
                    if frame.ref < seq and (frame.type == M.PONG or frame.ref <= self._owed):
                        continue  # a late reply to a request we gave up on (a lost ping, an interrupted request)
                    break
                self._owed = 0
            except TimeoutError:
                if reader.broken or not keep_on_timeout:
                    self._drop()
                    waited = self.timeout if timeout is None else timeout
                    raise TcpConnectError(
                        f"{self.uri}: no reply within {waited:g} s (timed out); the connection was closed", "timeout"
                    ) from None
                raise
            except P.ProtocolError as exc:
                self._drop()
                raise TcpConnectError(f"{self.uri}: protocol error: {exc.message}", "protocol") from None
            except OSError as exc:
                self._drop()
                raise TcpConnectError(f"{self.uri}: the connection to the car was lost ({exc.strerror or exc})", "lost") from None
            except BaseException:  # KeyboardInterrupt (Ctrl-C; SIGTERM in the CLI) in the middle of the request
                self._interrupted(seq, sending, sent, reader)
                raise
            finally:
                reader.recv_timeout = self.timeout
                if hold:
                    interrupts.depth -= 1
                    if interrupts.held and not interrupts.depth:
                        interrupts.release()  # the signal that came during the request
        if frame.ref == seq and frame.type in expect:  # the common case (expect never holds ERROR; BYE only for BYE)
            return frame
        if frame.type == M.ERROR:
            self._raise_error(frame)
        if frame.type == M.BYE and mtype != M.BYE:
            self._drop()
            reason = _json_or_empty(frame.payload).get("reason", "no reason given")
            raise TcpConnectError(f"{self.uri}: the server said bye ({reason})", "lost")
        if frame.ref != seq:
            self._drop()
            raise TcpConnectError(f"{self.uri}: reply to request {frame.ref} while waiting for {seq}", "protocol")
        if frame.type not in expect:
            self._drop()
            raise TcpConnectError(f"{self.uri}: unexpected {frame.name} in reply to {M(mtype).name}", "protocol")
        return frame

    def _interrupted(self, seq: int, sending: bool, sent: bool, reader: P.FrameReader) -> None:
        """A KeyboardInterrupt (Ctrl-C; SIGTERM in the CLI) landed inside a request: keep the stream
        in step so that the run's own stop and bye still work. Its reply, if one is coming, is
        skipped by the next request; a request that never left is forgotten; a request cut in the
        middle of its bytes (or a reply in the middle of a large payload) leaves the stream broken:
        the connection is dropped, and the server stops the car on its own."""
        if reader.broken or (sending and not sent):
            self._drop()
        elif not sending:
            self._seq = seq - 1
        else:
            self._owed = seq

    def _raise_error(self, frame: P.Frame) -> None:
        err = _error_fields(frame)
        code, message = err["code"], err["message"]
        if err["fatal"]:
            self._drop()
        if code == "control_lost":
            raise TcpConnectError(f"{self.uri}: this connection lost control of the car: {message}", "lost")
        if code == "timeout":
            raise TcpConnectError(f"{self.uri}: the server closed the connection: {message}", "lost")
        if code == "bad_value":
            raise InputError(message)
        if code == "unsupported":
            raise NotBuiltError(f"{self.uri}: {message}")
        raise CarError(f"{self.uri}: server refused: {code}: {message}")

    # --- commands ---------------------------------------------------------------------------------
    def _need_control(self, what: str) -> None:
        if self.role != "control":
            raise CarError(f"{self.uri}: {what} needs the control role; this connection is a monitor (read-only)")

    def write(self, throttle: float, steering: float, leds: Any = None) -> Command:
        """Send a command; returns it as the server applied it (after its own limits)."""
        cmd = self.validate(throttle, steering, leds)
        return self._apply(cmd)

    def _apply(self, cmd: Command) -> Command:
        self._need_control("driving")
        frame = self._request(M.COMMAND, expect=_APPLIED, framed=P.COMMAND_FRAME,
                              values=(cmd.throttle, cmd.steering, *cmd.leds, 0))
        self._commanded = True
        thr, ste, lamps = P.unpack_applied(frame.payload)
        return Command(thr, ste, lamps)

    def write_read(self, throttle: float, steering: float, leds: Any = None) -> Readout:
        """Send a command and get the readout taken right after it, in one round trip."""
        cmd = self.validate(throttle, steering, leds)
        if self.role != "control":
            self._need_control("driving")
        frame = self._request(M.COMMAND, expect=_READOUT, framed=P.COMMAND_FRAME,
                              values=(cmd.throttle, cmd.steering, *cmd.leds, P.FLAG_READ_BACK))
        self._commanded = True
        return self._readout(frame)

    def stop(self) -> None:
        """Throttle 0, wheels straight (the served car's own stop)."""
        self._need_control("stop")
        self._request(M.STOP, expect=(M.OK,))

    def advance(self, dt: float) -> None:
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt >= 0.0):
            raise InputError(f"advance: dt must be a non-negative number of seconds, got {dt!r}")
        if not self._lockstep:
            time.sleep(dt)
            return
        self._need_control("advance")
        left = float(dt)
        while True:  # long advances go in chunks of the protocol's limit
            step = min(left, P.MAX_ADVANCE)
            self._request(M.ADVANCE, P.pack_scalar(step), expect=(M.TIME,))
            left -= step
            if left <= 0.0:
                break

    # --- reads ------------------------------------------------------------------------------------
    def _readout(self, frame: P.Frame) -> Readout:
        values, status = P.readout_values(frame.payload)
        self.status = status
        if status & P.STATUS_WATCHDOG and self._commanded:
            if not self._warned_trip:
                self._warned_trip = True
                log.warning("%s: the server's watchdog stopped the car (no command in time)", self.uri)
        else:
            self._warned_trip = False
        return _new_tuple(Readout, values)

    def read(self) -> Readout:
        return self._readout(self._request(M.READ, expect=_READOUT))

    @property
    def time(self) -> float:
        return P.unpack_scalar(self._request(M.GET_TIME, expect=(M.TIME,)).payload, "time")

    @property
    def stepped(self) -> bool:
        return self._lockstep

    @property
    def capabilities(self) -> list[str]:
        return list((self.welcome.get("identity") or {}).get("capabilities") or [])

    def identity(self) -> Identity:
        ident = self.welcome.get("identity") or {}
        extra = dict(ident.get("extra") or {})
        extra.update(
            server=self.uri,
            remote_backend=ident.get("backend"),
            protocol=self.protocol,
            lockstep=self._lockstep,
            role=self.role,
        )
        return Identity(name=str(ident.get("name", "?")), backend="tcp", capabilities=self.capabilities, extra=extra)

    def truth(self) -> Truth | None:
        if "truth" not in self._caps:
            return None
        return Truth(**P.unpack_truth(self._request(M.GET_TRUTH, expect=(M.TRUTH,)).payload))

    def _frame(self, request: int, reply: int, cap: str, what: str) -> Any:
        if cap not in self._caps:
            raise NotBuiltError(f"{self.uri}: the served car has no {what}")
        # a first frame may take seconds (the served simulator builds its sensor), a 2 MB frame
        # over Wi-Fi a while: frames wait longer than commands
        frame = self._request(request, expect=(reply,), timeout=max(self.timeout, self.frame_timeout))
        try:
            t, arrays = P.unpack_arrays(frame.payload, what)
        except P.ProtocolError as exc:
            raise CarError(f"{self.uri}: bad {what} frame: {exc.message}") from None
        return make_frame(reply, t, arrays)

    def read_lidar(self) -> Any:
        return self._frame(M.GET_LIDAR, M.LIDAR, "lidar", "LIDAR")

    def read_rgbd(self) -> Any:
        return self._frame(M.GET_RGBD, M.RGBD, "rgbd", "RGBD camera")

    def read_csi(self) -> Any:
        return self._frame(M.GET_CSI, M.CSI, "csi", "CSI cameras")

    def ping(self, payload: bytes = b"", timeout: float | None = None) -> float:
        """One round trip; returns the latency in seconds. A ``timeout`` raises TimeoutError and
        keeps the connection (a late pong is skipped later)."""
        t0 = time.perf_counter()
        frame = self._request(M.PING, payload, expect=(M.PONG,), timeout=timeout, keep_on_timeout=timeout is not None)
        rtt = time.perf_counter() - t0
        if bytes(frame.payload) != bytes(payload):
            raise TcpConnectError(f"{self.uri}: pong does not echo the ping", "protocol")
        return rtt

    # --- lifecycle --------------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the car (controllers), say bye, close. Never raises for a dead connection: the
        server stops the car by itself when a controller's connection drops."""
        if self.closed:
            return
        try:
            if self.role == "control" and self._sock is not None:
                try:
                    self.stop()
                except CarError:
                    pass
        finally:
            self.closed = True
            self._close()

    def _close(self) -> None:
        if self._sock is None:
            return
        try:
            self._request(M.BYE, expect=(M.BYE,), timeout=min(self.timeout, 1.0))
        except (CarError, TimeoutError, NotBuiltError, InputError):
            pass
        self._drop()


def _json_or_empty(payload: bytes | bytearray) -> dict[str, Any]:
    try:
        return P.decode_json(payload, "frame") if len(payload) else {}
    except P.ProtocolError:
        return {}


def _error_fields(frame: P.Frame) -> dict[str, Any]:
    err = _json_or_empty(frame.payload)
    code = err.get("code") if isinstance(err.get("code"), str) else "error"
    message = err.get("message") if isinstance(err.get("message"), str) else "(no message)"
    retry = err.get("retry_after_s")
    return {"code": code, "message": message, "fatal": bool(err.get("fatal", code in P.FATAL_CODES)),
            "retry_after_s": retry if isinstance(retry, (int, float)) else None}
