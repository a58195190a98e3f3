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


def test_an_unchanged_image_is_sent_once_and_each_call_gets_its_own_copy():
    a, b = socket.socketpair()
    trusted, student = Channel(a, trusted_peer=False), Channel(b, trusted_peer=True)
    rng = np.random.default_rng(1)
    frame = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    depth = rng.random((480, 640)).astype(np.float32)

    def requests():
        for k in range(3):
            trusted.send(("call", k, (frame, depth, 0.5)))
        frame[0, 0, 0] ^= 0xFF  # the same array, changed in place: sent again
        trusted.send(("call", 3, (frame, depth)))
        frozen = frame.copy()
        frozen.flags.writeable = False
        trusted.send(("call", 4, (frozen,)))

    sender = threading.Thread(target=requests)
    sender.start()
    got = [student.recv() for _ in range(5)]
    sender.join()
    for g in got[:3]:  # whole and equal, each its own writable copy
        assert np.array_equal(g[2][0], got[0][2][0]) and np.array_equal(g[2][1], depth) and g[2][2] == 0.5
        assert g[2][0].flags.writeable and g[2][0].dtype == np.uint8 and g[2][1].dtype == np.float32
    got[1][2][0][:] = 0  # what the student's block does to its argument reaches no other call
    assert np.array_equal(got[2][2][0], got[0][2][0]) and got[0][2][0].any()
    assert np.array_equal(got[3][2][0], frame) and not np.array_equal(got[3][2][0], got[0][2][0])
    assert np.array_equal(got[3][2][1], depth)
    assert np.array_equal(got[4][2][0], frame) and not got[4][2][0].flags.writeable  # read-only stays read-only
    a.close()
    b.close()


def test_an_unchanged_image_costs_its_bytes_once():
    """The second request with the same frame is a few dozen bytes on the socket, not 921,600."""
    a, b = socket.socketpair()
    trusted = Channel(a, trusted_peer=False)
    frame = np.random.default_rng(2).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    sizes = []
    for k in range(2):
        done = threading.Thread(target=trusted.send, args=(("call", k, (frame, (1.0, 2.0, 3.0))),))
        done.start()
        n = 0
        b.settimeout(0.5)
        try:
            while True:
                n += len(b.recv(1 << 20))
        except TimeoutError:
            pass
        done.join()
        sizes.append(n)
    assert sizes[0] > frame.nbytes and sizes[1] < 1000
    a.close()
    b.close()


def test_a_very_large_array_is_sent_each_time_and_kept_by_neither_end(monkeypatch):
    from qcarlab.sandbox import codec

    monkeypatch.setattr(codec, "KEEP_MAX", 1 << 17)
    a, b = socket.socketpair()
    trusted, student = Channel(a, trusted_peer=False), Channel(b, trusted_peer=True)
    big = np.arange(1 << 15, dtype=np.float64)  # 256 KB
    sender = threading.Thread(target=lambda: [trusted.send(("call", k, (big,))) for k in range(2)])
    sender.start()
    got = [student.recv() for _ in range(2)]
    sender.join()
    assert all(np.array_equal(g[2][0], big) for g in got) and not trusted.sent and not student.kept
    a.close()
    b.close()
