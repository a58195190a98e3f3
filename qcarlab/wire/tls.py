"""Optional TLS for the qcarlab protocol (the standard library's :mod:`ssl`): ``qcarlab serve
--tls-cert FILE --tls-key FILE`` on the server, ``--car tcps://HOST:PORT`` on the client.

The frames inside are the same bytes (docs/protocol.md); TLS only wraps the stream, so that the
token and the commands do not cross the network in plain text and a client knows it reached the
car it trusts. The client checks the server's certificate against the system's trusted
authorities, or against ``QCARLAB_TLS_CA`` (a PEM file: for a self-signed certificate, the
certificate itself), and the host name in the URI against the certificate's names.

The server's and the client's sockets are non-blocking (every wait goes through a poll with a
deadline, :class:`~qcarlab.wire.protocol.Waiter`); :class:`TLSSocket` makes a non-blocking
``ssl.SSLSocket`` look like a plain one to the frame reader and writer: "would block" as
``BlockingIOError`` whichever direction TLS needs, no scatter-gather ``sendmsg``, TLS's own
close as the end of the stream. The handshake runs on the connection's own thread, within the
hello deadline (a client that never finishes it holds one pending slot, like one that never says
hello).
"""

from __future__ import annotations

import os
import ssl
import time
from pathlib import Path
from typing import Any

from qcarlab.errors import InputError

CA_ENV = "QCARLAB_TLS_CA"  # the client's trusted certificate(s), PEM (default: the system's)


def server_context(cert: str | Path, key: str | Path | None = None) -> ssl.SSLContext:
    """A TLS 1.2+ server context from a PEM certificate (chain) and its private key (``key`` None:
    the key is in the certificate file). Bad files: one InputError line naming them."""
    cert_path = Path(cert)
    key_path = Path(key) if key is not None else None
    for what, p in (("--tls-cert", cert_path), ("--tls-key", key_path)):
        if p is not None and not p.is_file():
            raise InputError(f"{what} {p}: no such file")
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(str(cert_path), str(key_path) if key_path is not None else None)
    except ssl.SSLError as exc:
        raise InputError(f"--tls-cert {cert_path} / --tls-key {key_path or cert_path}: not a PEM certificate and "
                         f"its private key ({exc.reason or exc})") from None
    except OSError as exc:
        raise InputError(f"--tls-cert {cert_path}: cannot read ({exc.strerror or exc})") from None
    secret = key_path or cert_path
    try:
        mode = secret.stat().st_mode
    except OSError:
        mode = 0
    if mode & 0o044:  # group or others may read the private key
        import logging

        logging.getLogger("qcarlab.net").warning(
            f"{secret}: the private key can be read by other users of this machine (mode {mode & 0o777:o}); "
            f"chmod 600 {secret}")
    return ctx


def client_context(ca: str | Path | None = None) -> ssl.SSLContext:
    """A client context that checks the server's certificate and name: against ``ca`` (a PEM file),
    else ``QCARLAB_TLS_CA``, else the system's trusted authorities."""
    ca = ca if ca is not None else (os.environ.get(CA_ENV) or None)
    if ca is not None and not Path(ca).is_file():
        raise InputError(f"{CA_ENV} / tls_ca {ca}: no such file (the server's certificate, PEM)")
    try:
        ctx = ssl.create_default_context(cafile=str(ca) if ca is not None else None)
    except ssl.SSLError as exc:
        raise InputError(f"{CA_ENV} / tls_ca {ca}: not a PEM certificate ({exc.reason or exc})") from None
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    return ctx


class TLSSocket:
    """A non-blocking :class:`ssl.SSLSocket` with the plain socket's manners (see the module)."""

    def __init__(self, ssock: ssl.SSLSocket):
        self._s = ssock

    # --- I/O as FrameReader and send_frame use it ----------------------------------------------
    def recv_into(self, buffer: Any, nbytes: int = 0) -> int:
        try:
            return self._s.recv_into(buffer, nbytes)
        except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
            raise BlockingIOError from None
        except ssl.SSLZeroReturnError:  # the peer's TLS close: the end of the stream
            return 0
        except ssl.SSLError as exc:
            raise ConnectionResetError(f"TLS: {exc.reason or exc}") from None

    def send(self, data: Any) -> int:
        try:
            return self._s.send(data)
        except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
            raise BlockingIOError from None
        except ssl.SSLError as exc:
            raise ConnectionResetError(f"TLS: {exc.reason or exc}") from None

    def sendall(self, data: Any) -> None:
        self._s.sendall(data)

    def pending(self) -> int:
        """Bytes TLS has decrypted and not handed out yet."""
        return self._s.pending()

    # --- the rest, as the socket's ------------------------------------------------------------------
    def fileno(self) -> int:
        return self._s.fileno()

    def settimeout(self, value: float | None) -> None:
        self._s.settimeout(value)

    def setsockopt(self, *args: Any) -> None:
        self._s.setsockopt(*args)

    def getpeername(self) -> Any:
        return self._s.getpeername()

    def getsockname(self) -> Any:
        return self._s.getsockname()

    def shutdown(self, how: int) -> None:
        self._s.shutdown(how)

    def close(self) -> None:
        self._s.close()

    @property
    def version(self) -> str | None:
        return self._s.version()

    def handshake(self, deadline: float, waiter: Any) -> None:
        """Complete the TLS handshake by ``deadline`` (time.monotonic()); TimeoutError after it,
        ssl.SSLError (or OSError) when it fails."""
        while True:
            try:
                self._s.do_handshake()
                return
            except ssl.SSLWantReadError:
                left = deadline - time.monotonic()
                if left <= 0 or not waiter.readable(left):
                    raise TimeoutError("TLS handshake not complete in time") from None
            except ssl.SSLWantWriteError:
                left = deadline - time.monotonic()
                if left <= 0 or not waiter.writable(left):
                    raise TimeoutError("TLS handshake not complete in time") from None
