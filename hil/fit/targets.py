"""The paper's platform as a fitted preset: the plant (and the KF / high-gain observer defaults) fitted to a paper's
published figures (:func:`fit_targets`, docs/emulator.md, paper-000).

A targets file (:class:`TargetsConfig`, e.g. ``profiles/targets/seed-000.yaml``) lists each published figure with
the campaign cell that measures it (campaign file, profile label, controller label, metric). A trial of the search
draws the plant parameters of :data:`hil.fit.ranges.PLAUSIBLE` (and the controller parameters the file names), runs
every measuring cell on the ``sim`` clock as its campaign would (the campaign's own session, overrides and metrics:
:func:`hil.campaign.runner.cell_session` and :func:`hil.campaign.runner.run_cell`, in a warm worker process), and
scores the weighted sum of squared log ratios ``sum w_i log(fitted_i / paper_i)^2``. A ratio is clipped to
``[1/10, 10]``: a missing metric (a session that faulted) or a non-positive one (a lead where the paper has a lag)
counts as a factor 10 off, so the sampler still learns from it. Each trial also stores the paper's premises
(:data:`PREMISES`) as user attributes, so the study itself shows how close to each premise the search came.
Trials run ``jobs`` at a time. A trial stops early (pruned) once the targets measured so far already sum to more than
the best complete trial's objective: every term is a square, so the rest can only add to it, and a pruned trial could
never have been the best (docs/emulator.md, "The paper's platform as a fitted preset", Method).

The study is Optuna's (TPE, seeded, multivariate) in an RDB storage (SQLite by default), resumable; the
storage, heartbeat and quiet-failure helpers are :mod:`hil.tune`'s. The best trial's plant is written with
:func:`hil.fit.ranges.dump_plant`, then measured again on the verification seeds at each campaign's full duration:
those numbers make the residual table.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from hil.campaign.metrics import METRICS
from hil.campaign.model import ControllerEntry
from hil.campaign.runner import cell_session, load_campaign, run_cell
from hil.config import ConfigError, load_model, one_line, resolve_relative
from hil.control.registry import controller_params
from hil.fit import ranges
from hil.session import emulator_for_plant
from hil.tune import (
    check_study_name,
    check_trials,
    failed,
    run_study,
    start_study,
    storage_url,
    unstable_reason,
)

if TYPE_CHECKING:
    import optuna

__all__ = [
    "PREMISES",
    "Measured",
    "Premise",
    "Residual",
    "Target",
    "TargetsConfig",
    "TargetsResult",
    "fit_targets",
    "load_targets",
    "measure",
    "objective",
    "premise_values",
    "residual_markdown",
    "residuals",
]

FIT_DIR = Path("runs") / "fit" / "targets"
RATIO_CLIP = 10.0  # a target off by more than this factor (or missing) scores as this factor
MAX_JOBS = 64  # trials (or verification cells) at once


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Cell(_Strict):
    """A campaign cell: which campaign, which profile and controller (labels as the campaign names them)."""

    campaign: Path = Field(description="a campaign YAML (relative to the targets file)")
    profile: str = Field(min_length=1, description="the campaign's profile label")
    controller: str = Field(min_length=1, description="the campaign's controller label")

    _rel = field_validator("campaign", mode="before")(resolve_relative)


class Target(Cell):
    """One published figure and the metric of the cell that measures it."""

    id: str = Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")
    kind: Literal["metric"] = Field("metric", description="metric: one campaign metric, mean over the seeds")
    figure: str = Field("", description="where the paper shows it")
    metric: str
    paper: float = Field(gt=0, description="the paper's value (positive: the residual is a log ratio)")
    weight: float = Field(1.0, ge=0)
    tolerance: float = Field(1.5, gt=1, description="the factor the fitted twin is held to")

    @field_validator("metric")
    @classmethod
    def _known_metric(cls, v: str) -> str:

        if v not in METRICS:
            raise ValueError(f"unknown metric {v!r}")
        return v


class Measurement(Cell):
    """A cell measured beside the targets (a premise needs it); ``gain_from``: its observer bandwidth is that
    controller parameter's value (e.g. plain ESO at the high-gain omega_o)."""

    id: str = Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")
    gain_from: str | None = None


class ControllerParam(_Strict):
    """A controller parameter the fit searches: ``fields`` of every controller in ``controllers`` set to one value."""

    name: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")
    fields: list[str] = Field(min_length=1)
    controllers: list[str] = Field(min_length=1)
    low: float = Field(gt=0)
    high: float = Field(gt=0)
    log: bool = False
    default: float = Field(gt=0, description="the shipped value (the search's first trial)")

    @model_validator(mode="after")
    def _check(self) -> ControllerParam:

        if not self.low < self.high:
            raise ValueError(f"high: the range {self.low:g}..{self.high:g} is empty")
        if not self.low <= self.default <= self.high:
            raise ValueError(f"default: {self.default:g} is outside {self.low:g}..{self.high:g}")
        for c in self.controllers:
            for end in (self.low, self.high):
                controller_params(c, dict.fromkeys(self.fields, end))  # one line naming the field if not
        return self


