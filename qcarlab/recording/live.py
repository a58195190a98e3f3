"""The live view: a Foxglove WebSocket server streaming a run's channels as they happen.

    view = LiveView(port=8765)           # loopback; LiveView("0.0.0.0", 8765, token=...) for a network
    rec = Recorder(None, live=view)      # or Recorder("run.mcap", live=view): file and live at once

In Foxglove: Open connection -> Foxglove WebSocket -> ``ws://127.0.0.1:8765``. The server is
foxglove-sdk's; it encodes nothing for channels nobody subscribed to.

Anything but loopback needs a token, as ``qcarlab serve`` does: the SDK's server then listens on
loopback only, and a small proxy on the asked address lets a client through when its URL carries
``?token=SECRET`` (``ws://HOST:8765/?token=SECRET`` in Foxglove's connection dialog), comparing it
in constant time; others get HTTP 403.
"""

from __future__ import annotations

import asyncio
import hmac
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
        self.proxy: _TokenProxy | None = None

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

        behind = self.proxy_needed
        try:
            self.server = foxglove.start_server(name="qcarlab", host="127.0.0.1" if behind else self.host,
                                                port=0 if behind else self.port, context=context,
                                                server_listener=Listener())
        except Exception as exc:  # the SDK's error: the port is taken, the address is not ours
            raise InputError(f"--live: cannot listen on {self.host}:{self.port} ({exc})") from None
        if behind:
            self.proxy = _TokenProxy(self.host, self.port, "127.0.0.1", self.server.port, self.token)
            self.proxy.start()
        if self.announce is not None:
            self.announce(f"live view: in Foxglove, Open connection -> Foxglove WebSocket -> {self.url}")

    @property
    def proxy_needed(self) -> bool:
        return not is_loopback(self.host)

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


class _TokenProxy:
    """A WebSocket proxy (the ``websockets`` library) that admits clients whose URL has the token."""

    def __init__(self, host: str, port: int, target_host: str, target_port: int, token: str):
        require("--live on a network address", "websockets")
        self.host, self.port = host, port
        self.target = f"ws://{target_host}:{target_port}"
        self.token = token.encode()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="qcarlab-live-proxy", daemon=True)

    def start(self) -> None:
        self._thread.start()
        self._ready.wait(10.0)
        if self._error is not None:
            raise InputError(f"--live: cannot listen on {self.host}:{self.port} ({self._error})")

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(5.0)

    def _run(self) -> None:
        try:
            asyncio.run(self._serve())
        except BaseException as exc:  # reported to start()
            self._error = exc
            self._ready.set()

    def _admit(self, connection, request):
        given = parse_qs(urlsplit(request.path).query).get("token", [""])[0].encode()
        if not hmac.compare_digest(given, self.token):
            return connection.respond(403, "a token is needed: ws://HOST:PORT/?token=SECRET\n")
        return None

    async def _serve(self) -> None:
        import websockets
        from websockets.asyncio.client import connect
        from websockets.asyncio.server import serve

        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()

        async def handle(client) -> None:
            protocols = [client.subprotocol] if client.subprotocol else None
            async with connect(self.target, subprotocols=protocols, max_size=None) as upstream:
                async def pump(a, b):
                    try:
                        async for msg in a:
                            await b.send(msg)
                    except websockets.ConnectionClosed:
                        pass
                    finally:
                        await b.close()

                await asyncio.gather(pump(client, upstream), pump(upstream, client))

        subprotocols = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
        async with serve(handle, self.host, self.port, process_request=self._admit, subprotocols=subprotocols,
                         max_size=None) as server:
            self.port = server.sockets[0].getsockname()[1]
            self._ready.set()
            await self._stop.wait()
