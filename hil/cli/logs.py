"""`hil report`, `hil export`, `hil recover`: what the bench does with logs and campaign directories."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import typer

from hil.cli._common import app, check_input_file, check_out_dir, console, fail, finite, note, print_json


@app.command()
def report(
    log: Annotated[Path, typer.Argument(help="A session log (.h5), or a campaign directory.")],
    json_out: Annotated[bool, typer.Option("--json", help="Print the metrics (or the campaign's outcome) as JSON.")] = (
        False),
    settle_s: Annotated[float, typer.Option(min=0, help="Leave out the first seconds.")] = 1.0,
) -> None:
    """Metrics of a session log (rate error, miss distance, drive ripple, latency, link errors), or a
    campaign directory's report: Markdown and a self-contained HTML page with the paper's tables and plots."""
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.cli.session import print_summary  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.config import ConfigError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    finite("--settle-s", settle_s)
    if not log.is_dir():
        check_input_file(log)
    if log.is_dir():
        try:
            done = api.report_campaign(log)
        except ConfigError as exc:
            raise fail(str(exc)) from None
        if json_out:
            from hil.cli.campaign import campaign_json  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

            print_json(campaign_json(done))
        elif done.report is not None:
            note(f"report: {done.report.markdown}\n        {done.report.html}  ({len(done.report.pngs)} plots)")
        return
    try:
        summary = api.report_log(log, settle_s=settle_s)
    except ConfigError as exc:
        raise fail(str(exc)) from None
    if json_out:
        print_json(summary)
    else:
        print_summary(summary)


@app.command()
def export(
    log: Annotated[Path, typer.Argument(help="A session log (.h5).")],
    fmt: Annotated[Literal["parquet", "csv"], typer.Option("--format", help="The file format.")] = "parquet",
    out: Annotated[Path | None, typer.Option(help="Output directory (default: beside the log).")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print the written files as JSON.")] = False,
) -> None:
    """Export every group of a log to Parquet or CSV files, units kept (docs/log-format.md, "Export")."""
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    check_input_file(log)
    check_out_dir(out if out is not None else log.parent, "--out" if out is not None else "the log's directory")
    try:
        paths = api.export_log(log, fmt, out)
    except api.LogError as exc:
        raise fail(str(exc)) from None
    if json_out:
        print_json({"log": str(log), "format": fmt, "files": [str(p) for p in paths]})
        return
    for p in paths:
        console.print(str(p), highlight=False)


@app.command()
def recover(
    log: Annotated[Path, typer.Argument(help="A log left by a crashed session.")],
    json_out: Annotated[bool, typer.Option("--json", help="Print the recovered log's path as JSON.")] = False,
) -> None:
    """Make a log left by a crash (SIGKILL, power loss) open normally; the original is kept beside it."""
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    check_input_file(log)
    try:
        result = api.recover_log(log)
    except api.LogError as exc:
        raise fail(str(exc)) from None
    if json_out:
        print_json({"log": str(log), "recovered": str(result)})
        return
    console.print(str(result), highlight=False)
