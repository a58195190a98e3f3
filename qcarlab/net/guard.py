"""The server's door: token rules, the slow-down of wrong tokens per address, refusal logging.

    guard = TokenGuard()
    wait, _ = guard.admit("10.0.0.7")    # > 0: refuse at once, do not even compare the token
    ok = token_matches(given, secret)    # constant time, whatever the lengths
    guard.failed("10.0.0.7") if not ok else guard.succeeded("10.0.0.7")

A wrong token costs nothing for the first ``FREE_FAILURES`` tries from an address; then the
address must wait ``min(BASE_S * 2**(n - FREE_FAILURES - 1), MAX_S)`` seconds after its n-th
failure before a token is compared again (0.5, 1, 2, 4, ... 30 s): about 2,900 guesses a day
at most, against about 1,950 a second without it. A right token clears the address; an
address quiet for ``FORGET_S`` is forgotten.

Rotating addresses does not multiply that: beside the per-address rule, the tokens of every
address that has not shown the right token in the last day share one budget (``GLOBAL_BURST``
at once, then ``GLOBAL_PER_S``): about 8,600 compared a day in all. A hello beyond it is refused
without its token being compared (``retry_after_s`` says when the budget has room). Addresses
that showed the right token (the lab's laptops) are never held by the global budget, only by
their own. Entries come only from compared tokens, so churning addresses cannot push a
penalised one out of the table.

Refusals (connections that never became a client: wrong token, busy, full, no hello, bad first
frame, HTTP) are logged through :class:`RefusalLog`: the first of each kind in an interval gets
its own line, the rest are counted and summed up in one line at the end of the interval.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import secrets
import threading
import time
from collections import OrderedDict

MIN_TOKEN = 16
MAX_TOKEN = 256
FREE_FAILURES = 3
BASE_S = 0.5
MAX_S = 30.0
FORGET_S = 600.0
MAX_ADDRESSES = 4096
GLOBAL_BURST = 30  # tokens compared for addresses without a recent right token, all together, at once ...
GLOBAL_PER_S = 0.1  # ... then one every 10 s (about 8,600 a day from every address together)
TRUSTED_S = 86400.0  # an address that showed the right token is trusted for a day ...
MAX_TRUSTED = 256  # ... the last 256 of them (only the right token adds one)


def new_token() -> str:
    """A fresh random token: 32 URL-safe characters (192 bits)."""
    return secrets.token_urlsafe(24)


def token_problem(token: str) -> str | None:
    """Why ``token`` is not acceptable as a server's token (None when it is)."""
    if not token.isprintable() or token != token.strip():
        return "--token must be printable, without leading or trailing spaces"
    if len(token) > MAX_TOKEN:
        return f"--token must be at most {MAX_TOKEN} characters"
    if len(token) < MIN_TOKEN:
        return (
            f"--token must be at least {MIN_TOKEN} characters (got {len(token)}): generate one with "
            "`qcarlab serve --new-token` and pass it by QCARLAB_TOKEN"
        )
    return None


def token_matches(given: object, secret: str) -> bool:
    """Constant-time comparison of the client's token with the server's (digests, so neither the
    value nor the length leaks through timing)."""
    if not isinstance(given, str):
        return False
    a = hashlib.sha256(given.encode("utf-8", "surrogatepass")).digest()
    b = hashlib.sha256(secret.encode("utf-8")).digest()
    return hmac.compare_digest(a, b)


def penalty_s(failures: int) -> float:
    """Seconds an address waits after its ``failures``-th wrong token in a row."""
    if failures <= FREE_FAILURES:
        return 0.0
    return min(BASE_S * 2.0 ** (failures - FREE_FAILURES - 1), MAX_S)


