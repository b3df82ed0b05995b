"""Labs are backends passed to the run core (hil.session.Lab): chosen by name, or handed in; nothing process-wide."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path

import pytest

import hil
from hil.config import ConfigError, SessionConfig
from hil.link import LinkError
from hil.session import (
    LABS,
    EmulatorLab,
    HardwareLab,
    InProcessLab,
    Lab,
    LabRun,
    Session,
    SimLab,
    SimLink,
    lab_for,
)
from tests.factories import session_config


def test_the_table_names_each_lab_and_lab_for_picks_the_one_loopback_and_clock_ask_for() -> None:
    config = session_config()
    assert set(LABS) == {"hardware", "emulator", "sim"}
    assert type(lab_for(config, loopback=False)) is HardwareLab
    sim = lab_for(config, loopback=True, clock="sim")
    assert type(sim) is InProcessLab and sim.clock == "sim" and sim.emulated
    lockstep = lab_for(config, loopback=True, clock="lockstep")
    assert type(lockstep) is EmulatorLab and lockstep.clock == "lockstep"
    default = lab_for(config, loopback=True)  # the session's own emulator.clock
    assert default.clock == config.emulator.clock
    with pytest.raises(ConfigError, match="clock='sim': runs the emulated lab in this process; needs loopback"):
        lab_for(config, loopback=False, clock="sim")
    with pytest.raises(ConfigError, match="clock: 'fast' is not realtime, lockstep or sim"):
        lab_for(config, clock="fast")  # type: ignore[arg-type]


def test_each_lab_refuses_what_it_cannot_run_before_anything_starts(tmp_path: Path) -> None:
    config = session_config()
    with pytest.raises(ConfigError, match="ports: not set in the session file"):
        HardwareLab().check(config)  # the shipped session names no ports
    with pytest.raises(ConfigError, match="capture"):
        InProcessLab().check(config, capture=True)  # the sim lab's links carry no bytes
    oracle = session_config(controller={"name": "oracle", "params": {}})
    with pytest.raises(ConfigError, match="oracle"):
        EmulatorLab("lockstep").check(oracle)  # the oracle reads the sim lab's true plant state
    InProcessLab().check(oracle)
    with pytest.raises(ConfigError, match="realtime or lockstep"):
        EmulatorLab("sim")


class CountingLab(Lab):
    """A lab of a test's own: the in-process lab, counting the sessions it runs and tagging their logs."""

    name = "counting"
    clock = "sim"
    emulated = True

    def __init__(self) -> None:
        self.sessions: list[Session] = []

    async def run(self, config: SessionConfig, out_dir: Path, *, progress: Callable[[int, int], None] | None,
                  on_session: Callable[[Session], None], capture_dir: Path | None) -> LabRun:
        def seen(session: Session) -> None:
            self.sessions.append(session)
            on_session(session)

        return await InProcessLab().run(config, out_dir, progress=progress, on_session=seen, capture_dir=capture_dir)


def test_a_lab_passed_in_runs_the_session_and_the_next_run_without_one_is_unaffected(tmp_path: Path) -> None:
    config = session_config(duration_s=0.5)
    mine = CountingLab()
    held = hil.run(config, out=tmp_path / "mine", lab=mine, loopback=False)  # the lab wins over loopback/clock
    assert held.status == "completed" and held.clock == "sim", held.message
    assert len(mine.sessions) == 1 and held.log_path is not None and held.log_path.parent == tmp_path / "mine"
    plain = hil.run(config, out=tmp_path / "plain", clock="sim")  # no lab: nothing of the last one is left over
    assert plain.status == "completed" and len(mine.sessions) == 1
    assert len(held.log.loop) == len(plain.log.loop)  # the same session either way (sim is reproducible)


def test_a_link_without_a_file_descriptor_says_so_to_the_loop_thread() -> None:
    async def main() -> None:
        lab = SimLab(session_config().emulator.config, seed=0)
        link = SimLink("servo", lab, None)
        assert link.fd is None
        with pytest.raises(LinkError, match="servo: this link has no file descriptor for the loop thread"):
            link.pause_reading()
        link.resume_reading()  # never paused: nothing to give back

    asyncio.run(main())
