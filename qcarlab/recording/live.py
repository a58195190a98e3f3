"""The live view: a Foxglove WebSocket server streaming a run's channels as they happen.

    view = LiveView(port=8765)           # loopback; LiveView("0.0.0.0", 8765, token=...) for a network
    rec = Recorder(None, live=view)      # or Recorder("run.mcap", live=view): file and live at once

In Foxglove or Lichtblick: Open connection -> Foxglove WebSocket -> ``ws://127.0.0.1:8765``. The
server is foxglove-sdk's, on loopback at a port of its own; it encodes nothing for channels nobody
subscribed to. The address asked for is a small relay's (:class:`_Front`), which lets in clients
that offer either subprotocol name, ``foxglove.sdk.v1`` (the SDK's, Foxglove's app, Lichtblick
since its foxglove.sdk.v1 support) or the older ``foxglove.websocket.v1`` (older Lichtblick,
``@foxglove/ws-protocol``'s client): the same protocol, renamed in 2025.

Anything but loopback needs a token, as ``qcarlab serve`` does: the relay then lets a client
through only when its URL carries ``?token=SECRET`` (``ws://HOST:8765/?token=SECRET`` in the
connection dialog), comparing it in constant time; others get HTTP 403.
"""

from __future__ import annotations

import contextlib
import hmac
import socket
import threading
from typing import Any
from urllib.parse import parse_qs, urlsplit

from qcarlab.errors import InputError
from qcarlab.recording import require

DEFAULT_PORT = 8765


def is_loopback(host: str) -> bool:
    from qcarlab.net.server import is_loopback as net_loopback

    return net_loopback(host)


def parse_live(text: str | int | None, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``8765`` / ``HOST:PORT`` -> (host, port); port 0 picks a free one."""
    if text is None or text == "":
        return default_host, DEFAULT_PORT
    s = str(text).strip()
    host, sep, port_text = s.rpartition(":")
    if not sep:
        host, port_text = default_host, s
    host = host.strip("[]") or default_host
    if not port_text.isdigit() or not 0 <= int(port_text) < 65536:
        raise InputError(f"--live-port {text!r}: expected PORT or HOST:PORT with a port in 0-65535")
    return host, int(port_text)


class LiveView:
    """A Foxglove WebSocket server for one :class:`~qcarlab.recording.writer.Recorder`'s context."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, token: str | None = None,
                 announce=None):
        require("--live")
        if not is_loopback(host) and not token:
            raise InputError(f"refusing to stream the live view on {host or 'all interfaces'} without a token: "
                             "anyone on that network could watch; set QCARLAB_TOKEN (or serve --token), "
                             "or use 127.0.0.1")
        self.host, self.port, self.token = host, int(port), token or None
        self.announce = announce
        self.server = None
        self.proxy: _Front | None = None

    def attach(self, context: Any, on_subscribe=None) -> None:
        """Serve ``context``'s channels; ``on_subscribe(topic)`` is called (from the server's thread)
        when a client subscribes to a topic."""
        import foxglove

        class Listener:  # the callbacks the server calls; only a subscription matters here
            def on_subscribe(self, client, channel) -> None:
                if on_subscribe is not None:
                    on_subscribe(channel.topic)

            def on_unsubscribe(self, client, channel) -> None:
                pass

        try:  # the SDK's server on loopback; the address asked for is the front's (see _Front)
            self.server = foxglove.start_server(name="qcarlab", host="127.0.0.1", port=0, context=context,
                                                server_listener=Listener())
        except Exception as exc:  # the SDK's error: no port to be had
            raise InputError(f"--live: cannot start the live view's server ({exc})") from None
        try:
            self.proxy = _Front(self.host, self.port, "127.0.0.1", self.server.port, self.token)
        except BaseException:
            self.server.stop()
            self.server = None
            raise
        self.proxy.start()
        if self.announce is not None:
            self.announce(f"live view: in Foxglove or Lichtblick, Open connection -> Foxglove WebSocket -> {self.url}")

    @property
    def bound_port(self) -> int:
        if self.proxy is not None:
            return self.proxy.port
        return self.server.port if self.server is not None else self.port

    @property
    def url(self) -> str:
        host = self.host if self.host not in ("", "0.0.0.0", "::") else "HOST"
        host = f"[{host}]" if ":" in host else host
        return f"ws://{host}:{self.bound_port}" + ("/?token=SECRET" if self.token else "")

    def stop(self) -> None:
        if self.proxy is not None:
            self.proxy.stop()
            self.proxy = None
        if self.server is not None:
            self.server.stop()
            self.server = None


