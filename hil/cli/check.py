"""`hil check`: validate config files without running anything."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import typer

from hil.cli._common import app, console, fail, print_json

Kind = Literal["session", "campaign", "controller", "swing", "hexapod", "emulator", "plant", "targets"]


@app.command()
def check(
    files: Annotated[list[Path], typer.Argument(help="Session, campaign, controller, swing, hexapod, emulator or "
                                                     "plant YAML files.")],
    kind: Annotated[Kind | None, typer.Option(
        help="What the files are (default: from their folder under profiles/, else from their keys).")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print the results as JSON.")] = False,
) -> None:
    """Validate config files as `hil run`, `hil campaign` and the emulator would, without running anything:
    a summary line per good file, a one-line error per bad one (stderr), exit 2 if any is bad."""
    from hil.api import check_file  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.config import ConfigError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    results, bad = [], 0
    for path in files:
        try:
            results.append(check_file(path, kind) | {"ok": True})
        except ConfigError as exc:
            bad += 1
            results.append({"file": str(path), "ok": False, "error": str(exc)})
            if not json_out:
                fail(str(exc))  # one line on stderr per bad file
            continue
        if not json_out:
            console.print(f"[green]ok[/] {path}: {results[-1]['summary']}", highlight=False, soft_wrap=True)
    if json_out:
        print_json({"ok": not bad, "files": results})
    if bad:
        raise typer.Exit(2)
