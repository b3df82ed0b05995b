"""The study's report: tune.md and tune.html in the campaign report's style (hil.reporting's document model),
with the optimisation history and the parameters' importances (Optuna's default evaluator, once
MIN_IMPORTANCE_TRIALS trials completed)."""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil.campaign import CampaignError, load_results
from hil.campaign.report import profile_table
from hil.reporting import (
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
    legend_below,
    new_figure,
    render_html,
    render_markdown,
    save_figure,
)
from hil.study import rdb_storage
from hil.tune._result import TRIALS, TuneResult

if TYPE_CHECKING:
    import optuna


def _plot_history(result: TuneResult, path: Path) -> Path | None:

    done = [t for t in result.trials if t.state == "COMPLETE" and t.value is not None]
    if not done:
        return None
    fig, ax = new_figure()
    a = ax[0, 0]
    value = {t.number: t.value for t in done if t.value is not None}
    ok = [t for t in done if t.feasible]
    bad = [t for t in done if not t.feasible]
    if ok:
        a.plot([t.number for t in ok], [value[t.number] for t in ok], "o", ms=3.5, color="C0",
               label="feasible trial")
    if bad:
        a.plot([t.number for t in bad], [value[t.number] for t in bad], "x", ms=4, color="C3",
               label="infeasible trial")
    failed = [t.number for t in result.trials if t.state == "FAIL"]
    pick = min if result.direction == "minimize" else max
    best: float | None = None
    xs: list[int] = []
    ys: list[float] = []
    for t in sorted(ok, key=lambda t: t.number):
        best = value[t.number] if best is None else pick(best, value[t.number])
        xs.append(t.number)
        ys.append(best)
    if xs:
        a.step(xs, ys, where="post", color="k", lw=1.2, label="best feasible so far")
    if failed:
        lo = min(value.values())
        a.plot(failed, [lo] * len(failed), "|", ms=8, color="0.5", label="failed (unstable) trial")
    a.set(title=f"{result.study}: {result.objective} per trial ({result.direction})", xlabel="trial",
          ylabel=result.objective)
    if all(v > 0 for v in value.values()):
        a.set_yscale("log")
    a.grid(alpha=0.3)
    legend_below(fig, a)
    return save_figure(fig, path)


def _plot_pareto(result: TuneResult, path: Path) -> Path | None:
    """The first two objectives of every complete trial, the feasible Pareto front joined, the chosen point ringed."""
    done = [t for t in result.trials if t.state == "COMPLETE" and t.values is not None]
    if len(result.objectives) < 2 or not done:
        return None
    fig, ax = new_figure()
    a = ax[0, 0]
    on_front = set(result.pareto)
    rest = [t for t in done if t.number not in on_front]
    for group, style, label in (([t for t in rest if t.feasible], dict(marker="o", color="0.6", ms=3.5), "feasible"),
                                ([t for t in rest if not t.feasible], dict(marker="x", color="C3", ms=4),
                                 "infeasible")):
        if group:
            a.plot([t.values[0] for t in group], [t.values[1] for t in group], ls="", label=label, **style)  # type: ignore[index]
    front = sorted((t for t in done if t.number in on_front), key=lambda t: t.values[0])  # type: ignore[index]
    if front:
        a.plot([t.values[0] for t in front], [t.values[1] for t in front], "o-", color="C0", ms=5,  # type: ignore[index]
               label="Pareto front (feasible)")
    chosen = next((t for t in done if t.number == result.best_trial), None)
    if chosen is not None:
        a.plot([chosen.values[0]], [chosen.values[1]], "o", ms=12, mfc="none", mec="k", mew=1.5,  # type: ignore[index]
               label=f"chosen: trial {chosen.number}")
    a.set(title=f"{result.study}: {result.objectives[0]} against {result.objectives[1]}",
          xlabel=f"{result.objectives[0]} ({result.directions[0]}d)",
          ylabel=f"{result.objectives[1]} ({result.directions[1]}d)")
    a.grid(alpha=0.3)
    legend_below(fig, a)
    return save_figure(fig, path)


