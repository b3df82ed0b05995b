"""`hil fit`: the emulated plant fitted to a platform's session logs, or to the paper's figures (docs/fit.md)."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from hil.cli._common import app, as_flags, console, err_console, fail, no_progress, note, print_json

if TYPE_CHECKING:
    from hil.api import Recording


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
    jobs: Annotated[int | None, typer.Option(min=1, max=64, help="--targets: trials run at once, each cell in a "
                                             "warm worker process (default: one per CPU).")] = None,
    prune: Annotated[bool, typer.Option("--prune/--no-prune", help="--targets: stop a trial once the targets "
                                        "measured so far sum to more than the best trial's objective (they can "
                                        "only add up: it could not have become the best).")] = True,
    plan: Annotated[Path | None, typer.Option(
        help="Print the recordings a fit needs on the lab of this session YAML (your own: its ports and limits): "
             "the commands, their durations and why; their session files are written beside the report.")] = None,
    record: Annotated[Path | None, typer.Option(
        help="Record that set on the lab of this session YAML (with --loopback or --hardware), then fit it.")] = None,
    loopback: Annotated[bool, typer.Option("--loopback", help="--record: on the emulated lab (sim clock).")] = False,
    hardware: Annotated[bool, typer.Option("--hardware", help="--record: on the lab's boards (the session's "
                                                              "ports).")] = False,
    json_out: Annotated[bool, typer.Option("--json", help="Print the outcome as JSON.")] = False,
) -> None:
    """Fit the emulated plant (a digital twin) to LOGs of one platform, or with --targets to published figures.
    Writes the plant YAML (--out) and a report (fit.md, fit.html, plots). --plan SESSION says what to record,
    --record SESSION records it and fits. Exit 2 on bad input."""
    command = "hil fit " + " ".join(shlex.quote(a) for a in sys.argv[2:])
    report = report_dir or Path("runs/fit") / out.stem
    if plan is not None or record is not None:
        if logs or targets is not None or (plan is not None and record is not None):
            raise fail("--plan, --record: give one session YAML, and no logs or --targets")
        if plan is not None:
            _print_plan(plan, report / "sessions", json_out)
            return
        if loopback == hardware:
            raise fail("--record: say where: --loopback (the emulated lab) or --hardware (the lab's boards)")
        logs = _record(record, report / "sessions", loopback=loopback, json_out=json_out)  # type: ignore[arg-type]
    if targets is not None:
        if logs:
            raise fail("--targets: give either logs or a targets file, not both")
        _fit_targets(targets, out, trials, storage, study, resume, seed, json_out, report_dir, jobs=jobs,
                     prune=prune)
        return
    if not logs:
        raise fail("LOGS: give the session logs to fit (or --targets FILE)")
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    if out.suffix not in (".yaml", ".yml"):
        raise fail(f"--out: {out} is not a .yaml file")
    quiet = no_progress(json_out)
    with err_console.status("fitting", spinner="dots") if not quiet else _Null() as status:
        def progress(text: str) -> None:
            if status is not None:
                status.update(f"fitting: {text}")

        try:
            result = api.fit_logs(logs, prior=prior, progress=progress)
        except api.FitInputError as exc:
            raise fail(str(exc)) from None
        except (OSError, ValueError) as exc:
            raise fail(f"fit: {exc}") from None
        plant_path = result.write(out, command=command)
        progress("re-running the sessions on the twin" if rerun else "report")
        files, checks = api.write_fit_report(result, plant_path, report, rerun=rerun, command=command)
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
                      {"fitted": "[green]fitted[/]", "weak": "[red]weak[/]",
                       "bound": "[yellow]bound[/]"}.get(e.status, "prior"))
    console.print(table)
    for e in result.estimates:
        if e.status in ("weak", "prior", "bound") and e.note:
            note(as_flags(f"  {e.name}: {e.status}: {e.source}; {e.note}"))
    for c in checks:
        note(f"  twin check {c.log}: {c.metric} logged {c.logged:.4g}, twin {c.twin:.4g} {c.unit} "
             f"(x{c.ratio:.3f})")
    for n in result.notes:
        note(f"  note: {n}")
    note(f"report: {files.markdown} (and {files.html.name})")


def _command(rec: Recording, session_file: str) -> str:
    """The command that records ``rec`` (a :class:`hil.api.Recording`) from its session file."""
    if rec.sweep is None:
        return f"hil run {session_file}"
    s = rec.sweep
    return (f"hil ident {session_file} --axis {s.axis} --f-start-hz {s.f_start_hz:g} --f-stop-hz {s.f_stop_hz:g} "
            f"--sweep-s {s.duration_s:g} --amplitude-dps {s.amplitude_dps:g} --offset-dps {s.offset_dps:g}")


def _plan_of(session: Path) -> list[Recording]:
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.config import ConfigError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    try:
        return api.fit_plan(session)
    except ConfigError as exc:
        raise fail(str(exc)) from None


def _print_plan(session: Path, sessions_dir: Path, json_out: bool) -> None:
    """The recording set for ``session``'s lab: each recording's command, duration and purpose."""
    plan = _plan_of(session)
    rows: list[dict[str, Any]] = []
    for rec in plan:
        file = str(rec.write(sessions_dir))
        rows.append({"name": rec.name, "kind": rec.kind, "seconds": rec.seconds, "why": rec.why,
                     "command": _command(rec, file)})
    if json_out:
        print_json({"recordings": rows, "total_s": sum(r["seconds"] for r in rows)})
        return
    total = sum(r["seconds"] for r in rows)
    console.print(f"[bold]hil fit: what to record on the lab of {session}[/] ({len(rows)} logs, {total:.0f} s of "
                  "running; add --loopback to each command for the emulated lab)", soft_wrap=True)
    for i, r in enumerate(rows, 1):
        console.print(f"{i}. [bold]{r['name']}[/] ({r['seconds']:g} s): {r['why']}", soft_wrap=True)
        console.print(f"   {r['command']}", soft_wrap=True, highlight=False, markup=False)
    console.print(f"Then: hil fit LOGS... (or all of it at once: hil fit --record {session} --hardware)",
                  soft_wrap=True, highlight=False, markup=False)


def _record(session: Path, sessions_dir: Path, *, loopback: bool, json_out: bool) -> list[Path]:
    """Run the recording set; the logs' paths."""
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    plan = _plan_of(session)
    for rec in plan:
        rec.write(sessions_dir)
    with err_console.status("recording", spinner="dots") if not no_progress(json_out) else _Null() as status:
        def progress(text: str) -> None:
            if status is not None:
                status.update(f"recording: {text}")
            else:
                note(f"recording: {text}")

        try:
            logs = api.fit_record(plan, loopback=loopback, progress=progress)
        except RuntimeError as exc:
            raise fail(f"--record: {exc}", code=1) from None
    for path in logs:
        note(f"recorded {path}")
    return logs


def _fit_targets(targets: Path, out: Path, trials: int, storage: str | None, study: str | None, resume: bool,  # noqa: PLR0917
                 seed: int, json_out: bool, report_dir: Path | None, *, jobs: int | None, prune: bool) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    with Progress(TextColumn(f"[bold]fit {targets.stem}[/]"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[last]}"), TimeElapsedColumn(), console=err_console,
                  disable=no_progress(json_out), transient=True) as bar:
        task = bar.add_task("trials", total=trials, last="")

        def progress(line: str) -> None:
            bar.update(task, advance=1 if line.startswith("trial") else 0, last=line[:60])

        try:
            result = api.fit_targets(targets, out_plant=out, trials=trials, storage=storage, study=study, seed=seed,
                                 resume=resume, progress=progress, out_dir=report_dir, jobs=jobs, prune=prune)
        except (OSError, ValueError) as exc:
            raise fail(str(exc)) from None
    if json_out:
        print_json(result.to_json())
        return
    from rich.table import Table  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    note(f"{result.complete} of {result.trials} trials complete ({result.failed} failed, {result.pruned} pruned), "
         f"best trial {result.best_trial}: objective {result.best_value}; {result.wall_s:.0f} s")
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
