"""The bench as a library: what the `hil` command line does, for notebooks and scripts (docs/api.md).

A typed entry for every command, and no logic of its own: each entry calls the package that does the work; the
names the command line needs of those packages (exceptions, result types, constants) are re-exported here, the
experiments' loaded on first use. Bad input raises :class:`hil.config.ConfigError` (a ValueError with a one-line
message naming the field or parameter; a few entries raise their package's own ValueError, as their docstrings
say: FitInputError, CaptureError) before anything reaches a board; the command line prints that line and exits 2.

    import hil
    result = hil.run("profiles/sessions/demo.yaml", clock="sim")     # or: await hil.run_async(...)
    log = result.log                                                  # hil.read_log(result.log_path)
    log.loop.plot(x="t_s", y=["rate_err_el_dps", "rate_err_az_dps"])
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Coroutine, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from hil.analysis import IDENT_SWEEP, json_safe, summarize_log
from hil.config import (
    ConfigError,
    SessionConfig,
    SweptSine,
    load_session,
    require_regular_file,
)
from hil.control.registry import K_M_DEFAULT
from hil.ident import IdentRun, run_ident
from hil.link import (
    CaptureDecode,
    CaptureError,
    CaptureReader,
    Finding,
    SelftestReport,
    TimedFrame,
    board_of,
    decode_capture,
    find_capture,
    is_capture,
    main_sync,
)
from hil.log import LogError, RecoverReport, export_log, recover_log
from hil.log.reader import NotASessionLog
from hil.protocol import Decoder, Frame, frame_json, hex_bytes
from hil.session import (
    CLOCKS,
    LABS,
    BenchLab,
    Clock,
    Lab,
    Progress,
    RunResult,
    check_hardware,
    prepare_run,
    read_log,
    run,
    run_async,
)

if TYPE_CHECKING:
    from rich.console import Console

    from hil.campaign import METRICS, CampaignConfig, CampaignResult, CampaignRun, CellResult
    from hil.campaign.engines import Engine, Interrupted
    from hil.campaign.report import format_values
    from hil.campaign.runner import CampaignInterrupted
    from hil.campaign.runner import interrupted as campaign_interrupted
    from hil.config import MqttConfig
    from hil.fit.logs import FitInputError
    from hil.fit.record import Recording
    from hil.fit.report import TwinCheck
    from hil.fit.targets import TargetsResult
    from hil.fit.twin import TwinFit
    from hil.protocol.docgen import DOC_PATH as PROTOCOL_DOC
    from hil.replay import PlaybackResult, ReplayError, ReplayResult, write_playback_json
    from hil.replay import write_outputs as write_replay_outputs
    from hil.reporting import ReportFiles
    from hil.tune import Constraint, ParamSpec, TrialInfo, TuneResult

__all__ = [
    "CLOCKS",
    "K_M_DEFAULT",
    "LABS",
    "METRICS",
    "PROTOCOL_DOC",
    "BenchLab",
    "CampaignConfig",
    "CampaignInterrupted",
    "CampaignResult",
    "CampaignRun",
    "CaptureDecode",
    "CaptureError",
    "CellResult",
    "Clock",
    "ConfigError",
    "Decoder",
    "Finding",
    "FitInputError",
    "Frame",
    "IdentRun",
    "Interrupted",
    "Lab",
    "LogError",
    "PlaybackResult",
    "Progress",
    "Recording",
    "RecoverReport",
    "ReplayError",
    "ReplayResult",
    "RunResult",
    "SelftestReport",
    "TargetsResult",
    "TimedFrame",
    "TrialInfo",
    "TuneResult",
    "TwinCheck",
    "TwinFit",
    "board_of",
    "campaign_interrupted",
    "check_file",
    "decode_capture",
    "doctor",
    "emulator_command",
    "export_log",
    "find_capture",
    "fit_logs",
    "fit_plan",
    "fit_record",
    "fit_targets",
    "format_values",
    "frame_json",
    "hex_bytes",
    "ident",
    "is_capture",
    "json_safe",
    "load_campaign",
    "load_session",
    "open_capture",
    "prepare_campaign",
    "prepare_run",
    "protocol_docs",
    "read_log",
    "recover_log",
    "replay_capture",
    "replay_log",
    "report",
    "report_campaign",
    "report_log",
    "run",
    "run_async",
    "run_campaign",
    "selftest",
    "tune",
    "watch",
    "write_fit_report",
    "write_playback_json",
    "write_replay_outputs",
]

# Names of the experiments, loaded on first use (`hil run` starts without them): name -> (module, its name there)
_LAZY = {
    "CampaignConfig": ("hil.campaign", "CampaignConfig"),
    "CampaignRun": ("hil.campaign", "CampaignRun"),
    "CampaignResult": ("hil.campaign", "CampaignResult"),
    "CellResult": ("hil.campaign", "CellResult"),
    "METRICS": ("hil.campaign", "METRICS"),
    "Interrupted": ("hil.campaign.engines", "Interrupted"),
    "format_values": ("hil.campaign.report", "format_values"),
    "CampaignInterrupted": ("hil.campaign.runner", "CampaignInterrupted"),
    "campaign_interrupted": ("hil.campaign.runner", "interrupted"),
    "FitInputError": ("hil.fit.logs", "FitInputError"),
    "Recording": ("hil.fit.record", "Recording"),
    "TwinCheck": ("hil.fit.report", "TwinCheck"),
    "TargetsResult": ("hil.fit.targets", "TargetsResult"),
    "TwinFit": ("hil.fit.twin", "TwinFit"),
    "PROTOCOL_DOC": ("hil.protocol.docgen", "DOC_PATH"),
    "PlaybackResult": ("hil.replay", "PlaybackResult"),
    "ReplayError": ("hil.replay", "ReplayError"),
    "ReplayResult": ("hil.replay", "ReplayResult"),
    "write_playback_json": ("hil.replay", "write_playback_json"),
    "write_replay_outputs": ("hil.replay", "write_outputs"),
    "TrialInfo": ("hil.tune", "TrialInfo"),
    "TuneResult": ("hil.tune", "TuneResult"),
}


def __getattr__(name: str) -> Any:
    """A name of ``_LAZY``, imported from its module on first use."""
    try:
        module, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), attr)
    setattr(sys.modules[__name__], name, value)
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


def load_campaign(path: str | Path) -> CampaignConfig:
    """A campaign YAML (profiles x controllers x seeds, metrics, thresholds, acceptance rules)."""
    from hil.campaign import load_campaign_file  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return load_campaign_file(path)


def prepare_campaign(campaign: CampaignConfig | str | Path, *, out: str | Path | None = None,
                     hardware: bool = False, clock: Literal["sim", "lockstep"] = "sim",
                     engine: Literal["local", "dask"] | Engine = "local", scheduler: str | None = None,
                     workers: int | None = None, shared_dir: str | Path | None = None,
                     plant: str | Path | None = None,
                     ) -> tuple[CampaignConfig, Path, dict[str, dict[str, Any]]]:
    """Check a campaign without running it: (config, its directory, every cell's session). ConfigError otherwise.
    The engine options are checked as given (the scheduler is not contacted here: :func:`run_campaign` does).
    ``plant``: run every cell on this plant file (a fitted twin, docs/fit.md) instead of the sessions' own."""
    from hil.campaign import prepare_campaign as prepare  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return prepare(campaign, out=out, hardware=hardware, clock=clock, engine=engine, scheduler=scheduler,
                   workers=workers, shared_dir=shared_dir, plant=plant)


def run_campaign(campaign: CampaignConfig | str | Path, *, out: str | Path | None = None, jobs: int = 1,
                 resume: bool = False, hardware: bool = False, clock: Literal["sim", "lockstep"] = "sim",
                 write_report: bool = True, on_cell: Callable[[CellResult], None] | None = None,
                 engine: Literal["local", "dask"] | Engine = "local", scheduler: str | None = None,
                 workers: int | None = None, shared_dir: str | Path | None = None,
                 plant: str | Path | None = None) -> CampaignRun:
    """Run (or with ``resume`` finish) a swing campaign, its verdict and report (`hil campaign`); the
    parameters, the dask engine and Ctrl-C are :func:`hil.campaign.run_and_report`'s."""
    from hil.campaign import run_and_report  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return run_and_report(campaign, out=out, jobs=jobs, resume=resume, hardware=hardware, clock=clock,
                          write_report=write_report, on_cell=on_cell, engine=engine, scheduler=scheduler,
                          workers=workers, shared_dir=shared_dir, plant=plant)


def report(path: str | Path, *, settle_s: float = 1.0) -> dict[str, Any] | CampaignRun:
    """A session log's metrics (a dict, as `hil report LOG` prints it: :func:`report_log`), or for a campaign
    directory its report written again (Markdown, HTML and plots) with the campaign's results: a
    :class:`CampaignRun` (:func:`report_campaign`)."""
    return report_campaign(path) if Path(path).is_dir() else report_log(path, settle_s=settle_s)


def report_campaign(path: str | Path) -> CampaignRun:
    """A campaign directory's report written again (Markdown, HTML and plots), with the campaign's results."""
    from hil.campaign import report_campaign as report_again  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return report_again(path)


def report_log(path: str | Path, *, settle_s: float = 1.0) -> dict[str, Any]:
    """A session log's metrics, as `hil report LOG` prints them (:func:`hil.analysis.summarize_log`)."""
    path = Path(path)
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
          on_pass: Callable[[int, SweptSine], None] | None = None, lab: Lab | None = None) -> IdentRun:
    """Frequency-sweep identification (`hil ident`, seed 000 Figs. 8-9, docs/ident.md): the levelled sweeps,
    the Bode plot and the fit; the parameters are :func:`hil.ident.run_ident`'s."""
    return run_ident(session, axis=axis, loopback=loopback, clock=clock, out=out, f_start_hz=f_start_hz,
                     f_stop_hz=f_stop_hz, sweep_s=sweep_s, amplitude_dps=amplitude_dps, offset_dps=offset_dps,
                     level=level, progress=progress, on_pass=on_pass, lab=lab)


