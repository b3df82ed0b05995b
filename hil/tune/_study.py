"""Controller tuning: an Optuna study over a campaign's cells (`hil tune`, docs/tuning.md).

A trial is the campaign's cells (every profile x seed) for one controller entry, with the trial's parameters
merged over that entry's own, run through :func:`hil.campaign.runner.run_campaign` (cells as processes, or on a
dask cluster). Its value is the mean of one metric over those cells (minimised when the metric is lower-is-better,
as every metric of :data:`hil.campaign.metrics.METRICS` is). A trial whose loop is unstable (a cell that did not
complete, a drive sitting at its limit, a lost target, a missing or NaN metric) is a failed trial
(``TrialState.FAIL``): the sampler never takes it for a good region, and the study goes on. Constraints
(``drive_ripple_el_counts<=800``) and the campaign's per-cell thresholds are Optuna constraints (<= 0 feasible,
stored on the trial), so TPE learns where the infeasible region lies.

The study lives in an Optuna RDB storage (SQLite by default, ``runs/tune/STUDY/tune.db``; any SQLAlchemy URL for
a study shared by several machines), so it survives the process and ``resume`` continues it up to the trial
target. The best feasible trial's parameters are written as a controller YAML (``hil check``-able) and a report
(tune.md + tune.html, the campaign report's style) sums the study up.
"""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import json
import math
import re
import shutil
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from hil.config import ConfigError, require_writable_dir

if TYPE_CHECKING:
    import optuna

    from hil.campaign.model import CampaignConfig, CampaignResult, ControllerEntry

__all__ = ["Constraint", "ParamSpec", "TrialInfo", "TuneResult", "parse_constraints", "parse_params", "tune"]

TUNE_DIR = Path("runs") / "tune"
TRIALS = "trials"
SATURATION_MAX_FRAC = 0.05  # a cell whose drive sits at its limit longer than this (after settling) is unstable
TRACK_VALID_MIN_FRAC = 0.5  # a tracking cell with fewer valid frames than this (after settling) lost the target
HEARTBEAT_S = 30  # RDB heartbeat: a trial left RUNNING by a killed run is failed after GRACE_S
GRACE_S = 120
_PARAM = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*=\s*([^\s.][^\s]*?)\s*\.\.\s*([^\s:]+)\s*((?::\s*[a-z]+\s*)*)$")
_CONSTRAINT = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(<=|>=)\s*(\S+)\s*$")


# --- the search space and the constraints ----------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    """One tuned parameter: ``name=low..high`` sampled uniformly, ``:log`` log-uniformly, ``:int`` as integers."""

    name: str
    low: float
    high: float
    log: bool = False
    integer: bool = False

    def suggest(self, trial: optuna.Trial) -> float | int:
        if self.integer:
            return trial.suggest_int(self.name, int(self.low), int(self.high), log=self.log)
        return trial.suggest_float(self.name, self.low, self.high, log=self.log)

    def __str__(self) -> str:
        kind = (":int" if self.integer else "") + (":log" if self.log else "")
        return f"{self.name}={self.low:g}..{self.high:g}{kind}"


