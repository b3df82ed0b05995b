"""What keeps watchers from costing the bench (docs/service.md, "Watching the bench"): a token bucket per client, so
that one client polling in a tight loop is answered 429 instead of taking the manager's time from everyone, and a
status computed at most every :data:`STATUS_TTL_S` however many clients ask, since it only changes that often.

A client is its address and its user (the token's, or ``X-Hil-User`` on a service without tokens): pages and
pollers on the lab PC itself share an address, and are still told apart by user.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

RATE_PER_S = 50.0  # each client's sustained requests a second (a page asks for far fewer: it gets a feed)
BURST = 100.0  # and what it may ask at once
STATUS_TTL_S = 0.1  # the status is computed anew at most this often (it is published every 1 s and on changes)
MAX_CLIENTS = 4096  # clients remembered; the longest idle are forgotten first


@dataclass
class _Bucket:
    tokens: float
    at_s: float


class RateLimiter:
    """A token bucket per client key: :meth:`admit` returns None (go on) or the seconds until the next token."""

    def __init__(self, rate_per_s: float = RATE_PER_S, burst: float = BURST,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.rate_per_s = rate_per_s
        self.burst = burst
        self.clock = clock
        self._buckets: dict[str, _Bucket] = {}
        self.refused = 0

    def admit(self, key: str) -> float | None:
        now = self.clock()
        bucket = self._buckets.pop(key, None)  # popped and put back: the dict's order is least recently seen first
        if bucket is None:
            bucket = _Bucket(self.burst, now)
            if len(self._buckets) >= MAX_CLIENTS:
                del self._buckets[next(iter(self._buckets))]
        bucket.tokens = min(self.burst, bucket.tokens + (now - bucket.at_s) * self.rate_per_s)
        bucket.at_s = now
        self._buckets[key] = bucket
        if bucket.tokens >= 1.0 - 1e-9:  # a token that float arithmetic left a hair short is a token
            bucket.tokens -= 1.0
            return None
        self.refused += 1
        return (1.0 - bucket.tokens) / self.rate_per_s