class Search(_Strict):
    ranges: Literal["plausible", "draw"] = Field("plausible", description="PLAUSIBLE's full range or its draw range")
    plant_params: Literal["all"] | list[str] = "all"
    controller_params: list[ControllerParam] = Field(default_factory=list)

    @field_validator("plant_params")
    @classmethod
    def _known(cls, v: Any) -> Any:
        if isinstance(v, list):
            for name in v:
                if name not in ranges.BY_NAME:
                    raise ValueError(f"unknown plant parameter {name!r} (hil.fit.ranges.PLAUSIBLE)")
        return v

    def plant_ranges(self) -> list[ranges.ParamRange]:
        return list(ranges.PLAUSIBLE) if self.plant_params == "all" else [ranges.BY_NAME[n] for n in self.plant_params]

    def bounds(self, p: ranges.ParamRange) -> tuple[float, float]:
        return p.draw_range if self.ranges == "draw" else (p.lo, p.hi)


class Seeds(_Strict):
    seeds: list[int] = Field(min_length=1)
    duration_s: float | None = Field(None, gt=0, description="cap on every session's duration (None: the campaign's)")


class TargetsConfig(_Strict):
    """A targets file: the paper's figures, each with the campaign cell that measures it, and the search."""

    name: str = Field(pattern=r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$")
    source: str = ""
    plant: Path = Field(description="the base plant YAML (relative to this file)")
    trial: Seeds = Seeds(seeds=[1], duration_s=9.0)
    verify: Seeds = Seeds(seeds=[1, 2, 3])
    search: Search = Search()
    measurements: list[Measurement] = Field(default_factory=list)
    targets: list[Target] = Field(min_length=1)

    _rel = field_validator("plant", mode="before")(resolve_relative)

    @model_validator(mode="after")
    def _check(self) -> TargetsConfig:
        ids = [t.id for t in self.targets] + [m.id for m in self.measurements]
        for i, x in enumerate(ids):
            if x in ids[:i]:
                raise ValueError(f"id {x!r} is given twice")
        names = {p.name for p in self.search.controller_params}
        for i, m in enumerate(self.measurements):
            if m.gain_from is not None and m.gain_from not in names:
                raise ValueError(f"measurements.{i}.gain_from: {m.gain_from!r} is not a search.controller_params name")
        return self


def load_targets(path: str | Path) -> TargetsConfig:
    """A targets file, validated; every campaign it names is readable and has the profile and controller labels.
    ValueError with one line naming the file and the field."""

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such targets file")
    try:
        config = load_model(TargetsConfig, path)
    except ConfigError as exc:
        raise ValueError(str(exc)) from None
    except ValidationError as exc:  # pragma: no cover - load_model turns these into ConfigError
        raise ValueError(one_line(str(path), exc)) from None
    if not config.plant.is_file():
        raise ValueError(f"{path}: plant: no such file {config.plant}")
    for where, cells in (("targets", config.targets), ("measurements", config.measurements)):
        for i, cell in enumerate(cells):
            try:
                camp = _campaign(cell.campaign)
            except ValueError as exc:
                raise ValueError(f"{path}: {where}.{i}.campaign: {' '.join(str(exc).split())}") from None
            if cell.profile not in [p.label for p in camp.profiles]:
                raise ValueError(f"{path}: {where}.{i}.profile: {cell.profile!r} is not a profile of campaign "
                                 f"{camp.name!r}")
            if cell.controller not in [c.label for c in camp.controllers]:
                raise ValueError(f"{path}: {where}.{i}.controller: {cell.controller!r} is not a controller of "
                                 f"campaign {camp.name!r}")
    return config


_CAMPAIGNS: dict[Path, Any] = {}


def _campaign(path: Path) -> Any:

    if path not in _CAMPAIGNS:
        if not Path(path).is_file():
            raise ValueError(f"no such file {path}")
        _CAMPAIGNS[path] = load_campaign(path)
    return _CAMPAIGNS[path]


# --- measuring -------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Measured:
    """What the cells gave: per target / measurement id the value on each seed (NaN where missing), and the cells
    that were unstable (id -> why)."""

    per_seed: dict[str, list[float]]
    unstable: dict[str, str]
    wall_s: float = 0.0

    def value(self, key: str) -> float:
        xs = [x for x in self.per_seed.get(key, []) if math.isfinite(x)]
        return sum(xs) / len(xs) if xs and len(xs) == len(self.per_seed[key]) else math.nan

    @property
    def values(self) -> dict[str, float]:
        return {k: self.value(k) for k in self.per_seed}


def controller_overrides(config: TargetsConfig, values: Mapping[str, float], controller: str) -> dict[str, Any]:
    """The parameters a cell's controller gets from the searched ``values`` (name -> value)."""
    out: dict[str, Any] = {}
    for p in config.search.controller_params:
        if controller in p.controllers and p.name in values:
            out.update(dict.fromkeys(p.fields, float(values[p.name])))
    return out


def proposed_controllers(config: TargetsConfig, values: Mapping[str, float]) -> dict[str, dict[str, float]]:
    """controller name -> the parameters the fit chose for it."""
    names = sorted({c for p in config.search.controller_params for c in p.controllers})
    return {c: controller_overrides(config, values, c) for c in names}


def _run_cell(cell: Cell, seed: int, *, duration: float | None, params: dict[str, Any], plant_path: Path,
              work: Path) -> tuple[dict[str, float], str]:
    """One cell on the sim clock, in a warm worker (:func:`hil.campaign.runner.run_cell`, as a campaign runs it):
    (its metrics, '' or why it is unstable). :class:`CellInterrupted` if the cell was stopped by a signal."""
    camp = _campaign(cell.campaign)
    if duration is not None and camp.duration_s is not None:
        duration = min(duration, camp.duration_s)
    camp = camp.model_copy(update={"seeds": [seed], "duration_s": duration or camp.duration_s})
    spec = next(s for s in camp.cells() if s.profile.label == cell.profile and s.controller.label == cell.controller)
    entry = spec.controller
    spec = spec.model_copy(update={"controller": ControllerEntry(label=entry.label, name=entry.name,
                                                                 params={**entry.params, **params})})
    out = work / f"{spec.cell_id}-{abs(hash((str(cell.campaign), tuple(params.items())))):x}"
    data = cell_session(camp, spec, out / "cells" / spec.cell_id)
    # without the wire's time: the paper's figures are of its whole loop, whose delay the plant's gyro lag and delay
    # stand for (docs/emulator.md, "The wire"; profiles/emulator/paper-000.yaml)
    emulator = emulator_for_plant(plant_path, work, base=data["emulator"]["config"], wire_time=False)
    data["emulator"] = {**data["emulator"], "config": str(emulator)}
    try:
        result = run_cell(camp, spec, out, session=data)
    finally:
        shutil.rmtree(out, ignore_errors=True)
    if result.status == "interrupted":
        raise CellInterrupted(f"cell {spec.cell_id}: {result.message or 'interrupted'}")
    if result.status == "error":  # a session that cannot run on this plant: no metrics, reported as unstable
        return {}, f"session error: {' '.join(result.message.split())[:200]}"
    if result.health is None:  # no log, or its metrics could not be worked out
        return {}, "; ".join(result.failures)[:200] or f"session {result.status}: no log"
    if result.status != "completed":
        return dict(result.metrics), f"session {result.status}: {result.message}".rstrip(": ")
    return dict(result.metrics), unstable_reason(*result.health)


class CellInterrupted(RuntimeError):
    """A measuring cell was stopped (SIGINT, SIGTERM): the measurement is incomplete."""


def measure(config: TargetsConfig, plant: Mapping[str, Any] | str | Path, controller_values: Mapping[str, float],
            *, seeds: Sequence[int] | None = None, full: bool = False, work_dir: str | Path | None = None,
            ids: Sequence[str] | None = None, jobs: int = 1, first: Mapping[str, float] | None = None,
            on_cell: Callable[[Measured], None] | None = None) -> Measured:
    """Run every cell the targets and measurements need (each once per seed, ``sim`` clock, each in a warm worker
    process, ``jobs`` at a time) on ``plant`` (a plant dict or YAML file) with ``controller_values``
    (search.controller_params name -> value; missing ones keep their ``default``). ``full``: each campaign's own
    duration and ``verify.seeds``; else ``trial.duration_s`` and ``trial.seeds``. ``ids``: only these targets /
    measurements. The cells run in the file's order, the targets' cells before the measurements' (``first``: id ->
    weight; the cells whose ids weigh most run first, the rest in the file's order). ``on_cell``: called
    after each cell (in this thread) with what is measured so far (an id whose cells are all done has its values);
    an exception it raises stops the measurement (cells running finish, none starts) and propagates."""

    t0 = time.monotonic()
    values = {p.name: p.default for p in config.search.controller_params}
    values.update({k: float(v) for k, v in controller_values.items()})
    plan = config.verify if full else config.trial
    seeds = list(seeds) if seeds is not None else list(plan.seeds)
    duration = None if full else plan.duration_s
    own = work_dir is None
    work = Path(tempfile.mkdtemp(prefix="hil-targets-")) if own else Path(work_dir)  # type: ignore[arg-type]
    work.mkdir(parents=True, exist_ok=True)
    try:
        plant_path = Path(plant) if isinstance(plant, str | Path) else ranges.dump_plant(plant, work / "plant.yaml")
        wanted = [*config.targets, *config.measurements]
        if ids is not None:
            wanted = [c for c in wanted if c.id in set(ids)]
        cells: dict[tuple[Any, ...], tuple[Cell, dict[str, Any]]] = {}
        owners: dict[tuple[Any, ...], list[Any]] = {}
        for c in wanted:
            params = controller_overrides(config, values, _campaign_entry(c).name)
            if isinstance(c, Measurement) and c.gain_from is not None:
                params["omega_o_rad_s"] = float(values[c.gain_from])
            key = (str(c.campaign), c.profile, c.controller, tuple(sorted(params.items())))
            cells.setdefault(key, (c, params))
            owners.setdefault(key, []).append(c)
        order = list(cells)
        if first is not None:  # the cells whose targets weigh most first; stable: the file's order otherwise
            order.sort(key=lambda key: -sum(first.get(owner.id, 0.0) for owner in owners[key]))
        runs = [(key, seed) for key in order for seed in seeds]
        got: dict[tuple[Any, ...], dict[int, tuple[dict[str, float], str]]] = {key: {} for key in cells}

        def one(item: tuple[tuple[Any, ...], int]) -> tuple[tuple[Any, ...], int, tuple[dict[str, float], str]]:
            key, seed = item
            cell, params = cells[key]
            return key, seed, _run_cell(cell, seed, duration=duration, params=params, plant_path=plant_path,
                                        work=work)

        def so_far() -> Measured:
            per_seed: dict[str, list[float]] = {}
            unstable: dict[str, str] = {}
            for key, done in got.items():
                if len(done) < len(seeds):
                    continue
                for seed in seeds:
                    metrics, why = done[seed]
                    for owner in owners[key]:
                        metric = owner.metric if isinstance(owner, Target) else "rate_err_el_std_dps"
                        per_seed.setdefault(owner.id, []).append(metrics.get(metric, math.nan))
                        if why:
                            unstable[owner.id] = f"seed {seed}: {why}"
            return Measured(per_seed, unstable, time.monotonic() - t0)

        todo = iter(runs)
        with ThreadPoolExecutor(max_workers=max(1, jobs), thread_name_prefix="hil-measure") as pool:
            # a cell starts only once ``on_cell`` has seen the one before it ended: a stop starts nothing more
            running = {pool.submit(one, item) for item in itertools.islice(todo, max(1, jobs))}
            while running:
                done, running = wait(running, return_when=FIRST_COMPLETED)
                for future in done:
                    key, seed, outcome = future.result()
                    got[key][seed] = outcome
                    if on_cell is not None:
                        on_cell(so_far())
                    running |= {pool.submit(one, item) for item in itertools.islice(todo, 1)}
        measured = so_far()
        measured.per_seed = {c.id: measured.per_seed[c.id] for c in wanted}  # the file's order
        return measured
    finally:
        if own:
            shutil.rmtree(work, ignore_errors=True)


def _campaign_entry(cell: Cell) -> Any:
    camp = _campaign(cell.campaign)
    return next(c for c in camp.controllers if c.label == cell.controller)


# --- scoring ---------------------------------------------------------------------------------------------------------


def clipped_ratio(fitted: float, paper: float) -> float:
    """fitted / paper, clipped to [1/RATIO_CLIP, RATIO_CLIP]; NaN counts as too large, <= 0 as too small."""
    if not math.isfinite(fitted):
        return RATIO_CLIP
    return min(RATIO_CLIP, max(1.0 / RATIO_CLIP, fitted / paper))


def objective(config: TargetsConfig, values: Mapping[str, float]) -> float:
    """sum over the targets of ``weight * log(ratio)^2`` (:func:`clipped_ratio`); ``values``: id -> fitted."""
    return sum(target_terms(config, {t.id: values.get(t.id, math.nan) for t in config.targets}).values())


def partial_objective(config: TargetsConfig, values: Mapping[str, float]) -> float:
    """:func:`objective` over the targets in ``values`` only (those measured so far): a lower bound of the whole
    objective, whose terms are all squares."""
    return sum(target_terms(config, values).values())


@dataclasses.dataclass(frozen=True)
class Premise:
    """One of the paper's premises as a number: ``value`` of the measured ids, which holds when it is ``>= bound``
    (``sense`` ">=") or ``<= bound``; ``unstable_holds``: an unstable ``unstable_id`` cell makes it hold."""

    id: str
    text: str
    sense: Literal[">=", "<="]
    bound: float
    needs: tuple[str, ...]
    value: Callable[[Mapping[str, float]], float]
    unstable_id: str | None = None

    def holds(self, value: float, unstable: Mapping[str, str] | None = None) -> bool:
        if self.unstable_id is not None and unstable and self.unstable_id in unstable:
            return True
        if not math.isfinite(value):
            return False
        return value >= self.bound if self.sense == ">=" else value <= self.bound


def _worst_factor(v: Mapping[str, float]) -> float:
    paper = {"table1-eso-std": 0.32, "table1-esokf-std": 0.17, "table1-hg-std": 0.11, "table2-eso-std": 6.02,
             "table2-hg-std": 2.71, "table3-eso-std": 15.60, "table3-hg-std": 6.15}
    factors = [max(v[k] / p, p / v[k]) if math.isfinite(v.get(k, math.nan)) and v[k] > 0 else math.inf
               for k, p in paper.items()]
    return max(factors)


PREMISES: tuple[Premise, ...] = (
    Premise("a", "gyro noise limits the observer gain: at the high-gain omega_o plain ESO is unstable or its rate "
            "std >= 1.2 x ESO+KF's at that gain", ">=", 1.2, ("eso-high-gain", "table1-hg-std"),
            lambda v: v["eso-high-gain"] / v["table1-hg-std"], unstable_id="eso-high-gain"),
    Premise("b1", "ESO+KF beats ESO at the same gain (rate std ratio ESO+KF / ESO < 1)", "<=", 1.0,
            ("table1-esokf-std", "table1-eso-std"), lambda v: v["table1-esokf-std"] / v["table1-eso-std"]),
    Premise("b2", "high-gain ESO+KF beats ESO+KF (rate std ratio < 1)", "<=", 1.0,
            ("table1-hg-std", "table1-esokf-std"), lambda v: v["table1-hg-std"] / v["table1-esokf-std"]),
    Premise("c", "miss std grows with the swing amplitude (ESO, 3 deg / 1 deg >= 1.5; paper 2.59)", ">=", 1.5,
            ("table3-eso-std", "table2-eso-std"), lambda v: v["table3-eso-std"] / v["table2-eso-std"]),
    Premise("d", "each Table 1-3 std within a factor 1.5 of the paper's (the worst factor)", "<=", 1.5,
            ("table1-eso-std", "table1-esokf-std", "table1-hg-std", "table2-eso-std", "table2-hg-std",
             "table3-eso-std", "table3-hg-std"), _worst_factor),
)


def premise_values(values: Mapping[str, float]) -> dict[str, float]:
    """premise id -> its value, for every premise whose ids were measured (NaN where a value is missing)."""
    out = {}
    for p in PREMISES:
        if all(k in values for k in p.needs):
            try:
                x = p.value(values)
            except ZeroDivisionError:
                x = math.nan
            out[p.id] = float(x) if math.isfinite(x) or x == math.inf else math.nan
    return out


@dataclasses.dataclass(frozen=True)
class Residual:
    id: str
    figure: str
    what: str
    paper: float
    fitted: float
    ratio: float
    tolerance: float

    @property
    def within(self) -> bool:
        return math.isfinite(self.ratio) and self.ratio > 0 and max(self.ratio, 1 / self.ratio) <= self.tolerance


def residuals(config: TargetsConfig, values: Mapping[str, float]) -> list[Residual]:
    out = []
    for t in config.targets:
        f = values.get(t.id, math.nan)
        out.append(Residual(t.id, t.figure, f"{t.controller}, {t.profile}: {t.metric}", t.paper, f,
                            f / t.paper if math.isfinite(f) else math.nan, t.tolerance))
    return out


def residual_markdown(rows: Sequence[Residual]) -> str:
    lines = ["| target | figure | measured as | paper | fitted twin | ratio | within |",
             "| --- | --- | --- | ---: | ---: | ---: | --- |"]
    for r in rows:
        lines.append(f"| {r.id} | {r.figure} | {r.what} | {r.paper:g} | {r.fitted:.4g} | {r.ratio:.2f} | "
                     f"{'yes' if r.within else 'no'} (x{r.tolerance:g}) |")
    return "\n".join(lines) + "\n"


# --- the study -------------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class PremiseResult:
    id: str
    text: str
    bound: str
    values: list[float]  # per verification seed (premise on that seed's numbers)
    value: float  # on the mean over the seeds
    holds: bool  # on every seed
    search_best: float | None  # the best value any trial reached
    search_best_trial: int | None
    search_held_trials: int  # trials on which it held


@dataclasses.dataclass
class TargetsResult:
    """A targets fit: the study, the best trial, the written plant, the verification's residuals and premises."""

    targets: str
    study: str
    storage: str
    out_dir: Path
    plant_path: Path | None
    residuals_path: Path | None
    trials: int
    complete: int
    failed: int
    trials_run: int
    wall_s: float
    pruned: int = 0
    best_trial: int | None = None
    best_value: float | None = None
    plant_params: dict[str, float] = dataclasses.field(default_factory=dict)
    controller_params: dict[str, float] = dataclasses.field(default_factory=dict)
    controllers: dict[str, dict[str, float]] = dataclasses.field(default_factory=dict)
    verify_objective: float | None = None
    residuals: list[Residual] = dataclasses.field(default_factory=list)
    premises: list[PremiseResult] = dataclasses.field(default_factory=list)
    measured: dict[str, list[float]] = dataclasses.field(default_factory=dict)
    unstable: dict[str, str] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["out_dir"] = str(self.out_dir)
        d["plant_path"] = None if self.plant_path is None else str(self.plant_path)
        d["residuals_path"] = None if self.residuals_path is None else str(self.residuals_path)
        return json.loads(json.dumps(d, default=str, allow_nan=True))


def target_terms(config: TargetsConfig, values: Mapping[str, float]) -> dict[str, float]:
    """Each measured target's term of :func:`objective` (id -> ``weight * log(ratio)^2``)."""
    return {t.id: t.weight * math.log(clipped_ratio(values[t.id], t.paper)) ** 2 for t in config.targets
            if t.id in values}


def mean_terms(config: TargetsConfig, study: Any) -> dict[str, float]:
    """Each target's mean term over the study's finished trials that measured it: the cells whose targets are
    usually furthest off run first, so a trial that cannot beat the best is found out after fewer cells."""
    sums: dict[str, float] = {}
    counts: dict[str, int] = {}
    for trial in study.get_trials(deepcopy=False):
        measured = trial.user_attrs.get("measured") or {}
        values = {k: (math.nan if v is None else float(v)) for k, v in measured.items()}
        for key, term in target_terms(config, values).items():
            sums[key] = sums.get(key, 0.0) + term
            counts[key] = counts.get(key, 0) + 1
    return {key: sums[key] / counts[key] for key in sums}


def default_jobs() -> int:
    """Trials at once by default: one per CPU this process may use."""
    return max(1, min(MAX_JOBS, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else
                      os.cpu_count() or 1))


def best_complete_value(study: Any) -> float | None:
    """The lowest finite objective of the study's complete trials (None before the first)."""
    from optuna.trial import TrialState  # noqa: PLC0415  (heavy (Optuna, SQLAlchemy): loaded only when a study runs)

    values = [t.value for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
              if t.value is not None and math.isfinite(t.value)]
    return min(values) if values else None


def _store_measured(trial: Any, m: Measured) -> None:
    """The trial's measured values, unstable cells and the premises' values (those measured) as user attributes."""
    vals = m.values
    trial.set_user_attr("measured", {k: (v if math.isfinite(v) else None) for k, v in vals.items()})
    trial.set_user_attr("unstable", m.unstable)
    held = 0
    for p in PREMISES:
        x = premise_values(vals).get(p.id)
        if x is None:
            continue
        ok = p.holds(x, m.unstable)
        held += ok
        trial.set_user_attr(f"premise_{p.id}", x if math.isfinite(x) else None)
        trial.set_user_attr(f"premise_{p.id}_holds", ok)
    trial.set_user_attr("premises_held", held)


def _trial_values(config: TargetsConfig, trial: Any) -> tuple[dict[str, float], dict[str, float]]:
    names = {p.name for p in config.search.controller_params}
    plant = {k: float(v) for k, v in trial.params.items() if k not in names}
    ctrl = {k: float(v) for k, v in trial.params.items() if k in names}
    return plant, ctrl


def _first_trial(config: TargetsConfig, base: Mapping[str, Any]) -> dict[str, float]:
    """The base plant's own values (clipped into the searched ranges) and the shipped controller defaults."""
    out: dict[str, float] = {}
    for p in config.search.plant_ranges():
        lo, hi = config.search.bounds(p)
        v = ranges.get_param(base, p.name)
        if v is not None:
            out[p.name] = min(hi, max(lo, float(v)))
    out.update({p.name: p.default for p in config.search.controller_params})
    return out


def fit_targets(targets_path: str | Path, *, out_plant: str | Path, trials: int = 100, storage: str | None = None,
                study: str | None = None, seed: int = 0, resume: bool = False,
                progress: Callable[[str], None] | None = None, out_dir: str | Path | None = None,
                timeout_s: float | None = None, verify: bool = True, jobs: int | None = None,
                prune: bool = True) -> TargetsResult:
    """Fit a plant (and the searched controller parameters) to a paper's published figures.

    ``targets_path``: a :class:`TargetsConfig` YAML. An Optuna study (TPE, seeded with ``seed``) of ``trials`` trials
    in all (``resume`` runs only those still missing; ``timeout_s`` stops this run earlier), stored in ``storage`` (an
    SQLAlchemy URL; default SQLite ``OUT/targets.db``, ``OUT`` = ``out_dir`` or ``runs/fit/targets/STUDY``); ``study``
    defaults to the targets file's name. Each trial runs the measuring cells on the ``sim`` clock with the file's
    trial seeds and durations and minimises :func:`objective`; the premises' values are stored on it. The best
    trial's plant goes to ``out_plant`` (YAML with a header saying how it was made); with ``verify`` it is measured
    again on the verification seeds at full duration, and ``OUT/residuals.md`` holds the residual table and the
    premises. ``jobs`` trials run at once (default: one per CPU), each cell in a warm worker process; the
    verification runs ``jobs`` cells at once. ``prune``: a trial stops once its targets so far sum to more than the
    best complete trial's objective (:func:`partial_objective`). ``progress`` gets one line per trial. ValueError
    (one line) for bad input (a missing or invalid targets file, an unknown target kind or metric, an existing study
    without ``resume``)."""
    config = load_targets(targets_path)
    check_trials(trials)
    jobs = default_jobs() if jobs is None else jobs
    if not 1 <= jobs <= MAX_JOBS:
        raise ConfigError(f"jobs={jobs}: need 1..{MAX_JOBS}")
    study_name = check_study_name(study or config.name)
    out_plant = Path(out_plant)
    if out_plant.is_dir():
        raise ValueError(f"out_plant={str(out_plant)!r}: a directory (give the plant YAML's path)")
    out = Path(out_dir) if out_dir is not None else FIT_DIR / study_name
    out.mkdir(parents=True, exist_ok=True)
    url = f"sqlite:///{(out / 'targets.db').absolute()}" if storage is None else storage_url(storage, out)
    base = ranges.load_plant_dict(config.plant)
    space = config.search.plant_ranges()
    meta = {"targets": config.name, "ranges": config.search.ranges, "space": [p.name for p in space]
            + [p.name for p in config.search.controller_params]}
    run = start_study(study_name, url, trials=trials, resume=resume, direction="minimize", meta=meta, seed=seed,
                      startup_trials=min(20, max(2, trials // 10)), constant_liar=True,
                      first_params=_first_trial(config, base))
    st, todo = run.study, run.todo
    trials_dir = out / "trials"
    from optuna import TrialPruned  # noqa: PLC0415  (heavy (Optuna, SQLAlchemy): loaded only when a study runs)

    so_far_t0: dict[int, float] = {}  # trial number -> when it started

    def objective_fn(trial: optuna.Trial) -> float:
        values: dict[str, float] = {}
        for p in space:
            lo, hi = config.search.bounds(p)
            values[p.name] = trial.suggest_float(p.name, lo, hi, log=p.log)
        ctrl = {p.name: trial.suggest_float(p.name, p.low, p.high, log=p.log)
                for p in config.search.controller_params}
        work = trials_dir / f"{trial.number:05d}"
        t0 = so_far_t0[trial.number] = time.monotonic()
        try:
            plant = ranges.apply_params(base, values)
            try:
                ranges.validate_plant(plant)
            except ValueError as exc:
                raise ValueError(f"plant: {' '.join(str(exc).split())[:300]}") from None
            m = measure(config, plant, ctrl, work_dir=work, first=mean_terms(config, st) if prune else None,
                        on_cell=lambda so_far: check_bound(trial, so_far))
        except TrialPruned:
            raise
        except Exception as exc:  # an invalid plant or a broken trial is a failed trial, never the study's end
            return failed(trial, exc)
        finally:
            shutil.rmtree(work, ignore_errors=True)
        _store_measured(trial, m)
        trial.set_user_attr("wall_s", time.monotonic() - t0)
        return objective(config, m.values)

    def check_bound(trial: optuna.Trial, so_far: Measured) -> None:
        """Prune ``trial`` once the targets measured so far sum to more than the best complete trial's objective."""
        bound = partial_objective(config, so_far.values)
        trial.report(bound, step=len(so_far.per_seed))
        if not prune:
            return
        best = best_complete_value(st)
        if best is not None and bound > best:
            _store_measured(trial, so_far)
            trial.set_user_attr("pruned", f"{bound:.4g} after {len(so_far.per_seed)} ids > best {best:.4g}")
            trial.set_user_attr("wall_s", time.monotonic() - so_far_t0[trial.number])
            raise TrialPruned(f"the targets so far sum to {bound:.4g}, more than the best trial's {best:.4g}")

    def callback(s: optuna.Study, t: optuna.trial.FrozenTrial) -> None:
        if progress is None:
            return
        try:
            best = f"{s.best_value:.4g} (trial {s.best_trial.number})"
        except ValueError:
            best = "-"
        if t.state.name == "COMPLETE":
            progress(f"trial {t.number}: objective {t.value:.4g}, premises held {t.user_attrs.get('premises_held')}"
                     f"/{len(PREMISES)}, {t.user_attrs.get('wall_s', 0):.1f} s; best {best}")
        elif t.state.name == "PRUNED":
            progress(f"trial {t.number}: pruned: {t.user_attrs.get('pruned', '')}; best {best}")
        else:
            progress(f"trial {t.number}: {t.state.name.lower()}: {t.user_attrs.get('failure', '')}; best {best}")

    wall = run_study(run, objective_fn, n_jobs=jobs, timeout_s=timeout_s, callbacks=[callback])
    all_trials = st.get_trials(deepcopy=False)
    complete = [t for t in all_trials if t.state.name == "COMPLETE" and t.value is not None and math.isfinite(t.value)]
    result = TargetsResult(targets=str(targets_path), study=study_name, storage=url, out_dir=out, plant_path=None,
                           residuals_path=None, trials=len(all_trials), complete=len(complete),
                           failed=sum(t.state.name == "FAIL" for t in all_trials),
                           pruned=sum(t.state.name == "PRUNED" for t in all_trials), trials_run=todo, wall_s=wall)
    if not complete:
        return result
    best = min(complete, key=lambda t: (t.value, t.number))
    plant_values, ctrl_values = _trial_values(config, best)
    result.best_trial, result.best_value = best.number, float(best.value)
    result.plant_params, result.controller_params = plant_values, ctrl_values
    result.controllers = proposed_controllers(config, {**{p.name: p.default for p in config.search.controller_params},
                                                       **ctrl_values})
    plant = ranges.apply_params(base, plant_values)
    header = _header(config, targets_path, out_plant, result, study=study_name, url=url)
    result.plant_path = ranges.dump_plant(plant, out_plant, header)
    search = _search_premises(all_trials)
    if verify:
        m = measure(config, plant, ctrl_values, full=True, jobs=jobs)
        _fill_verification(config, result, m, search)
    else:  # the best trial's own numbers (trial seeds and durations)
        vals = {k: (math.nan if v is None else float(v)) for k, v in best.user_attrs.get("measured", {}).items()}
        result.residuals = residuals(config, vals)
        result.unstable = dict(best.user_attrs.get("unstable", {}))
        for p in PREMISES:
            x = premise_values(vals).get(p.id)
            if x is not None:
                result.premises.append(PremiseResult(p.id, p.text, f"{p.sense} {p.bound:g}", [x], x,
                                                     p.holds(x, result.unstable), *search[p.id]))
    result.residuals_path = out / "residuals.md"
    result.residuals_path.write_text(summary_markdown(result))
    (out / "result.json").write_text(json.dumps(result.to_json(), indent=2, default=str))
    return result


def _header(config: TargetsConfig, targets_path: str | Path, out_plant: Path, result: TargetsResult, *, study: str,
            url: str) -> str:
    ctrl = ", ".join(f"{k} {v:.4g}" for k, v in result.controller_params.items())
    n = len(config.search.plant_ranges())
    what = "every hil.fit.ranges.PLAUSIBLE parameter" if config.search.plant_params == "all" else \
        f"{n} hil.fit.ranges.PLAUSIBLE parameter{'s' if n > 1 else ''}"
    return "\n".join([
        f"{config.source or config.name}: the plant fitted to the paper's published figures "
        "(docs/emulator.md, paper-000).",
        f"Made by: hil.fit.fit_targets({str(targets_path)!r}, out_plant={str(out_plant)!r}, trials={result.trials})",
        f"(`hil fit` with these targets: seeded Optuna TPE study {study!r}, {url.split(':', 1)[0]} storage; best of "
        f"{result.complete} complete trials: trial {result.best_trial}).",
        f"Objective: sum over the targets of weight * log(fitted / paper)^2 on {len(config.trial.seeds)} seed(s),",
        f"sessions <= {config.trial.duration_s:g} s on the sim clock: {result.best_value:.4g}. Searched: {what} "
        f"over its {config.search.ranges} range{',' if ctrl else '.'}",
        *([f"and the controller parameters {ctrl} (chosen by the same fit)."] if ctrl else []),
        f"Base plant: {config.plant.name}; parameters the fit does not search keep its values.",
        "",
    ])


def _search_premises(all_trials: Sequence[Any]) -> dict[str, tuple[float | None, int | None, int]]:
    out = {}
    for p in PREMISES:
        best, best_n, held = None, None, 0
        for t in all_trials:
            if t.state.name != "COMPLETE":
                continue
            x = t.user_attrs.get(f"premise_{p.id}")
            held += bool(t.user_attrs.get(f"premise_{p.id}_holds"))
            if x is None:
                continue
            if best is None or (x > best if p.sense == ">=" else x < best):
                best, best_n = float(x), t.number
        out[p.id] = (best, best_n, held)
    return out


def _fill_verification(config: TargetsConfig, result: TargetsResult, m: Measured,
                       search: Mapping[str, tuple[float | None, int | None, int]]) -> None:
    vals = m.values
    result.measured = m.per_seed
    result.unstable = m.unstable
    result.verify_objective = objective(config, vals)
    result.residuals = residuals(config, vals)
    n = min(len(v) for v in m.per_seed.values())
    per_seed_premises = [premise_values({k: v[i] for k, v in m.per_seed.items()}) for i in range(n)]
    mean = premise_values(vals)
    for p in PREMISES:
        if p.id not in mean:
            continue
        xs = [d.get(p.id, math.nan) for d in per_seed_premises]
        holds = bool(xs) and all(p.holds(x, m.unstable) for x in xs)
        result.premises.append(PremiseResult(p.id, p.text, f"{p.sense} {p.bound:g}", xs, mean[p.id], holds,
                                             *search[p.id]))


def summary_markdown(result: TargetsResult) -> str:
    """The residual table and the premises (verification seeds) with the search's best value per premise."""
    parts = [f"# {result.study}: fitted to the paper's figures\n",
             f"Study {result.study!r} ({result.storage}): {result.trials} trials, {result.complete} complete, "
             f"{result.failed} failed; best trial {result.best_trial}, objective {result.best_value:.4g} "
             f"(trial seeds and durations); on the verification seeds at full duration "
             f"{result.verify_objective if result.verify_objective is not None else math.nan:.4g}.\n",
             f"Plant: {result.plant_path}. Controllers: "
             + "; ".join(f"{c}: " + ", ".join(f"{k} {v:.4g}" for k, v in ps.items())
                         for c, ps in result.controllers.items()) + "\n",
             f"## Residuals ({'mean over the verification seeds' if result.measured else 'the best trial'})\n",
             residual_markdown(result.residuals),
             "## Premises\n",
             "| premise | holds when | per seed | holds on every seed | search best (trial) | trials where it held |",
             "| --- | --- | --- | --- | --- | ---: |"]
    for p in result.premises:
        seeds = ", ".join(f"{x:.3g}" for x in p.values)
        sb = "-" if p.search_best is None else f"{p.search_best:.3g} ({p.search_best_trial})"
        parts.append(f"| {p.id}: {p.text} | {p.bound} | {seeds} | {'yes' if p.holds else 'no'} | {sb} | "
                     f"{p.search_held_trials} |")
    if result.unstable:
        parts.append("\nUnstable cells: " + "; ".join(f"{k} ({v})" for k, v in result.unstable.items()))
    return "\n".join(parts) + "\n"
