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
import itertools
import json
import math
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from hil.campaign import CampaignError, load_campaign
from hil.campaign.engines import EngineError, check_options
from hil.campaign.metrics import METRICS, log_health
from hil.campaign.model import CellResult, ControllerEntry
from hil.campaign.runner import cell_sessions, run_campaign
from hil.config import ConfigError, require_writable_dir
from hil.control import registry
from hil.control.registry import effective_params
from hil.log.truth import truth_path
from hil.study import (
    check_study_name,
    check_trials,
    failed,
    run_study,
    start_study,
    storage_url,
    unstable_reason,
)
from hil.tune._report import write_tune_report
from hil.tune._result import TRIALS, TrialInfo, TuneResult
from hil.tune._space import (
    Constraint,
    Objective,
    ParamSpec,
    check_cells,
    parse_constraints,
    parse_objective,
    parse_params,
)

if TYPE_CHECKING:
    import optuna

    from hil.campaign.model import CampaignConfig, CampaignResult, ControllerEntry

__all__ = [
    "tune",
]

TUNE_DIR = Path("runs") / "tune"
MAX_OBJECTIVES = 3  # a multi-objective study's metrics at most
HELDOUT_SEEDS = 3  # seeds after the campaign's own on which the report compares the tuned gains


# --- one trial -------------------------------------------------------------------------------


def choose_controller(config: CampaignConfig, label: str | None) -> ControllerEntry:
    """The campaign's controller entry ``label``; by default the first that is not the baseline."""
    labels = [c.label for c in config.controllers]
    if label is not None:
        for c in config.controllers:
            if c.label == label:
                return c
        raise ConfigError(f"controller={label!r}: not a controller label of campaign {config.name!r} "
                          f"({', '.join(labels)})")
    return next((c for c in config.controllers if c.label != config.baseline), config.controllers[0])


def trial_campaign(config: CampaignConfig, entry: ControllerEntry, params: dict[str, Any]) -> CampaignConfig:
    """The campaign one trial runs: its profiles and seeds, only ``entry`` with ``params`` merged over its own,
    no baseline, acceptance or paper values (one controller has nothing to be compared with)."""

    merged = ControllerEntry(label=entry.label, name=entry.name, params={**entry.params, **params})
    return config.model_copy(update={"controllers": [merged], "baseline": None, "acceptance": [], "paper": {}})


def drive_limit(config: CampaignConfig) -> float:
    """The drive limit (counts) of the trial campaign's one controller."""
    entry = config.controllers[0]
    return float(effective_params({"name": entry.name, "params": entry.params})["u_max_counts"])


def cell_score(cell: CellResult, out_dir: Path, metric: str | None, *, settle_s: float,
               u_max: float | None) -> tuple[float, float | None, float | None]:
    """One cell of a trial -> (its objective value, scored by magnitude for a lag; the fraction of the time the drive
    sat at its limit; the fraction of valid tracking frames). ValueError (one line) when the cell did not complete,
    is unstable (:func:`unstable_reason`) or lacks the metric. ``metric`` None: a cell outside the objective's
    cells (its value NaN). ``u_max`` None: the log is not read."""
    if cell.status == "lost_target":  # the session's own verdict (hil.session.TrackJudge): the rule's words
        raise ValueError(f"cell {cell.cell_id}: lost the target: {cell.message}")
    if cell.status != "completed":
        raise ValueError(f"cell {cell.cell_id}: session {cell.status}: {cell.message}".rstrip(": "))
    sat = valid = None
    if u_max is not None:
        if cell.log is None:
            raise ValueError(f"cell {cell.cell_id}: no log")
        log = Path(cell.log) if Path(cell.log).is_absolute() else out_dir / cell.log
        # the cell's worker read the log already, with the session's own drive limit (the trial's)
        sat, valid = cell.health if cell.health is not None else log_health(log, settle_s, u_max)
        why = unstable_reason(sat, valid)
        if why:
            raise ValueError(f"cell {cell.cell_id}: {why}")
    return (math.nan if metric is None else metric_value(cell, metric)), sat, valid


def metric_value(cell: CellResult, metric: str) -> float:
    """The cell's ``metric`` as a study scores it (a lag by its magnitude: a lead is no better than the same lag);
    ValueError (one line) when the cell lacks it."""
    value = cell.metrics.get(metric, math.nan)
    if not math.isfinite(value):
        raise ValueError(f"cell {cell.cell_id}: {metric} is not available")
    return abs(value) if METRICS[metric].magnitude else float(value)


