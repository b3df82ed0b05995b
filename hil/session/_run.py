"""Run one session, as `hil run` and :func:`hil.run` do: check its inputs, start the emulated lab if asked, run
the :class:`~hil.session.Session` and return a :class:`RunResult` (docs/api.md). Campaigns, tuning and fitting run
their sessions through here; the faces (hil.api, hil.cli) re-export it.

Every function here raises :class:`hil.config.ConfigError` (a ValueError with a one-line message naming the field
or option) for bad input, before anything reaches a board.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import logging
import shutil
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from firmware_stub.config import ConfigError as EmulatorConfigError
from hil.analysis import summarize_log
from hil.config import (
    ConfigError,
    PortConfig,
    SessionConfig,
    load_session,
    named,
    require_regular_file,
    require_writable_dir,
)
from hil.control.registry import ControllerConfigError, require_sim_clock
from hil.link import LinkError, PortUnavailable
from hil.log import LogError
from hil.log.frames import read_log_frames
from hil.log.schema import estimated_log_bytes
from hil.protocol import LINKS
from hil.session._lab import current_lab
from hil.session._loopback import EmulatorProcess
from hil.session._session import Session, SessionResult
from hil.session._sim import CAPTURE_REFUSED, run_sim_session

if TYPE_CHECKING:
    from hil.log.frames import LogFrames

_log = logging.getLogger("hil.session")
Clock = Literal["realtime", "lockstep", "sim"]
CLOCKS: tuple[str, ...] = ("realtime", "lockstep", "sim")
Progress = Callable[[int, int], None]  # (cycles done, cycles in the session)


@dataclasses.dataclass
class RunResult:
    """What a session ended with. ``status``: completed | fault | interrupted; ``exit_code`` as the command line's
    (0 completed, 1 fault, 130/143 a signal); ``log`` opens the log as DataFrames."""

    status: str
    exit_code: int
    message: str
    log_path: Path | None
    clock: str
    session: SessionResult = dataclasses.field(repr=False)
    emulator: dict[str, Any] = dataclasses.field(default_factory=dict, repr=False)  # the emulator's own summary
    capture: dict[str, Any] = dataclasses.field(default_factory=dict)  # path, records, bytes, dropped, error

    @functools.cached_property
    def log(self) -> LogFrames:
        """The session's log (:func:`read_log`)."""
        if self.log_path is None:
            raise ConfigError(f"this session wrote no log ({self.status}: {self.message})")
        return read_log(self.log_path)

    def summary(self, settle_s: float = 1.0) -> dict[str, Any]:
        """The metrics `hil report LOG` prints: rate error, miss distance, drive ripple, latency, link errors."""
        if self.log_path is None or not self.log_path.exists():
            return {}
        return summarize_log(self.log_path, settle_s)

    def log_loss(self) -> str:
        """What a session whose logging stopped early kept: '' when it did not stop early."""
        session = self.session
        if not session.log_error:
            return ""
        where = "no log file is left" if self.log_path is None else f"{session.log_rows} rows kept"
        return (f"logging stopped early: {session.log_error}; {where} of {session.stats.cycles} cycles run "
                "(the session ended as a fault)")

    def record(self, summary: dict[str, Any] | None = None) -> dict[str, Any]:
        """The JSON record `hil run` prints: status, exit code, message, log, clock, the capture and the log's loss if
        any, and :meth:`summary` (given, or read here) with ``incomplete`` when logging stopped early."""
        summary = dict(self.summary() if summary is None else summary)
        lost = self.log_loss()
        if lost:  # the log says only that no summary was written; the session knows why
            summary["incomplete"] = lost
        return {"status": self.status, "exit_code": self.exit_code, "message": self.message,
                "log": str(self.log_path) if self.log_path else None, "clock": self.clock,
                **({"capture": self.capture} if self.capture else {}),
                **({"log_error": self.session.log_error, "log_rows_kept": self.session.log_rows,
                    "cycles_run": self.session.stats.cycles} if self.session.log_error else {}), **summary}


def as_session_config(config: SessionConfig | str | Path) -> SessionConfig:
    """``config`` itself, or the session file at that path, loaded and checked (ConfigError)."""
    return config if isinstance(config, SessionConfig) else load_session(config)