def replay_log(log: str | Path, controller: str | None = None,
               params: Mapping[str, Any] | str | Path | None = None, *, settle_s: float = 1.0) -> ReplayResult:
    """Re-run a controller open loop on a logged gyro and drive stream (`hil replay LOG`, docs/capture.md):
    its estimates, would-be drive, noise and lag beside the logged controller's. ``params``: a dict, a
    ``"k=v,..."`` string or a controller YAML path. :func:`write_replay_outputs` writes its plot and JSON."""
    from hil import replay  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    try:
        return replay.replay_log(Path(log), controller, params, settle_s=settle_s)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def replay_capture(capture: str | Path, *, ports: Mapping[str, str] | Sequence[str] | None = None,
                   ports_file: str | Path | None = None, clock: Literal["lockstep", "realtime"] | None = None,
                   seed: int | None = None, timing: Literal["samples", "clock"] = "samples",
                   record_dir: str | Path | None = None, links: Sequence[str] | None = None,
                   emulator_config: str | Path | None = None) -> PlaybackResult:
    """Play a capture's host-side frames back at the boards (``ports``: link -> path, or ``"LINK=PATH"`` strings,
    over ``ports_file``'s) or, with neither, a fresh emulator (``clock``, ``seed``, ``emulator_config``: default the
    captured emulator's) with the original timing (`hil replay CAPTURE`, docs/capture.md). ``record_dir``: where the
    replay's own capture goes; ``links``: only these. :func:`write_playback_json` writes its JSON."""
    from hil import replay  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    try:
        return replay.replay_capture(Path(capture), ports=ports, ports_file=ports_file, clock=clock, seed=seed,
                                     timing=timing, record_dir=record_dir, links=links,
                                     emulator_config=emulator_config)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def tune(campaign: CampaignConfig | str | Path, params: str | Sequence[str] | Sequence[ParamSpec], *,
         objective: str | Sequence[str] = "miss_std_px", trials: int = 100, controller: str | None = None,
         constraints: str | Sequence[str | Constraint] | None = None, engine: Literal["local", "dask"] = "local",
         scheduler: str | None = None, shared_dir: str | Path | None = None, workers: int = 1, jobs: int = 1,
         storage: str | None = None, study: str | None = None, resume: bool = False, out: str | Path | None = None,
         write_profile: str | Path | None = None, seed: int = 0, keep_logs: bool = False,
         write_report: bool = True, on_trial: Callable[[TrialInfo], None] | None = None, prune: bool = True,
         warm_start: bool = True, heldout_seeds: int = 3, heldout_duration_s: float | None = None) -> TuneResult:
    """Controller gains by search (`hil tune`, docs/tuning.md): an Optuna study whose trials are the campaign's
    cells for one controller with the trial's parameters; the study lives in an RDB (SQLite by default). The
    options as :func:`hil.tune.tune`; ConfigError (one line) for bad input or an existing study without
    ``resume``."""
    from hil import tune as tuning  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return tuning.tune(campaign, params, objective=objective, trials=trials, controller=controller,
                       constraints=constraints, engine=engine, scheduler=scheduler, shared_dir=shared_dir,
                       workers=workers, jobs=jobs, storage=storage, study=study, resume=resume, out=out,
                       write_profile=write_profile, seed=seed, keep_logs=keep_logs, write_report=write_report,
                       on_trial=on_trial, prune=prune, warm_start=warm_start, heldout_seeds=heldout_seeds,
                       heldout_duration_s=heldout_duration_s)


