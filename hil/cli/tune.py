"""`hil tune`: an Optuna study over a campaign's cells, through :func:`hil.api.tune` (docs/tuning.md)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import typer

from hil.cli._common import Verbosity, app, console, err_console, fail, no_progress, note, print_json

if TYPE_CHECKING:
    from hil.api import TrialInfo


@app.command()
def tune(  # noqa: PLR0917 (typer maps parameters to options)
    file: Annotated[Path, typer.Argument(help="Campaign YAML whose cells every trial runs (see profiles/campaigns/).")],
    params: Annotated[str, typer.Option(
        "--params", help='Search space: "name=low..high[:log|:int], ..." over the controller\'s parameters.')],
    objective: Annotated[list[str] | None, typer.Option(
        metavar="METRIC[@GLOB]",
        help="Metric to minimise: its mean over the campaign's profiles and seeds; METRIC@GLOB: over the cells whose "
        "profile label matches GLOB only (e.g. 'los_rate_std_dps@vibration*'). Give it 2-3 times for a "
        "multi-objective study: the report shows the Pareto front and the controller file holds its point nearest "
        "the best of each. Default miss_std_px.")] = None,
    trials: Annotated[int, typer.Option(min=1, max=100_000, help="Trials in the study in all (with --resume: "
                                                                   "only the missing ones run).")] = 100,
    controller: Annotated[str | None, typer.Option(
        help="The campaign's controller label to tune (default: the first that is not the baseline).")] = None,
    constraint: Annotated[list[str] | None, typer.Option(
        "--constraint", help='"metric<=value" or "metric>=value" on every cell, or "metric<=value@GLOB" on the cells '
        "whose profile label matches GLOB; repeatable.")] = None,
    engine: Annotated[Literal["local", "dask"], typer.Option(
        help="local: cells as processes here; dask: on a LocalCluster of --workers, or --scheduler.")] = "local",
    scheduler: Annotated[str | None, typer.Option(help="dask scheduler address (tcp://host:8786).")] = None,
    shared_dir: Annotated[Path | None, typer.Option(
        help="dask: a directory the workers share with this machine (else cells' files come back as data).")] = None,
    workers: Annotated[int, typer.Option(min=1, max=256, help="Trials run at once.")] = 1,
    jobs: Annotated[int, typer.Option(min=1, max=64, help="Cells of one trial run at once.")] = 1,
    storage: Annotated[str | None, typer.Option(
        help="Optuna storage, an SQLAlchemy URL (default: sqlite:///OUT/tune.db).")] = None,
    study: Annotated[str | None, typer.Option(help="Study name (default: the campaign's name).")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue an existing study up to --trials.")] = False,
    out: Annotated[Path | None, typer.Option(help="Study directory (default: runs/tune/STUDY).")] = None,
    write_profile: Annotated[Path | None, typer.Option(
        help="Also write the tuned controller YAML here (e.g. profiles/controllers/eso_kf-tuned.yaml).")] = None,
    seed: Annotated[int, typer.Option(min=0, max=2**32 - 1, help="The sampler's seed.")] = 0,
    keep_logs: Annotated[bool, typer.Option("--keep-logs", help="Keep every trial's session logs.")] = False,
    prune: Annotated[bool, typer.Option(
        "--prune/--no-prune", help="Stop a trial after a cell once its running mean of --objective trails the best "
        "trial's over the same cells by more than 25 % (docs/tuning.md, Pruning).")] = True,
    warm_start: Annotated[bool, typer.Option(
        "--warm-start/--no-warm-start", help="A new study's first trial is the controller's own parameters (the "
        "shipped gains).")] = True,
    heldout_seeds: Annotated[int, typer.Option(
        min=0, max=50, help="After the study, compare the tuned gains with the shipped ones, the baseline and the "
        "oracle on this many seeds after the campaign's own (0: none); in the report and the summary.")] = 3,
    heldout_duration: Annotated[float | None, typer.Option(
        min=0.5, help="The held-out cells' duration, s (default the campaign's).")] = None,
    report_too: Annotated[bool, typer.Option("--report/--no-report", help="Write tune.md and tune.html.")] = True,
    json_out: Annotated[bool, typer.Option("--json", help="Print the outcome as JSON.")] = False,
) -> None:
    """Tune a controller on a campaign's cells with Optuna (TPE): each trial runs the campaign's profiles x seeds
    with the trial's parameters, scored by the mean of --objective (minimised); unstable trials fail, constraints
    steer the sampler. Writes OUT/NAME-tuned.yaml and the report. Exit 1 if no trial was feasible."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.config import ConfigError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    if scheduler is not None and engine != "dask":
        raise fail("--scheduler: needs --engine dask")
    if Verbosity.level < 1:  # Optuna's own lines (study created, every trial) only with -v
        import optuna  # noqa: PLC0415  (heavy (Optuna, SQLAlchemy): loaded only when a study runs)

        optuna.logging.set_verbosity(optuna.logging.WARNING)
    with Progress(TextColumn(f"[bold]tune {file.stem}[/]"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[last]}"), TimeElapsedColumn(), console=err_console,
                  transient=True, disable=no_progress(json_out)) as bar:
        task = bar.add_task("trials", total=None, last="")

        def on_trial(t: TrialInfo) -> None:
            what = ({"FAIL": "failed", "PRUNED": "pruned"}.get(t.state)
                    or f"{t.value:.4g}" + ("" if t.feasible else " infeasible"))
            bar.update(task, advance=1, last=f"trial {t.number}: {what}")

        try:
            result = api.tune(file, params, objective=objective or "miss_std_px", trials=trials, controller=controller,
                              constraints=constraint, engine=engine, scheduler=scheduler, shared_dir=shared_dir,
                              workers=workers, jobs=jobs,
                              storage=storage, study=study, resume=resume, out=out, write_profile=write_profile,
                              seed=seed, keep_logs=keep_logs, write_report=report_too, on_trial=on_trial,
                              prune=prune, warm_start=warm_start, heldout_seeds=heldout_seeds,
                              heldout_duration_s=heldout_duration)
        except ConfigError as exc:
            raise fail(str(exc)) from None
    if json_out:
        print_json(result.to_json())
    else:
        console.print(f"study {result.study}: {len(result.trials)} trials ({result.trials_run} this run, "
                      f"{result.wall_s:.1f} s wall): {result.n_complete} complete, {result.n_infeasible} infeasible, "
                      f"{result.n_failed} failed, {result.n_pruned} pruned", highlight=False)
        if result.best_trial is None:
            console.print("[bold red]no feasible trial[/]", highlight=False)
        else:
            shown = ", ".join(f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}"
                              for k, v in (result.best_params or {}).items())
            scores = ", ".join(f"mean {o} {v:.4g} ({d}d)" for o, v, d in zip(
                result.objectives, result.best_values or [], result.directions, strict=False))
            front = f" (of the Pareto front's {len(result.pareto)})" if len(result.objectives) > 1 else ""
            console.print(f"best: trial {result.best_trial}{front}, {scores}: {shown}", highlight=False)
            if result.heldout:
                held = {k: v["mean"] for k, v in result.heldout.items() if not k.startswith("_")}
                console.print(f"held-out seeds {', '.join(map(str, result.heldout_seeds))}: mean {result.objective} "
                              + ", ".join(f"{k} {v:.4g}" for k, v in held.items()), highlight=False)
            note(f"controller: {result.yaml_path}" + (f"\n            {result.profile_path}"
                                                      if result.profile_path else ""))
        if result.report is not None:
            note(f"report: {result.report.markdown}\n        {result.report.html}")
        note(f"storage: {result.storage}")
    raise typer.Exit(0 if result.best_trial is not None else 1)
