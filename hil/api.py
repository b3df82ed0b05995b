"""The bench as a library: what the `hil` command line does, for notebooks and scripts (docs/api.md).

Every function here raises :class:`hil.config.ConfigError` (a ValueError with a one-line message naming the field
or option) for bad input, before anything reaches a board; the command line prints that line and exits 2.

    import hil
    result = hil.run("profiles/sessions/demo.yaml", clock="sim")     # or: await hil.run_async(...)
    log = result.log                                                  # hil.read_log(result.log_path)
    log.loop.plot(x="t_s", y=["rate_err_el_dps", "rate_err_az_dps"])
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

from hil.config import ConfigError, SessionConfig, load_session, require_regular_file, require_writable_dir
from hil.log.schema import estimated_log_bytes
from hil.ports import PortUnavailable

if TYPE_CHECKING:
    from hil.campaign import CampaignConfig, CampaignResult, CellResult
    from hil.campaign.engines import Engine
    from hil.campaign.report import ReportFiles
    from hil.log.frames import LogFrames
    from hil.session import Session, SessionResult

_log = logging.getLogger("hil.api")
Clock = Literal["realtime", "lockstep", "sim"]
CLOCKS: tuple[str, ...] = ("realtime", "lockstep", "sim")
Progress = Callable[[int, int], None]  # (cycles done, cycles in the session)

__all__ = ["CampaignRun", "IdentRun", "RunResult", "check_file", "ident", "load_session", "read_log", "replay_capture",
           "replay_log", "report", "run", "run_async", "run_campaign", "tune"]


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
        from hil.summary import summarize_log

        if self.log_path is None or not self.log_path.exists():
            return {}
        return summarize_log(self.log_path, settle_s)


def _session_config(config: SessionConfig | str | Path) -> SessionConfig:
    return config if isinstance(config, SessionConfig) else load_session(config)


def prepare_run(config: SessionConfig | str | Path, *, loopback: bool = True, clock: Clock | None = None,
                out: str | Path | None = None) -> tuple[SessionConfig, str, Path]:
    """Check a run's inputs without starting anything: (config, clock, log directory). ConfigError otherwise."""
    config = _session_config(config)
    if clock is not None and clock not in CLOCKS:
        raise ConfigError(f"clock: {clock!r} is not realtime, lockstep or sim")
    out_dir = Path(out) if out is not None else config.logging.dir
    require_writable_dir(out_dir, "--out" if out is not None else "logging.dir")
    _require_log_room(config, out_dir, "--out" if out is not None else "logging.dir")
    if not loopback:
        if clock == "sim":
            raise ConfigError("--clock sim: runs the emulated lab in this process; add --loopback")
        if config.ports is None:
            raise ConfigError("ports: not set in the session file; give the lab's serial ports, or pass --loopback")
        if config.safety.emulator_stall_grace_ms:
            raise ConfigError("safety.emulator_stall_grace_ms: only for emulated boards (--loopback); real boards "
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


def _require_log_room(config: SessionConfig, out_dir: Path, what: str) -> None:
    """The session's log fits on the disk it goes to (an estimate from the log's channels and rates, with
    margin); ConfigError naming ``what`` otherwise, before anything starts."""
    need = estimated_log_bytes(config.duration_s + SETUP_AND_WIND_DOWN_S)
    probe = out_dir.absolute()
    while not probe.exists():
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if need > free:
        raise ConfigError(f"{what} {out_dir}: the log of this {config.duration_s:g} s session needs about "
                          f"{need / 1e6:.1f} MB and {probe} has {free / 1e6:.1f} MB free; free some space or log "
                          "elsewhere")


def _require_clock(config: SessionConfig, clock: str) -> None:
    """The controller can run on this clock (the oracle needs the sim clock's true plant state)."""
    from hil.control.registry import ControllerConfigError, require_sim_clock

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
    from hil.config import PortConfig
    from hil.session import Session

    config, clock_name, out_dir = prepare_run(config, loopback=loopback, clock=clock, out=out)
    capture_dir = Path(capture) if capture is not None else None
    if capture_dir is not None:
        if clock_name == "sim":
            raise ConfigError("--capture: the sim clock's links pass messages, not bytes: nothing to capture; run on "
                              "the lockstep clock for the same run over ptys")
        require_writable_dir(capture_dir, "--capture")
    hook = on_session or (lambda _s: None)
    if clock_name == "sim":
        from firmware_stub.config import ConfigError as EmulatorConfigError
        from hil.session import run_sim_session

        try:
            result, emulator = await run_sim_session(config, out_dir, progress=progress, on_session=hook)
        except EmulatorConfigError as exc:
            raise ConfigError(str(exc)) from None
        return _result(result, "sim", emulator)
    if not loopback:
        assert config.ports is not None
        ports = {name: port for name in ("servo", "driver", "image", "hexapod")
                 if (port := getattr(config.ports, name)) is not None}
        session = Session(config, ports, out_dir, progress=progress,
                          log_attrs={"loopback": False, "clock": "hardware"}, **_capture(capture_dir))
        hook(session)
        return _result(await _run_session(session), "hardware", {})
    from hil.session import EmulatorProcess
    from hil.transport import LinkError

    emulator = EmulatorProcess(config.emulator.config, clock=clock_name, seed=config.seed,
                               extra_args=config.emulator.process_args())
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


def _sync(coro_fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
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
    return _sync(run_async, config, loopback=loopback, clock=clock, out=out, capture=capture, progress=progress,
                 on_session=None)


def read_log(path: str | Path) -> LogFrames:
    """A session log as pandas DataFrames: ``.loop``, ``.image``, ``.hexapod``, ... (units in ``df.attrs["units"]``),
    ``.config``, ``.events``, ``.provenance``. Works on a log still being written and on a recovered one."""
    from hil.log import LogError
    from hil.log.frames import read_log_frames

    try:
        return read_log_frames(path)
    except LogError as exc:
        raise ConfigError(str(exc)) from None


@dataclasses.dataclass
class CampaignRun:
    """A campaign's outcome: ``result`` (every cell, the acceptance rules), ``out_dir``, ``report`` (the Markdown
    and HTML files, when written). ``table()`` gives one row per cell and metric as a DataFrame."""

    result: CampaignResult
    out_dir: Path
    report: ReportFiles | None = None

    @property
    def passed(self) -> bool:
        return self.result.passed

    def table(self) -> Any:
        """Every cell's metrics, one row per cell: profile, controller, seed, status, then a column per metric."""
        import pandas as pd

        rows = [{"cell": c.cell_id, "profile": c.profile, "controller": c.controller, "seed": c.seed,
                 "status": c.status, "passed": c.passed, **c.metrics} for c in self.result.cells]
        return pd.DataFrame(rows)


def load_campaign(path: str | Path) -> CampaignConfig:
    """A campaign YAML (profiles x controllers x seeds, metrics, thresholds, acceptance rules)."""
    from hil.campaign import CampaignError
    from hil.campaign import load_campaign as load

    try:
        return load(path)
    except CampaignError as exc:
        raise ConfigError(str(exc)) from None


def prepare_campaign(campaign: CampaignConfig | str | Path, *, out: str | Path | None = None,
                     hardware: bool = False, clock: Literal["sim", "lockstep"] = "sim",
                     engine: Literal["local", "dask"] | Engine = "local", scheduler: str | None = None,
                     workers: int | None = None, shared_dir: str | Path | None = None,
                     plant: str | Path | None = None,
                     ) -> tuple[CampaignConfig, Path, dict[str, dict[str, Any]]]:
    """Check a campaign without running it: (config, its directory, every cell's session). ConfigError otherwise.
    The engine options are checked as given (the scheduler is not contacted here: :func:`run_campaign` does).
    ``plant``: run every cell on this plant file (a fitted twin, docs/fit.md) instead of the sessions' own."""
    from hil.campaign import CampaignError
    from hil.campaign.engines import EngineError, check_options
    from hil.campaign.runner import cell_sessions

    source = str(campaign) if not hasattr(campaign, "cells") else "campaign"
    config: CampaignConfig = campaign if hasattr(campaign, "cells") else load_campaign(campaign)  # type: ignore[assignment]
    out_dir = Path(out) if out is not None else Path("runs") / "campaigns" / config.name
    require_writable_dir(out_dir, "--out")
    if plant is not None:
        config = _on_plant(config, Path(plant), out_dir)
    if clock not in ("sim", "lockstep"):
        raise ConfigError(f"--clock: {clock!r} is not sim or lockstep")
    try:
        check_options(engine, hardware=hardware, scheduler=scheduler, workers=workers, shared_dir=shared_dir)
    except EngineError as exc:
        raise ConfigError(str(exc)) from None
    from hil.control.registry import ControllerConfigError, require_sim_clock

    if (clock != "sim" or hardware) and (use := config.sim_only_metric()) is not None:
        raise ConfigError(f"{source}: {use} is read from the plant's truth, which only the sim clock records "
                          f"(not {'hardware' if hardware else clock}); run with --clock sim")
    for entry in config.controllers:  # the oracle needs the sim clock's true plant state
        try:
            require_sim_clock(entry.name, "hardware" if hardware else clock)
        except ControllerConfigError as exc:
            raise ConfigError(f"{source}: controllers[{entry.label}]: {exc}") from None
    try:  # every cell, before anything is written
        sessions = cell_sessions(config, out_dir, hardware, clock)
    except CampaignError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    return config, out_dir, sessions


def _on_plant(config: CampaignConfig, plant: Path, out_dir: Path) -> CampaignConfig:
    """The campaign with every cell's emulator on ``plant`` (an emulator file written into ``out_dir``)."""
    from firmware_stub.plant import PlantConfigError, load_plant_config
    from hil.fit.record import emulator_for_plant

    try:
        load_plant_config(plant)
    except PlantConfigError as exc:
        raise ConfigError(f"--plant: {exc}") from None
    emulator = emulator_for_plant(plant, out_dir)
    overrides = {**config.overrides, "emulator": {**(config.overrides.get("emulator") or {}),
                                                  "config": str(emulator.resolve())}}
    return config.model_copy(update={"overrides": overrides})


def run_campaign(campaign: CampaignConfig | str | Path, *, out: str | Path | None = None, jobs: int = 1,
                 resume: bool = False, hardware: bool = False, clock: Literal["sim", "lockstep"] = "sim",
                 write_report: bool = True, on_cell: Callable[[CellResult], None] | None = None,
                 engine: Literal["local", "dask"] | Engine = "local", scheduler: str | None = None,
                 workers: int | None = None, shared_dir: str | Path | None = None,
                 plant: str | Path | None = None) -> CampaignRun:
    """Run (or with ``resume`` finish) a swing campaign: every cell a session with its own log, then the
    acceptance verdict and (``write_report``) the report. ``out`` defaults to ``runs/campaigns/NAME``.
    Cells run ``jobs`` at a time on the ``sim`` clock (or ``lockstep``), or on the lab's ports (``hardware``).

    ``engine="dask"`` runs the cells on a dask.distributed cluster: ``scheduler`` (``"tcp://HOST:8786"``) an
    existing one's, else a LocalCluster of ``workers`` (default ``jobs``) processes started here and closed at the
    end; with a scheduler, ``workers`` waits for that many workers. The cells' files come back to ``out`` as bytes,
    or through ``shared_dir``, a directory every worker sees at the same path. An open
    :class:`hil.campaign.engines.Engine` may be given instead (its owner closes it). An unreachable scheduler is
    a ConfigError naming ``--scheduler``, raised before anything is written. ``plant``: every cell on this plant
    file (a fitted twin) instead of the one its session's emulator names.
    Blocking; inside a running event loop it runs the cells in worker threads, which is what it does anyway.
    A KeyboardInterrupt stops the cells running (each session the safe way) and raises
    :class:`hil.campaign.runner.CampaignInterrupted` (a KeyboardInterrupt) naming the cells done and cut short;
    the finished cells stay in ``out``, and ``resume=True`` runs the rest. No report is written then."""
    from hil.campaign import CampaignError
    from hil.campaign import run_campaign as run_cells

    config, out_dir, sessions = prepare_campaign(campaign, out=out, hardware=hardware, clock=clock, engine=engine,
                                                 scheduler=scheduler, workers=workers, shared_dir=shared_dir,
                                                 plant=plant)
    try:
        result = run_cells(config, out_dir, jobs=jobs, resume=resume, hardware=hardware, on_cell=on_cell,
                           sessions=sessions, engine=engine, scheduler=scheduler, workers=workers,
                           shared_dir=shared_dir)
    except CampaignError as exc:
        raise ConfigError(str(exc)) from None
    files = None
    if write_report:
        from hil.campaign.report import write_report as write

        try:
            files = write(out_dir)
        except CampaignError as exc:
            raise ConfigError(str(exc)) from None
    return CampaignRun(result=result, out_dir=out_dir, report=files)


def report(path: str | Path, *, settle_s: float = 1.0) -> Any:
    """A session log's metrics (a dict, as `hil report LOG --json`), or for a campaign directory its report written
    again (Markdown, HTML and plots) with the campaign's results: a :class:`CampaignRun`."""
    path = Path(path)
    if path.is_dir():
        from hil.campaign import CampaignError, load_results
        from hil.campaign.report import write_report

        try:
            return CampaignRun(result=load_results(path), out_dir=path, report=write_report(path))
        except CampaignError as exc:
            raise ConfigError(str(exc)) from None
    from hil.log import LogError
    from hil.log.reader import NotASessionLog
    from hil.summary import summarize_log

    try:
        require_regular_file(path)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    try:
        return summarize_log(path, settle_s)
    except NotASessionLog as exc:
        raise ConfigError(str(exc)) from None
    except (LogError, OSError, KeyError) as exc:
        raise ConfigError(f"{path}: not a readable session log ({exc}); if the session crashed: "
                          f"hil recover {path}") from None


MAX_EL_TRAVEL_DEG = 60.0  # ident: keep the elevation axis away from the az-el gimbal's 90 deg singularity


@dataclasses.dataclass
class IdentRun:
    """A swept-sine identification: the session that ran it (``run``), the measured frequency response (``frf``),
    the plant fit (``fit``: k_m, gyro bandwidth, delay), the Bode plot and the JSON written beside the log.
    ``fit`` is None when the session did not complete."""

    run: RunResult
    frf: Any = None
    fit: Any = None
    bode_png: Path | None = None
    json_path: Path | None = None
    report: dict[str, Any] = dataclasses.field(default_factory=dict)


def ident(session: SessionConfig | str | Path, *, axis: Literal["el", "az"] = "el", loopback: bool = True,
          clock: Clock | None = None, out: str | Path = "runs/ident", f_start_hz: float = 0.5,
          f_stop_hz: float = 300.0, sweep_s: float = 20.0, amplitude_dps: float = 2.0, offset_dps: float = 2.5,
          progress: Progress | None = None) -> IdentRun:
    """Frequency-sweep identification (seed 000 Figs. 8-9, docs/ident.md): a swept sine on one axis's rate command
    of the closed rate loop (``session``'s controller, tracking off, no swing), the plant's frequency response from
    the log, a Bode plot and the fit of k_m, the gyro's bandwidth and the delay. ValueError (ConfigError) for bad
    input; a fit that cannot be made raises ValueError naming the log."""
    import json
    import math

    from pydantic import ValidationError

    from hil.config import one_line
    from hil.control.registry import K_M_DEFAULT
    from hil.ident import SweptSine, bode_plot, identify_log
    from hil.log import read_log as read_arrays

    if axis not in ("el", "az"):
        raise ConfigError(f"--axis: {axis!r} is not el or az")
    for option, value in (("--f-start-hz", f_start_hz), ("--f-stop-hz", f_stop_hz), ("--sweep-s", sweep_s),
                          ("--amplitude-dps", amplitude_dps), ("--offset-dps", offset_dps)):
        if not math.isfinite(value):
            raise ConfigError(f"{option}: {value!r} is not a finite number")
    out_dir = require_writable_dir(Path(out), "--out")
    base = _session_config(session)
    try:
        sweep = SweptSine(f_start_hz=f_start_hz, f_stop_hz=f_stop_hz, duration_s=sweep_s,
                          amplitude_dps=amplitude_dps, axis=axis, offset_dps=offset_dps)
        data = base.model_dump(mode="json", exclude_none=True)
        data.update(name=f"{base.name}-ident-{axis}", duration_s=sweep.total_s + 0.5, excitation=sweep.model_dump(),
                    tracking={**data.get("tracking", {}), "enabled": False}, profile={"segments": []},
                    mqtt=base.mqtt, hexapod=base.hexapod)  # the objects themselves: their dumps hide secrets
        config = SessionConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(one_line("ident", exc)) from None
    travel_deg = abs(offset_dps) * sweep.total_s
    if axis == "el" and travel_deg > MAX_EL_TRAVEL_DEG:
        raise ConfigError(f"--offset-dps: the elevation axis would turn {travel_deg:.0f} deg during the sweep (at "
                          f"most {MAX_EL_TRAVEL_DEG:g}: near 90 deg the cross-elevation gyro loses the azimuth axis); "
                          "lower --offset-dps or --sweep-s, or identify --axis az")
    result = run(config, loopback=loopback, clock=clock, out=out_dir, progress=progress)
    if result.status != "completed" or result.log_path is None:
        return IdentRun(run=result)
    try:
        frf, fit = identify_log(read_arrays(result.log_path), sweep)
    except ValueError as exc:
        raise ValueError(f"{result.log_path}: cannot identify: {exc}") from None
    png = bode_plot(frf, fit, out_dir / f"bode-{axis}.png", title=config.name)
    error_pct = 100.0 * (fit.k_m_dps2_per_count - K_M_DEFAULT) / K_M_DEFAULT
    js = out_dir / f"ident-{axis}.json"
    data = {"log": str(result.log_path), "axis": axis, "sweep": sweep.model_dump(),
            "k_m_dps2_per_count": fit.k_m_dps2_per_count, "k_m_vs_default_pct": error_pct,
            "gyro_bandwidth_hz": fit.gyro_bandwidth_hz, "delay_ms": fit.delay_ms, "rms_error_db": fit.rms_error_db,
            "f_range_hz": list(fit.f_range_hz), "bins": fit.n_bins, "bode_png": str(png)}
    js.write_text(json.dumps(data, indent=2))
    return IdentRun(run=result, frf=frf, fit=fit, bode_png=png, json_path=js, report=data)


def replay_log(log: str | Path, controller: str | None = None, params: Any = None, *, settle_s: float = 1.0) -> Any:
    """Re-run a controller open loop on a logged gyro and drive stream (`hil replay LOG`, docs/capture.md):
    its estimates, would-be drive, noise and lag beside the logged controller's. ``params``: a dict, a
    ``"k=v,..."`` string or a controller YAML path. Returns a ``hil.replay.ReplayResult``."""
    from hil import replay

    try:
        return replay.replay_log(Path(log), controller, params, settle_s=settle_s)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def replay_capture(capture: str | Path, **options: Any) -> Any:
    """Play a capture's host-side frames back at the boards or a fresh emulator with the original timing
    (`hil replay CAPTURE --to-emulator`, docs/capture.md); ``options`` as ``hil.replay.replay_capture``.
    Returns a ``hil.replay.PlaybackResult``."""
    from hil import replay

    try:
        return replay.replay_capture(Path(capture), **options)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def tune(campaign: Any, params: Any, **options: Any) -> Any:
    """Controller gains by search (`hil tune`, docs/tuning.md): an Optuna study whose trials are the campaign's
    cells for one controller with the trial's parameters; the study lives in an RDB (SQLite by default). Returns a
    ``hil.tune.TuneResult``; ``options`` as ``hil.tune.tune``."""
    from hil import tune as tuning

    return tuning.tune(campaign, params, **options)


def check_file(path: str | Path, kind: str | None = None) -> dict[str, Any]:
    """Validate one config file without running anything: {"file", "kind", "summary"}; ConfigError otherwise.
    The kind (session, campaign, controller, swing, hexapod, emulator, plant, targets) comes from ``kind``, else
    from the folder it is in (``profiles/KIND/``), else from its keys."""
    from hil.checks import check_config_file

    return check_config_file(Path(path), kind)
