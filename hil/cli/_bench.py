"""What the commands that reach a `hil serve` service share: the client, its refusals as one line, and a run on
the service with a progress bar (`hil run|ident|campaign --bench URL`, `hil queue`, `hil bench`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from hil.cli._common import err_console, fail, no_progress, note

EXIT_BAD_INPUT = 2


def client(url: str | None):  # type: ignore[no-untyped-def]
    from hil.config import ConfigError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.service import Bench  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    try:
        return Bench(url)
    except ConfigError as exc:
        raise fail(str(exc)) from None


def call(fn, *args: Any, **kwargs: Any) -> Any:  # type: ignore[no-untyped-def]
    """A client call; the service's refusal as one line (exit 2 for bad input, 1 otherwise)."""
    from hil.config import ConfigError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.service import BenchError  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    try:
        return fn(*args, **kwargs)
    except BenchError as exc:
        raise fail(str(exc), code=EXIT_BAD_INPUT if exc.status in (400, 404, 409, 422) else 1) from None
    except ConfigError as exc:
        raise fail(str(exc)) from None


def bench_for(bench: str | None, loopback: bool) -> str | None:
    """The service a run goes to: ``--bench``, else ``$HIL_BENCH`` unless ``--loopback`` asks for a local run."""
    return bench or (None if loopback else os.environ.get("HIL_BENCH") or None)


def run_on_bench(url: str, file: Path, out: Path | None, json_out: bool, *, kind: str = "session",
                 options: dict[str, Any] | None = None) -> Any:
    """Submit ``file`` to the service, follow it with a progress bar, download the log; the RunResult and the
    item's history record."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    bench = client(url)
    with Progress(TextColumn("[bold]{task.fields[what]}[/]"), BarColumn(), TimeRemainingColumn(),
                  console=err_console, transient=True, disable=no_progress(json_out)) as bar:
        task = bar.add_task("run", total=None, what=f"{file.name} on {bench.url}")

        def on_view(view: dict[str, Any]) -> None:
            if view["state"] == "queued":
                stopped = view.get("queue_stopped")
                why = (f"; the queue is stopped ({stopped}): `hil queue start --bench {bench.url}` starts it"
                       if stopped else "")
                bar.update(task, what=f"{file.name}: waiting in {bench.url}'s queue (place {view['position']}){why}")
            elif view.get("total"):
                bar.update(task, total=view["total"], completed=view.get("cycles", 0),
                           what=f"{file.name} on {bench.url}")

        result, record = call(bench.run_item, file, out=out, on_view=on_view, kind=kind, options=options)
    if not json_out:
        note(f"ran on {bench.url} as {bench.user} (item {record['uid']})")
    return result, record