def fit_plan(session: SessionConfig | str | Path) -> list[Recording]:
    """The recordings a fit needs on ``session``'s lab (what `hil fit` plans, docs/fit.md "What to record"): each a
    :class:`hil.fit.record.Recording` (its session, length and purpose; ``write(dir)`` writes its session file)."""
    from hil.fit.record import recording_plan  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return recording_plan(session if isinstance(session, SessionConfig) else load_session(session))


def fit_record(plan: Sequence[Recording], *, loopback: bool, out_dir: str | Path | None = None,
               progress: Callable[[str], Any] | None = None, level: bool = True) -> list[Path]:
    """Run a recording plan (as `hil fit` records one) on the emulated lab (``loopback``: the sim clock) or on the lab's
    boards; the logs' paths in the plan's order. RuntimeError naming the recording when one does not complete."""
    from hil.fit.record import record  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return record(list(plan), loopback=loopback, out_dir=out_dir, progress=progress, level=level)


def fit_logs(logs: Sequence[str | Path], *, prior: str | Path | Mapping[str, Any] | None = None,
             progress: Callable[[str], Any] | None = None) -> TwinFit:
    """The plant fitted to one platform's session logs (`hil fit LOGS`, docs/fit.md): a
    :class:`hil.fit.twin.TwinFit` (its estimates; ``write(path, command=...)`` writes the plant YAML). ``prior``:
    the plant kept where the logs say nothing. :class:`FitInputError` (a ValueError, one line) for bad input."""
    from hil.fit.twin import fit_logs as fit  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return fit(list(logs), prior=prior, progress=progress)