def _heldout_section(result: TuneResult) -> list[Any]:
    """The tuned gains beside the shipped ones, the baseline and the oracle on seeds the study never saw."""
    numbers = {k: v for k, v in (result.heldout or {}).items() if not k.startswith("_")}
    names = result.objectives or [result.objective]
    baseline = next(iter(numbers), None)
    ref, oracle = (numbers[baseline]["mean"] if baseline else math.nan), numbers.get("oracle", {}).get("mean", math.nan)
    rows = []
    for label, n in numbers.items():
        gap = (ref - n["mean"]) / (ref - oracle) if math.isfinite(oracle) and math.isfinite(ref) and ref != oracle \
            else math.nan
        rows.append([Cell(label), *(Cell(format_number(n["means"].get(o, math.nan))) for o in names),
                     Cell(", ".join(format_number(x) for x in n["values"])),
                     Cell("—" if not math.isfinite(gap) else f"{100 * gap:.0f} %"),
                     Cell(", ".join(n["failed"]) or "none", status="fail" if n["failed"] else None)])
    wall = (result.heldout or {}).get("_wall_s", {}).get("mean", math.nan)
    return [Heading(2, "On held-out seeds"),
            Text(f"Seeds {', '.join(map(str, result.heldout_seeds))} (the study ran seeds of its campaign only), "
                 f"{result.heldout_duration_s or 'the campaign'}{' s' if result.heldout_duration_s else ''} cells, "
                 f"{wall:.0f} s wall. Gap closed: (first row - x) / (first row - oracle) on {names[0]}."),
            Table(["controller", *(f"{o}, mean" for o in names), f"{names[0]} per cell", "gap closed",
                   "failed cells"], rows, align="l" + "r" * len(names) + "lrl")]


MIN_IMPORTANCE_TRIALS = 4  # complete trials below which importances are not computed


def _importances(study: optuna.Study) -> tuple[dict[str, float], str]:
    """Optuna's parameter importances (its default evaluator) over the complete trials, or ({}, why not)."""
    import optuna  # noqa: PLC0415  (heavy (Optuna, SQLAlchemy): loaded only when a study runs)

    n = sum(t.state == optuna.trial.TrialState.COMPLETE for t in study.get_trials(deepcopy=False))
    if n < MIN_IMPORTANCE_TRIALS:
        return {}, f"{n} complete trial(s), need {MIN_IMPORTANCE_TRIALS}"
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        try:
            first = (lambda t: t.values[0]) if len(study.directions) > 1 else None  # the first objective's
            imp = optuna.importance.get_param_importances(study, target=first)
        except (RuntimeError, ValueError, ZeroDivisionError) as exc:
            return {}, " ".join(str(exc).split())
    for w in seen:
        if "too small" in str(w.message):  # Optuna then returns equal importances, which say nothing
            return {}, " ".join(str(w.message).split())
    return imp, ""


def _plot_importances(imp: dict[str, float], path: Path) -> Path | None:

    if not imp:
        return None
    fig, ax = new_figure(height=0.5 + 0.45 * len(imp))
    names = list(imp)[::-1]
    ax[0, 0].barh(names, [imp[n] for n in names], color="C0")
    ax[0, 0].set(title="parameter importances (Optuna's default evaluator, complete trials)", xlabel="importance")
    ax[0, 0].grid(alpha=0.3, axis="x")
    return save_figure(fig, path)


