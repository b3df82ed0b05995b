"""The sample watchdog: no GYRO_SAMPLE for ``watchdog_ms`` -> zero drive, DISABLE (docs/reliability.md).

:class:`Watchdog` is the judgement alone, with no thread of its own. Two things drive it:

- the realtime loop thread (_loop_thread): the watchdog is the timeout of its blocking read of the servo link,
  so nothing else in the process wakes up at 1 kHz or competes for the GIL on the hot path;
- :class:`EventLoopWatchdog` for the lockstep clock, where the loop runs in the event loop (the emulator's world
  waits for the bench, so only a dead or frozen emulator goes silent): an asyncio timer looks now and then.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

StallReport = Callable[[float, float, str], None]  # (late_s, silent_s, by: "bench" | "emulator" | "host")


class Watchdog:
    """Trips on a silence it saw itself, on time.

    Its driver stores the time of every sample in ``last``. A driver looks (:meth:`look`) when the time it was told to
    wait has run out. A trip needs the silence to be seen by a look that was itself on time: a look more than
    ``late_s`` after it was due means the host did not run the bench (nor, on the same CPU, an emulator), so
    samples may be queued unread. It then reports ``on_host_stall(late_s, silent_s, "bench")`` and gives the board
    one timeout from now; it trips on the first on-time look that still finds the silence, and at ``GIVE_UP`` x
    timeout of silence whatever its own timing.

    ``grace_s`` (emulated boards only, ``safety.emulator_stall_grace_ms``): a silence past the timeout is *held*
    instead of tripping, until ``grace_s``. If the next sample comes with the board's word that its own clock was
    late (CLOCK_LATE: the emulator was not run by the host it shares with the bench), or comes without a sample
    lost before it (the bytes were held up on their way through the shared host), :meth:`release` reports a host
    stall; if samples were lost (the board or its link failed), or nothing comes within ``grace_s``, it trips.
    A link fault injected as a latency spike (samples held, none lost) is then a host stall too: fault-injection
    sessions run without the grace.
    """

    LATE_S = 1e-3
    GIVE_UP = 10.0

    def __init__(self, timeout_s: float, on_host_stall: StallReport | None = None, *, grace_s: float = 0.0,
                 late_s: float = LATE_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.timeout_s = timeout_s
        self.grace_s = grace_s
        self.late_s = late_s
        self.on_host_stall = on_host_stall
        self.clock = clock
        self.last = clock()
        self.armed = False
        self.held = False

    def arm(self) -> None:
        """Start judging (again) from now: restartable any number of times."""
        self.last = self.clock()
        self.held = False
        self.armed = True

    def disarm(self) -> None:
        self.armed = False
        self.held = False

    def look(self, now: float, due: float | None) -> float | None:
        """One look at ``now`` by a driver that meant to look at ``due`` (None: its first look).

        Returns how long to wait before the next look, or None: trip."""
        silent = now - self.last
        if silent < self.timeout_s:
            return min(self.timeout_s - silent, 0.05)
        late = 0.0 if due is None else now - due
        if late > self.late_s and silent < self.GIVE_UP * self.timeout_s:
            if self.on_host_stall is not None:
                self.on_host_stall(late, silent, "bench")
            return self.timeout_s
        if silent < self.grace_s:
            self.held = True
            return min(self.grace_s - silent, 0.05)
        return None

    def release(self, now: float, board_late_s: float, lost: int | None) -> bool:
        """A sample came while a silence was held. True (a host stall, reported) if the emulator said its clock was
        ``board_late_s`` late (``by="emulator"``), or if no sample was lost on the way (``lost == 0``: the board sent
        on time and the host it shares with the bench held the bytes up, ``by="host"``); False (trip) if samples
        were lost (the board or its link failed) or it is not known (``lost`` None: the first sample of a run)."""
        self.held = False
        silent = now - self.last
        if board_late_s > 0:
            by, late = "emulator", board_late_s
        elif lost == 0:
            by, late = "host", silent
        else:
            return False
        if self.on_host_stall is not None:
            self.on_host_stall(late, silent, by)
        return True


class EventLoopWatchdog:
    """Drives a :class:`Watchdog` from the event loop with one timer (lockstep; see the module docstring).

    asyncio's timers wake up to ~1 ms late, so a look counts as late only past ``late_s`` = 1 ms + that."""

    TIMER_SLACK_S = 1e-3

    def __init__(self, timeout_s: float, on_trip: Callable[[float], None], on_host_stall: StallReport | None = None,
                 *, clock: Callable[[], float] = time.monotonic) -> None:
        self.dog = Watchdog(timeout_s, on_host_stall, late_s=Watchdog.LATE_S + self.TIMER_SLACK_S, clock=clock)
        self.on_trip = on_trip
        self._timer: asyncio.TimerHandle | None = None

    def feed(self) -> None:
        self.dog.last = self.dog.clock()

    def arm(self) -> None:
        self.dog.arm()
        self._schedule(self.dog.timeout_s, None)

    def disarm(self) -> None:
        self.dog.disarm()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    close = disarm

    def _schedule(self, wait_s: float, now: float | None) -> None:
        due = (self.dog.clock() if now is None else now) + wait_s
        self._timer = asyncio.get_running_loop().call_later(wait_s, self._look, due)

    def _look(self, due: float) -> None:
        self._timer = None
        if not self.dog.armed:
            return
        now = self.dog.clock()
        wait = self.dog.look(now, due)
        if wait is None:
            self.dog.disarm()
            self.on_trip(now - self.dog.last)
        else:
            self._schedule(wait, now)
