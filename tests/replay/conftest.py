"""Sessions against the emulator with a capture, shared by the capture tests (each runs once per test run)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from hil.config import SessionConfig
from hil.link import find_capture
from hil.session import Session, SessionResult
from tests.factories import run_session, session_config

DURATION_S = 1.5


@dataclass
class CapturedRun:
    result: SessionResult
    capture: Path
    log: Path
    session: Session
    emulator: dict


def run_captured(config: SessionConfig, out: Path, clock: str) -> CapturedRun:
    """One session against a fresh emulator with ``capture_dir``: its result, capture file and log."""
    # a watchdog far above any pause of a loaded machine: these runs are about what the links carried
    run = run_session(config, out, clock=clock, watchdog_ms=1000.0, emulated=True, capture_dir=out / "capture",
                      log_dir=out / "logs")
    result = run.result
    assert result.status == "completed", result.message
    assert result.log_path is not None
    return CapturedRun(result, find_capture(out / "capture"), result.log_path, run.session, run.emulator)


@pytest.fixture(scope="session")
def lockstep_run(tmp_path_factory: pytest.TempPathFactory) -> CapturedRun:
    """1.5 s of the shipped ESO session with tracking, lockstep, captured."""
    return run_captured(session_config(duration_s=DURATION_S, seed=3), tmp_path_factory.mktemp("lockstep"),
                        "lockstep")


@pytest.fixture(scope="session")
def realtime_run(tmp_path_factory: pytest.TempPathFactory) -> CapturedRun:
    """The same session in real time: the loop thread reads the servo link and writes DRIVE_CMD itself."""
    config = session_config(duration_s=DURATION_S, seed=3, controller={"name": "eso_kf", "params": {}})
    return run_captured(config, tmp_path_factory.mktemp("realtime"), "realtime")
