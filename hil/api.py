"""The bench as a library: what the `hil` command line does, for notebooks and scripts (docs/api.md).

Every function here raises :class:`hil.config.ConfigError` (a ValueError with a one-line message naming the field
or option) for bad input, before anything reaches a board; the command line prints that line and exits 2.

    import hil
    result = hil.run("profiles/sessions/demo.yaml", clock="sim")     # or: await hil.run_async(...)
    log = result.log                                                  # hil.read_log(result.log_path)
    log.loop.plot(x="t_s", y=["rate_err_el_dps", "rate_err_az_dps"])
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from hil.analysis import IDENT_SWEEP, summarize_log
from hil.config import (
    ConfigError,
    SessionConfig,
    load_session,
    require_regular_file,
    require_writable_dir,
)
from hil.control.registry import ControllerConfigError, require_sim_clock
from hil.ident import IdentRun, run_ident
from hil.link import Finding
from hil.log import LogError
from hil.log.reader import NotASessionLog
from hil.session import (
    CLOCKS,
    LABS,
    BenchLab,
    Clock,
    Lab,
    Progress,
    RunResult,
    check_hardware,
    emulator_for_plant,
    prepare_run,
    read_log,
    run,
    run_async,
)

if TYPE_CHECKING:
    from hil.campaign import CampaignConfig, CampaignResult, CellResult
    from hil.campaign.engines import Engine
    from hil.reporting import ReportFiles

__all__ = [
    "CLOCKS",
    "LABS",
    "BenchLab",
    "CampaignRun",
    "Clock",
    "IdentRun",
    "Lab",
    "Progress",
    "RunResult",
    "check_file",
    "doctor",
    "ident",
    "load_session",
    "prepare_campaign",
    "prepare_run",
    "read_log",
    "replay_capture",
    "replay_log",
    "report",
    "run",
    "run_async",
    "run_campaign",
    "tune",
]


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
        import pandas as pd  # noqa: PLC0415  (heavy: loaded only for DataFrames)

        rows = [{"cell": c.cell_id, "profile": c.profile, "controller": c.controller, "seed": c.seed,
                 "status": c.status, "passed": c.passed, **c.metrics} for c in self.result.cells]
        return pd.DataFrame(rows)


def load_campaign(path: str | Path) -> CampaignConfig:
    """A campaign YAML (profiles x controllers x seeds, metrics, thresholds, acceptance rules)."""
    from hil.campaign import CampaignError  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)
    from hil.campaign import load_campaign as load  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

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
    from hil.campaign import CampaignError  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)
    from hil.campaign.engines import EngineError, check_options  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)
    from hil.campaign.runner import cell_sessions  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    source = str(campaign) if not hasattr(campaign, "cells") else "campaign"
    config: CampaignConfig = campaign if hasattr(campaign, "cells") else load_campaign(campaign)  # type: ignore[assignment]
    out_dir = Path(out) if out is not None else Path("runs") / "campaigns" / config.name
    require_writable_dir(out_dir, "out")
    if plant is not None:
        config = _on_plant(config, Path(plant), out_dir)
    if clock not in ("sim", "lockstep"):
        raise ConfigError(f"clock={clock!r}: not sim or lockstep")
    try:
        check_options(engine, hardware=hardware, scheduler=scheduler, workers=workers, shared_dir=shared_dir)
    except EngineError as exc:
        raise ConfigError(str(exc)) from None

    if (clock != "sim" or hardware) and (use := config.sim_only_metric()) is not None:
        raise ConfigError(f"{source}: {use} is read from the plant's truth, which only the sim clock records "
                          f"(not {'hardware' if hardware else clock}); run with clock='sim'")
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
    from firmware_stub.plant import PlantConfigError, load_plant_config  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    try:
        load_plant_config(plant)
    except PlantConfigError as exc:
        raise ConfigError(f"plant={str(plant)!r}: {exc}") from None
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
    a ConfigError naming the scheduler, raised before anything is written. ``plant``: every cell on this plant
    file (a fitted twin) instead of the one its session's emulator names.
    Blocking; inside a running event loop it runs the cells in worker threads, which is what it does anyway.
    A KeyboardInterrupt stops the cells running (each session the safe way) and raises
    :class:`hil.campaign.runner.CampaignInterrupted` (a KeyboardInterrupt) naming the cells done and cut short;
    the finished cells stay in ``out``, and ``resume=True`` runs the rest. No report is written then."""
    from hil.campaign import CampaignError  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)
    from hil.campaign import run_campaign as run_cells  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

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
        from hil.campaign.report import write_report as write  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

        try:
            files = write(out_dir)
        except CampaignError as exc:
            raise ConfigError(str(exc)) from None
    return CampaignRun(result=result, out_dir=out_dir, report=files)


def report(path: str | Path, *, settle_s: float = 1.0) -> Any:
    """A session log's metrics (a dict, as `hil report LOG` prints it), or for a campaign directory its report written
    again (Markdown, HTML and plots) with the campaign's results: a :class:`CampaignRun`."""
    path = Path(path)
    if path.is_dir():
        from hil.campaign import CampaignError, load_results  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)
        from hil.campaign.report import write_report  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

        try:
            return CampaignRun(result=load_results(path), out_dir=path, report=write_report(path))
        except CampaignError as exc:
            raise ConfigError(str(exc)) from None

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


