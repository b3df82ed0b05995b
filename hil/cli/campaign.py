"""`hil campaign`: swing campaigns, through :func:`hil.api.run_campaign`."""

from __future__ import annotations

import contextlib
import shlex
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import typer
from rich.table import Table

from hil.cli._bench import call, client, say, waiting_line
from hil.cli._common import app, check_out_dir, console, err_console, fail, no_progress, note, print_json

if TYPE_CHECKING:
    from hil.api import CampaignResult, CellResult


def campaign_json(run: Any) -> dict[str, Any]:
    """A campaign's outcome as plain data: verdict, every cell, the acceptance rules, the report's files."""
    result = run.result
    return {"campaign": result.config.name, "dir": str(run.out_dir), "passed": result.passed,
            "complete": result.complete, "wall_s": result.wall_s, "jobs": result.jobs,
            "cells": [c.model_dump(mode="json") | {"passed": c.passed} for c in result.cells],
            "acceptance": [r.model_dump(mode="json") for r in result.acceptance],
            "report": None if run.report is None else {"markdown": str(run.report.markdown),
                                                      "html": str(run.report.html),
                                                      "plots": [str(p) for p in run.report.pngs]}}


def resume_command(ctx: typer.Context) -> str:
    """The command line given, as ``hil ...`` with ``--resume`` (added if it was not there): the arguments, then
    every option given in the order given, quoted for a POSIX shell."""
    words = ["hil"]
    for level in (ctx.parent, ctx):
        if level is None:
            continue
        if level is ctx:
            words.append(ctx.info_name or "campaign")
        params = {p.name: p for p in level.command.params}
        arguments, options = [], []
        for name, value in level.params.items():  # click fills the options in the order they were given
            param, source = params.get(name), level.get_parameter_source(name)
            if param is None or source is None or source.name not in ("COMMANDLINE", "ENVIRONMENT"):
                continue
            flag = max(param.opts, key=len)
            if param.param_type_name == "argument":
                arguments.append(str(value))
            elif getattr(param, "count", False):
                options += [flag] * int(value)
            elif getattr(param, "is_flag", False):
                if value:
                    options.append(flag)
                elif param.secondary_opts:
                    options.append(max(param.secondary_opts, key=len))
            else:
                options += [flag, str(value)]
        words += arguments + options
    if "--resume" not in words:
        words.append("--resume")
    return shlex.join(words)


def interrupted_json(stop: Any, command: str) -> dict[str, Any]:
    """An interrupted campaign as plain data: the cells done (kept by --resume), cut short, left to run, and the
    command that finishes it."""
    return {"status": "interrupted", "signal": stop.signal, "exit_code": stop.exit_code,
            "campaign": stop.config.name, "dir": str(stop.out_dir), "cells_done": len(stop.done),
            "cells_total": stop.total, "done": stop.done, "cut_short": stop.cut_short, "to_run": stop.to_run,
            "resume_command": command}


def print_interrupted(stop: Any, command: str) -> None:
    """What an interrupted campaign leaves: the cells done and cut short, and the command that finishes it."""
    from rich.markup import escape  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    def say(text: str) -> None:
        console.print(text, highlight=False, soft_wrap=True)

    done = f": {escape(', '.join(stop.done))}" if stop.done else ""
    say(f"[bold yellow]interrupted[/] ({stop.signal}): {len(stop.done)} of {stop.total} cells done{done}")
    say(f"cut short: {escape(', '.join(stop.cut_short)) or 'none'}")
    if stop.to_run:
        say(f"left to run: {len(stop.to_run)} ({escape(', '.join(stop.to_run))})")
    say(f"campaign: {escape(str(stop.out_dir))}")
    say(f"finish it with: {escape(command)}")


@contextlib.contextmanager
def stop_on_signals() -> Iterator[None]:
    """While in the block, SIGINT and SIGTERM raise :class:`hil.api.Interrupted` naming the signal (the campaign
    then stops its cells with it); the previous handlers come back after."""
    from hil.api import Interrupted  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, _frame: object) -> None:
        raise Interrupted(signum)

    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@app.command()
