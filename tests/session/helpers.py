"""Run bench sessions against the emulator (its own process, real ptys) and read what both sides recorded."""

from __future__ import annotations

import asyncio
import hashlib
import json
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import numpy as np

from hil.config import PROFILES, PortConfig, SessionConfig, load_session
from hil.log.reader import read_log
from hil.session import EmulatorProcess, Session, SessionResult

BASE_SESSION = PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml"


def session_config(**overrides: Any) -> SessionConfig:
    """The shipped 1 deg / 1 Hz ESO session with fields replaced (validated like a file)."""
    data = load_session(BASE_SESSION).model_dump()
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return SessionConfig.model_validate(data)


class Run:
    def __init__(self, result: SessionResult, records: list[dict[str, Any]], emulator: dict[str, Any]) -> None:
        self.result = result
        self.records = records
        self.emulator = emulator
        self.telemetry = result.telemetry

    def kinds(self, link: str | None = None) -> list[str]:
        return [r["kind"] for r in self.records if link is None or r["link"] == link]


During = Callable[[EmulatorProcess, Session], Awaitable[None]]


def run_session(config: SessionConfig, out: Path, *, clock: str = "lockstep", emulator_args: list[str] | None = None,
                during: During | None = None, watchdog_ms: float | None = None,
                after: Callable[[EmulatorProcess], None] | None = None, emulated: bool = False) -> Run:
    """One session against a fresh emulator; ``during`` runs beside the session, ``after`` once it has returned
    (the emulator still running)."""
    fault_log = out / "emulator-records.jsonl"
    args = [*config.emulator.process_args(), *(emulator_args or []), "--fault-log", str(fault_log)]
    if watchdog_ms is None and clock == "lockstep":
        watchdog_ms = 1000.0
    emulator = EmulatorProcess(config.emulator.config, clock=clock, seed=config.seed, extra_args=args)
    ports = emulator.start()
    try:
        session = Session(config, {n: PortConfig(port=p) for n, p in ports.items() if n != "control"}, out,
                          watchdog_ms=watchdog_ms, lockstep=clock == "lockstep", emulated=emulated)

        async def main() -> SessionResult:
            task = asyncio.create_task(session.run())
            if during is not None:
                await during(emulator, session)
            return await task

        result = asyncio.run(main())
        if after is not None:
            after(emulator)
    finally:
        summary = emulator.stop()
    records = [json.loads(line) for line in fault_log.read_text().splitlines()] if fault_log.exists() else []
    return Run(result, records, summary)


async def wait_cycles(session: Session, n: int, timeout_s: float = 30.0) -> None:
    """Until the session's loop has run n cycles."""
    for _ in range(int(timeout_s / 0.005)):
        if session.loop_ is not None and session.loop_.stats.cycles >= n:
            return
        await asyncio.sleep(0.005)
    raise TimeoutError(f"the session did not reach {n} cycles")


def logged_events(log_path: Path) -> list[tuple[str, dict[str, Any]]]:
    """The events of a session log as (kind, detail) pairs, decoded as the log's reader does (a detail cut at the
    log's detail length comes back as ``{"text": ...}``)."""
    from hil.log import read_log_frames

    return [(e["kind"], e["detail"]) for e in read_log_frames(log_path, groups=["events"]).event_details()]


HOST_CLOCK = {"t_host_ns", "latency_us"}  # the host's own monotonic clock: differs between any two runs


def within_session(group: str, g: dict, loop: dict, ticks: int) -> int:  # type: ignore[type-arg]
    """Rows of ``group`` that belong to the session's first ``ticks`` ticks (after them, the wind-down depends
    on how long the host took to start it: wall time in lockstep)."""
    if group == "loop":
        return ticks
    if group == "image":  # frames exposed before the last sample of the session, board clock
        return int(np.count_nonzero(np.asarray(g["t_exposure_s"]) <= loop["t_s"][ticks - 1]))
    if group == "timing":
        return int(np.count_nonzero(np.asarray(g["tick"]) < ticks))
    if group == "drive":  # DRIVE_STATUS every 10 world ticks, logged beside the loop tick it arrived after
        return int(np.count_nonzero(np.asarray(g["loop_tick"]) < ticks))
    return ticks // 10  # hexapod: POSE every 10 world ticks from the first


def assert_same_channels(a: Path, b: Path, ticks: int) -> int:
    """Every dataset of /loop, /image, /hexapod, /timing and /drive in the session's first ``ticks`` ticks equal,
    the host's clock aside. Returns the number of values compared."""
    la, lb = read_log(a), read_log(b)
    compared = 0
    for group in ("loop", "image", "hexapod", "timing", "drive"):
        ga, gb = la.groups[group], lb.groups[group]
        assert set(ga) == set(gb), group
        n = within_session(group, ga, la.groups["loop"], ticks)
        assert n == within_session(group, gb, lb.groups["loop"], ticks), group
        for channel in sorted(set(ga) - HOST_CLOCK):
            x, y = np.asarray(ga[channel])[:n], np.asarray(gb[channel])[:n]
            assert len(x) == n and len(y) == n, (group, channel, len(x), len(y), n)
            np.testing.assert_array_equal(x, y, err_msg=f"/{group}/{channel}")
            compared += n
    return compared


def channel_digests(log_path: Path, ticks: int) -> dict[str, str]:
    """SHA-256 of every /loop, /image, /hexapod and /timing dataset over the session's first ``ticks`` ticks, the
    host's clock aside: what a lockstep run reproduces byte for byte."""
    log = read_log(log_path)
    out = {}
    for group in ("loop", "image", "hexapod", "timing"):
        g = log.groups[group]
        n = within_session(group, g, log.groups["loop"], ticks)
        for channel in sorted(set(g) - HOST_CLOCK):
            data = np.ascontiguousarray(np.asarray(g[channel])[:n])
            out[f"/{group}/{channel}"] = f"{data.dtype.str}:{n}:{hashlib.sha256(data.tobytes()).hexdigest()[:16]}"
    return out