def ident(session: SessionConfig | str | Path, *, axis: Literal["el", "az"] = "el", loopback: bool = True,
          clock: Clock | None = None, out: str | Path = "runs/ident", f_start_hz: float = IDENT_SWEEP.f_start_hz,
          f_stop_hz: float = IDENT_SWEEP.f_stop_hz, sweep_s: float = IDENT_SWEEP.duration_s,
          amplitude_dps: float = IDENT_SWEEP.amplitude_dps, offset_dps: float = IDENT_SWEEP.offset_dps,
          level: bool = True, progress: Progress | None = None,
          on_pass: Callable[[int, Any], None] | None = None, lab: Lab | None = None) -> IdentRun:
    """Frequency-sweep identification (seed 000 Figs. 8-9, docs/ident.md): a swept sine on one axis's rate command
    of the closed rate loop (``session``'s controller, tracking off, no swing), the plant's frequency response from
    the log, a Bode plot and the fit of k_m, the gyro's bandwidth and the delay.

    With ``level`` (the default) the sweep levels itself (docs/ident.md "Levelling"): ``amplitude_dps`` and
    ``offset_dps`` are where it starts; up to three more sweeps raise the amplitude where the coherence fails and
    the drive has headroom, lower it where the drive saturates, raise the offset while the axis reverses (at most
    60 deg of travel), each pass turning the axis back. The fit is made on the widest coherent band only, and
    ``band_hz`` reports it. ``on_pass(i, sweep)`` announces each pass. ``lab``: the lab to run on
    (:class:`hil.session.Lab`), whatever ``loopback`` and ``clock`` say. ValueError (ConfigError) for bad input; a
    fit that cannot be made raises ValueError naming the log."""
    return run_ident(session, axis=axis, loopback=loopback, clock=clock, out=out, f_start_hz=f_start_hz,
                     f_stop_hz=f_stop_hz, sweep_s=sweep_s, amplitude_dps=amplitude_dps, offset_dps=offset_dps,
                     level=level, progress=progress, on_pass=on_pass, lab=lab)


def replay_log(log: str | Path, controller: str | None = None, params: Any = None, *, settle_s: float = 1.0) -> Any:
    """Re-run a controller open loop on a logged gyro and drive stream (`hil replay LOG`, docs/capture.md):
    its estimates, would-be drive, noise and lag beside the logged controller's. ``params``: a dict, a
    ``"k=v,..."`` string or a controller YAML path. Returns a ``hil.replay.ReplayResult``."""
    from hil import replay  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    try:
        return replay.replay_log(Path(log), controller, params, settle_s=settle_s)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def replay_capture(capture: str | Path, **options: Any) -> Any:
    """Play a capture's host-side frames back at the boards or a fresh emulator with the original timing
    (`hil replay CAPTURE`, docs/capture.md); ``options`` as ``hil.replay.replay_capture``.
    Returns a ``hil.replay.PlaybackResult``."""
    from hil import replay  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    try:
        return replay.replay_capture(Path(capture), **options)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def tune(campaign: Any, params: Any, **options: Any) -> Any:
    """Controller gains by search (`hil tune`, docs/tuning.md): an Optuna study whose trials are the campaign's
    cells for one controller with the trial's parameters; the study lives in an RDB (SQLite by default). Returns a
    ``hil.tune.TuneResult``; ``options`` as ``hil.tune.tune``."""
    from hil import tune as tuning  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return tuning.tune(campaign, params, **options)


def check_file(path: str | Path, kind: str | None = None) -> dict[str, Any]:
    """Validate one config file without running anything: {"file", "kind", "summary"}; ConfigError otherwise.
    The kind (session, campaign, controller, swing, hexapod, emulator, plant, targets) comes from ``kind``, else
    from the folder it is in (``profiles/KIND/``), else from its keys."""
    from hil.checks import check_config_file  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return check_config_file(Path(path), kind)


def doctor(session: SessionConfig | str | Path | None = None, *, sysfs: str | Path = "/sys", boards: bool = True,
           listen_s: float = 2.0) -> list[Finding]:
    """Is the hardware ready (`hil doctor`, docs/service.md)? Every check of every port: ``session``'s ports, or
    with none every serial adapter in /dev/serial/by-id/ at the default line rate (hil.protocol.LINE_RATE_BAUD).
    ConfigError for a session without ports. With a session, also what the wire adds to every cycle at its rates
    (hil.link.wire_delay: a warning over ``ports.wire_delay_budget_us``).

    With a session and ``boards`` (the default), the boards are asked too (hil.boards.check_boards), on each port
    whose own checks passed: an ``ident`` finding per link the session opens (the board's IDENT and its catalogue
    fingerprint against this bench's), and a ``servo stream`` finding: the stream started, listened to ``listen_s``
    and stopped, its rate and jitter against 1 kHz and the session's ``safety.watchdog_ms``. The motor driver is
    never enabled and the hexapod never moved. ``boards=False`` checks the ports alone, without a byte sent."""
    return check_hardware(session, sysfs=sysfs, boards=boards, listen_s=listen_s)
