"""Optional TLS (issue 16): ``qcarlab serve --tls-cert/--tls-key``, ``--car tcps://HOST:PORT``.
A self-signed certificate is made for each test run with the ``openssl`` command (skipped when it
is not on PATH). Loopback only, bounded in time."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from qcarlab.car import open_car
from qcarlab.car.tcp import TcpCar, TcpConnectError
from qcarlab.errors import InputError
from qcarlab.net.server import CarServer
from qcarlab.net.testing import RawClient, SyntheticCar
from qcarlab.wire.tls import server_context

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "tls-lab-token-0123456789abcdef"


def make_cert(d: Path, names: str) -> tuple[Path, Path]:
    """A self-signed EC certificate for ``names`` (subjectAltName syntax) and its key, valid one day."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not on PATH: no certificate to test TLS with")
    crt, key = d / "car.crt", d / "car.key"
    run = subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
         "-keyout", str(key), "-out", str(crt), "-days", "1", "-subj", "/CN=qcarlab test car",
         "-addext", f"subjectAltName={names}"],
        capture_output=True, text=True, timeout=60)
    if run.returncode != 0:
        pytest.skip(f"openssl could not make a certificate: {run.stderr.strip()[:200]}")
    return crt, key


@pytest.fixture(scope="module")
def cert(tmp_path_factory):
    """(certificate, key) PEM files for 127.0.0.1 and localhost."""
    return make_cert(tmp_path_factory.mktemp("tls"), "IP:127.0.0.1,DNS:localhost")


@pytest.fixture
def tls_server(cert):
    servers = []

    def make(car=None, **kw):
        car = car or SyntheticCar()
        server = CarServer(car, "127.0.0.1", 0, tls=server_context(*cert), **kw).start()
        servers.append(server)
        return server, car

    yield make
    for s in servers:
        s.stop()


class Tap:
    """A TCP relay on loopback that keeps every byte it passes on (what a network would see)."""

    def __init__(self, target: tuple[str, int]):
        self.target = target
        self.seen = bytearray()
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.address = self.listener.getsockname()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        try:
            a, _ = self.listener.accept()
        except OSError:
            return
        b = socket.create_connection(self.target)
        for src, dst in ((a, b), (b, a)):
            threading.Thread(target=self._pump, args=(src, dst), daemon=True).start()

    def _pump(self, src, dst) -> None:
        try:
            while data := src.recv(65536):
                self.seen += data
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def close(self) -> None:
        self.listener.close()


def test_a_tls_client_drives_a_tls_server(tls_server, cert):
    server, car = tls_server()
    assert server.uri.startswith("tcps://127.0.0.1:")
    with open_car(server.uri, tls_ca=str(cert[0])) as ctl:
        assert ctl.uri == server.uri
        assert ctl.write(0.2, 0.1).throttle == pytest.approx(0.2)
        assert car.cmd.throttle == pytest.approx(0.2)
        assert ctl.read().throttle == pytest.approx(0.2)
        assert ctl.read_rgbd().color.shape == (480, 640, 3)  # a frame of 2 MB through TLS
        assert ctl.read_lidar().ranges.shape == car.lidar[1].shape


def test_the_token_and_the_commands_do_not_cross_the_network_in_plain_text(tls_server, cert):
    server, car = tls_server(token=TOKEN)
    tap = Tap(server.address)
    try:
        with TcpCar(*tap.address, tls=True, tls_ca=str(cert[0]), token=TOKEN) as ctl:
            ctl.write(0.15, 0.0)
            ctl.read()
        assert car.cmd.throttle in (0.0, pytest.approx(0.15))
        assert len(tap.seen) > 1000 and TOKEN.encode() not in tap.seen and b"QC\x01" not in tap.seen
    finally:
        tap.close()
    # the same through a plain server: the token is there for anyone on the network to read
    plain = CarServer(SyntheticCar(), "127.0.0.1", 0, token=TOKEN).start()
    tap = Tap(plain.address)
    try:
        with TcpCar(*tap.address, token=TOKEN) as ctl:
            ctl.read()
        assert TOKEN.encode() in tap.seen
    finally:
        tap.close()
        plain.stop()


def test_a_certificate_the_client_does_not_trust_is_refused_in_one_line(tls_server, monkeypatch):
    server, _ = tls_server()
    monkeypatch.delenv("QCARLAB_TLS_CA", raising=False)
    with pytest.raises(TcpConnectError) as exc:
        TcpCar(*server.address, tls=True)  # the system's authorities: a self-signed certificate is not theirs
    assert exc.value.kind == "tls" and "not trusted" in str(exc.value) and "QCARLAB_TLS_CA" in str(exc.value)
    assert "\n" not in str(exc.value)


