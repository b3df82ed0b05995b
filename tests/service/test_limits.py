"""Each client's requests are a token bucket (hil.service._limits): a burst, then the sustained rate, and a client
is told how long to wait; clients do not share a bucket."""

from __future__ import annotations

from hil.service._limits import RateLimiter


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_burst_then_the_sustained_rate_and_the_wait_said() -> None:
    clock = Clock()
    limiter = RateLimiter(rate_per_s=10.0, burst=5.0, clock=clock)
    assert [limiter.admit("a") for _ in range(5)] == [None] * 5
    wait = limiter.admit("a")
    assert wait is not None and abs(wait - 0.1) < 1e-9
    assert limiter.admit("b") is None  # another client has its own bucket
    clock.now += 0.1
    assert limiter.admit("a") is None and limiter.admit("a") is not None
    clock.now += 10.0  # idle: the bucket refills to the burst, no further
    assert [limiter.admit("a") for _ in range(6)].count(None) == 5
    assert limiter.refused == 3


def test_a_client_polling_at_100_hz_gets_the_rate_and_no_more() -> None:
    clock = Clock()
    limiter = RateLimiter(rate_per_s=20.0, burst=40.0, clock=clock)
    admitted = 0
    for _ in range(1000):  # 10 s at 100 Hz
        admitted += limiter.admit("poller") is None
        clock.now += 0.01
    assert 40 + 200 - 2 <= admitted <= 40 + 200 + 1  # the burst, then 20 a second
