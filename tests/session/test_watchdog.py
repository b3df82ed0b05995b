"""The watchdog trips on silence it saw itself; a wake-up the host delayed makes it look again first."""

from __future__ import annotations

import asyncio
import threading
import time

from hil.session import Watchdog


class HostClock:
    """time.monotonic plus a jump the test adds: a stretch in which the host ran none of the bench."""

    def __init__(self) -> None:
        self.jump_s = 0.0
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            return time.monotonic() + self.jump_s

    def stall(self, seconds: float) -> None:
        with self._lock:
            self.jump_s += seconds


async def watch(timeout_s: float, scenario, run_s: float = 0.08):  # type: ignore[no-untyped-def]
    """Run a fed watchdog, play ``scenario(clock, dog, stalls)`` on the event loop, return (trips, stalls)."""
    trips: list[float] = []
    stalls: list[tuple[float, float]] = []
    clock = HostClock()
    dog = Watchdog(timeout_s, trips.append, lambda late, silent: stalls.append((late, silent)), clock=clock)
    dog.start()
    try:
        await scenario(clock, dog, stalls)
        await asyncio.sleep(run_s)
    finally:
        dog.close()
    return trips, stalls


async def feed_for(dog: Watchdog, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        dog.feed()
        await asyncio.sleep(0.0005)


def test_silence_trips_once() -> None:
    async def scenario(clock: HostClock, dog: Watchdog, stalls: list) -> None:  # type: ignore[type-arg]
        await feed_for(dog, 0.02)  # fed: no trip

    trips, stalls = asyncio.run(watch(0.005, scenario))
    assert len(trips) == 1 and 0.005 <= trips[0] < Watchdog.GIVE_UP * 0.005 + 0.01
    if not stalls:  # no late look on the way (a quiet host): the trip came within ~2 ms of the timeout
        assert trips[0] < 0.005 + 0.02


def test_a_late_look_reports_a_host_stall_and_gives_the_board_one_timeout_from_then() -> None:
    async def looks() -> tuple[list, list]:  # type: ignore[type-arg]
        stalls: list[tuple[float, float]] = []
        dog = Watchdog(0.005, lambda s: None, lambda late, silent: stalls.append((late, silent)), clock=lambda: 0.0)
        dog.last = 100.0
        seen = [
            dog.look(100.003, due=100.003),  # fed 3 ms ago: look again when the 5 ms are up
            dog.look(100.006, due=100.006),  # 6 ms of silence, seen on time: trip
            dog.look(100.025, due=100.005),  # 25 ms of silence, but this look is 20 ms late: a host stall
        ]
        dog.last = 100.026  # the samples queued during the stall come in
        seen.append(dog.look(100.030, due=100.030))  # on time, 4 ms of silence: carry on
        seen.append(dog.look(100.045, due=100.025))  # 19 ms of silence, 20 ms late: another host stall
        seen.append(dog.look(100.050, due=100.050))  # still silent, and this look is on time: trip
        seen.append(dog.look(100.080, due=100.010))  # 54 ms of silence: trip, however late the look
        await asyncio.sleep(0)  # the stall reports reach the event loop
        return seen, stalls

    seen, stalls = asyncio.run(looks())
    assert seen[0] is not None and abs(seen[0] - 0.002) < 1e-9
    assert seen[1] is None
    assert seen[2] == 0.005  # one whole timeout from the late look
    assert seen[3] is not None and abs(seen[3] - 0.001) < 1e-9
    assert seen[4] == 0.005 and seen[5] is None and seen[6] is None
    assert [(round(late, 3), round(silent, 3)) for late, silent in stalls] == [(0.02, 0.025), (0.02, 0.019)]


def test_a_board_that_stays_silent_after_a_host_stall_trips_at_the_next_on_time_look() -> None:
    async def scenario(clock: HostClock, dog: Watchdog, stalls: list) -> None:  # type: ignore[type-arg]
        await feed_for(dog, 0.01)
        clock.stall(0.02)

    trips, stalls = asyncio.run(watch(0.005, scenario, run_s=0.15))
    assert len(stalls) >= 1 and len(trips) == 1
    assert 0.02 <= trips[0] <= Watchdog.GIVE_UP * 0.005 + 0.05  # one timeout after the stall on a quiet host


def test_silence_past_the_give_up_limit_trips_without_looking_again() -> None:
    async def scenario(clock: HostClock, dog: Watchdog, stalls: list) -> None:  # type: ignore[type-arg]
        await feed_for(dog, 0.01)
        clock.stall(Watchdog.GIVE_UP * 0.005 + 0.01)

    trips, stalls = asyncio.run(watch(0.005, scenario))
    assert stalls == [] and len(trips) == 1 and trips[0] >= Watchdog.GIVE_UP * 0.005
