"""Labs: where a session's boards are and how its time runs, one backend each, passed to the run core.

As python-can's ``BusABC`` is any CAN interface and ``can.interfaces`` names them, a :class:`Lab` is any lab the
bench can run a session on, and :data:`LABS` names the ones a session file or an option can ask for:

- ``hardware`` (:class:`HardwareLab`): the lab's boards on the serial ports the session file names;
- ``emulator`` (:class:`EmulatorLab`): the emulated lab in its own process on pseudo-terminals, on the
  ``realtime`` clock (paced at 1 kHz) or the ``lockstep`` one (it waits for the bench; byte-reproducible);
- ``sim`` (:class:`InProcessLab`): the emulated lab's boards and plant in the bench's own process, messages
  passed as objects (the same log as lockstep).

:class:`BenchLab` is not in the table: it is the ports a long-running process (`hil serve`'s worker) claimed once
and holds, which that process passes to every run it makes (``lab=``). Nothing is process-global: a run without a
lab gets the one :func:`lab_for` chooses from its ``loopback`` and ``clock``.

A backend implements :meth:`Lab.check` (refuse what it cannot run, before anything starts) and :meth:`Lab.run`
(run one :class:`~hil.session.Session` on it); the run core (``hil.session.run_async``) does the rest.
"""

from __future__ import annotations

import asyncio
import logging
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from firmware_stub.config import ConfigError as EmulatorConfigError
from hil.config import ConfigError, PortConfig, SessionConfig, require_regular_file
from hil.control.registry import ControllerConfigError, require_sim_clock
from hil.link import LinkError, PortClaims, PortUnavailable
from hil.protocol import LINKS
from hil.session._loopback import EmulatorProcess
from hil.session._session import Session, SessionResult
from hil.session._sim import CAPTURE_REFUSED, run_sim_session

_log = logging.getLogger("hil.session")
SessionHook = Callable[[Session], None]
EMULATED_CLOCKS: tuple[str, ...] = ("realtime", "lockstep", "sim")  # how an emulated lab's time can run


@dataclass
class LabRun:
    """What one session on a lab ended with: the session's result and the emulator's summary (empty for boards)."""

    session: SessionResult
    emulator: dict[str, Any] = field(default_factory=dict)


class Lab(ABC):
    """A lab the bench runs sessions on. ``clock`` is the log's ``clock`` attribute: how the session's time runs
    there (``hardware`` for the lab's own boards); ``emulated``: its boards are the emulator's."""

    name: ClassVar[str]
    clock: str
    emulated: bool

    def check(self, config: SessionConfig, *, capture: bool = False) -> None:
        """Refuse (ConfigError, one line) a session this lab cannot run, before anything starts. Every lab checks
        that the controller runs on its clock (the oracle reads the sim clock's true plant state)."""
        try:
            require_sim_clock(config.controller.name, self.clock)
        except ControllerConfigError as exc:
            raise ConfigError(str(exc)) from None

    @abstractmethod
    async def run(self, config: SessionConfig, out_dir: Path, *, progress: Callable[[int, int], None] | None,
                  on_session: SessionHook, capture_dir: Path | None) -> LabRun:
        """Run one session of ``config`` on this lab, logging into ``out_dir``; ``on_session`` gets the
        :class:`Session` once it exists. :meth:`check` has passed."""


def _capture(capture_dir: Path | None) -> dict[str, Any]:
    return {} if capture_dir is None else {"capture_dir": capture_dir}


async def _run_session(session: Session) -> SessionResult:
    """``session.run()``; a port it cannot own (missing, not a serial port, held by another bench) is bad input."""
    try:
        return await session.run()
    except PortUnavailable as exc:
        raise ConfigError(str(exc)) from None


class HardwareLab(Lab):
    """The lab's boards on the serial ports of the session file's ``ports:`` (claimed for the session)."""

    name = "hardware"
    clock = "hardware"
    emulated = False

    def check(self, config: SessionConfig, *, capture: bool = False) -> None:
        if config.ports is None:
            raise ConfigError("ports: not set in the session file; give the lab's serial ports, or pass loopback=True")
        if config.safety.emulator_stall_grace_ms:
            raise ConfigError("safety.emulator_stall_grace_ms: only for emulated boards (loopback=True); real boards "
                              "are never late, so remove it from a lab session")
        super().check(config, capture=capture)

    async def run(self, config: SessionConfig, out_dir: Path, *, progress: Callable[[int, int], None] | None,
                  on_session: SessionHook, capture_dir: Path | None) -> LabRun:
        assert config.ports is not None
        ports = {name: port for name in LINKS if (port := getattr(config.ports, name)) is not None}
        session = Session(config, ports, out_dir, progress=progress,
                          log_attrs={"loopback": False, "clock": "hardware"}, **_capture(capture_dir))
        on_session(session)
        return LabRun(await _run_session(session))


def _require_emulator_file(config: SessionConfig) -> None:
    try:  # the emulator validates it; a missing one is refused here, before anything starts
        require_regular_file(config.emulator.config)
    except ValueError as exc:
        raise ConfigError(f"emulator.config: {exc}") from None


