"""Cars: the :class:`Car` interface and ``open_car``, which picks the backend from a URI.

- ``"sim"``: the built-in simulator in this process (seeded, stepped time by default);
- ``"tcp://HOST:PORT"``: a car served by ``qcarlab serve`` (simulated or physical);
- ``"replay:FILE"``: a recording (``--record``'s MCAP, or a rosbag2 with ``topics=``) played back.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from qcarlab.car.base import Car, Command, Identity, Pose, Readout, Truth
from qcarlab.constants import DEFAULT_PARAMS, QCarParams, load_params
from qcarlab.errors import InputError, NotBuiltError

__all__ = ["Car", "Command", "Identity", "Pose", "Readout", "Truth", "open_car", "parse_car_uri"]


def parse_car_uri(uri: str) -> tuple[str, str | None, int | None]:
    """Split ``sim`` / ``tcp://HOST:PORT`` / ``tcps://HOST:PORT`` (TLS) / ``replay:FILE`` into
    (scheme, host or file, port); bad URIs raise InputError."""
    text = (uri or "").strip()
    if text in ("sim", "sim://", "sim:"):
        return "sim", None, None
    if text.startswith("replay:"):
        path = text[len("replay:") :]
        if not path:
            raise InputError(f"car address {uri!r}: expected replay:FILE (an .mcap recording or a rosbag2)")
        return "replay", path, None
    for scheme in ("tcp", "tcps"):
        if text.startswith(f"{scheme}://"):
            rest = text[len(scheme) + 3 :].rstrip("/")
            _check_authority(rest, uri, scheme)
            host, sep, port_text = rest.rpartition(":")
            if not sep or not host or not port_text.isdigit() or not 0 < int(port_text) < 65536:
                raise InputError(f"car address {uri!r}: expected {scheme}://HOST:PORT with a port in 1-65535")
            return scheme, host.strip("[]"), int(port_text)
    raise InputError(f"car address {uri!r}: expected 'sim' or 'tcp://HOST:PORT' (or 'replay:FILE', a recording)")


_HOST_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789-._")


def _check_authority(authority: str, uri: str, scheme: str) -> None:
    """HOST:PORT with HOST a name, an IPv4 address or a bracketed IPv6 address ([::1]:18960)."""
    if authority.startswith("["):
        close = authority.find("]")
        if close < 0:
            raise InputError(f"car address {uri!r}: unclosed '[' in the address; IPv6 addresses are written "
                             f"{scheme}://[::1]:PORT")
        inner, rest = authority[1:close], authority[close + 1 :]
        if not inner or not all(c in "0123456789abcdefABCDEF:.%" or c.isalnum() for c in inner) or ":" not in inner:
            raise InputError(f"car address {uri!r}: {inner!r} is not an IPv6 address")
        if not rest.startswith(":"):
            raise InputError(f"car address {uri!r}: expected {scheme}://[IPV6]:PORT")
        return
    host = authority.rpartition(":")[0]
    if "]" in authority or ":" in host:
        raise InputError(f"car address {uri!r}: IPv6 addresses go in brackets: {scheme}://[::1]:PORT")
    if host and not set(host) <= _HOST_CHARS:
        raise InputError(f"car address {uri!r}: {host!r} is not a host name or address")


def open_car(
    uri: str = "sim",
    *,
    world: Any = None,
    seed: int = 0,
    on_stand: bool | None = None,
    realtime: bool = False,
    params: QCarParams | str | Path | None = None,
    throttle_limit: float | None = None,
    start: tuple[float, float, float] | None = None,
    realism: Any = None,
    **options: Any,
) -> Car:
    """Open a car. Use it in a ``with`` block so it is stopped and released however the block ends.

    ``world`` is a world name, a world/ROS-map file or a loaded World (simulated cars only);
    ``params`` a :class:`QCarParams` or a YAML file overriding the simulator's car parameters.
    ``on_stand``: a simulated car starts on its stand if True, on the floor otherwise; for a TCP
    car an explicit value is checked against the served car's and a mismatch is reported.
    ``realism``: the simulator's realism profile (``"lab"``, ``"ideal"``, a YAML file or a
    :class:`~qcarlab.sim.realism.Realism`; None = ideal); a served or recorded car has its own.
    """
    scheme, host, port = parse_car_uri(uri)
    if realism is not None and scheme != "sim":
        raise InputError("--realism sets the built-in simulator's imperfections; a served car's are set by "
                         "qcarlab serve --realism, a recording's were recorded")
    if scheme == "replay":  # the recording's own parameters unless others are given
        from qcarlab.car.replay import ReplayCar

        given = params if isinstance(params, QCarParams) else (load_params(params) if params is not None else None)
        return ReplayCar(host, topics=options.get("topics"), params=given, throttle_limit=throttle_limit)
    if not isinstance(params, QCarParams):
        params = load_params(params) if params is not None else DEFAULT_PARAMS
    if scheme == "sim":
        from qcarlab.car.sim import SimCar

        if isinstance(world, (str, Path)):
            from qcarlab.sim.world import load_world

            world = load_world(world, params)
        return SimCar(
            params,
            seed=seed,
            on_stand=bool(on_stand),
            world=world,
            start=start,
            realtime=realtime,
            throttle_limit=throttle_limit,
            realism=realism,
        )
    try:
        from qcarlab.car.tcp import TcpCar
    except ImportError:
        raise NotBuiltError("--car tcp://...: the TCP car is not built yet (issue 5)") from None
    if scheme == "tcps":  # TLS (qcarlab serve --tls-cert): tls_ca=, else QCARLAB_TLS_CA, else the system's CAs
        options.setdefault("tls", True)
    # the server decides seed, world and stand; the client's on_stand only warns on a mismatch
    return TcpCar(host, port, params=params, throttle_limit=throttle_limit, on_stand=on_stand, **options)