def _number(text: str, what: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise ConfigError(f"{what}: {text!r} is not a number") from None
    if not math.isfinite(x):
        raise ConfigError(f"{what}: {text!r} is not a finite number")
    return x


def _controllers() -> dict[str, Any]:
    """Every controller by name: the registry's, and those that run only on the sim clock (the oracle)."""
    from hil.control import registry

    return {**registry.REGISTRY, **getattr(registry, "SIM_ONLY", {})}


def _numeric_fields(controller: str) -> dict[str, bool]:
    """The controller's numeric parameters: name -> whether it is an integer."""
    out = {}
    for name, field in _controllers()[controller].params.model_fields.items():
        if field.annotation is int:
            out[name] = True
        elif field.annotation is float:
            out[name] = False
    return out


def parse_params(text: str | Sequence[str], controller: str, base: dict[str, Any] | None = None) -> list[ParamSpec]:
    """``"omega_o_rad_s=100..2000:log, kp_counts_per_dps=1000..20000:log"`` -> one :class:`ParamSpec` each.

    Names must be numeric parameters of ``controller`` (hil.control.registry); ``low < high``, finite, positive
    for ``:log``, whole numbers for ``:int`` (an integer parameter is always sampled as one); each end of the range
    must validate for the controller with ``base`` (the entry's other parameters). ConfigError naming --params."""
    from hil.control.registry import ControllerConfigError, controller_params

    models = _controllers()
    if controller not in models:
        known = ", ".join(sorted(models))
        raise ConfigError(f"--controller: unknown controller {controller!r} (controllers: {known})")
    items = [s for part in ([text] if isinstance(text, str) else list(text)) for s in part.split(",")]
    items = [s for s in items if s.strip()]
    if not items:
        raise ConfigError("--params: nothing to tune (give name=low..high[:log|:int], comma-separated)")
    fields = _numeric_fields(controller)
    specs: list[ParamSpec] = []
    for item in items:
        m = _PARAM.match(item)
        if m is None:
            raise ConfigError(f"--params: {item.strip()!r} is not name=low..high[:log|:int]")
        name, lo_text, hi_text, kinds = m.groups()
        where = f"--params: {name}"
        if name not in fields:
            known = ", ".join(fields)
            numeric = name in models[controller].params.model_fields
            what = "not a numeric parameter" if numeric else "unknown parameter"
            raise ConfigError(f"{where}: {what} of controller {controller!r} (numeric parameters: {known})")
        if any(s.name == name for s in specs):
            raise ConfigError(f"{where}: given twice")
        flags = [k.strip() for k in kinds.split(":") if k.strip()]
        for flag in flags:
            if flag not in ("log", "int"):
                raise ConfigError(f"{where}: unknown suffix ':{flag}' (':log' or ':int')")
        lo, hi = _number(lo_text, where), _number(hi_text, where)
        log, integer = "log" in flags, "int" in flags or fields[name]
        if not lo < hi:
            raise ConfigError(f"{where}: the range {lo:g}..{hi:g} is empty (need low < high)")
        if log and lo <= 0:
            raise ConfigError(f"{where}: ':log' needs a positive range (got {lo:g}..{hi:g})")
        if integer and (lo != int(lo) or hi != int(hi)):
            raise ConfigError(f"{where}: an integer range needs whole numbers (got {lo:g}..{hi:g})")
        for end in (lo, hi):
            try:
                controller_params(controller, {**(base or {}), name: int(end) if integer else end})
            except ControllerConfigError as exc:
                raise ConfigError(f"{where}: {end:g} is not valid: {exc}") from None
        specs.append(ParamSpec(name, lo, hi, log=log, integer=integer))
    return specs


@dataclasses.dataclass(frozen=True)
class Constraint:
    """``metric <= bound`` (or ``>=``) on every cell of a trial: its Optuna value is the worst cell's excess."""

    metric: str
    op: Literal["<=", ">="]
    bound: float

    def value(self, values: Sequence[float]) -> float:
        """<= 0 when every value meets it; else how far the worst misses."""
        if self.op == "<=":
            return max(values) - self.bound
        return self.bound - min(values)

    def __str__(self) -> str:
        return f"{self.metric}{self.op}{self.bound:g}"


def parse_constraints(items: str | Sequence[str | Constraint] | None) -> list[Constraint]:
    """``"drive_ripple_el_counts<=800"`` (one each, or comma-separated) -> :class:`Constraint`; ConfigError naming
    --constraint for an unknown metric, another operator or a bound that is not a finite number."""
    from hil.campaign.metrics import METRICS

    if items is None:
        return []
    raw = [items] if isinstance(items, str) else list(items)
    out: list[Constraint] = []
    for item in raw:
        if isinstance(item, Constraint):
            out.append(item)
            continue
        for part in (p for p in item.split(",") if p.strip()):
            m = _CONSTRAINT.match(part)
            if m is None:
                raise ConfigError(f"--constraint: {part.strip()!r} is not metric<=value or metric>=value")
            metric, op, bound = m.groups()
            if metric not in METRICS:
                raise ConfigError(f"--constraint: unknown metric {metric!r} (metrics: {', '.join(METRICS)})")
            out.append(Constraint(metric, op, _number(bound, f"--constraint: {metric}")))  # type: ignore[arg-type]
    return out


# --- results ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TrialInfo:
    """One finished trial as the study stored it."""

    number: int
    state: str  # COMPLETE, FAIL, PRUNED, RUNNING
    value: float | None
    params: dict[str, Any]
    feasible: bool | None  # None: failed (no constraints evaluated)
    constraints: dict[str, float]  # name (metric<=bound) -> the worst cell's excess, <= 0 holds
    failure: str
    wall_s: float | None


@dataclasses.dataclass
class TuneResult:
    """A study's outcome. ``best_params``: the best feasible trial's tuned parameters (None if no trial was
    feasible); ``params``: the whole controller entry's parameters with them merged in, as the YAML holds them."""

    study: str
    storage: str
    out_dir: Path
    campaign: str
    controller_label: str
    controller: str
    objective: str
    direction: str
    space: list[ParamSpec]
    constraints: list[Constraint]
    trials: list[TrialInfo]
    trials_run: int
    wall_s: float
    engine: str
    workers: int
    best_trial: int | None = None
    best_value: float | None = None
    best_params: dict[str, Any] | None = None
    params: dict[str, Any] | None = None
    yaml_path: Path | None = None
    profile_path: Path | None = None
    report: Any = None  # hil.campaign.report.ReportFiles

    @property
    def n_complete(self) -> int:
        return sum(t.state == "COMPLETE" for t in self.trials)

    @property
    def n_failed(self) -> int:
        return sum(t.state == "FAIL" for t in self.trials)

    @property
    def n_infeasible(self) -> int:
        return sum(t.state == "COMPLETE" and t.feasible is False for t in self.trials)

    def to_json(self) -> dict[str, Any]:
        return {"study": self.study, "storage": self.storage, "dir": str(self.out_dir), "campaign": self.campaign,
                "controller": {"label": self.controller_label, "name": self.controller},
                "objective": self.objective, "direction": self.direction,
                "space": [str(s) for s in self.space], "constraints": [str(c) for c in self.constraints],
                "trials": len(self.trials), "trials_run": self.trials_run, "complete": self.n_complete,
                "failed": self.n_failed, "infeasible": self.n_infeasible, "wall_s": self.wall_s,
                "engine": self.engine, "workers": self.workers, "best_trial": self.best_trial,
                "best_value": self.best_value, "best_params": self.best_params, "params": self.params,
                "yaml": None if self.yaml_path is None else str(self.yaml_path),
                "profile": None if self.profile_path is None else str(self.profile_path),
                "report": None if self.report is None else {"markdown": str(self.report.markdown),
                                                            "html": str(self.report.html),
                                                            "plots": [str(p) for p in self.report.pngs]}}


# --- one trial -------------------------------------------------------------------------------


def choose_controller(config: CampaignConfig, label: str | None) -> ControllerEntry:
    """The campaign's controller entry ``label``; by default the first that is not the baseline."""
    labels = [c.label for c in config.controllers]
    if label is not None:
        for c in config.controllers:
            if c.label == label:
                return c
        raise ConfigError(f"--controller: {label!r} is not a controller label of campaign {config.name!r} "
                          f"({', '.join(labels)})")
    return next((c for c in config.controllers if c.label != config.baseline), config.controllers[0])


def trial_campaign(config: CampaignConfig, entry: ControllerEntry, params: dict[str, Any]) -> CampaignConfig:
    """The campaign one trial runs: its profiles and seeds, only ``entry`` with ``params`` merged over its own,
    no baseline, acceptance or paper values (one controller has nothing to be compared with)."""
    from hil.campaign.model import ControllerEntry

    merged = ControllerEntry(label=entry.label, name=entry.name, params={**entry.params, **params})
    return config.model_copy(update={"controllers": [merged], "baseline": None, "acceptance": [], "paper": {}})


def log_health(path: Path, settle_s: float, u_max: float) -> tuple[float, float | None]:
    """(fraction of the samples with either drive at its limit, fraction of valid tracking frames or None when the
    session did not track) after ``settle_s``."""
    import numpy as np

    from hil.log import read_log

    data = read_log(path)
    loop, image = data.groups["loop"], data.groups.get("image") or {}
    t = loop["t_s"]
    t0 = float(t[0]) if t.size else 0.0
    keep = (t - t0) >= settle_s
    n = int(keep.sum())
    sat = 0.0
    if n:
        at_limit = np.zeros(n, dtype=bool)
        for axis in ("el", "az"):
            at_limit |= np.abs(loop[f"drive_{axis}_counts"][keep].astype(float)) >= u_max - 1.0
        sat = float(at_limit.mean())
    valid = None
    config = data.attrs.get("config") or {}
    tracking = isinstance(config, dict) and bool((config.get("tracking") or {}).get("enabled"))
    if tracking and image and "t_exposure_s" in image and image["t_exposure_s"].size:
        frames = (image["t_exposure_s"] - t0) >= settle_s
        if frames.any():
            valid = float((image["track_valid"][frames] > 0).mean())
    return sat, valid


def unstable_reason(saturated_frac: float, valid_frac: float | None) -> str:
    """Why a session with this :func:`log_health` counts as unstable, "" if it does not: the one rule of tuning and of
    the paper-targets fit. A drive at its limit more than SATURATION_MAX_FRAC of the time, or (a tracking session)
    fewer than TRACK_VALID_MIN_FRAC of the frames valid."""
    if saturated_frac > SATURATION_MAX_FRAC:
        return f"unstable: the drive sat at its limit {100 * saturated_frac:.0f} % of the time"
    if valid_frac is not None and valid_frac < TRACK_VALID_MIN_FRAC:
        return f"lost the target: {100 * valid_frac:.0f} % valid frames"
    return ""


def evaluate(result: CampaignResult, out_dir: Path, objective: str, constraints: Sequence[Constraint],
             *, check_logs: bool = True) -> tuple[float, list[float], dict[str, Any]]:
    """A trial's campaign result -> (objective, constraint values, attributes). ValueError (one line) when the
    trial is unstable or its numbers are missing: the caller scores it as failed."""
    from hil.campaign.metrics import METRICS
    from hil.control.registry import effective_params

    config: CampaignConfig = result.config
    cells = result.cells
    if len(cells) != len(config.cells()):
        raise ValueError(f"{len(config.cells()) - len(cells)} cell(s) did not run")
    for c in cells:
        if c.status != "completed":
            raise ValueError(f"cell {c.cell_id}: session {c.status}: {c.message}".rstrip(": "))
    attrs: dict[str, Any] = {}
    if check_logs:
        entry = config.controllers[0]
        u_max = float(effective_params({"name": entry.name, "params": entry.params})["u_max_counts"])
        sats, valids = [], []
        for c in cells:
            if c.log is None:
                raise ValueError(f"cell {c.cell_id}: no log")
            log = Path(c.log) if Path(c.log).is_absolute() else out_dir / c.log
            sat, valid = log_health(log, config.settle_s, u_max)
            sats.append(sat)
            if valid is not None:
                valids.append(valid)
            why = unstable_reason(sat, valid)
            if why:
                raise ValueError(f"cell {c.cell_id}: {why}")
        attrs["saturated_frac"] = max(sats)
        if valids:
            attrs["track_valid_frac"] = min(valids)

    def values(metric: str) -> list[float]:
        out = []
        for c in cells:
            v = c.metrics.get(metric, math.nan)
            if not math.isfinite(v):
                raise ValueError(f"cell {c.cell_id}: {metric} is not available")
            out.append(float(v))
        return out

    obj = values(objective)
    if METRICS[objective].magnitude:  # a lag's lead is no better than the same lag: scored by its magnitude
        obj = [abs(v) for v in obj]
    attrs["cells"] = {c.cell_id: c.metrics.get(objective) for c in cells}
    every = list(constraints) + [Constraint(m, op, bound) for m, t in config.thresholds.items()  # type: ignore[arg-type]
                                 for op, bound in (("<=", t.max), (">=", t.min)) if bound is not None]
    cons = [c.value(values(c.metric)) for c in every]
    attrs["constraint_names"] = [str(c) for c in every]
    return sum(obj) / len(obj), cons, attrs


# --- the study -------------------------------------------------------------------------------


def storage_url(storage: str | None, out_dir: Path) -> str:
    if storage is None:
        return f"sqlite:///{(out_dir / 'tune.db').absolute()}"
    if "://" not in storage:
        raise ConfigError(f"--storage: {storage!r} is not a database URL (e.g. sqlite:///tune.db, "
                          "postgresql://user@host/db)")
    return storage


def rdb_storage(url: str) -> Any:
    import optuna
    import sqlalchemy.exc

    kwargs: dict[str, Any] = {"connect_args": {"timeout": 60}} if url.startswith("sqlite") else {}
    try:
        with warnings.catch_warnings():  # the heartbeat is marked experimental
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            return optuna.storages.RDBStorage(url, engine_kwargs=kwargs, heartbeat_interval=HEARTBEAT_S,
                                              grace_period=GRACE_S)
    except (sqlalchemy.exc.SQLAlchemyError, ImportError, ValueError) as exc:
        msg = " ".join(str(exc).split())
        raise ConfigError(f"--storage {url}: cannot open: {msg[:200]}") from None


def _trial_infos(study: optuna.Study) -> list[TrialInfo]:
    from optuna.trial import TrialState

    out = []
    for t in study.get_trials(deepcopy=False):
        cons = dict(t.constraints)
        feasible = None if t.state != TrialState.COMPLETE else all(c <= 0 for c in cons.values())
        wall = t.duration.total_seconds() if t.duration is not None else None
        out.append(TrialInfo(t.number, t.state.name, t.value if t.state == TrialState.COMPLETE else None,
                             dict(t.params), feasible, cons, str(t.user_attrs.get("failure", "")), wall))
    return out


def _best(trials: list[TrialInfo], direction: str) -> TrialInfo | None:
    ok = [t for t in trials if t.state == "COMPLETE" and t.feasible and t.value is not None
          and math.isfinite(t.value)]
    if not ok:
        return None
    return (min if direction == "minimize" else max)(ok, key=lambda t: (t.value, t.number))


def _engine_options(engine: str, scheduler: str | None, shared_dir: str | Path | None) -> dict[str, Any]:
    """The runner's keyword arguments for the engine, checked (nothing started); without a scheduler the dask
    engine's address is filled in once the study's LocalCluster runs (:func:`_start_cluster`)."""
    from hil.campaign import runner

    if engine not in ("local", "dask"):
        raise ConfigError(f"--engine: {engine!r} is not local or dask")
    supported = "engine" in inspect.signature(runner.run_campaign).parameters
    if engine == "local":
        if scheduler is not None or shared_dir is not None:
            raise ConfigError(f"{'--scheduler' if scheduler is not None else '--shared-dir'}: only with --engine dask")
        return {"engine": "local"} if supported else {}
    if not supported:
        raise ConfigError("--engine dask: this bench's campaign runner has no dask engine")
    try:
        from hil.campaign.engines import EngineError, check_options
    except ImportError:
        pass
    else:
        try:
            check_options("dask", scheduler=scheduler, shared_dir=shared_dir)
        except EngineError as exc:
            raise ConfigError(str(exc)) from None
    return {"engine": "dask", "scheduler": scheduler, **({} if shared_dir is None else {"shared_dir": str(shared_dir)})}


def _start_cluster(options: dict[str, Any], workers: int) -> Any:
    """The study's LocalCluster (dask engine, no scheduler given): ``workers`` processes of one thread, its
    address put in ``options``; None when there is nothing to start."""
    if options.get("engine") != "dask" or options.get("scheduler") is not None:
        return None
    from distributed import LocalCluster

    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, dashboard_address=None)
    options["scheduler"] = cluster.scheduler_address
    return cluster


