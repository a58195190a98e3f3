"""Ctrl-C and SIGTERM held off while a request to a served car is on the wire.

A KeyboardInterrupt raised between a request's bytes going out and its reply coming in leaves the
connection out of step: the run's own stop then reads the interrupted request's reply as its own
("reply to request 583 while waiting for 584") and the run is lost. The CLI installs
:func:`handler` for SIGINT and SIGTERM; inside :func:`hold` (a request of
:class:`qcarlab.car.tcp.TcpCar`) a first signal is only noted, and raised as KeyboardInterrupt as
soon as the request is complete (a reply comes within milliseconds; a request waits at most its
timeout). A second signal during the same request is raised at once (the client then drops the
connection if it cannot tell where the stream stands; the server stops the car on its own).

    depth += 1                 # what TcpCar._request does, without a context manager's cost
    try: ...
    finally:
        depth -= 1
        if held and not depth: release()
"""

from __future__ import annotations

import threading

MAIN = threading.main_thread().ident  # signal handlers run in this thread: only its requests hold them
depth = 0  # requests in progress in this (main) thread
held = 0  # the signal noted during one, 0 when none


def handler(signum: int, _frame: object) -> None:
    """SIGINT/SIGTERM: KeyboardInterrupt now, or when the request in progress is complete."""
    global held
    if depth and not held:
        held = signum
        return
    held = 0
    raise KeyboardInterrupt


def release() -> None:
    """Raise the KeyboardInterrupt of a signal held during a request (none: nothing)."""
    global held
    if held:
        held = 0
        raise KeyboardInterrupt
