"""A campaign as the faces run it (`hil campaign`, :func:`hil.run_campaign`): checked whole before anything is
written, its cells run, its report written; bad input is a :class:`hil.config.ConfigError` naming the parameter or
the campaign file's field."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from hil.campaign.engines import Engine, EngineError, check_options
from hil.campaign.model import CampaignConfig, CampaignResult, CellResult
from hil.campaign.report import write_report as write_campaign_report
from hil.campaign.runner import CampaignError, cell_sessions, load_results
from hil.campaign.runner import load_campaign as load
from hil.campaign.runner import run_campaign as run_cells
from hil.config import ConfigError, require_writable_dir
from hil.control.registry import ControllerConfigError, require_sim_clock
from hil.session import emulator_for_plant

if TYPE_CHECKING:
    from hil.reporting import ReportFiles


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


def load_campaign_file(path: str | Path) -> CampaignConfig:
    """A campaign YAML (profiles x controllers x seeds, metrics, thresholds, acceptance rules); ConfigError."""
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
    The engine options are checked as given (the scheduler is not contacted here: :func:`run_and_report` does).
    ``plant``: run every cell on this plant file (a fitted twin, docs/fit.md) instead of the sessions' own."""
    source = "campaign" if isinstance(campaign, CampaignConfig) else str(campaign)
    config = campaign if isinstance(campaign, CampaignConfig) else load_campaign_file(campaign)
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
    emulator = emulator_for_plant(plant, out_dir)
    overrides = {**config.overrides, "emulator": {**(config.overrides.get("emulator") or {}),
                                                  "config": str(emulator.resolve())}}
    return config.model_copy(update={"overrides": overrides})


def run_and_report(campaign: CampaignConfig | str | Path, *, out: str | Path | None = None, jobs: int = 1,
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
        try:
            files = write_campaign_report(out_dir)
        except CampaignError as exc:
            raise ConfigError(str(exc)) from None
    return CampaignRun(result=result, out_dir=out_dir, report=files)


def report_campaign(path: str | Path) -> CampaignRun:
    """A campaign directory's report written again (Markdown, HTML and plots), with the campaign's results."""
    path = Path(path)
    try:
        return CampaignRun(result=load_results(path), out_dir=path, report=write_campaign_report(path))
    except CampaignError as exc:
        raise ConfigError(str(exc)) from None