def test_the_name_in_the_uri_must_be_the_certificates(cert, tmp_path, monkeypatch):
    """A certificate for another car (here: only the name "car7.lab") is refused even when it is
    trusted: the address in the URI is not among its names."""
    other_crt, other_key = make_cert(tmp_path, "DNS:car7.lab")
    server = CarServer(SyntheticCar(), "127.0.0.1", 0, tls=server_context(other_crt, other_key)).start()
    try:
        monkeypatch.setenv("QCARLAB_TLS_CA", str(other_crt))
        with pytest.raises(TcpConnectError) as exc:
            TcpCar(*server.address, tls=True)
        assert exc.value.kind == "tls" and "not trusted" in str(exc.value) and "127.0.0.1" in str(exc.value)
    finally:
        server.stop()
    theirs = CarServer(SyntheticCar(), "127.0.0.1", 0, tls=server_context(*cert)).start()
    try:
        monkeypatch.setenv("QCARLAB_TLS_CA", str(cert[0]))
        with TcpCar("localhost", theirs.address[1], tls=True) as ok:  # a name the certificate has
            ok.read()
    finally:
        theirs.stop()


def test_plain_and_tls_ends_that_do_not_match_are_told_apart(tls_server, cert, netlog):
    server, _ = tls_server()
    with pytest.raises(TcpConnectError) as exc:  # a plain client to a TLS server
        TcpCar(*server.address, timeout=2.0)
    assert exc.value.kind == "protocol" and "tcps://" in str(exc.value)
    plain = CarServer(SyntheticCar(), "127.0.0.1", 0).start()
    try:
        with pytest.raises(TcpConnectError) as exc:  # a TLS client to a plain server
            TcpCar(*plain.address, tls=True, tls_ca=str(cert[0]), timeout=2.0)
        assert exc.value.kind == "tls" and "--tls-cert" in str(exc.value)
    finally:
        plain.stop()
    with TcpCar(*server.address, tls=True, tls_ca=str(cert[0])) as ctl:  # the server still serves
        ctl.read()
    deadline = time.monotonic() + 2.0
    while not any("TLS handshake failed" in line for line in netlog) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert any("TLS handshake failed" in line for line in netlog)


def test_a_connection_that_never_completes_the_handshake_is_cut_off_at_the_hello_deadline(tls_server):
    server, _ = tls_server(hello_timeout=0.3)
    with RawClient(server.address, timeout=3.0) as raw:  # connects, sends nothing
        t0 = time.monotonic()
        assert raw.closed_by_peer(2.0)
        assert time.monotonic() - t0 < 0.3 + 0.5


def test_the_watchdog_guards_a_tls_controller_too(tls_server, cert):
    server, car = tls_server(watchdog=0.1)
    with TcpCar(*server.address, tls=True, tls_ca=str(cert[0])) as ctl:
        ctl.write(0.2, 0.0)
        t0 = time.monotonic()
        while car.cmd.throttle != 0.0 and time.monotonic() - t0 < 1.0:
            time.sleep(0.005)
        assert car.cmd.throttle == 0.0 and server.trips == 1


def test_serve_with_a_bad_certificate_is_bad_input(cli, tmp_path):
    junk = tmp_path / "junk.pem"
    junk.write_text("not a certificate\n")
    code, out, err = cli("serve", "--port", "0", "--tls-cert", junk)
    assert code == 2 and "--tls-cert" in err and len(err.strip().splitlines()) == 1
    code, out, err = cli("serve", "--port", "0", "--tls-cert", tmp_path / "missing.pem")
    assert code == 2 and "no such file" in err
    code, out, err = cli("serve", "--port", "0", "--tls-key", junk)
    assert code == 2 and "--tls-key needs --tls-cert" in err
    with pytest.raises(InputError):
        server_context(junk)


def test_serve_tls_and_ping_tcps_from_the_command_line(cert):
    """As a user types it: serve with the certificate, ping with QCARLAB_TLS_CA naming it."""
    crt, key = cert
    proc = subprocess.Popen([sys.executable, "-m", "qcarlab", "serve", "--port", "0", "--tls-cert", str(crt),
                             "--tls-key", str(key)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line, deadline = "", time.monotonic() + 90
        while "tcps://" not in line and time.monotonic() < deadline and proc.poll() is None:
            line = proc.stdout.readline()
        assert "tcps://127.0.0.1:" in line and "TLS" in line, line
        uri = line[line.index("tcps://"):].split()[0]
        env = dict(os.environ, QCARLAB_TLS_CA=str(crt))
        ping = subprocess.run([sys.executable, "-m", "qcarlab", "ping", uri, "--count", "3", "--interval", "0"],
                              cwd=ROOT, capture_output=True, text=True, timeout=60, env=env)
        assert ping.returncode == 0, ping.stderr
        env.pop("QCARLAB_TLS_CA")
        untrusted = subprocess.run([sys.executable, "-m", "qcarlab", "ping", uri, "--count", "1"],
                                   cwd=ROOT, capture_output=True, text=True, timeout=60, env=env)
        assert untrusted.returncode == 1 and "not trusted" in untrusted.stderr
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)
    assert proc.returncode == 0


def test_a_private_key_others_can_read_draws_a_warning(cert, tmp_path, netlog):
    import os
    import shutil as sh

    crt, key = tmp_path / "c.crt", tmp_path / "c.key"
    sh.copy(cert[0], crt)
    sh.copy(cert[1], key)
    os.chmod(key, 0o600)
    server_context(crt, key)
    assert not [ln for ln in netlog if "private key" in ln]
    os.chmod(key, 0o644)
    server_context(crt, key)
    assert any(f"{key}: the private key can be read by other users of this machine (mode 644); chmod 600" in ln
               for ln in netlog), netlog
