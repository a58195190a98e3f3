"""The student's process: loads the student's files and calls their blocks when the trusted side asks.

It runs confined (:mod:`qcarlab.sandbox.jail`) and answers one request at a time on its socket
(:mod:`qcarlab.sandbox.codec`, never pickle)::

    ("load", path)                    -> ("ok", {name: (id, "function" | "class")})   the file's blocks
    ("call", id, args, method, kwargs) -> ("ok", value)                         a function, an instance
                                                                                (or its method)
    ("new", id)                       -> ("ok", (instance id, callable, methods))  a class's instance
    ("get", instance, attribute)      -> ("ok", value)                          e.g. a controller's .state
    ("calls", [(id, args, method, kwargs), ...])                               several calls, in order,
                                      -> ("ok", ([reply, ...], [seconds, ...]))  one reply each (as "call"'s)
                                                                                up to the first that raised
    any of them                       -> ("raised", kind, type, message, traceback)
                                         ("input", message)                     the file cannot be loaded
                                         ("value", message)                     a value that cannot be sent

It holds nothing the grade depends on: every value it returns is checked by the trusted side, and
everything it could change (its own copy of qcarlab, its files) is its own.
"""

from __future__ import annotations

import inspect
import os
import socket
import sys
import time
from pathlib import Path
from typing import Any

from qcarlab.sandbox import codec


#: A byte shared with the trusted side (:class:`qcarlab.sandbox.client.BlockHost`): the index of the
#: call of a ``calls`` request now running, so that a block that does not return is named.
progress: Any = None

#: The first message of the student's process, sent before any of the student's code runs: an exit
#: after it is the student's doing (even with the sandbox's own set-up failure code).
READY = ("ready",)


def _raised(exc: BaseException, file: str) -> tuple:
    from qcarlab.blocks import RaisedInBlock

    what = RaisedInBlock.of(exc, Path(file))
    return ("raised", what.kind, what.type_name, what.message, what.traceback)


def serve(sock: socket.socket) -> None:
    """Answer requests until the trusted side closes the socket."""
    from qcarlab.blocks import _import_file
    from qcarlab.errors import QcarlabError

    channel = codec.Channel(sock, trusted_peer=True)
    targets: list[tuple[Any, str]] = []  # id -> (function, class or instance; its file)
    try:  # confined, and nothing of the student's has run yet: from here on, an exit is theirs
        channel.send(READY)
    except OSError:
        return
    while True:
        try:
            msg = channel.recv()
        except (EOFError, OSError, codec.CodecError):
            return
        op = msg[0] if isinstance(msg, (list, tuple)) and msg else None
        file = str(msg[1]) if op == "load" else ""
        try:
            if op == "load":
                path = str(msg[1])
                try:
                    module = _import_file(Path(path))
                except QcarlabError as exc:
                    reply: tuple = ("input", str(exc))
                else:
                    found = {}
                    for name, value in vars(module).items():
                        if inspect.isfunction(value) or inspect.isclass(value):
                            found[name] = (len(targets), "class" if inspect.isclass(value) else "function")
                            targets.append((value, path))
                    reply = ("ok", found)
            elif op == "call":
                fn, file = targets[msg[1]]
                if msg[3]:
                    fn = getattr(fn, msg[3])
                reply = ("ok", fn(*msg[2], **msg[4]) if msg[4] else fn(*msg[2]))
            elif op == "calls":
                reply = ("ok", _calls(targets, msg[1]))
            elif op == "new":
                cls, file = targets[msg[1]]
                obj = cls()
                targets.append((obj, file))
                methods = [m for m in dir(obj) if not m.startswith("_") and callable(getattr(obj, m, None))]
                reply = ("ok", (len(targets) - 1, callable(obj), methods))
            elif op == "get":
                obj, file = targets[msg[1]]
                reply = ("ok", getattr(obj, msg[2]))
            else:
                return
        except BaseException as exc:  # noqa: BLE001 - the student's code may raise anything
            reply = _raised(exc, file)
        try:
            channel.send(reply)
        except codec.CodecError as exc:
            channel.send(_sendable(reply) if op == "calls" else ("value", f"{exc}"))
        except OSError:
            return


def _calls(targets: list[tuple[Any, str]], calls: list) -> tuple[list[tuple], list[float]]:
    """A ``calls`` request: each call's reply (``("ok", value)`` or the exception's), in order,
    stopping after the first that raised, and the seconds each took."""
    replies, seconds = [], []
    mark = progress
    for i, (key, args, method, kwargs) in enumerate(calls):
        if mark is not None:
            mark[0] = i
        fn, file = targets[key]
        if method:
            fn = getattr(fn, method)
        t0 = time.perf_counter()
        try:
            replies.append(("ok", fn(*args, **kwargs) if kwargs else fn(*args)))
        except BaseException as exc:  # noqa: BLE001 - the student's code may raise anything
            replies.append(_raised(exc, file))
        seconds.append(time.perf_counter() - t0)
        if replies[-1][0] != "ok":
            break
    return replies, seconds


def _sendable(reply: tuple) -> tuple:
    """A ``calls`` reply that did not encode: its replies up to the first value that does not,
    which becomes ``("value", why)``."""
    replies, seconds = reply[1]
    for i, one in enumerate(replies):
        try:
            codec.encode(one)
        except codec.CodecError as exc:
            return ("ok", (replies[:i] + [("value", f"{exc}")], seconds[:i + 1]))
    return ("value", "a reply that cannot be sent")


def main(fd: int) -> None:
    """The student's process after :func:`qcarlab.sandbox.jail.confine`: serve on ``fd``, then exit
    (skipping the interpreter's teardown, so nothing of the student's runs at exit)."""
    code = 0
    try:
        serve(socket.socket(fileno=fd))
    except BaseException:  # noqa: BLE001
        code = 1
    finally:
        exit_now(code)


def exit_now(code: int) -> None:
    """Flush stdout and stderr, then end this process at once (``os._exit``: no interpreter teardown,
    no atexit handler, nothing of a forked parent's runs again)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # noqa: BLE001
            pass
    os._exit(code & 0xFF)


__all__ = ["exit_now", "main", "serve"]
