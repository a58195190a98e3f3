"""Property-based fuzz (hypothesis): malformed frames on a controller's or a stranger's connection
never crash the server, never leave the car moving, and never stop it serving a bystander.

The default run sends a few hundred cases; ``pytest -m slow`` sends at least 10,000 frames
(``benchmarks/bench_net.py --fuzz`` too)."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, example, given, settings

from qcarlab.wire import protocol as P
from qcarlab.wire.protocol import MsgType as M
from qcarlab.net.server import CarServer
from qcarlab.net.testing import RawClient, SyntheticCar, fuzz_strategy, run_fuzz_case


def fuzz(max_examples: int) -> int:
    car = SyntheticCar(sensors=("lidar",))
    server = CarServer(car, "127.0.0.1", 0, watchdog=5.0, hello_timeout=1.0, io_timeout=1.0).start()
    bystander = RawClient(server.address)
    bystander.hello("monitor")
    sent = [0]

    # one case always sends a valid command: what hypothesis generates depends on the modules
    # loaded (it draws on constants found in them), so "commands got through" must not rest on it
    valid = P.COMMAND.pack(0.05, 0.0, *([0.0] * 12), 0)
    valid_case = (True, [P.HEADER.pack(P.MAGIC, P.VERSION, M.COMMAND, 2, 0, len(valid)) + valid, b"\xff" * 8])

    @settings(max_examples=max_examples, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(fuzz_strategy())
    @example(valid_case)
    def case(example):
        hello, chunks = example
        sent[0] += len(chunks)
        assert run_fuzz_case(server.address, hello, chunks), "the server kept a broken connection open"
        assert car.cmd.throttle == 0.0, "a controller left and the car kept moving"
        assert bystander.request(M.PING, b"alive").type == M.PONG

    try:
        case()
    finally:
        bystander.close()
        server.stop()
    assert not server.sessions
    assert car.n_commands > car.n_stops > 0  # commands got through, and every controller was stopped
    return sent[0]


def test_fuzz_malformed_frames_quick():
    assert fuzz(250) >= 250


@pytest.mark.slow
def test_fuzz_ten_thousand_malformed_frames():
    assert fuzz(5000) >= 10_000
