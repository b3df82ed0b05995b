"""The targets fit (:func:`fit_targets`): the Optuna study, its pruning, the best plant and its verification."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil.config import ConfigError
from hil.fit import ranges
from hil.fit._targets_measure import Measured, measure, proposed_controllers
from hil.fit._targets_schema import TargetsConfig, load_targets
from hil.fit._targets_score import (
    PREMISES,
    Residual,
    objective,
    paper_figures,
    partial_objective,
    premise_values,
    residual_markdown,
    residuals,
    target_terms,
)
from hil.study import (
    check_study_name,
    check_trials,
    failed,
    run_study,
    start_study,
    storage_url,
)

if TYPE_CHECKING:
    import optuna

FIT_DIR = Path("runs") / "fit" / "targets"
MAX_JOBS = 64  # trials (or verification cells) at once


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


def _store_measured(config: TargetsConfig, trial: Any, m: Measured) -> None:
    """The trial's measured values, unstable cells and the premises' values (those measured) as user attributes."""
    vals = m.values
    trial.set_user_attr("measured", {k: (v if math.isfinite(v) else None) for k, v in vals.items()})
    trial.set_user_attr("unstable", m.unstable)
    held = 0
    for p in PREMISES:
        x = premise_values(config, vals).get(p.id)
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
        _store_measured(config, trial, m)
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
            _store_measured(config, trial, so_far)
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
    best_value, best = min(((t.value, t) for t in complete if t.value is not None),
                           key=lambda vt: (vt[0], vt[1].number))
    plant_values, ctrl_values = _trial_values(config, best)
    result.best_trial, result.best_value = best.number, float(best_value)
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
            x = premise_values(config, vals).get(p.id)
            if x is not None:
                result.premises.append(PremiseResult(p.id, p.describe(paper_figures(config)), f"{p.sense} {p.bound:g}",
                                                     [x], x, p.holds(x, result.unstable), *search[p.id]))
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
    per_seed_premises = [premise_values(config, {k: v[i] for k, v in m.per_seed.items()}) for i in range(n)]
    mean = premise_values(config, vals)
    for p in PREMISES:
        if p.id not in mean:
            continue
        xs = [d.get(p.id, math.nan) for d in per_seed_premises]
        holds = bool(xs) and all(p.holds(x, m.unstable) for x in xs)
        result.premises.append(PremiseResult(p.id, p.describe(paper_figures(config)), f"{p.sense} {p.bound:g}", xs,
                                             mean[p.id], holds, *search[p.id]))


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