def write_tune_report(result: TuneResult, study: optuna.Study | None = None) -> ReportFiles:
    """tune.md, tune.html and the plots into the study's directory: the best parameters, the optimisation history,
    the parameter importances, the best trial's campaign table, the trials. Returns a ReportFiles."""
    import optuna  # noqa: PLC0415  (heavy (Optuna, SQLAlchemy): loaded only when a study runs)


    if study is None:
        study = optuna.load_study(study_name=result.study, storage=rdb_storage(result.storage))
    out = result.out_dir
    out.mkdir(parents=True, exist_ok=True)
    pngs: list[Path] = []
    doc: list[Any] = [Heading(1, f"Tuning {result.controller_label} ({result.controller}) on {result.campaign}")]
    feasible = result.best_trial is not None
    shown = ", ".join(f"{o} {format_number(v)}" for o, v in zip(result.objectives or [result.objective],
                                                                  result.best_values or [math.nan], strict=False))
    head = f"trial {result.best_trial}: {shown}" if feasible else "no feasible trial"
    aim = ("objectives: " + ", ".join(f"mean {o} ({d}d)" for o, d in zip(result.objectives, result.directions,
                                                                         strict=True))
           + f"; the tuned point: the Pareto front's ({len(result.pareto)} trials) nearest the best of each"
           if len(result.objectives) > 1 else f"objective: mean {result.objective}, {result.direction}d")
    doc.append(Banner(head, f"{len(result.trials)} trials: {result.n_complete} complete "
                            f"({result.n_infeasible} infeasible), {result.n_failed} failed (unstable), "
                            f"{result.n_pruned} pruned; {aim}.", feasible))
    doc.append(Heading(2, "Best parameters"))
    if result.params is not None:
        rows = [[Cell(k), Cell(f"{v:.6g}" if isinstance(v, float) else str(v)),
                 Cell("tuned" if k in (result.best_params or {}) else "campaign")] for k, v in result.params.items()]
        doc.append(Table(["parameter", "value", "from"], rows, align="lrl"))
        if result.yaml_path is not None:
            doc.append(Text(f"Controller file: {result.yaml_path.name} (hil check {result.yaml_path.name})."))
    else:
        doc.append(Text("No trial was complete and feasible: nothing to write."))
    if result.heldout:
        doc.extend(_heldout_section(result))
    doc.append(Heading(2, "Search"))
    doc.append(Bullets([Item(f"space: {', '.join(str(s) for s in result.space)}"),
                        Item("constraints: " + (", ".join(str(c) for c in result.constraints) or "none")
                             + " (and the campaign's thresholds, on every cell)"),
                        Item(f"sampler: TPE (multivariate), seeded; {result.workers} trial(s) at a time, "
                             f"engine {result.engine}"),
                        Item(f"trials: {result.n_complete} complete, {result.n_failed} failed (unstable or broken; "
                             f"stopped at the first such cell), {result.n_pruned} pruned (stopped after a cell, "
                             "over 25 % behind the best trial on the same cells)"),
                        Item(f"storage: {result.storage}, study {result.study}")]))
    hist = _plot_history(result, out / "tune-history.png")
    if hist is not None:
        pngs.append(hist)
        doc.append(Figure(hist, "optimisation history: each complete trial, the best feasible so far"))
    pareto = _plot_pareto(result, out / "tune-pareto.png")
    if pareto is not None:
        pngs.append(pareto)
        doc.append(Heading(2, "Pareto front"))
        doc.append(Figure(pareto, "every complete trial; the feasible trials no other beats on every objective"))
        front = [t for t in result.trials if t.number in set(result.pareto)]
        doc.append(Table(["trial", *result.objectives, "parameters"],
                         [[Cell(str(t.number) + (" (chosen)" if t.number == result.best_trial else "")),
                           *(Cell(format_number(v)) for v in t.values or ()),
                           Cell(", ".join(f"{k}={v:.4g}" for k, v in t.params.items()))] for t in front],
                         align="l" + "r" * len(result.objectives) + "l"))
        doc.append(Text("The chosen point (the controller file) is the front's nearest the best of every "
                        "objective, each scaled from its best (0) to its worst (1) on the front."))
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
