"""The realtime loop thread (LoopThread): the watchdog is its read timeout, recoveries restart it any number of
times, it takes the loop's CPU itself, and with emulated boards a stall of the shared host is told from a board fault
by the emulator's own CLOCK_LATE."""

from __future__ import annotations

import asyncio
import os
import signal
import threading

import pytest

from firmware_stub.control import ControlClient
from hil.session import EmulatorProcess, Session
from tests.factories import run_session, session_config
from tests.session.helpers import logged_events

pytestmark = pytest.mark.realtime


def ended(session: Session) -> bool:
    return session._finished is not None and session._finished.done()


async def wait_cycles(session: Session, n: int, timeout_s: float = 30.0) -> None:
    """Until the loop has run n cycles, or the session has ended (a loaded machine may end it early; the test's
    assertions on the result then say whether that was right)."""
    for _ in range(int(timeout_s / 0.005)):
        if ended(session) or (session.loop_ is not None and session.loop_.stats.cycles >= n):
            return
        await asyncio.sleep(0.005)
    raise TimeoutError(f"the session did not reach {n} cycles")


async def wait_armed(session: Session, timeout_s: float = 10.0) -> None:
    """Until the loop drives and its watchdog watches (after a recovery, too); gives up if the session has ended."""
    for _ in range(int(timeout_s / 0.002)):
        if session.loop_ and session.loop_.armed and session.loop_thread and session.loop_thread.dog.armed:
            return
        if ended(session):
            return
        await asyncio.sleep(0.002)
    raise TimeoutError("the session did not re-arm")


@pytest.mark.slow
def test_five_watchdog_trips_are_five_recoveries_each_with_a_new_loop_thread(tmp_path) -> None:
    threads: list[object] = []

    async def stall_five_times(emu: EmulatorProcess, session: Session) -> None:
        await wait_cycles(session, 300)
        with ControlClient(emu.ports["control"]) as ctl:
            for _ in range(5):
                await wait_armed(session)
                threads.append(session.loop_thread)
                ctl.call("inject", link="servo", kind="stall", duration_ms=60)
                await asyncio.sleep(0.15)
        await wait_armed(session)
        threads.append(session.loop_thread)
        session.stop("five stalls done")  # the duration is a ceiling: a busy machine recovers slower

    safety = {"watchdog_ms": 20, "on_fault": "recover", "max_recoveries": 50, "recover_after_ms": 20}
    run = run_session(session_config(duration_s=30.0, safety=safety), tmp_path, clock="realtime",
                      during=stall_five_times)
    assert run.result.status in ("completed", "stopped"), run.result.message
    faults = run.result.stats.faults
    trips = sum("watchdog" in f for f in faults)
    # each 60 ms stall trips the 20 ms watchdog, unless a loaded host descheduled the bench during it: then the
    # silence is the host's (a host_stall event), never tripped on; every trip is recovered
    assert trips >= 1 and trips + run.result.stats.host_stalls >= 5, (faults, run.result.stats.host_stalls)
    assert run.result.stats.recoveries == trips, faults
    assert len({id(t) for t in threads}) == trips + 1  # each recovery ran a loop thread of its own
    assert not any(t.alive for t in threads)  # type: ignore[attr-defined]
    kinds = [k for k, _ in logged_events(run.result.log_path)]
    assert kinds.count("recovered") == run.result.stats.recoveries
    assert not [t for t in threading.enumerate() if t.name == "hil-loop"]  # none left behind


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="placement needs two CPUs")
def test_the_loop_thread_takes_the_loop_cpu_and_the_event_loop_goes_with_the_helpers(tmp_path) -> None:
    cpus = sorted(os.sched_getaffinity(0))
    before = os.sched_getaffinity(0)
    seen: dict[str, set[int]] = {}

    async def look(emulator: EmulatorProcess, session: Session) -> None:
        await wait_cycles(session, 200)
        await wait_armed(session)
        assert session.loop_thread is not None and session.log is not None
        assert session.loop_thread.native_id is not None
        seen["loop thread"] = os.sched_getaffinity(session.loop_thread.native_id)
        seen["event loop"] = os.sched_getaffinity(0)
        seen["writer"] = os.sched_getaffinity(session.log.writer_pid)

    config = session_config(duration_s=1.0, host={"loop_cpu": -1}, emulator={"cpu": -1},
                            safety={"on_fault": "recover", "max_recoveries": 50})
    run = run_session(config, tmp_path, clock="realtime", during=look, watchdog_ms=50)
    assert run.result.status == "completed", run.result.message
    last = cpus[-1]
    assert seen == {"loop thread": {last}, "event loop": set(cpus) - {last}, "writer": set(cpus) - {last}}
    assert os.sched_getaffinity(0) == before


