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

from hil.analysis import summarize_log
from hil.config import (
    ConfigError,
    SessionConfig,
    load_session,
    named,
    require_writable_dir,
)
from hil.log import LogError
from hil.log.frames import read_log_frames
from hil.log.schema import estimated_log_bytes
from hil.session._lab import Lab, lab_for
from hil.session._session import Session, SessionResult

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
                out: str | Path | None = None, lab: Lab | None = None) -> tuple[SessionConfig, str, Path]:
    """Check a run's inputs without starting anything: (config, clock, log directory). ConfigError otherwise.
    ``lab``: the lab to run on (:mod:`hil.session._lab`); default the one ``loopback`` and ``clock`` ask for."""
    config, chosen, out_dir = _prepare(config, loopback=loopback, clock=clock, out=out, lab=lab, capture=None)
    return config, chosen.clock, out_dir


def _prepare(config: SessionConfig | str | Path, *, loopback: bool, clock: Clock | None, out: str | Path | None,
             lab: Lab | None, capture: Path | None) -> tuple[SessionConfig, Lab, Path]:
    config = as_session_config(config)
    if clock is not None and clock not in CLOCKS:
        raise ConfigError(f"clock: {clock!r} is not realtime, lockstep or sim")
    out_dir = Path(out) if out is not None else config.logging.dir
    require_writable_dir(out_dir, "out" if out is not None else "logging.dir")
    require_log_room(config, out_dir, "out" if out is not None else "logging.dir")
    chosen = lab if lab is not None else lab_for(config, loopback=loopback, clock=clock)
    chosen.check(config, capture=capture is not None)
    if capture is not None:
        require_writable_dir(capture, "capture")
    return config, chosen, out_dir


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


async def run_async(config: SessionConfig | str | Path, *, loopback: bool = True, clock: Clock | None = None,
                    out: str | Path | None = None, capture: str | Path | None = None,
                    progress: Progress | None = None,
                    on_session: Callable[[Session], None] | None = None, lab: Lab | None = None) -> RunResult:
    """Run one session and return its :class:`RunResult`; awaitable inside a running event loop (Jupyter).

    ``config``: a :class:`SessionConfig` or the path of a session YAML. ``loopback``: against the emulated lab
    (started here) rather than the lab's ports. ``clock`` (loopback): ``realtime`` (paced 1 kHz over ptys),
    ``lockstep`` (the full protocol over ptys, byte-reproducible) or ``sim`` (boards and plant in this process;
    the same log as lockstep); default the session's ``emulator.clock``. ``lab``: a lab to run on instead
    (:class:`hil.session.Lab`, e.g. the ports `hil serve`'s worker holds), whatever ``loopback`` and ``clock``
    say. ``out``: the log directory (default ``logging.dir``). ``capture``: a directory for every link's raw bytes
    (docs/capture.md). ``on_session``: called with the :class:`hil.session.Session` once it exists (to end it
    early: ``session.interrupt()``)."""
    capture_dir = Path(capture) if capture is not None else None
    config, chosen, out_dir = _prepare(config, loopback=loopback, clock=clock, out=out, lab=lab, capture=capture_dir)
    done = await chosen.run(config, out_dir, progress=progress, on_session=on_session or (lambda _s: None),
                            capture_dir=capture_dir)
    return RunResult(status=done.session.status, exit_code=done.session.exit_code, message=done.session.message,
                     log_path=done.session.log_path, clock=chosen.clock, session=done.session,
                     emulator=done.emulator, capture=done.session.capture)


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

        def keep_session(session: Any) -> None:
            sessions.append(session)
            caller_hook(session)

        kwargs["on_session"] = keep_session
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
        progress: Progress | None = None, lab: Lab | None = None) -> RunResult:
    """:func:`run_async`, blocking; works in a script and inside a running event loop (a notebook cell)."""
    return run_coroutine(run_async, config, loopback=loopback, clock=clock, out=out, capture=capture, progress=progress,
                         on_session=None, lab=lab)


def read_log(path: str | Path) -> LogFrames:
    """A session log as pandas DataFrames: ``.loop``, ``.image``, ``.hexapod``, ... (units in ``df.attrs["units"]``),
    ``.config``, ``.events``, ``.provenance``. Works on a log still being written and on a recovered one."""
    try:
        return read_log_frames(path)
    except LogError as exc:
        raise ConfigError(str(exc)) from None