def write_fit_report(fit: TwinFit, plant_path: str | Path, out_dir: str | Path, *, rerun: bool = True,
                     command: str = "hil fit") -> tuple[ReportFiles, list[TwinCheck]]:
    """A fit's report (fit.md, fit.html, plots) into ``out_dir``, the static and swing sessions re-run on the twin
    at ``plant_path`` unless ``rerun`` is False: the report's files and the twin checks."""
    from hil.fit.report import write_fit_report as write  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return write(fit, Path(plant_path), Path(out_dir), rerun=rerun, command=command)


def fit_targets(targets: str | Path, *, out_plant: str | Path, trials: int = 100, storage: str | None = None,
                study: str | None = None, seed: int = 0, resume: bool = False,
                progress: Callable[[str], None] | None = None, out_dir: str | Path | None = None,
                timeout_s: float | None = None, verify: bool = True, jobs: int | None = None,
                prune: bool = True) -> TargetsResult:
    """A plant (and the searched controller parameters) fitted to a paper's published figures (`hil fit` with a
    targets file, docs/fit.md): an Optuna study over the targets file's cells; the options as
    :func:`hil.fit.targets.fit_targets`."""
    from hil.fit.targets import fit_targets as fit  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return fit(targets, out_plant=out_plant, trials=trials, storage=storage, study=study, seed=seed, resume=resume,
               progress=progress, out_dir=out_dir, timeout_s=timeout_s, verify=verify, jobs=jobs, prune=prune)


