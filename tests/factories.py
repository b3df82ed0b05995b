"""What the tests build, in one place: session configs, dicts and files from the shipped sessions, and short
sessions run on the emulator process (lockstep or realtime, optionally captured) or on the in-process ``sim`` lab
with the Session object kept.

A test that needs a session builds it here; a helper that reads what a session left (log digests, events) lives
beside the tests that read it (tests/session/helpers.py).
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import yaml

from hil.config import PROFILES, PortConfig, SessionConfig, load_session, session_yaml
from hil.session import EmulatorProcess, Session, SessionResult, SimLab, sim_ports

BASE_SESSION = PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml"  # the shipped 1 deg / 1 Hz ESO session
DEMO_SESSION = PROFILES / "sessions" / "demo.yaml"
INCLUDED = ("controller", "profile", "hexapod_limits")  # the session file's fields that name other files


def session_config(**overrides: Any) -> SessionConfig:
    """The shipped 1 deg / 1 Hz ESO session with fields replaced (a dict merges into a section), validated like a
    file."""
    data = load_session(BASE_SESSION).model_dump()
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return SessionConfig.model_validate(data)


def session_data(**changes: Any) -> dict[str, Any]:
    """The shipped 1 deg / 1 Hz ESO session as the dict of its YAML, with absolute paths, top-level fields
    replaced: what a user writes into a file of their own."""
    data = yaml.safe_load(BASE_SESSION.read_text())
    for key in INCLUDED:
        data[key] = str((BASE_SESSION.parent / data[key]).resolve())
    data["emulator"]["config"] = str((BASE_SESSION.parent / data["emulator"]["config"]).resolve())
    data.update(changes)
    return data


def write_yaml(path: Path, data: Any) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def short_session(directory: Path, duration_s: float = 2.0, name: str = "short", **changes: object) -> Path:
    """The demo session, ``duration_s`` long, as a file that stands on its own (every file it names inlined)."""
    data = yaml.safe_load(session_yaml(load_session(DEMO_SESSION)))
    data.update(name=name, duration_s=duration_s, **changes)
    return write_yaml(directory / f"{name}.yaml", data)


class Run:
    """A session run on the emulator process: its result, the emulator's fault records and summary."""

    def __init__(self, result: SessionResult, records: list[dict[str, Any]], emulator: dict[str, Any],
                 session: Session) -> None:
        self.result = result
        self.records = records
        self.emulator = emulator
        self.session = session
        self.telemetry = result.telemetry

    def kinds(self, link: str | None = None) -> list[str]:
        return [r["kind"] for r in self.records if link is None or r["link"] == link]


During = Callable[[EmulatorProcess, Session], Awaitable[None]]


def run_session(config: SessionConfig, out: Path, *, clock: str = "lockstep", emulator_args: list[str] | None = None,
                during: During | None = None, watchdog_ms: float | None = None,
                after: Callable[[EmulatorProcess], None] | None = None, emulated: bool = False,
                capture_dir: Path | None = None, log_dir: Path | None = None) -> Run:
    """One session against a fresh emulator process on ``clock``; ``during`` runs beside the session, ``after``
    once it has returned (the emulator still running). Lockstep's watchdog is 1 s unless told (the emulator may be
    descheduled on a loaded machine). ``capture_dir``: every link's bytes captured there."""
    fault_log = out / "emulator-records.jsonl"
    args = [*config.emulator.process_args(), *(emulator_args or []), "--fault-log", str(fault_log)]
    if watchdog_ms is None and clock == "lockstep":
        watchdog_ms = 1000.0
    emulator = EmulatorProcess(config.emulator.config, clock=clock, seed=config.seed, extra_args=args)
    ports = emulator.start()
    try:
        extra: dict[str, Any] = {} if capture_dir is None else {"capture_dir": capture_dir}
        session = Session(config, {n: PortConfig(port=p) for n, p in ports.items() if n != "control"},
                          log_dir or out, watchdog_ms=watchdog_ms, lockstep=clock == "lockstep", emulated=emulated,
                          **extra)

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
    return Run(result, records, summary, session)


def sim_session(config: SessionConfig, out: Path, *, ports: dict[str, PortConfig] | None = None,
                prepare: Callable[[Session], None] | None = None) -> tuple[Session, SessionResult]:
    """One session on the in-process ``sim`` lab whose Session object the test keeps; ``prepare(session)`` runs
    once it exists, before it starts. ``ports``: the links it opens (default all four)."""

    async def main() -> tuple[Session, SessionResult]:
        lab = SimLab(config.emulator.config, seed=config.seed)
        session = Session(config, sim_ports() if ports is None else ports, out, lockstep=True,
                          open_link=lab.open_link, watchdog=False)
        lab.on_error = session.fault
        if prepare is not None:
            prepare(session)
        async with lab:
            result = await session.run()
        return session, result

    return asyncio.run(main())