def prepare_run(config: SessionConfig | str | Path, *, loopback: bool = True, clock: Clock | None = None,
                out: str | Path | None = None) -> tuple[SessionConfig, str, Path]:
    """Check a run's inputs without starting anything: (config, clock, log directory). ConfigError otherwise."""
    config = as_session_config(config)
    if clock is not None and clock not in CLOCKS:
        raise ConfigError(f"clock: {clock!r} is not realtime, lockstep or sim")
    out_dir = Path(out) if out is not None else config.logging.dir
    require_writable_dir(out_dir, "out" if out is not None else "logging.dir")
    require_log_room(config, out_dir, "out" if out is not None else "logging.dir")
    lab = current_lab()
    if lab is not None:  # this process serves a lab (hil serve's worker): every session runs on its ports
        _require_clock(config, lab.clock)
        return config, lab.clock, out_dir
    if not loopback:
        if clock == "sim":
            raise ConfigError("clock='sim': runs the emulated lab in this process; needs loopback=True")
        if config.ports is None:
            raise ConfigError("ports: not set in the session file; give the lab's serial ports, or pass loopback=True")
        if config.safety.emulator_stall_grace_ms:
            raise ConfigError("safety.emulator_stall_grace_ms: only for emulated boards (loopback=True); real boards "
                              "are never late, so remove it from a lab session")
        _require_clock(config, "hardware")
        return config, "hardware", out_dir
    try:  # the emulator validates it; a missing one is refused here, before anything starts
        require_regular_file(config.emulator.config)
    except ValueError as exc:
        raise ConfigError(f"emulator.config: {exc}") from None
    clock_name = clock or config.emulator.clock
    _require_clock(config, clock_name)
    return config, clock_name, out_dir


SETUP_AND_WIND_DOWN_S = 15.0  # logged beyond duration_s: connecting, arming, the hexapod's way home (<= 5 s)


def require_log_room(config: SessionConfig, out_dir: Path, what: str) -> None:
    """The session's log fits on the disk it goes to (an estimate from the log's channels and rates, with
    margin); ConfigError naming ``what`` otherwise, before anything starts."""
    need = estimated_log_bytes(config.duration_s + SETUP_AND_WIND_DOWN_S)
    probe = out_dir.absolute()
    while not probe.exists():
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if need > free:
        raise ConfigError(f"{named(what, out_dir)}: the log of this {config.duration_s:g} s session needs about "
                          f"{need / 1e6:.1f} MB and {probe} has {free / 1e6:.1f} MB free; free some space or log "
                          "elsewhere")


def _require_clock(config: SessionConfig, clock: str) -> None:
    """The controller can run on this clock (the oracle needs the sim clock's true plant state)."""
    try:
        require_sim_clock(config.controller.name, clock)
    except ControllerConfigError as exc:
        raise ConfigError(str(exc)) from None


async def run_async(config: SessionConfig | str | Path, *, loopback: bool = True, clock: Clock | None = None,
                    out: str | Path | None = None, capture: str | Path | None = None,
                    progress: Progress | None = None,
                    on_session: Callable[[Session], None] | None = None) -> RunResult:
    """Run one session and return its :class:`RunResult`; awaitable inside a running event loop (Jupyter).

    ``config``: a :class:`SessionConfig` or the path of a session YAML. ``loopback``: against the emulated lab
    (started here) rather than the lab's ports. ``clock`` (loopback): ``realtime`` (paced 1 kHz over ptys),
    ``lockstep`` (the full protocol over ptys, byte-reproducible) or ``sim`` (boards and plant in this process;
    the same log as lockstep); default the session's ``emulator.clock``. ``out``: the log directory (default
    ``logging.dir``). ``capture``: a directory for every link's raw bytes (docs/capture.md). ``on_session``: called
    with the :class:`hil.session.Session` once it exists (to end it early: ``session.interrupt()``)."""
    config, clock_name, out_dir = prepare_run(config, loopback=loopback, clock=clock, out=out)
    capture_dir = Path(capture) if capture is not None else None
    if capture_dir is not None:
        if clock_name == "sim":
            raise ConfigError(CAPTURE_REFUSED)
        require_writable_dir(capture_dir, "capture")
    hook = on_session or (lambda _s: None)
    lab = current_lab()
    if lab is not None:
        session = Session(config, lab.ports, out_dir, progress=progress, emulated=lab.emulated, claims=lab.claims,
                          log_attrs={"loopback": lab.emulated, "clock": lab.clock, **lab.extra},
                          **_capture(capture_dir))
        hook(session)
        if lab.on_session is not None:
            lab.on_session(session)
        return _result(await _run_session(session), lab.clock, {})
    if clock_name == "sim":
        try:
            result, emulator = await run_sim_session(config, out_dir, progress=progress, on_session=hook)
        except EmulatorConfigError as exc:
            raise ConfigError(str(exc)) from None
        return _result(result, "sim", emulator)
    if not loopback:
        assert config.ports is not None
        ports = {name: port for name in LINKS
                 if (port := getattr(config.ports, name)) is not None}
        session = Session(config, ports, out_dir, progress=progress,
                          log_attrs={"loopback": False, "clock": "hardware"}, **_capture(capture_dir))
        hook(session)
        return _result(await _run_session(session), "hardware", {})
    bauds = [f"--baud={name}={baud}" for name, baud in config.link_baudrates().items()]  # the ports' line rates
    emulator = EmulatorProcess(config.emulator.config, clock=clock_name, seed=config.seed,
                               extra_args=[*config.emulator.process_args(), *bauds])
    _log.info("starting the emulated lab: %s clock, seed %d, %s", clock_name, config.seed, config.emulator.config)
    try:  # stopped on every way out, a cancellation while it starts included
        try:
            started = await asyncio.to_thread(emulator.start)
        except LinkError as exc:
            raise ConfigError(str(exc)) from None
        ports = {name: PortConfig(port=path) for name, path in started.items() if name != "control"}
        # lockstep: the emulator waits for us, and we may wait for a descheduled emulator
        watchdog_ms = max(config.safety.watchdog_ms, 1000.0) if clock_name == "lockstep" else None
        session = Session(config, ports, out_dir, watchdog_ms=watchdog_ms, progress=progress,
                          log_attrs={"loopback": True, "clock": clock_name}, lockstep=clock_name == "lockstep",
                          emulated=True, **_capture(capture_dir))
        hook(session)
        result = await _run_session(session)
    finally:
        summary = await asyncio.shield(asyncio.to_thread(emulator.stop))
    return _result(result, clock_name, summary)