class EmulatorLab(Lab):
    """The emulated lab of the session's ``emulator:`` in its own process on pseudo-terminals, started for the
    session and stopped after it: ``realtime`` (paced at 1 kHz) or ``lockstep`` (the full protocol, waiting for
    the bench: byte-reproducible)."""

    name = "emulator"
    emulated = True

    def __init__(self, clock: str = "realtime") -> None:
        if clock not in ("realtime", "lockstep"):
            raise ConfigError(f"clock: {clock!r}: the emulator process runs realtime or lockstep")
        self.clock = clock

    def check(self, config: SessionConfig, *, capture: bool = False) -> None:
        _require_emulator_file(config)
        super().check(config, capture=capture)

    async def run(self, config: SessionConfig, out_dir: Path, *, progress: Callable[[int, int], None] | None,
                  on_session: SessionHook, capture_dir: Path | None) -> LabRun:
        bauds = [f"--baud={name}={baud}" for name, baud in config.link_baudrates().items()]  # the ports' line rates
        emulator = EmulatorProcess(config.emulator.config, clock=self.clock, seed=config.seed,
                                   extra_args=[*config.emulator.process_args(), *bauds])
        _log.info("starting the emulated lab: %s clock, seed %d, %s", self.clock, config.seed, config.emulator.config)
        try:  # stopped on every way out, a cancellation while it starts included
            try:
                started = await asyncio.to_thread(emulator.start)
            except LinkError as exc:
                raise ConfigError(str(exc)) from None
            ports = {name: PortConfig(port=path) for name, path in started.items() if name != "control"}
            lockstep = self.clock == "lockstep"
            # lockstep: the emulator waits for us, and we may wait for a descheduled emulator
            watchdog_ms = max(config.safety.watchdog_ms, 1000.0) if lockstep else None
            session = Session(config, ports, out_dir, watchdog_ms=watchdog_ms, progress=progress,
                              log_attrs={"loopback": True, "clock": self.clock}, lockstep=lockstep,
                              emulated=True, **_capture(capture_dir))
            on_session(session)
            result = await _run_session(session)
        finally:
            summary = await asyncio.shield(asyncio.to_thread(emulator.stop))
        return LabRun(result, summary)


class InProcessLab(Lab):
    """The emulated lab's boards and plant in this process (the ``sim`` clock): messages passed as objects, no
    ptys, the same log as lockstep. Its links carry no bytes, so there is nothing to capture."""

    name = "sim"
    clock = "sim"
    emulated = True

    def check(self, config: SessionConfig, *, capture: bool = False) -> None:
        _require_emulator_file(config)
        super().check(config, capture=capture)
        if capture:
            raise ConfigError(CAPTURE_REFUSED)

    async def run(self, config: SessionConfig, out_dir: Path, *, progress: Callable[[int, int], None] | None,
                  on_session: SessionHook, capture_dir: Path | None) -> LabRun:
        try:
            result, emulator = await run_sim_session(config, out_dir, progress=progress, on_session=on_session)
        except EmulatorConfigError as exc:
            raise ConfigError(str(exc)) from None
        return LabRun(result, emulator)


LABS: dict[str, Callable[..., Lab]] = {  # the labs a session can ask for by name
    HardwareLab.name: HardwareLab,
    EmulatorLab.name: EmulatorLab,
    InProcessLab.name: InProcessLab,
}


def lab_for(config: SessionConfig, *, loopback: bool = True, clock: str | None = None) -> Lab:
    """The lab a run asks for with ``loopback`` and ``clock``:
    the hardware without loopback, else the emulated lab on ``clock`` (default the session's ``emulator.clock``),
    in this process for ``sim``. ConfigError for a clock no lab has."""
    if clock is not None and clock not in EMULATED_CLOCKS:
        raise ConfigError(f"clock: {clock!r} is not realtime, lockstep or sim")
    if not loopback:
        if clock == "sim":
            raise ConfigError("clock='sim': runs the emulated lab in this process; needs loopback=True")
        return LABS["hardware"]()
    clock_name = clock or config.emulator.clock
    return LABS["sim"]() if clock_name == "sim" else LABS["emulator"](clock_name)


@dataclass
class BenchLab(Lab):
    """Ports held for longer than a session (`hil serve`'s worker claims them once; docs/service.md, "Ports owned,
    once"): link name -> port, the claims that hold them, and whether they are the emulated lab's (its sessions
    are logged ``loopback`` on the realtime clock, with the emulator's grace). A session on it claims nothing and
    lets go of nothing, whatever its file's ``ports:`` or ``loopback`` say."""

    ports: dict[str, PortConfig]
    claims: PortClaims
    emulated: bool
    description: str = ""
    extra: dict[str, Any] = field(default_factory=dict)  # log attributes of its sessions (a "provenance" adds)
    on_session: SessionHook | None = None  # called with each Session once it exists, on its event loop

    name = "held"

    def __post_init__(self) -> None:
        self.clock = "realtime" if self.emulated else "hardware"

    async def run(self, config: SessionConfig, out_dir: Path, *, progress: Callable[[int, int], None] | None,
                  on_session: SessionHook, capture_dir: Path | None) -> LabRun:
        session = Session(config, self.ports, out_dir, progress=progress, emulated=self.emulated, claims=self.claims,
                          log_attrs={"loopback": self.emulated, "clock": self.clock, **self.extra},
                          **_capture(capture_dir))
        on_session(session)
        if self.on_session is not None:
            self.on_session(session)
        return LabRun(await _run_session(session))
