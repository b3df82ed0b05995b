"""`hil fit`: the emulated plant fitted to a platform's session logs, or to the paper's figures (docs/fit.md)."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Annotated

import typer

from hil.cli._common import app, console, err_console, fail, no_progress, note, print_json


@app.command()
def fit(  # noqa: PLR0917 (typer maps parameters to options)
    logs: Annotated[list[Path] | None, typer.Argument(
        help="Session logs of one platform: static, `hil ident` sweeps, swing sessions (any mix).")] = None,
    out: Annotated[Path, typer.Option(help="The plant YAML to write (e.g. profiles/plant/my-gimbal.yaml).")] = Path(
        "runs/fit/plant.yaml"),
    prior: Annotated[Path | None, typer.Option(
        help="Plant whose values are kept where the logs say nothing (default: profiles/plant/default.yaml).")] = None,
    report_dir: Annotated[Path | None, typer.Option(
        help="Where fit.md, fit.html and the plots go (default: runs/fit/NAME).")] = None,
    rerun: Annotated[bool, typer.Option("--rerun/--no-rerun",
                                        help="Re-run the static and swing sessions on the twin (sim clock).")] = True,
    targets: Annotated[Path | None, typer.Option(
        help="Fit to published figures instead of logs: a targets file (profiles/targets/).")] = None,
    trials: Annotated[int, typer.Option(min=1, max=100_000, help="--targets: trials of the search.")] = 100,
    storage: Annotated[str | None, typer.Option(help="--targets: Optuna storage URL (default: SQLite beside "
                                                      "the report).")] = None,
    study: Annotated[str | None, typer.Option(help="--targets: study name.")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="--targets: continue the study.")] = False,
    seed: Annotated[int, typer.Option(min=0, max=2**32 - 1, help="--targets: the sampler's seed.")] = 0,
    json_out: Annotated[bool, typer.Option("--json", help="Print the outcome as JSON.")] = False,
) -> None:
    """Fit the emulated plant (a digital twin) to LOGs of one platform, or with --targets to published figures.
    Writes the plant YAML (--out) and a report (fit.md, fit.html, plots). Exit 2 on bad input."""
    command = "hil fit " + " ".join(shlex.quote(a) for a in sys.argv[2:])
    if targets is not None:
        if logs:
            raise fail("--targets: give either logs or a targets file, not both")
        _fit_targets(targets, out, trials, storage, study, resume, seed, json_out, report_dir)
        return
    if not logs:
        raise fail("LOGS: give the session logs to fit (or --targets FILE)")
    from hil.fit.logs import FitInputError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.fit.report import write_fit_report  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.fit.twin import fit_logs  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    if out.suffix not in (".yaml", ".yml"):
        raise fail(f"--out: {out} is not a .yaml file")
    report = report_dir or Path("runs/fit") / out.stem
    quiet = no_progress(json_out)
    with err_console.status("fitting", spinner="dots") if not quiet else _Null() as status:
        def progress(text: str) -> None:
            if status is not None:
                status.update(f"fitting: {text}")

        try:
            result = fit_logs(list(logs), prior=prior, progress=progress)
        except FitInputError as exc:
            raise fail(str(exc)) from None
        except (OSError, ValueError) as exc:
            raise fail(f"fit: {exc}") from None
        plant_path = result.write(out, command=command)
        progress("re-running the sessions on the twin" if rerun else "report")
        files, checks = write_fit_report(result, plant_path, report, rerun=rerun, command=command)
    if json_out:
        print_json({
            "plant": str(plant_path), "report": str(files.markdown), "html": str(files.html),
            "estimates": [vars(e) for e in result.estimates],
            "checks": [{**vars(c), "ratio": c.ratio} for c in checks],
            "notes": result.notes,
        })
        return
    from rich.table import Table  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    table = Table(title=f"hil fit: {len(result.logs)} logs -> {plant_path}", title_justify="left")
    for col in ("parameter", "value", "+- 1 sigma", "unit", "prior", "status"):
        table.add_column(col, justify="right" if col in ("value", "+- 1 sigma", "prior") else "left")
    for e in result.estimates:
        table.add_row(e.name, _g(e.value), _g(e.sigma), e.unit, _g(e.prior),
                      {"fitted": "[green]fitted[/]", "bound": "[yellow]bound[/]"}.get(e.status, "prior"))
    console.print(table)
    for c in checks:
        note(f"  twin check {c.log}: {c.metric} logged {c.logged:.4g}, twin {c.twin:.4g} {c.unit} "
             f"(x{c.ratio:.3f})")
    for n in result.notes:
        note(f"  note: {n}")
    note(f"report: {files.markdown} (and {files.html.name})")


def _fit_targets(targets: Path, out: Path, trials: int, storage: str | None, study: str | None, resume: bool,  # noqa: PLR0917
                 seed: int, json_out: bool, report_dir: Path | None) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    from hil.fit.targets import fit_targets  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    with Progress(TextColumn(f"[bold]fit {targets.stem}[/]"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[last]}"), TimeElapsedColumn(), console=err_console,
                  disable=no_progress(json_out), transient=True) as bar:
        task = bar.add_task("trials", total=trials, last="")

        def progress(line: str) -> None:
            bar.update(task, advance=1 if line.startswith("trial") else 0, last=line[:60])

        try:
            result = fit_targets(targets, out_plant=out, trials=trials, storage=storage, study=study, seed=seed,
                                 resume=resume, progress=progress, out_dir=report_dir)
        except (OSError, ValueError) as exc:
            raise fail(str(exc)) from None
    if json_out:
        print_json(result.to_json())
        return
    from rich.table import Table  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    note(f"{result.complete} of {result.trials} trials complete ({result.failed} failed), best trial "
         f"{result.best_trial}: objective {result.best_value}; {result.wall_s:.0f} s")
    table = Table(title=f"{targets.name}: paper vs fitted twin", title_justify="left")
    for col in ("target", "paper", "twin", "ratio"):
        table.add_column(col, justify="left" if col == "target" else "right")
    for r in result.residuals:
        table.add_row(f"{r.figure}: {r.what}", _g(r.paper), _g(r.fitted), f"{r.ratio:.2f}")
    console.print(table)
    for pr in result.premises:
        note(f"  premise {pr.id}: {'holds' if pr.holds else 'does not hold'} ({pr.text}; {_g(pr.value)} {pr.bound})")
    note(f"plant: {result.plant_path}; residuals: {result.residuals_path}")


def _g(x: float | None) -> str:
    return "-" if x is None else f"{x:.5g}"


class _Null:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        return None