def _controller_yaml(entry: ControllerEntry, params: dict[str, Any], note: list[str]) -> str:
    import yaml

    head = ["# hil.config.ControllerConfig: a controller of hil.control's registry (docs/control.md) and its "
            "parameters.",
            *(f"# {line}" for line in note)]
    body = yaml.safe_dump({"name": entry.name, "params": params}, sort_keys=False)
    return "\n".join(head) + "\n" + body


def tune(campaign: CampaignConfig | str | Path, params: str | Sequence[str] | Sequence[ParamSpec], *,
         objective: str = "miss_std_px", trials: int = 100, controller: str | None = None,
         constraints: str | Sequence[str | Constraint] | None = None, engine: str = "local",
         scheduler: str | None = None, shared_dir: str | Path | None = None, workers: int = 1, jobs: int = 1,
         storage: str | None = None,
         study: str | None = None, resume: bool = False, out: str | Path | None = None,
         write_profile: str | Path | None = None, seed: int = 0, keep_logs: bool = False,
         write_report: bool = True, on_trial: Callable[[TrialInfo], None] | None = None) -> TuneResult:
    """Tune one controller of ``campaign`` with Optuna (TPE, seeded): ``trials`` trials in total in the study
    (``resume`` runs only those still missing), ``workers`` at a time (threads; each trial runs its cells ``jobs``
    at a time through the campaign runner, or on the dask ``engine``: a LocalCluster of ``workers`` started for
    the study, or ``scheduler``'s cluster; ``shared_dir``: a directory the workers share with this process). The
    objective (mean of ``objective`` over the campaign's profiles and
    seeds) is minimised; ``constraints`` and the campaign's thresholds must hold on every cell.

    ``params``: ``"name=low..high[:log|:int], ..."`` (:func:`parse_params`). ``controller``: the campaign's
    controller label (default: the first that is not the baseline). ``out``: default ``runs/tune/STUDY``;
    ``storage``: an SQLAlchemy URL (default SQLite ``OUT/tune.db``); ``study``: default the campaign's name.
    Writes ``OUT/NAME-tuned.yaml`` (and ``write_profile``) from the best feasible trial, and the report.
    ``on_trial``: called after every trial of this run. ConfigError (one line) for bad input or an existing study
    without ``resume``."""
    import optuna

    from hil.campaign import CampaignError, load_campaign
    from hil.campaign.metrics import METRICS
    from hil.campaign.runner import cell_sessions, run_campaign

    try:
        config: CampaignConfig = campaign if hasattr(campaign, "cells") else load_campaign(campaign)  # type: ignore
    except CampaignError as exc:
        raise ConfigError(str(exc)) from None
    if objective not in METRICS:
        raise ConfigError(f"--objective: unknown metric {objective!r} (metrics: {', '.join(METRICS)})")
    if not 1 <= trials <= 100_000:
        raise ConfigError(f"--trials: {trials} (need 1..100000)")
    if not 1 <= workers <= 256 or not 1 <= jobs <= 64:
        raise ConfigError(f"--workers {workers} / --jobs {jobs}: need 1..256 and 1..64")
    entry = choose_controller(config, controller)
    space = params if params and all(isinstance(p, ParamSpec) for p in params) else \
        parse_params(params, entry.name, entry.params)  # type: ignore[arg-type]
    space = list(space)  # type: ignore[arg-type]
    cons = parse_constraints(constraints)
    study_name = study or config.name
    if not re.match(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$", study_name):
        raise ConfigError(f"--study: {study_name!r} is not a name (letters, digits, '_', '.', '-')")
    out_dir = Path(out) if out is not None else TUNE_DIR / study_name
    require_writable_dir(out_dir, "--out")
    if write_profile is not None and Path(write_profile).is_dir():
        raise ConfigError(f"--write-profile {write_profile}: is a directory (give the YAML file's path)")
    direction = "minimize" if METRICS[objective].lower_is_better else "maximize"
    try:  # every cell of a trial, before anything is written
        cell_sessions(trial_campaign(config, entry, {}), out_dir / TRIALS / "probe")
    except (CampaignError, ValueError) as exc:
        raise ConfigError(f"{config.name}: {' '.join(str(exc).split())}") from None

    kwargs = _engine_options(engine, scheduler, shared_dir)

    out_dir.mkdir(parents=True, exist_ok=True)
    url = storage_url(storage, out_dir)
    rdb = rdb_storage(url)
    exists = study_name in optuna.study.get_all_study_names(rdb)
    if exists and not resume:
        raise ConfigError(f"--study {study_name}: already in {url}; pass --resume to continue it, or choose another "
                          "--study")
    meta = {"campaign": config.name, "controller_label": entry.label, "controller": entry.name,
            "objective": objective, "space": [str(s) for s in space]}
    with warnings.catch_warnings():  # multivariate TPE is marked experimental
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        sampler = optuna.samplers.TPESampler(seed=seed, n_startup_trials=min(10, max(2, trials // 10)),
                                             multivariate=True)
    st = open_study(rdb, study_name, sampler, direction, meta=meta, exists=exists)
    finished = {"COMPLETE", "FAIL", "PRUNED"}
    done = sum(t.state.name in finished for t in st.get_trials(deepcopy=False))
    todo = max(0, trials - done)

    lock = threading.Lock()

    def objective_fn(trial: optuna.Trial) -> float:
        values = {s.name: s.suggest(trial) for s in space}
        trial_dir = out_dir / TRIALS / f"{trial.number:05d}"
        t0 = time.monotonic()
        try:
            try:
                cfg = trial_campaign(config, entry, values)
            except ValueError as exc:  # a combination of parameters the controller refuses
                raise ValueError(f"parameters: {' '.join(str(exc).split())}") from None
            if trial_dir.exists():
                shutil.rmtree(trial_dir)
            result = run_campaign(cfg, trial_dir, jobs=jobs, **kwargs)
            value, cvals, attrs = evaluate(result, trial_dir, objective, cons)
        except Exception as exc:  # an unstable or broken trial is a failed trial, never the study's end
            trial.set_user_attr("failure", " ".join(str(exc).split())[:500] or type(exc).__name__)
            trial.set_user_attr("wall_s", time.monotonic() - t0)
            return math.nan  # Optuna: a NaN objective marks the trial FAIL
        finally:
            if not keep_logs and trial_dir.exists():
                from hil.log.truth import truth_path

                for log in trial_dir.rglob("*.h5"):
                    log.unlink(missing_ok=True)
                    truth_path(log).unlink(missing_ok=True)  # the sim clock's truth file beside it
        for key, v in attrs.items():
            trial.set_user_attr(key, v)
        for name, v in zip(attrs["constraint_names"], cvals, strict=True):
            trial.set_constraint(name, v)  # TPE: feasible when every value is <= 0
        trial.set_user_attr("wall_s", time.monotonic() - t0)
        return value

    def callback(s: optuna.Study, frozen: optuna.trial.FrozenTrial) -> None:
        if on_trial is None:
            return
        with lock:
            cons_v = dict(frozen.constraints)
            ok = frozen.state.name == "COMPLETE"
            on_trial(TrialInfo(frozen.number, frozen.state.name, frozen.value if ok else None, dict(frozen.params),
                               all(c <= 0 for c in cons_v.values()) if ok else None, cons_v,
                               str(frozen.user_attrs.get("failure", "")),
                               frozen.duration.total_seconds() if frozen.duration else None))

    t0 = time.monotonic()
    cluster = _start_cluster(kwargs, workers) if todo else None
    try:
        with quiet_nan_warnings():
            if todo:
                st.optimize(objective_fn, n_trials=todo, n_jobs=workers, callbacks=[callback])
    finally:
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close()
    wall = time.monotonic() - t0
    infos = _trial_infos(st)
    result = TuneResult(study=study_name, storage=url, out_dir=out_dir, campaign=config.name,
                        controller_label=entry.label, controller=entry.name, objective=objective,
                        direction=direction, space=space, constraints=cons, trials=infos, trials_run=todo,
                        wall_s=wall, engine=engine, workers=workers)
    best = _best(infos, direction)
    if best is not None:
        result.best_trial, result.best_value, result.best_params = best.number, best.value, best.params
        result.params = {**entry.params, **best.params}
        note = [f"Tuned by `hil tune` (study {study_name!r}, trial {best.number} of {len(infos)}): mean "
                f"{objective} {best.value:.6g} over the profiles and seeds of campaign {config.name!r}, {entry.label}.",
                "Empty params = the registry's defaults; these override them."]
        text = _controller_yaml(entry, result.params, note)
        result.yaml_path = out_dir / f"{entry.name}-tuned.yaml"
        result.yaml_path.write_text(text)
        if write_profile is not None:
            result.profile_path = Path(write_profile)
            result.profile_path.parent.mkdir(parents=True, exist_ok=True)
            result.profile_path.write_text(text)
        (out_dir / "best.json").write_text(json.dumps({"trial": best.number, "value": best.value,
                                                      "params": result.params}, indent=2))
    if write_report:
        result.report = write_tune_report(result, st)
    return result


@contextlib.contextmanager
def quiet_nan_warnings() -> Any:
    """Optuna logs a warning for every trial that returns NaN; the failed trials are reported here instead."""
    import logging

    log = logging.getLogger("optuna")
    level = log.level
    if level < logging.ERROR and not logging.getLogger("hil").isEnabledFor(logging.INFO):
        log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        log.setLevel(level)


# --- the report ------------------------------------------------------------------------------


def _plot_history(result: TuneResult, path: Path) -> Path | None:
    from hil.campaign.report import legend_below, new_figure, save_figure

    done = [t for t in result.trials if t.state == "COMPLETE" and t.value is not None]
    if not done:
        return None
    fig, ax = new_figure()
    a = ax[0, 0]
    ok = [t for t in done if t.feasible]
    bad = [t for t in done if not t.feasible]
    if ok:
        a.plot([t.number for t in ok], [t.value for t in ok], "o", ms=3.5, color="C0", label="feasible trial")
    if bad:
        a.plot([t.number for t in bad], [t.value for t in bad], "x", ms=4, color="C3", label="infeasible trial")
    failed = [t.number for t in result.trials if t.state == "FAIL"]
    pick = min if result.direction == "minimize" else max
    best, xs, ys = None, [], []
    for t in sorted(ok, key=lambda t: t.number):
        best = t.value if best is None else pick(best, t.value)
        xs.append(t.number)
        ys.append(best)
    if xs:
        a.step(xs, ys, where="post", color="k", lw=1.2, label="best feasible so far")
    if failed:
        lo = min(t.value for t in done)
        a.plot(failed, [lo] * len(failed), "|", ms=8, color="0.5", label="failed (unstable) trial")
    a.set(title=f"{result.study}: {result.objective} per trial ({result.direction})", xlabel="trial",
          ylabel=result.objective)
    if all(t.value > 0 for t in done):
        a.set_yscale("log")
    a.grid(alpha=0.3)
    legend_below(fig, a)
    return save_figure(fig, path)


MIN_IMPORTANCE_TRIALS = 4  # complete trials below which importances are not computed


def _importances(study: optuna.Study) -> tuple[dict[str, float], str]:
    """Optuna's parameter importances (its default evaluator) over the complete trials, or ({}, why not)."""
    import optuna

    n = sum(t.state == optuna.trial.TrialState.COMPLETE for t in study.get_trials(deepcopy=False))
    if n < MIN_IMPORTANCE_TRIALS:
        return {}, f"{n} complete trial(s), need {MIN_IMPORTANCE_TRIALS}"
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        try:
            imp = optuna.importance.get_param_importances(study)
        except (RuntimeError, ValueError, ZeroDivisionError) as exc:
            return {}, " ".join(str(exc).split())
    for w in seen:
        if "too small" in str(w.message):  # Optuna then returns equal importances, which say nothing
            return {}, " ".join(str(w.message).split())
    return imp, ""


def _plot_importances(imp: dict[str, float], path: Path) -> Path | None:
    from hil.campaign.report import new_figure, save_figure

    if not imp:
        return None
    fig, ax = new_figure(height=0.5 + 0.45 * len(imp))
    names = list(imp)[::-1]
    ax[0, 0].barh(names, [imp[n] for n in names], color="C0")
    ax[0, 0].set(title="parameter importances (Optuna's default evaluator, complete trials)", xlabel="importance")
    ax[0, 0].grid(alpha=0.3, axis="x")
    return save_figure(fig, path)


def open_study(rdb: Any, study_name: str, sampler: Any, direction: str, *, meta: dict[str, Any],
               exists: bool) -> Any:
    """Create the study, or load it (``exists``) and check it was made with the same ``meta`` (its user attributes:
    the space, the objective, ...); ConfigError naming ``--resume`` if not. A new study gets ``meta`` stored."""
    import optuna

    st = optuna.create_study(storage=rdb, sampler=sampler, study_name=study_name, direction=direction,
                             load_if_exists=True)
    for key, value in meta.items():
        if not exists:
            st.set_user_attr(key, value)
        elif st.user_attrs.get(key) != value:
            raise ConfigError(f"--resume: study {study_name!r} was made with {key} {st.user_attrs.get(key)!r}, "
                              f"not {value!r}; choose another --study")
    return st


def write_tune_report(result: TuneResult, study: optuna.Study | None = None) -> Any:
    """tune.md, tune.html and the plots into the study's directory: the best parameters, the optimisation history,
    the parameter importances, the best trial's campaign table, the trials. Returns a ReportFiles."""
    import optuna

    from hil.campaign import CampaignError, load_results
    from hil.campaign.report import (
        Banner,
        Bullets,
        Cell,
        Figure,
        Heading,
        Item,
        ReportFiles,
        Table,
        Text,
        format_number,
        profile_table,
        render_html,
        render_markdown,
    )

    if study is None:
        study = optuna.load_study(study_name=result.study, storage=rdb_storage(result.storage))
    out = result.out_dir
    out.mkdir(parents=True, exist_ok=True)
    pngs: list[Path] = []
    doc: list[Any] = [Heading(1, f"Tuning {result.controller_label} ({result.controller}) on {result.campaign}")]
    feasible = result.best_trial is not None
    head = (f"trial {result.best_trial}: {result.objective} {format_number(result.best_value or math.nan)}" if feasible
            else "no feasible trial")
    doc.append(Banner(head, f"{len(result.trials)} trials: {result.n_complete} complete "
                            f"({result.n_infeasible} infeasible), {result.n_failed} failed (unstable); objective: "
                            f"mean {result.objective} over the campaign's profiles and seeds, {result.direction}d.",
                      feasible))
    doc.append(Heading(2, "Best parameters"))
    if result.params is not None:
        rows = [[Cell(k), Cell(f"{v:.6g}" if isinstance(v, float) else str(v)),
                 Cell("tuned" if k in (result.best_params or {}) else "campaign")] for k, v in result.params.items()]
        doc.append(Table(["parameter", "value", "from"], rows, align="lrl"))
        if result.yaml_path is not None:
            doc.append(Text(f"Controller file: {result.yaml_path.name} (hil check {result.yaml_path.name})."))
    else:
        doc.append(Text("No trial was complete and feasible: nothing to write."))
    doc.append(Heading(2, "Search"))
    doc.append(Bullets([Item(f"space: {', '.join(str(s) for s in result.space)}"),
                        Item("constraints: " + (", ".join(str(c) for c in result.constraints) or "none")
                             + " (and the campaign's thresholds, on every cell)"),
                        Item(f"sampler: TPE (multivariate), seeded; {result.workers} trial(s) at a time, "
                             f"engine {result.engine}"),
                        Item(f"storage: {result.storage}, study {result.study}")]))
    hist = _plot_history(result, out / "tune-history.png")
    if hist is not None:
        pngs.append(hist)
        doc.append(Figure(hist, "optimisation history: each complete trial, the best feasible so far"))
    imp, why = _importances(study)
    doc.append(Heading(2, "Parameter importances"))
    if imp:
        png = _plot_importances(imp, out / "tune-importances.png")
        if png is not None:
            pngs.append(png)
            doc.append(Figure(png, "parameter importances"))
        doc.append(Table(["parameter", "importance"], [[Cell(k), Cell(f"{v:.3f}")] for k, v in imp.items()],
                         align="lr"))
    else:
        doc.append(Text(f"Not computed: {why}." if why else "Not computed."))
    if result.best_trial is not None:
        trial_dir = out / TRIALS / f"{result.best_trial:05d}"
        doc.append(Heading(2, f"Best trial's campaign (trial {result.best_trial})"))
        try:
            best = load_results(trial_dir)
        except CampaignError as exc:
            doc.append(Text(f"Not available: {exc}"))
        else:
            for p in best.config.profiles:
                doc.append(Heading(3, p.label))
                doc.append(profile_table(best, p.label))
    doc.append(Heading(2, "Trials"))
    ranked = sorted(result.trials, key=lambda t: (t.state != "COMPLETE", not t.feasible,
                                                  (t.value if result.direction == "minimize" else -(t.value or 0))
                                                  if t.value is not None else math.inf, t.number))
    rows = []
    for t in ranked[:20]:
        state = t.state if t.state != "COMPLETE" else ("feasible" if t.feasible else "infeasible")
        rows.append([Cell(str(t.number)), Cell(state, status="pass" if t.feasible else "fail"),
                     Cell(format_number(t.value) if t.value is not None else "—"),
                     Cell(", ".join(f"{k}={v:.4g}" for k, v in t.params.items())),
                     Cell(t.failure or ", ".join(f"{k}: {c:+.3g}" for k, c in t.constraints.items()))])
    doc.append(Text(f"The best 20 of {len(result.trials)} (feasible first, then infeasible, then failed)."))
    doc.append(Table(["trial", "state", result.objective, "parameters", "constraints (<= 0 holds) / why it failed"],
                     rows, align="llrll"))
    doc.append(Heading(2, "Run"))
    doc.append(Bullets([Item(f"this run: {result.trials_run} trial(s), {result.wall_s:.1f} s wall, "
                             f"{result.workers} worker(s), engine {result.engine}")]))
    md, page = out / "tune.md", out / "tune.html"
    md.write_text(render_markdown(doc, out), encoding="utf-8")
    page.write_text(render_html(doc), encoding="utf-8")
    return ReportFiles(md, page, pngs)