async def _run_session(session: Session) -> SessionResult:
    """``session.run()``; a port it cannot own (missing, not a serial port, held by another bench) is bad input."""
    try:
        return await session.run()
    except PortUnavailable as exc:
        raise ConfigError(str(exc)) from None


def _capture(capture_dir: Path | None) -> dict[str, Any]:
    return {} if capture_dir is None else {"capture_dir": capture_dir}


def _result(result: SessionResult, clock: str, emulator: dict[str, Any]) -> RunResult:
    return RunResult(status=result.status, exit_code=result.exit_code, message=result.message,
                     log_path=result.log_path, clock=clock, session=result, emulator=emulator,
                     capture=result.capture)


def _in_running_loop() -> bool:
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return False
    return True


def run_coroutine(coro_fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """Run a coroutine function to completion: here if no event loop runs in this thread, else (a notebook's
    loop) in a worker thread with its own loop, so the caller's loop is not re-entered. There an interrupt
    (KeyboardInterrupt) ends a running session as Ctrl-C does (:meth:`hil.session.Session.interrupt`)."""
    if not _in_running_loop():
        return asyncio.run(coro_fn(*args, **kwargs))
    loop = asyncio.new_event_loop()
    sessions: list[Any] = []
    if "on_session" in kwargs:
        caller_hook = kwargs["on_session"] or (lambda _s: None)
        kwargs["on_session"] = lambda s: (sessions.append(s), caller_hook(s))
    task: asyncio.Task[Any] | None = None

    def in_worker() -> Any:
        nonlocal task
        asyncio.set_event_loop(loop)
        task = loop.create_task(coro_fn(*args, **kwargs))
        try:
            return loop.run_until_complete(task)
        finally:
            loop.close()

    with ThreadPoolExecutor(1, thread_name_prefix="hil-run") as pool:
        future = pool.submit(in_worker)
        try:
            return future.result()
        except KeyboardInterrupt:  # the notebook's interrupt: end the session the safe way (disarm, log closed)
            with contextlib.suppress(RuntimeError):  # the loop may have closed meanwhile
                if sessions:
                    loop.call_soon_threadsafe(sessions[-1].interrupt)
                elif task is not None:
                    loop.call_soon_threadsafe(task.cancel)
            with contextlib.suppress(asyncio.CancelledError):
                future.result()
            raise


def run(config: SessionConfig | str | Path, *, loopback: bool = True, clock: Clock | None = None,
        out: str | Path | None = None, capture: str | Path | None = None,
        progress: Progress | None = None) -> RunResult:
    """:func:`run_async`, blocking; works in a script and inside a running event loop (a notebook cell)."""
    return run_coroutine(run_async, config, loopback=loopback, clock=clock, out=out, capture=capture, progress=progress,
                 on_session=None)


def read_log(path: str | Path) -> LogFrames:
    """A session log as pandas DataFrames: ``.loop``, ``.image``, ``.hexapod``, ... (units in ``df.attrs["units"]``),
    ``.config``, ``.events``, ``.provenance``. Works on a log still being written and on a recovered one."""
    try:
        return read_log_frames(path)
    except LogError as exc:
        raise ConfigError(str(exc)) from None