class TokenGuard:
    """Wrong-token bookkeeping per client address and for all of them together (thread-safe).

    ``admit(addr)`` before a token is compared: the seconds to wait (0: compare now, which takes
    one unit of the global budget from an address that has not shown the right token lately);
    then ``failed(addr)`` or ``succeeded(addr)``."""

    def __init__(self, clock=time.monotonic):
        self.clock = clock
        self._lock = threading.Lock()
        self._seen: OrderedDict[str, tuple[int, float, float]] = OrderedDict()  # addr -> (failures, until, last)
        self._trusted: OrderedDict[str, float] = OrderedDict()  # addr -> when it last showed the right token
        self._budget = float(GLOBAL_BURST)
        self._budget_at = clock()
        self.compared = 0  # tokens compared for addresses not trusted (admitted through the global budget)

    def wait_s(self, addr: str) -> float:
        """Seconds ``addr`` must still wait before its token is compared (0 = compare now); takes nothing."""
        now = self.clock()
        with self._lock:
            return self._wait(addr, now)

    def admit(self, addr: str) -> tuple[float, bool]:
        """Like :meth:`wait_s`, but a 0 takes one unit of the global budget (unless ``addr`` is
        trusted); also says whether a wait is the global budget's (True) or the address's own."""
        now = self.clock()
        with self._lock:
            own = self._own_wait(addr, now)
            if own > 0.0:
                return own, False
            wait = self._wait(addr, now)
            if wait == 0.0 and not self._is_trusted(addr, now):
                self._budget -= 1.0
                self.compared += 1
            return wait, wait > 0.0

    def _refill(self, now: float) -> None:
        self._budget = min(float(GLOBAL_BURST), self._budget + (now - self._budget_at) * GLOBAL_PER_S)
        self._budget_at = now

    def _is_trusted(self, addr: str, now: float) -> bool:
        when = self._trusted.get(addr)
        if when is None:
            return False
        if now - when > TRUSTED_S:
            del self._trusted[addr]
            return False
        return True

    def _own_wait(self, addr: str, now: float) -> float:
        entry = self._seen.get(addr)
        if entry is None:
            return 0.0
        if now - entry[2] > FORGET_S:
            del self._seen[addr]
            return 0.0
        return max(0.0, entry[1] - now)

    def _wait(self, addr: str, now: float) -> float:
        own = self._own_wait(addr, now)
        if own > 0.0 or self._is_trusted(addr, now):
            return own
        self._refill(now)
        if self._budget >= 1.0:
            return 0.0
        return (1.0 - self._budget) / GLOBAL_PER_S  # the budget for addresses not trusted is spent

    def failed(self, addr: str) -> float:
        """Count a wrong token from ``addr``; returns the wait it now has."""
        now = self.clock()
        with self._lock:
            failures, _, last = self._seen.pop(addr, (0, 0.0, now))
            if now - last > FORGET_S:
                failures = 0
            failures += 1
            wait = penalty_s(failures)
            self._seen[addr] = (failures, now + wait, now)
            if len(self._seen) > MAX_ADDRESSES:
                self._evict(now)
            return wait

    def _evict(self, now: float) -> None:
        """Make room: the oldest address whose wait is over (entries come only from compared tokens,
        which the global budget bounds: the table does not fill up within FORGET_S); a penalised
        address is never forgotten for others' sake while one that is not can go."""
        for addr, (_, until, last) in self._seen.items():
            if until <= now or now - last > FORGET_S:
                del self._seen[addr]
                return
        self._seen.popitem(last=False)

    def succeeded(self, addr: str) -> None:
        now = self.clock()
        with self._lock:
            self._seen.pop(addr, None)
            if not self._is_trusted(addr, now):
                self._refill(now)
                self._budget = min(float(GLOBAL_BURST), self._budget + 1.0)  # a right token costs the budget nothing
            self._trusted.pop(addr, None)
            self._trusted[addr] = now
            while len(self._trusted) > MAX_TRUSTED:
                self._trusted.popitem(last=False)

    def failures(self, addr: str) -> int:
        with self._lock:
            return self._seen.get(addr, (0, 0.0, 0.0))[0]


class RefusalLog:
    """Log refusals at a bounded rate: the first of each code per ``interval`` s in full, the rest as
    one summary line per interval ("refused 1,234 more connections in the last 10 s: ...")."""

    def __init__(self, logger: logging.Logger, interval: float = 10.0, clock=time.monotonic):
        self.log = logger
        self.interval = interval
        self.clock = clock
        self._lock = threading.Lock()
        self._window_start = clock()
        self._logged: set[str] = set()
        self._counts: dict[str, int] = {}
        self._last_peer = ""
        self.total = 0

    def refused(self, code: str, line: str, *args: object) -> None:
        """One refusal of kind ``code``; ``line % args`` is logged if it is the first of its kind."""
        now = self.clock()
        self.flush(now)
        with self._lock:
            self.total += 1
            if code not in self._logged:
                self._logged.add(code)
                first = True
            else:
                first = False
                self._counts[code] = self._counts.get(code, 0) + 1
                self._last_peer = str(args[0]) if args else ""
        if first:
            self._emit(line, *args)

    def flush(self, now: float | None = None) -> None:
        """End the interval if it is over: log the summary of what was counted, start a new one."""
        now = self.clock() if now is None else now
        with self._lock:
            if now - self._window_start < self.interval:
                return
            counts, last, span = self._counts, self._last_peer, now - self._window_start
            self._window_start = now
            self._logged = set()
            self._counts = {}
        if counts:
            n = sum(counts.values())
            kinds = ", ".join(f"{code} {k:,}" for code, k in sorted(counts.items(), key=lambda kv: -kv[1]))
            self._emit("refused %s more connection%s in the last %.0f s (%s); the last from %s",
                             f"{n:,}", "" if n == 1 else "s", span, kinds, last)

    def _emit(self, line: str, *args: object) -> None:
        try:
            self.log.warning(line, *args)
        except Exception:  # a failing handler (terminal gone) must not end a server thread
            pass