def evaluate(result: CampaignResult, out_dir: Path, objective: str | Objective, constraints: Sequence[Constraint],
             *, check_logs: bool = True,
             scored: dict[str, tuple[float, float | None, float | None]] | None = None,
             ) -> tuple[float, list[float], dict[str, Any]]:
    """A trial's campaign result -> (objective, constraint values, attributes): :func:`evaluate_all` for one
    objective."""
    values, cons, attrs = evaluate_all(result, out_dir, [objective], constraints, check_logs=check_logs,
                                       scored=scored)
    return values[0], cons, attrs


def evaluate_all(result: CampaignResult, out_dir: Path, objectives: Sequence[str | Objective],
                 constraints: Sequence[Constraint], *, check_logs: bool = True,
                 scored: dict[str, tuple[float, float | None, float | None]] | None = None,
                 ) -> tuple[list[float], list[float], dict[str, Any]]:
    """A trial's campaign result -> (each objective's mean over its cells, constraint values, attributes).
    ValueError (one line) when the trial is unstable or its numbers are missing: the caller scores it as failed.
    ``scored``: the cells already checked by :func:`cell_score` as they finished, by id (their logs are not read
    again)."""

    config: CampaignConfig = result.config
    cells = result.cells
    if len(cells) != len(config.cells()):
        raise ValueError(f"{len(config.cells()) - len(cells)} cell(s) did not run")
    for c in cells:  # the result's own word on each cell, whatever was scored as it ended
        if c.status != "completed":
            raise ValueError(f"cell {c.cell_id}: session {c.status}: {c.message}".rstrip(": "))
    u_max = drive_limit(config) if check_logs else None
    goals = [parse_objective(o) for o in objectives]
    scores = [(scored or {}).get(c.cell_id) or cell_score(c, out_dir, None, settle_s=config.settle_s, u_max=u_max)
              for c in cells]
    attrs: dict[str, Any] = {}
    if check_logs:
        attrs["saturated_frac"] = max(s[1] for s in scores if s[1] is not None)
        valids = [s[2] for s in scores if s[2] is not None]
        if valids:
            attrs["track_valid_frac"] = min(valids)

    def values(metric: str, judged: Constraint) -> list[float]:
        out = []
        for c in cells:
            if not judged.covers(c.profile):
                continue
            v = c.metrics.get(metric, math.nan)
            if not math.isfinite(v):
                raise ValueError(f"cell {c.cell_id}: {metric} is not available")
            out.append(float(v))
        return out

    means = []
    for goal in goals:
        judged = [metric_value(c, goal.metric) for c in cells if goal.covers(c.profile)]
        means.append(sum(judged) / len(judged))
    attrs["cells"] = {c.cell_id: c.metrics.get(goals[0].metric) for c in cells if goals[0].covers(c.profile)}
    every = list(constraints) + [Constraint(m, op, bound) for m, t in config.thresholds.items()  # type: ignore[arg-type]
                                 for op, bound in (("<=", t.max), (">=", t.min)) if bound is not None]
    cons = [c.value(values(c.metric, c)) for c in every]
    attrs["constraint_names"] = [str(c) for c in every]
    return means, cons, attrs


