"""Where the bench runs on the lab PC: the loop thread's CPU and scheduling class, helpers kept off it.

Measured on the 2-core VM (docs/performance.md, "CPU placement"): a GYRO_SAMPLE -> DRIVE_CMD round
trip between two processes on one core costs two context switches; across cores it costs two
wake-ups of the other core, which in a VM are inter-processor interrupts to a halted virtual CPU
(p50 ~40 us each). So the loop thread gets a core of its own, shared only with what it ping-pongs
with (an emulator in loopback), and the helper processes (log writer, telemetry) get the others.

Linux only (sched_setaffinity); where placement is impossible (one CPU, a CPU the process may not
use) the session runs unpinned and says so in its log.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from pathlib import Path
from typing import NamedTuple

SERVICE_RT_PRIORITY = 50  # `hil serve`'s worker runs its items' loop threads SCHED_FIFO at this, where it may


class Placement(NamedTuple):
    """The calling thread's CPUs and scheduling policy, to restore after a session."""

    cpus: frozenset[int]
    policy: int
    priority: int


def current_placement() -> Placement:
    return Placement(frozenset(os.sched_getaffinity(0)), os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)


def restore_placement(p: Placement) -> None:
    os.sched_setscheduler(0, p.policy, os.sched_param(p.priority))
    os.sched_setaffinity(0, p.cpus)


def allowed_cpus() -> list[int]:
    """The CPUs this process may run on, ascending."""
    return sorted(os.sched_getaffinity(0))


def resolve_cpu(cpu: int, cpus: list[int] | None = None) -> int:
    """``cpu`` as an index into the allowed CPUs (-1 = the last one, as in Python), the CPU number it names.

    Raises ValueError naming the allowed CPUs when there is no such CPU, or when it would leave no CPU for
    the helpers (placement needs two).
    """
    cpus = allowed_cpus() if cpus is None else cpus
    if len(cpus) < 2:
        raise ValueError(f"only CPU {cpus} is available: nothing to keep the helpers off")
    if not -len(cpus) <= cpu < len(cpus):
        raise ValueError(f"no CPU index {cpu}: this process may use CPUs {cpus} (index 0..{len(cpus) - 1}, "
                         "or -1 for the last)")
    return cpus[cpu]


def pin_this_thread(cpu: int) -> None:
    """Pin the calling thread (threads it starts later inherit it) to ``cpu``."""
    os.sched_setaffinity(0, {cpu})


def pin_this_thread_to(cpus: set[int]) -> None:
    """Pin the calling thread (threads it starts later inherit it) to any of ``cpus``."""
    os.sched_setaffinity(0, cpus)


def pin_process(pid: int, cpus: set[int]) -> None:
    """Pin every thread of process ``pid`` to ``cpus`` (threads it starts later inherit it)."""
    tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")] if Path(f"/proc/{pid}/task").is_dir() else [pid]
    for tid in tids:
        with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
            os.sched_setaffinity(tid, cpus)


def set_fifo(priority: int) -> None:
    """Run the calling thread SCHED_FIFO at ``priority``; children do not inherit it (OSError if refused)."""
    os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(priority))


def fifo_refusal(priority: int = SERVICE_RT_PRIORITY) -> str | None:
    """None when a thread of this process may run SCHED_FIFO at ``priority`` (tried on a thread started and ended
    here), else why not and how to grant it, in one line."""
    refused: list[str] = []

    def attempt() -> None:
        try:
            set_fifo(priority)
        except OSError as exc:
            refused.append(exc.strerror or str(exc))

    thread = threading.Thread(target=attempt, name="hil-fifo-check")
    thread.start()
    thread.join()
    if not refused:
        return None
    python = os.path.realpath(sys.executable)
    return (f"SCHED_FIFO {priority} refused ({refused[0]}): the 1 kHz loop then shares the CPU with everything else; "
            "grant it with a real-time priority limit for the lab's user (a line `USER - rtprio 80` in "
            f"/etc/security/limits.d/hil.conf, then log in again) or `sudo setcap cap_sys_nice+ep {python}`")