def _freeze_emulator(times: int, ms: float):  # type: ignore[no-untyped-def]
    """Stop the emulator's whole process ``times`` times for ``ms``: its clock comes back late, as on a busy host."""

    async def during(emu: EmulatorProcess, session: Session) -> None:
        assert emu.proc is not None
        await wait_cycles(session, 300)
        for _ in range(times):
            await wait_armed(session)
            os.kill(emu.proc.pid, signal.SIGSTOP)
            await asyncio.sleep(ms / 1000)
            os.kill(emu.proc.pid, signal.SIGCONT)
            await asyncio.sleep(0.2)

    return during


@pytest.mark.slow
def test_with_a_grace_an_emulator_the_host_did_not_run_is_a_stall_not_a_fault(tmp_path) -> None:
    safety = {"watchdog_ms": 5, "on_fault": "stop", "emulator_stall_grace_ms": 500}
    run = run_session(session_config(duration_s=2.0, safety=safety), tmp_path, clock="realtime",
                      during=_freeze_emulator(3, 40), emulated=True)
    assert run.result.status == "completed", run.result.message
    assert run.result.stats.faults == []
    stalls = [d for k, d in logged_events(run.result.log_path) if k == "host_stall"]
    # each freeze is one stall of 40 ms or so, less what the bench still had to read when it began; a loaded machine
    # adds shorter ones of its own, and where the bench's own thread was not run either the watchdog notices it first
    # (late_by "bench" instead of "emulator")
    assert run.result.stats.host_stalls >= 3, stalls
    frozen = [d for d in stalls if d["silent_ms"] >= 35]
    assert all(d["late_ms"] <= 1000 for d in frozen), frozen
    assert any(d["late_by"] == "emulator" and d["late_ms"] >= 35 for d in frozen), frozen
    assert run.result.stats.clock_late >= 3  # the emulator said so itself, before each late sample


def test_without_the_grace_the_same_freeze_trips_the_watchdog(tmp_path) -> None:
    safety = {"watchdog_ms": 5, "on_fault": "stop"}
    run = run_session(session_config(duration_s=2.0, safety=safety), tmp_path, clock="realtime",
                      during=_freeze_emulator(1, 40), emulated=True)
    assert run.result.status == "fault" and run.result.stats.faults[0].startswith("watchdog: no GYRO_SAMPLE")


def test_with_a_grace_a_board_silent_on_its_own_clock_still_trips(tmp_path) -> None:
    async def stall_link(emu: EmulatorProcess, session: Session) -> None:
        await wait_cycles(session, 300)
        await wait_armed(session)
        with ControlClient(emu.ports["control"]) as ctl:  # the emulator's clock runs on; the link holds the samples
            ctl.call("inject", link="servo", kind="stall", duration_ms=60)

    safety = {"watchdog_ms": 5, "on_fault": "stop", "emulator_stall_grace_ms": 500}
    run = run_session(session_config(duration_s=2.0, safety=safety), tmp_path, clock="realtime", during=stall_link,
                      emulated=True)
    if run.result.status == "completed":
        # a loaded host held the emulator's own clock during the stall as well: the emulator said so (CLOCK_LATE) and
        # the bench rightly took the silence for the host's. Only then may the session go on.
        stalls = [d for k, d in logged_events(run.result.log_path) if k == "host_stall"]
        assert run.result.stats.clock_late >= 1 and any(
            d["late_by"] == "emulator" and d["silent_ms"] >= 50 for d in stalls), (run.result.stats, stalls)
        return
    assert run.result.status == "fault", run.result.message
    assert run.result.stats.faults[0].startswith("watchdog: no GYRO_SAMPLE")
    silent_ms = float(run.result.stats.faults[0].split("for ")[1].split(" ms")[0])
    assert 5 <= silent_ms < 500  # when the held samples came, without CLOCK_LATE: not after the whole grace


def test_an_exception_in_the_loop_thread_disables_the_drive_and_ends_the_session_as_a_fault(tmp_path) -> None:
    async def break_the_loop(emu: EmulatorProcess, session: Session) -> None:
        await wait_cycles(session, 300)
        assert session.loop_ is not None

        def broken(tick: int, az: int, el: int) -> None:
            raise ZeroDivisionError("a bug in a controller")

        session.loop_.drive = broken

    run = run_session(session_config(duration_s=2.0, safety={"on_fault": "stop"}), tmp_path, clock="realtime",
                      during=break_the_loop, watchdog_ms=200)
    assert run.result.status == "fault"
    assert run.result.message == "loop thread failed: ZeroDivisionError: a bug in a controller"
    disables = [r for r in run.records if r["link"] == "driver" and r["kind"] == "drive_disable"]
    assert disables  # the emulated driver saw the power stage disabled
