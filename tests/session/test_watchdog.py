"""The watchdog trips on silence it saw itself; a look the host delayed looks again first; with a grace (emulated
boards), a silence that ends with the emulator's CLOCK_LATE is a host stall, any other trips."""

from __future__ import annotations

import asyncio
import threading
import time

from hil.session import EventLoopWatchdog, Watchdog

# the event-loop watchdogs below run in real time: a 50 ms timeout, so a busy machine's scheduling gaps (a few ms
# beside two CPU hogs) stay far inside it and only the stalls the tests make (HostClock) count
T = 0.05


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


async def watch(timeout_s: float, scenario, run_s: float = 16 * T):  # type: ignore[no-untyped-def]
    """Run a fed event-loop watchdog, play ``scenario(clock, dog)``, return (trips, stalls)."""
    trips: list[float] = []
    stalls: list[tuple[float, float]] = []
    clock = HostClock()
    dog = EventLoopWatchdog(timeout_s, trips.append, lambda late, silent, by: stalls.append((late, silent)),
                            clock=clock)
    dog.arm()
    try:
        await scenario(clock, dog)
        await asyncio.sleep(run_s)
    finally:
        dog.close()
    return trips, stalls


async def feed_for(dog: EventLoopWatchdog, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        dog.feed()
        await asyncio.sleep(0.0005)


def test_silence_trips_once() -> None:
    async def scenario(clock: HostClock, dog: EventLoopWatchdog) -> None:
        await feed_for(dog, 4 * T)  # fed: no trip

    trips, stalls = asyncio.run(watch(T, scenario))
    assert len(trips) == 1 and T <= trips[0] < Watchdog.GIVE_UP * T + 2 * T
    if not stalls:  # no late look on the way: the trip came within a fraction of the timeout after it
        assert trips[0] < T + 4 * T


def test_a_late_look_reports_a_host_stall_and_gives_the_board_one_timeout_from_then() -> None:
    stalls: list[tuple[float, float]] = []
    dog = Watchdog(0.005, lambda late, silent, by: stalls.append((late, silent)), clock=lambda: 0.0)
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
    assert seen[0] is not None and abs(seen[0] - 0.002) < 1e-9
    assert seen[1] is None
    assert seen[2] == 0.005  # one whole timeout from the late look
    assert seen[3] is not None and abs(seen[3] - 0.001) < 1e-9
    assert seen[4] == 0.005 and seen[5] is None and seen[6] is None
    assert [(round(late, 3), round(silent, 3)) for late, silent in stalls] == [(0.02, 0.025), (0.02, 0.019)]


def test_with_a_grace_a_silence_is_held_and_only_the_boards_clock_late_excuses_it() -> None:
    stalls: list[tuple[float, float]] = []
    dog = Watchdog(0.005, lambda late, silent, by: stalls.append((late, silent)), grace_s=0.2, clock=lambda: 0.0)
    dog.arm()
    dog.last = 10.0
    wait = dog.look(10.006, due=10.006)  # 6 ms of silence, on time: held, not a trip
    assert dog.held and wait is not None and abs(wait - 0.05) < 1e-9
    assert dog.release(10.040, board_late_s=0.039, lost=None)  # the sample came with CLOCK_LATE: the shared host
    assert not dog.held and [(round(a, 3), round(b, 3)) for a, b in stalls] == [(0.039, 0.04)]
    dog.last = 11.0
    assert dog.look(11.006, due=11.006) is not None and dog.held
    assert not dog.release(11.030, board_late_s=0.0, lost=29)  # on time by its own clock, samples lost: trip
    assert dog.look(11.040, due=11.040) is not None and dog.held
    assert not dog.release(11.050, board_late_s=0.0, lost=None)  # not known: trip
    assert len(stalls) == 1
    dog.last = 11.5
    assert dog.look(11.508, due=11.508) is not None and dog.held
    assert dog.release(11.512, board_late_s=0.0, lost=0)  # none lost, only held up on the way: the shared host
    assert [(round(a, 3), round(b, 3)) for a, b in stalls][1:] == [(0.012, 0.012)]
    dog.last = 12.0
    assert dog.look(12.199, due=12.199) is not None  # still within the grace
    assert dog.look(12.201, due=12.201) is None  # past the grace: trip, whatever comes later


def test_a_board_that_stays_silent_after_a_host_stall_trips_at_the_next_on_time_look() -> None:
    async def scenario(clock: HostClock, dog: EventLoopWatchdog) -> None:
        await feed_for(dog, 2 * T)
        clock.stall(4 * T)

    trips, stalls = asyncio.run(watch(T, scenario, run_s=30 * T))
    assert len(stalls) >= 1 and len(trips) == 1
    assert 4 * T <= trips[0] <= Watchdog.GIVE_UP * T + 10 * T  # one timeout after the stall


def test_silence_past_the_give_up_limit_trips_without_looking_again() -> None:
    async def scenario(clock: HostClock, dog: EventLoopWatchdog) -> None:
        await feed_for(dog, 2 * T)
        clock.stall(Watchdog.GIVE_UP * T + 2 * T)

    trips, stalls = asyncio.run(watch(T, scenario))
    assert stalls == [] and len(trips) == 1 and trips[0] >= Watchdog.GIVE_UP * T


def test_an_event_loop_watchdog_rearms_any_number_of_times() -> None:
    async def main() -> list[float]:
        trips: list[float] = []
        dog = EventLoopWatchdog(T, trips.append)
        for _ in range(5):
            dog.arm()
            await asyncio.sleep(6 * T)
        dog.close()
        return trips

    assert len(asyncio.run(main())) == 5
