"""Precise pacing for a board's clock without asyncio timers (see ../shared/FACTS.md).

A select() sleep wakes whenever a watched fd has data, so incoming bytes are read (and time-stamped)
as they arrive; the last SPIN_S before a deadline is a busy wait on perf_counter that still polls the
fds, so a command arriving during the spin gets its true arrival time. Measured on a 2-core VM:
lateness p50 ~0.2 us, p99 ~35 us (docs/performance.md has this machine's figures).
"""

from __future__ import annotations

import select
import time
from collections.abc import Callable, Mapping

SPIN_S = 200e-6

Readers = Mapping[int, Callable[[float], None]]  # fd -> on_readable(t_perf_s)


def poll_readers(readers: Readers, timeout_s: float) -> bool:
    """One select() over the readers' fds; calls each readable fd's callback. True if any was readable."""
    if not readers:
        if timeout_s > 0:
            time.sleep(timeout_s)
        return False
    try:
        readable, _, _ = select.select(list(readers), [], [], max(timeout_s, 0.0))
    except (OSError, ValueError):  # an fd closed under us (a link disconnecting): the caller rebuilds readers
        return False
    if not readable:
        return False
    now = time.perf_counter()
    for fd in readable:
        readers[fd](now)
    return True


def wait_until(deadline: float, readers: Readers | None = None) -> float:
    """Wait until perf_counter() >= deadline, serving readable fds meanwhile.

    Returns the lateness in seconds (how far past the deadline it returned).
    """
    readers = readers or {}
    while True:
        now = time.perf_counter()
        remaining = deadline - now
        if remaining <= 0:
            return -remaining
        poll_readers(readers, remaining - SPIN_S if remaining > SPIN_S else 0.0)


def wait_for(condition: Callable[[], bool], timeout_s: float, readers: Readers, stop: Callable[[], bool]) -> bool:
    """Serve the readers until condition() holds (True), timeout_s passes or stop() holds (False)."""
    give_up = time.perf_counter() + timeout_s
    while not condition():
        remaining = give_up - time.perf_counter()
        if remaining <= 0 or stop():
            return False
        poll_readers(readers, min(remaining, 0.05))
    return True