def open_capture(path: str | Path) -> CaptureDecode:
    """A capture opened for :func:`decode_capture` (`hil protocol decode CAPTURE`): its header read (``reader``:
    meta, links), its counters filled as the frames are read. CaptureError if it is not a capture."""
    return CaptureDecode(CaptureReader(Path(path)))


def protocol_docs(text: str) -> str:
    """The protocol document ``text`` (:data:`PROTOCOL_DOC`) with its generated blocks made from the catalogue
    (`hil protocol docs`); ValueError if a block's markers are missing."""
    from hil.protocol import docgen  # noqa: PLC0415  (loaded by the call that needs it)

    return docgen.apply(text)


def selftest(*, ticks: int = 3000, seed: int = 1, garbage_rate: float = 0.01, flip_rate: float = 0.005,
             progress: Callable[[int], None] | None = None) -> SelftestReport:
    """The protocol self-test (`hil selftest`): the bench against an emulated servo board on a pty, ``ticks``
    GYRO_SAMPLEs at 1 kHz with garbage bursts and flipped bits injected (``seed``); ``progress(frames)``."""
    return main_sync(ticks=ticks, seed=seed, garbage_rate=garbage_rate, flip_rate=flip_rate, progress=progress)


def watch(config: MqttConfig, *, seconds: float | None = None, console: Console,
          err_console: Console | None = None) -> Coroutine[Any, Any, int]:
    """The live telemetry of the bench publishing to ``config``'s broker (`hil watch`), drawn on ``console`` until
    ``seconds`` elapse (None: until cancelled): a coroutine, 0 when done, 1 if the broker cannot be reached."""
    from hil.telemetry import watch as watch_telemetry  # noqa: PLC0415  (loaded by the call that needs it)

    return watch_telemetry(config, seconds=seconds, console=console, err_console=err_console)


def emulator_command(*, config: str | Path | None = None, clock: Literal["realtime", "lockstep"] | None = None,
                     seed: int | None = None, ports_file: str | Path | None = None,
                     fault_log: str | Path | None = None, seconds: float | None = None) -> list[str]:
    """The command that runs the emulated lab on its own (`hil emulate`: ``python -m firmware_stub``), each
    setting given passed on (the others are the emulator config's)."""
    words = [sys.executable, "-m", "firmware_stub"]
    for flag, value in (("--config", config), ("--clock", clock), ("--seed", seed), ("--ports-file", ports_file),
                        ("--fault-log", fault_log), ("--seconds", seconds)):
        if value is not None:
            words += [flag, str(value)]
    return words


def check_file(path: str | Path, kind: str | None = None) -> dict[str, Any]:
    """Validate one config file without running anything: {"file", "kind", "summary"}; ConfigError otherwise.
    The kind (session, campaign, controller, swing, hexapod, emulator, plant, targets) comes from ``kind``, else
    from the folder it is in (``profiles/KIND/``), else from its keys."""
    from hil.checks import check_config_file  # noqa: PLC0415  (loaded by the call that needs it: `hil run` starts without the experiments)

    return check_config_file(Path(path), kind)


def doctor(session: SessionConfig | str | Path | None = None, *, sysfs: str | Path = "/sys", boards: bool = True,
           listen_s: float = 2.0) -> list[Finding]:
    """Is the hardware ready (`hil doctor`, docs/service.md)? Every check of every port, and with a session
    and ``boards`` the boards asked too; the parameters are :func:`hil.session.check_hardware`'s."""
    return check_hardware(session, sysfs=sysfs, boards=boards, listen_s=listen_s)