class _Front:
    """The live view's address: a byte relay in front of the SDK's loopback server.

    It reads a client's WebSocket handshake, lets it through to the SDK's server and then relays
    the bytes both ways untouched. Two things it does at the handshake: a client that offers only
    the older subprotocol name ``foxglove.websocket.v1`` (Lichtblick before its foxglove.sdk.v1
    support, ``@foxglove/ws-protocol``'s client, foxglove_bridge-era tools) is let in under it (the
    SDK accepts only ``foxglove.sdk.v1``, which is the same protocol under a new name: the name is
    swapped in the request and back in the reply); and, when a token is set, a client whose URL
    lacks ``?token=SECRET`` gets HTTP 403 (compared in constant time)."""

    def __init__(self, host: str, port: int, target_host: str, target_port: int, token: str | None):
        self.host, self.target = host, (target_host, target_port)
        self.token = token.encode() if token else None
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        try:
            self.sock = socket.create_server((host, port), family=family)
        except OSError as exc:
            raise InputError(f"--live: cannot listen on {host}:{port} ({exc.strerror or exc})") from None
        self.port = self.sock.getsockname()[1]
        self._open: set[socket.socket] = set()
        self._lock = threading.Lock()
        self._stopped = False
        self._thread = threading.Thread(target=self._accept, name="qcarlab-live-front", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stopped = True
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()
        with self._lock:
            for s in list(self._open):
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
        self._thread.join(5.0)

    def _accept(self) -> None:
        while not self._stopped:
            try:
                client, _ = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(client,), name="qcarlab-live-client", daemon=True).start()

    def _track(self, *socks: socket.socket, add: bool = True) -> None:
        with self._lock:
            for s in socks:
                (self._open.add if add else self._open.discard)(s)

    def _serve(self, client: socket.socket) -> None:
        upstream = None
        self._track(client)
        try:
            client.settimeout(HANDSHAKE_S)
            head, rest = _read_head(client)
            if head is None:
                return
            lines = head.split(b"\r\n")
            if self.token is not None:
                target = lines[0].split(b" ")[1] if len(lines[0].split(b" ")) > 1 else b"/"
                given = parse_qs(urlsplit(target.decode("latin-1")).query).get("token", [""])[0].encode()
                if not hmac.compare_digest(given, self.token):
                    body = b"a token is needed: ws://HOST:PORT/?token=SECRET\n"
                    client.sendall(b"HTTP/1.1 403 Forbidden\r\nContent-Type: text/plain\r\nContent-Length: "
                                   + str(len(body)).encode() + b"\r\nConnection: close\r\n\r\n" + body)
                    return
            offered = [v.strip() for line in lines[1:] if _header(line) == b"sec-websocket-protocol"
                       for v in line.split(b":", 1)[1].split(b",")]
            rename = OLD_SUBPROTOCOL in offered and SDK_SUBPROTOCOL not in offered
            if rename:
                lines = [_rename(line, OLD_SUBPROTOCOL, SDK_SUBPROTOCOL) for line in lines]
            upstream = socket.create_connection(self.target, timeout=HANDSHAKE_S)
            self._track(upstream)
            upstream.sendall(b"\r\n".join(lines) + b"\r\n\r\n" + rest)
            reply, extra = _read_head(upstream)
            if reply is None:
                return
            if rename:
                reply = b"\r\n".join(_rename(line, SDK_SUBPROTOCOL, OLD_SUBPROTOCOL) for line in reply.split(b"\r\n"))
            client.sendall(reply + b"\r\n\r\n" + extra)
            client.settimeout(None)
            upstream.settimeout(None)
            back = threading.Thread(target=_pump, args=(upstream, client), name="qcarlab-live-relay", daemon=True)
            back.start()
            _pump(client, upstream)
            back.join()
        except OSError:
            pass
        finally:
            for s in (client, upstream):
                if s is not None:
                    self._track(s, add=False)
                    s.close()


HANDSHAKE_S = 10.0  # a client's (and the SDK's) handshake, at most
OLD_SUBPROTOCOL, SDK_SUBPROTOCOL = b"foxglove.websocket.v1", b"foxglove.sdk.v1"


def _read_head(sock: socket.socket) -> tuple[bytes | None, bytes]:
    """An HTTP head (without its blank line) and the bytes after it; None when the peer went away
    or sent no head within 16 KiB."""
    buf = b""
    while b"\r\n\r\n" not in buf:
        if len(buf) > 16384:
            return None, b""
        chunk = sock.recv(4096)
        if not chunk:
            return None, b""
        buf += chunk
    head, _, rest = buf.partition(b"\r\n\r\n")
    return head, rest


def _header(line: bytes) -> bytes:
    return line.split(b":", 1)[0].strip().lower() if b":" in line else b""


def _rename(line: bytes, old: bytes, new: bytes) -> bytes:
    """A Sec-WebSocket-Protocol header line with the subprotocol ``old`` named ``new``."""
    if _header(line) != b"sec-websocket-protocol":
        return line
    name, values = line.split(b":", 1)
    return name + b": " + b", ".join(new if v.strip() == old else v.strip() for v in values.split(b","))


def _pump(src: socket.socket, dst: socket.socket) -> None:
    """Relay ``src``'s bytes to ``dst`` until ``src`` ends; then end ``dst``'s side too."""
    try:
        while True:
            data = src.recv(1 << 16)
            if not data:
                break
            dst.sendall(data)
    except OSError:
        pass
    finally:
        with contextlib.suppress(OSError):
            dst.shutdown(socket.SHUT_WR)