def compare_controllers(config: CampaignConfig, entry: ControllerEntry, tuned_params: dict[str, Any],
                        metrics: Sequence[str | Objective], *, seeds: Sequence[int] | None = None,
                        duration_s: float | None = None, jobs: int = 1, also: Sequence[str] = (),
                        oracle_params: dict[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """One campaign of the baseline, the entries labelled ``also``, ``entry`` with its own parameters (the shipped
    gains), ``entry`` with ``tuned_params`` and the oracle (the plant's true rate; the sim clock's, with
    ``oracle_params`` if given) on ``config``'s cells, or on ``seeds`` at ``duration_s``. Per controller label:
    ``mean`` and ``values`` (per cell) of ``metrics[0]`` (a lag by its magnitude), ``means`` of every metric,
    ``failed`` (cells that did not complete); ``_wall_s``: the campaign's wall time. A metric ``METRIC@GLOB``
    is averaged over the cells whose profile label matches."""
    goals = [parse_objective(m) for m in metrics]
    base = next((c for c in config.controllers if c.label == config.baseline), None)
    others = [c for c in config.controllers if c.label in also and c.label not in (entry.label,)
              and (base is None or c.label != base.label)]
    controllers = [*([base] if base is not None and base.label != entry.label else []), *others, entry,
                   ControllerEntry(label=f"{entry.label} tuned", name=entry.name, params=tuned_params)]
    if "oracle" in {**registry.REGISTRY, **getattr(registry, "SIM_ONLY", {})}:
        controllers.append(ControllerEntry(label="oracle", name="oracle", params=oracle_params or {}))
    update: dict[str, Any] = {"controllers": controllers, "acceptance": [], "paper": {}, "baseline": None,
                              "name": f"{config.name}-compare"}
    if seeds:
        update["seeds"] = list(seeds)
    if duration_s:
        update["duration_s"] = duration_s
    cfg = config.model_copy(update=update)
    with tempfile.TemporaryDirectory(prefix="hil-compare-") as tmp:
        t0 = time.monotonic()
        result = run_campaign(cfg, Path(tmp) / "c", jobs=jobs)
        wall = time.monotonic() - t0
    out: dict[str, dict[str, Any]] = {}
    for c in controllers:
        mine = [x for x in result.cells if x.controller == c.label]

        def mean_of(goal: Objective, cells: list[CellResult] = mine) -> float:
            judged = [cell.metrics.get(goal.metric, math.nan) for cell in cells if goal.covers(cell.profile)]
            v = [abs(x) if METRICS[goal.metric].magnitude else x for x in judged if math.isfinite(x)]
            return sum(v) / len(v) if v and len(v) == len(judged) else math.nan

        first = goals[0]
        out[c.label] = {"mean": mean_of(first),
                        "values": [x.metrics.get(first.metric, math.nan) for x in mine if first.covers(x.profile)],
                        "means": {str(g): mean_of(g) for g in goals},
                        "failed": [x.cell_id for x in mine if x.status != "completed"]}
    out["_wall_s"] = {"mean": wall}
    return out


# --- the study -------------------------------------------------------------------------------


def trial_info(t: optuna.trial.FrozenTrial) -> TrialInfo:
    """A finished (or running) trial as the result lists it; ``value`` the first objective's."""
    done = t.state.name == "COMPLETE" and t.values is not None
    cons = dict(t.constraints)
    return TrialInfo(t.number, t.state.name, t.values[0] if done else None, dict(t.params),
                     all(c <= 0 for c in cons.values()) if done else None, cons, str(t.user_attrs.get("failure", "")),
                     t.duration.total_seconds() if t.duration is not None else None,
                     tuple(t.values) if done else None)


def pareto_front(trials: Sequence[TrialInfo], directions: Sequence[str]) -> list[TrialInfo]:
    """The complete feasible trials no other complete feasible trial dominates (as good on every objective, better
    on one), by trial number."""
    sign = [1.0 if d == "minimize" else -1.0 for d in directions]
    ok = [t for t in trials if t.state == "COMPLETE" and t.feasible and t.values is not None
          and all(math.isfinite(v) for v in t.values)]
    keyed = [(t, [s * v for s, v in zip(sign, t.values or (), strict=True)]) for t in ok]

    def dominated(x: list[float]) -> bool:
        return any(all(a <= b for a, b in zip(y, x, strict=True)) and y != x for _, y in keyed)

    return sorted((t for t, x in keyed if not dominated(x)), key=lambda t: t.number)


def choose_on_front(front: Sequence[TrialInfo], directions: Sequence[str]) -> TrialInfo | None:
    """The point of the front nearest the best of every objective: each objective scaled to 0 (its best on the
    front) .. 1 (its worst), the smallest Euclidean norm (ties: the earlier trial)."""
    if not front:
        return None
    sign = [1.0 if d == "minimize" else -1.0 for d in directions]
    cols = list(zip(*[[s * v for s, v in zip(sign, t.values or (), strict=True)] for t in front], strict=True))
    lo, span = [min(c) for c in cols], [max(c) - min(c) for c in cols]

    def distance(t: TrialInfo) -> float:
        return math.hypot(*((s * v - a) / w if w > 0 else 0.0
                            for s, v, a, w in zip(sign, t.values or (), lo, span, strict=True)))

    return min(front, key=lambda t: (distance(t), t.number))


def _best(trials: list[TrialInfo], direction: str) -> TrialInfo | None:
    ok = [t for t in trials if t.state == "COMPLETE" and t.feasible and t.value is not None
          and math.isfinite(t.value)]
    if not ok:
        return None
    return (min if direction == "minimize" else max)(ok, key=lambda t: (t.value, t.number))


def _space(params: str | Sequence[str] | Sequence[ParamSpec], entry: ControllerEntry) -> list[ParamSpec]:
    """The study's search space: ``params`` as given (every item a :class:`ParamSpec`), else parsed for ``entry``'s
    controller (:func:`parse_params`; a :class:`ParamSpec` among strings as its own text)."""
    if isinstance(params, str):
        return parse_params(params, entry.name, entry.params)
    specs = [p for p in params if isinstance(p, ParamSpec)]
    if specs and len(specs) == len(params):
        return specs
    return parse_params([p if isinstance(p, str) else str(p) for p in params], entry.name, entry.params)


def _engine_options(engine: str, scheduler: str | None, shared_dir: str | Path | None) -> dict[str, Any]:
    """The runner's keyword arguments for the engine, checked by the campaign's own rule
    (:func:`hil.campaign.engines.check_options`, nothing started); without a scheduler the dask engine's address is
    filled in once the study's LocalCluster runs (:func:`_start_cluster`)."""
    try:
        check_options(engine, scheduler=scheduler, shared_dir=shared_dir)
    except EngineError as exc:
        raise ConfigError(str(exc)) from None
    if engine == "local":
        return {"engine": "local"}
    return {"engine": "dask", "scheduler": scheduler, **({} if shared_dir is None else {"shared_dir": str(shared_dir)})}


def _start_cluster(options: dict[str, Any], workers: int) -> Any:
    """The study's LocalCluster (dask engine, no scheduler given): ``workers`` processes of one thread, its
    address put in ``options``; None when there is nothing to start."""
    if options.get("engine") != "dask" or options.get("scheduler") is not None:
        return None
    from distributed import LocalCluster  # noqa: PLC0415  (heavy and optional: only the dask engine needs it)

    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, dashboard_address=None)
    options["scheduler"] = cluster.scheduler_address
    return cluster


def _controller_yaml(entry: ControllerEntry, params: dict[str, Any], note: list[str]) -> str:

    head = ["# hil.config.ControllerConfig: a controller of hil.control's registry (docs/control.md) and its "
            "parameters.",
            *(f"# {line}" for line in note)]
    body = yaml.safe_dump({"name": entry.name, "params": params}, sort_keys=False)
    return "\n".join(head) + "\n" + body


def tune(campaign: CampaignConfig | str | Path, params: str | Sequence[str] | Sequence[ParamSpec], *,
         objective: str | Sequence[str] = "miss_std_px", trials: int = 100, controller: str | None = None,
         constraints: str | Sequence[str | Constraint] | None = None, engine: str = "local",
         scheduler: str | None = None, shared_dir: str | Path | None = None, workers: int = 1, jobs: int = 1,
         storage: str | None = None,
         study: str | None = None, resume: bool = False, out: str | Path | None = None,
         write_profile: str | Path | None = None, seed: int = 0, keep_logs: bool = False,
         write_report: bool = True, on_trial: Callable[[TrialInfo], None] | None = None,
         prune: bool = True, warm_start: bool = True, heldout_seeds: int = HELDOUT_SEEDS,
         heldout_duration_s: float | None = None) -> TuneResult:
    """Tune one controller of ``campaign`` with Optuna (TPE, seeded): ``trials`` trials in total in the study
    (``resume`` runs only those still missing), ``workers`` at a time (threads; each trial runs its cells ``jobs``
    at a time through the campaign runner, or on the dask ``engine``: a LocalCluster of ``workers`` started for
    the study, or ``scheduler``'s cluster; ``shared_dir``: a directory the workers share with this process). The
    objective (mean of ``objective`` over the campaign's profiles and seeds; ``metric@GLOB``: over the cells whose
    profile label matches the glob) is minimised; ``constraints`` (``metric<=value[@GLOB]``: on every cell, or on
    the matching ones) and the campaign's thresholds must hold.

    ``params``: ``"name=low..high[:log|:int], ..."`` (:func:`parse_params`). ``controller``: the campaign's
    controller label (default: the first that is not the baseline). ``out``: default ``runs/tune/STUDY``;
    ``storage``: an SQLAlchemy URL (default SQLite ``OUT/tune.db``); ``study``: default the campaign's name.
    Writes ``OUT/NAME-tuned.yaml`` (and ``write_profile``) from the best feasible trial, and the report.
    ``on_trial``: called after every trial of this run. ``prune``: a trial reports the running mean of the objective
    after each cell and stops once it trails the best trial over the same cells by more than 25 %
    (:class:`hil.tune._prune.CellPruner`); a cell that fails or is unstable fails the trial at once either way.
    ``warm_start``: a new study's first trial is the entry's own parameters (the shipped gains, moved into the
    space's ranges). ``heldout_seeds`` (0: none): the shipped, the tuned and the oracle's gains (with the
    baseline) are compared on that many seeds after the campaign's own, at ``heldout_duration_s`` (default the
    campaign's), for the report. ConfigError (one line) for bad input or an existing study without ``resume``."""


    try:
        config = load_campaign(campaign) if isinstance(campaign, str | Path) else campaign
    except CampaignError as exc:
        raise ConfigError(str(exc)) from None
    goals = [parse_objective(o) for o in ([objective] if isinstance(objective, str | Objective) else objective)]
    if not 1 <= len(goals) <= MAX_OBJECTIVES:
        raise ConfigError(f"objective: give 1 to {MAX_OBJECTIVES} metrics (got {len(goals)})")
    goal, multi = goals[0], len(goals) > 1
    check_trials(trials)
    if not 1 <= workers <= 256 or not 1 <= jobs <= 64:
        raise ConfigError(f"workers={workers} / jobs={jobs}: need 1..256 and 1..64")
    entry = choose_controller(config, controller)
    space = _space(params, entry)
    cons = parse_constraints(constraints)
    check_cells([*goals, *cons], [p.label for p in config.profiles], f"campaign {config.name!r}")
    study_name = check_study_name(study or config.name)
    out_dir = Path(out) if out is not None else TUNE_DIR / study_name
    require_writable_dir(out_dir, "out")
    if write_profile is not None and Path(write_profile).is_dir():
        raise ConfigError(f"write_profile={str(write_profile)!r}: a directory (give the YAML file's path)")
    directions = ["minimize" if METRICS[g.metric].lower_is_better else "maximize" for g in goals]
    direction = directions[0]
    try:  # every cell of a trial, before anything is written
        cell_sessions(trial_campaign(config, entry, {}), out_dir / TRIALS / "probe")
    except (CampaignError, ValueError) as exc:
        raise ConfigError(f"{config.name}: {' '.join(str(exc).split())}") from None

    kwargs = _engine_options(engine, scheduler, shared_dir)

    out_dir.mkdir(parents=True, exist_ok=True)
    url = storage_url(storage, out_dir)
    meta = {"campaign": config.name, "controller_label": entry.label, "controller": entry.name,
            "objective": str(goal) if not multi else [str(g) for g in goals], "space": [str(s) for s in space]}
    import optuna  # noqa: PLC0415  (heavy (Optuna, SQLAlchemy): loaded only when a study runs)

    from hil.tune._prune import PRUNE_MARGIN, CellPruner  # noqa: PLC0415  (subclasses Optuna's pruner: heavy, as above)

    shipped = effective_params({"name": entry.name, "params": entry.params})
    first = {s.name: s.clip(shipped[s.name]) for s in space if shipped.get(s.name) is not None} if warm_start else None
    run = start_study(study_name, url, trials=trials, resume=resume, direction=directions, meta=meta, seed=seed,
                      startup_trials=min(10, max(2, trials // 10)), first_params=first,
                      pruner=CellPruner() if prune and not multi else None)  # Optuna prunes one objective only
    st, todo = run.study, run.todo
    cell_ids = [spec.cell_id for spec in trial_campaign(config, entry, {}).cells()  # the objective's cells, in the
                if goal.covers(spec.profile.label)]                                # order they report in

    lock = threading.Lock()

    def objective_fn(trial: optuna.Trial) -> float | tuple[float, ...]:
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
            scored: dict[str, tuple[float, float | None, float | None]] = {}
            reported = [0]  # cells reported so far, a prefix of cell_ids
            u_max = drive_limit(cfg)

            def on_cell(cell: CellResult) -> None:  # score each cell as it ends; report the running mean in order
                metric = goal.metric if goal.covers(cell.profile) and not multi else None
                scored[cell.cell_id] = cell_score(cell, trial_dir, metric, settle_s=cfg.settle_s, u_max=u_max)
                if multi:
                    return
                done = sum(1 for _ in itertools.takewhile(scored.__contains__, cell_ids))
                for step in range(reported[0], done):
                    mean = sum(scored[c][0] for c in cell_ids[:step + 1]) / (step + 1)
                    trial.report(mean, step)
                    reported[0] = step + 1
                    if step + 1 < len(cell_ids) and trial.should_prune():
                        trial.set_user_attr("failure", f"pruned after {step + 1} of {len(cell_ids)} cells: mean "
                                            f"{goal} {mean:.4g}, over {100 * PRUNE_MARGIN:.0f} % behind the "
                                            "best trial's on those cells")
                        raise optuna.TrialPruned()

            result = run_campaign(cfg, trial_dir, jobs=jobs, on_cell=on_cell, **kwargs)
            means, cvals, attrs = evaluate_all(result, trial_dir, goals, cons, scored=scored)
        except optuna.TrialPruned:
            trial.set_user_attr("wall_s", time.monotonic() - t0)
            raise
        except Exception as exc:  # an unstable or broken trial is a failed trial, never the study's end
            return failed(trial, exc, t0)
        finally:
            if not keep_logs and trial_dir.exists():

                for log in trial_dir.rglob("*.h5"):
                    log.unlink(missing_ok=True)
                    truth_path(log).unlink(missing_ok=True)  # the sim clock's truth file beside it
        for key, v in attrs.items():
            trial.set_user_attr(key, v)
        for name, v in zip(attrs["constraint_names"], cvals, strict=True):
            trial.set_constraint(name, v)  # TPE: feasible when every value is <= 0
        trial.set_user_attr("wall_s", time.monotonic() - t0)
        return tuple(means) if multi else means[0]

    def callback(s: optuna.Study, frozen: optuna.trial.FrozenTrial) -> None:
        if on_trial is None:
            return
        with lock:
            on_trial(trial_info(frozen))

    cluster = _start_cluster(kwargs, workers) if todo else None
    try:
        wall = run_study(run, objective_fn, n_jobs=workers, callbacks=[callback])
    finally:
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close()
    infos = [trial_info(t) for t in st.get_trials(deepcopy=False)]
    result = TuneResult(study=study_name, storage=url, out_dir=out_dir, campaign=config.name,
                        controller_label=entry.label, controller=entry.name, objective=str(goal),
                        direction=direction, space=space, constraints=cons, trials=infos, trials_run=todo,
                        wall_s=wall, engine=engine, workers=workers, objectives=[str(g) for g in goals],
                        directions=directions)
    if multi:
        front = pareto_front(infos, directions)
        result.pareto = [t.number for t in front]
        best = choose_on_front(front, directions)
    else:
        best = _best(infos, direction)
    if best is not None:
        result.best_trial, result.best_value, result.best_params = best.number, best.value, best.params
        result.best_values = [v for v in (best.values or (best.value,)) if v is not None]
        result.params = {**entry.params, **best.params}
        scores = ", ".join(f"mean {g} {v:.6g}" for g, v in zip(goals, result.best_values, strict=True))
        how = (f"the point of the Pareto front ({len(result.pareto)} trials) nearest the best of every objective; "
               if multi else "")
        note = [f"Tuned by `hil tune` (study {study_name!r}, trial {best.number} of {len(infos)}): {how}{scores} "
                f"over the profiles and seeds of campaign {config.name!r}, {entry.label}.",
                "Empty params = the registry's defaults; these override them."]
        text = _controller_yaml(entry, result.params, note)
        result.yaml_path = out_dir / f"{entry.name}-tuned.yaml"
        result.yaml_path.write_text(text)
        if write_profile is not None:
            result.profile_path = Path(write_profile)
            result.profile_path.parent.mkdir(parents=True, exist_ok=True)
            result.profile_path.write_text(text)
        (out_dir / "best.json").write_text(json.dumps({"trial": best.number, "value": best.value,
                                                      "values": result.best_values, "params": result.params,
                                                      **({"pareto": result.pareto} if multi else {})}, indent=2))
    if best is not None and heldout_seeds > 0:
        first_seed = max(config.seeds) + 1
        result.heldout_seeds = list(range(first_seed, first_seed + heldout_seeds))
        result.heldout_duration_s = heldout_duration_s or config.duration_s
        result.heldout = compare_controllers(config, entry, result.params or {}, goals, seeds=result.heldout_seeds,
                                             duration_s=result.heldout_duration_s, jobs=max(jobs, workers))
    if write_report:
        result.report = write_tune_report(result, st)
    return result
