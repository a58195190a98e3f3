"""The sandbox's channel carries images and small values, back to back, whole and unchanged."""

from __future__ import annotations

import socket
import threading

import numpy as np

from qcarlab.sandbox.codec import Channel


def test_large_and_small_values_back_to_back_arrive_whole():
    a, b = socket.socketpair()
    a.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 64 * 1024)  # an image over many reads
    trusted, student = Channel(a, trusted_peer=False), Channel(b, trusted_peer=True)
    rng = np.random.default_rng(0)
    values = [("call", 1, (rng.integers(0, 256, (480, 640, 3), dtype=np.uint8), (1.0, 2.0, 3.0))), ("small", 2),
              ("call", 3, (rng.integers(0, 256, (1500, 1000, 3), dtype=np.uint8),)), ("small", 4)]
    sender = threading.Thread(target=lambda: [trusted.send(v) for v in values])
    sender.start()
    got = [student.recv() for _ in values]  # the student's end reads the trusted side's requests
    sender.join()
    assert [g[0] for g in got] == ["call", "small", "call", "small"]
    assert np.array_equal(got[0][2][0], values[0][2][0]) and got[0][2][1] == (1.0, 2.0, 3.0)
    assert np.array_equal(got[2][2][0], values[2][2][0]) and got[3] == ("small", 4)
    # and the student's replies (decoded, not unpickled) the other way, an array among them
    reply = rng.random((600, 800))
    replier = threading.Thread(target=lambda: (student.send(("ok", reply)), student.send(("ok", 0.25))))
    replier.start()
    first, second = trusted.recv(), trusted.recv()
    replier.join()
    assert first[0] == "ok" and np.array_equal(first[1], reply) and second == ("ok", 0.25)
    a.close()
    b.close()
