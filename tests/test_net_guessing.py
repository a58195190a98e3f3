"""Token guessing across addresses (issue 30, item 4), on ``qcarlab serve`` and on the car-side
server: the slow-down per address is joined by one budget for every address that has not shown the
right token lately, so rotating through 127.x.y.z does not multiply the guesses (was: 8,124
compared in 10 s); and churning addresses cannot make the server forget a penalised one (was: the
table held 4,096 addresses and forgot the oldest)."""

from __future__ import annotations

import time

import pytest

from qcarlab.net import guard
from qcarlab.net.testing import RawClient, error_of
from qcarlab.onboard import car_server as cs
from qcarlab.wire.protocol import MsgType as M

TOKEN = "lab-car-7-0123456789abcdef"


from tests.test_net_admission import server  # noqa: E402,F401  (serve and the onboard server, with TOKEN)


def _hello(address, source, token):
    with RawClient(address, timeout=10.0, source=source) as raw:
        frame = raw.hello("monitor", token=token)
        return None if frame.type == M.WELCOME else error_of(frame)


def test_rotating_addresses_does_not_multiply_the_guesses(server):
    srv, address = server
    assert _hello(address, "127.0.0.1", TOKEN) is None  # the lab's laptop: it has shown the right token
    t0 = time.monotonic()
    compared = refused = 0
    for i in range(240):  # one wrong token from each of 240 addresses (each one's first: free per address)
        err = _hello(address, f"127.0.{1 + i // 200}.{1 + i % 200}", f"guess-{i:06d}-xxxxxxxxxx")
        assert err["code"] == "bad_token"
        if "try again in" in err["message"]:
            refused += 1  # not compared
        else:
            compared += 1
    elapsed = time.monotonic() - t0
    assert compared <= guard.GLOBAL_BURST + guard.GLOBAL_PER_S * elapsed + 1, (compared, elapsed)
    assert refused >= 240 - compared
    assert _hello(address, "127.0.0.1", TOKEN) is None  # a trusted address is not held by the others' budget
    err = _hello(address, "127.0.9.9", TOKEN)  # a new one is, until the budget has room (the price, documented)
    assert err is not None and err["retry_after_s"] > 0 and "without a right token" in err["message"]


@pytest.mark.parametrize("make", [lambda clock: guard.TokenGuard(clock=clock),
                                  lambda clock: cs.TokenGuard(clock=clock)], ids=["serve", "onboard"])
def test_churning_addresses_does_not_forget_a_penalised_one(make):
    clock = [1000.0]
    g = make(lambda: clock[0])
    for _ in range(8):
        g.failed("10.0.0.66")
    assert g.wait_s("10.0.0.66") == 8.0
    for i in range(guard.MAX_ADDRESSES + 200):  # others' wrong tokens, as many as the table holds and more
        g.failed(f"10.1.{i // 250}.{i % 250}")
    clock[0] += 1.0
    assert g.wait_s("10.0.0.66") == pytest.approx(7.0)
    assert g.failures("10.0.0.66") == 8