def campaign(  # noqa: PLR0917 (typer maps parameters to options)
    ctx: typer.Context,
    file: Annotated[Path, typer.Argument(help="Campaign YAML (see profiles/campaigns/).")],
    out: Annotated[Path | None, typer.Option(help=(
        "Campaign directory (default: runs/campaigns/NAME); with --bench, where every file of the item comes back."
    ))] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Finish a campaign in --out, skipping done cells.")] = False,
    jobs: Annotated[int, typer.Option(min=1, max=64, help=(
        "Cells run at once (loopback only); with --engine dask and no --scheduler, the worker processes "
        "started."))] = 1,
    hardware: Annotated[bool, typer.Option("--hardware", help="Run on the lab's ports, one cell at a time.")] = False,
    plant: Annotated[Path | None, typer.Option(
        help="Run every cell on this plant file (e.g. a fitted twin, profiles/plant/paper-000.yaml).")] = None,
    clock: Annotated[Literal["sim", "lockstep"], typer.Option(
        help="Loopback cells: sim (in-process) or lockstep (over ptys); the same logs either way.")] = "sim",
    engine: Annotated[Literal["local", "dask"], typer.Option(
        help="local: cells as processes of this machine; dask: on a dask.distributed cluster (docs/campaigns.md)."
    )] = "local",
    scheduler: Annotated[str | None, typer.Option(
        help="--engine dask: an existing scheduler, tcp://HOST:8786 (default: a local cluster of --jobs workers)."
    )] = None,
    workers: Annotated[int | None, typer.Option(min=1, max=1024, help=(
        "--engine dask: the local cluster's worker processes (default --jobs); with --scheduler, wait until "
        "this many workers have joined."))] = None,
    shared_dir: Annotated[Path | None, typer.Option(help=(
        "--engine dask: a directory every worker sees at the same path; the workers leave the cells' files "
        "there (default: they come back as bytes)."))] = None,
    report_too: Annotated[bool, typer.Option("--report/--no-report", help="Write the report at the end.")] = True,
    json_out: Annotated[bool, typer.Option("--json", help="Print the outcome as JSON.")] = False,
    bench: Annotated[str | None, typer.Option(
        help="Run it as one item of a `hil serve` service at this URL (its cells on the service's machine).")] = None,
) -> None:
    """Run a swing campaign: profiles x controllers x seeds, each cell a session with its own log; then the
    summary table, the acceptance verdict, and the report. Cells run here (--engine local) or on a dask cluster
    (--engine dask). Exit 1 if a threshold or an acceptance rule fails. Interrupted (Ctrl-C, SIGTERM): the cells
    running are stopped the safe way, the finished ones kept; it prints them and the --resume command that
    finishes the campaign, exit 130 (SIGTERM: 143)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.config import ConfigError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    if bench is not None:
        if out is not None:
            check_out_dir(out, "--out")
        raise typer.Exit(campaign_on_bench(bench, file, json_out, out))
    try:
        config, out_dir, _ = api.prepare_campaign(file, out=out, hardware=hardware, clock=clock, engine=engine,
                                                  scheduler=scheduler, workers=workers, shared_dir=shared_dir,
                                                  plant=plant)
    except ConfigError as exc:
        raise fail(str(exc)) from None
    n_cells = len(config.cells())
    try:
        with stop_on_signals(), Progress(
                TextColumn(f"[bold]{config.name}[/]"), BarColumn(), MofNCompleteColumn(),
                TextColumn("{task.fields[last]}"), TimeElapsedColumn(), console=err_console, transient=True,
                disable=no_progress(json_out)) as bar:
            task = bar.add_task("cells", total=n_cells, last="")

            def on_cell(cell: CellResult) -> None:
                mark = "ok" if cell.passed else "FAIL"
                bar.update(task, advance=1, last=f"{cell.cell_id} {mark}")

            try:
                run = api.run_campaign(config, out=out_dir, jobs=jobs, resume=resume, hardware=hardware,
                                       clock=clock, write_report=report_too, on_cell=on_cell, engine=engine,
                                       scheduler=scheduler, workers=workers, shared_dir=shared_dir)
            except ConfigError as exc:
                raise fail(str(exc)) from None
    except KeyboardInterrupt as exc:  # before or after the cells ran: the campaign as it stands on disk
        stop = exc if isinstance(exc, api.CampaignInterrupted) else api.campaign_interrupted(
            config, out_dir, getattr(exc, "signum", signal.SIGINT))
        command = resume_command(ctx)
        if json_out:
            print_json(interrupted_json(stop, command))
        else:
            print_interrupted(stop, command)
        raise typer.Exit(stop.exit_code) from None
    if json_out:
        print_json(campaign_json(run))
    else:
        print_campaign(run.result)
        if run.report is not None:
            note(f"report: {run.report.markdown}\n        {run.report.html}  ({len(run.report.pngs)} plots)")
        note(f"campaign: {out_dir}")
    raise typer.Exit(0 if run.passed else 1)


def campaign_on_bench(url: str, file: Path, json_out: bool, out: Path | None = None) -> int:
    """Submit the campaign to the service, wait for it, bring every file it wrote back into ``out`` (when given:
    its cells' logs, campaign.json, the report), print its outcome and where its report is; its exit code."""
    from rich.progress import Progress, TextColumn  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    bench = client(url)
    item = call(bench.add, file, kind="campaign")
    with Progress(TextColumn("{task.fields[what]}", markup=False), console=err_console, transient=True,
                  disable=no_progress(json_out)) as bar:
        task = bar.add_task("campaign", what=f"{file.name} on {bench.url}: queued")

        def on_view(view: dict[str, Any]) -> None:
            bar.update(task, what=waiting_line(file.name, bench.url, view) if view["state"] == "queued" else
                       f"{file.name} on {bench.url}: {view['state']}")

        # the client owns its item: Ctrl-C takes it off the queue or stops it, a second Ctrl-C aborts it
        record = call(bench.follow, item["uid"], progress=on_view, say=say, label=file.name)
    files = [] if out is None or not record.get("links") else call(bench.download_item, record["uid"], out)
    if json_out:
        print_json(record if out is None else {**record, "out": str(out), "files": [str(p) for p in files]})
    else:
        summary: dict[str, Any] = record.get("summary") or {}
        colour = "green" if record["exit_code"] == 0 else "red"
        verdicts: dict[object, str] = {True: "PASS", False: "FAIL"}
        verdict = verdicts.get(summary.get("passed"), "")
        console.print(f"[bold {colour}]{record['status']}[/] {verdict} {record.get('message', '')}".rstrip(),
                      highlight=False)
        if record["links"].get("report"):
            note(f"report: {bench.url}{record['links']['report']}")
        if out is not None:
            local = next((p for p in files if p.name == "report.html"), None)
            note(f"{len(files)} files in {out}" + (f"; the report: {local}" if local else ""))
        note(f"item {record['uid']} on {bench.url}")
    return int(bench.exit_code(record))


def print_campaign(result: CampaignResult) -> None:
    """The terminal table: one per profile, numbers formatted as in the report (format_values)."""
    from hil.api import METRICS, format_values  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    cfg = result.config
    for profile in cfg.profiles:
        t = Table(title=f"{cfg.title}: {profile.label}", title_justify="left")
        t.add_column("controller")
        for m in cfg.metrics:
            t.add_column(f"{METRICS[m].label} ({METRICS[m].unit})", justify="right")
        t.add_column("cells ok", justify="right")
        for c in cfg.controllers:
            row = [c.label] + [format_values(result.values(profile.label, c.label, m), metric=m) for m in cfg.metrics]
            cells = [x for x in result.cells if x.profile == profile.label and x.controller == c.label]
            row.append(f"{sum(x.passed for x in cells)}/{len(cfg.seeds)}")
            t.add_row(*row)
        console.print(t)
    for cell in result.cells:
        for why in cell.failures:
            console.print(f"[red]FAIL[/] {cell.cell_id}: {why}", highlight=False)
    for rule in result.acceptance:
        colour = "green" if rule.passed else "red"
        console.print(f"[bold {colour}]{'PASS' if rule.passed else 'FAIL'}[/] {rule.rule}", highlight=False)
        for line in rule.details:
            console.print(f"    {line}", highlight=False)
    state = "complete" if result.complete else "PARTIAL"
    console.print(f"{len(result.cells)} cells, {state}, {result.wall_s:.1f} s wall with {result.jobs} job(s): "
                  f"[bold {'green' if result.passed else 'red'}]{'PASS' if result.passed else 'FAIL'}[/]",
                  highlight=False)
