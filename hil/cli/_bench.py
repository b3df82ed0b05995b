"""What the commands that reach a `hil serve` service share: the client, its refusals as one line, and a run on
the service with a progress bar (`hil run|ident|campaign --bench URL`, `hil queue`, `hil bench`).

These commands load only the client (:class:`hil.service.Bench`, the standard library's HTTP) and the terminal UI;
a run loads what it needs to check its file when it has one."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, ParamSpec, TypeVar

from hil.cli._common import err_console, fail, no_progress, note

if TYPE_CHECKING:
    from hil.api import RunResult
    from hil.service import Bench

_P = ParamSpec("_P")
_T = TypeVar("_T")

EXIT_BAD_INPUT = 2


def client(url: str | None) -> Bench:
    from hil.service import Bench  # noqa: PLC0415  (the client loads on first use: `hil --help` stays fast)

    try:
        return Bench(url)
    except ValueError as exc:  # hil.config.ConfigError: no URL, or not an http(s) one
        raise fail(str(exc)) from None


def call(fn: Callable[_P, _T], *args: _P.args, **kwargs: _P.kwargs) -> _T:
    """A client call; the service's refusal as one line (exit 2 for bad input, 1 otherwise)."""
    from hil.service import BenchError  # noqa: PLC0415  (the client loads on first use: `hil --help` stays fast)

    try:
        return fn(*args, **kwargs)
    except BenchError as exc:
        raise fail(str(exc), code=EXIT_BAD_INPUT if exc.status in (400, 404, 409, 422) else 1) from None
    except ValueError as exc:
        from hil.config import ConfigError  # noqa: PLC0415  (loaded already when the call raised one)

        if not isinstance(exc, ConfigError):
            raise
        raise fail(str(exc)) from None


def say(line: str) -> None:
    """A line the client says while it follows its item (what a Ctrl-C did): stderr, above the progress bar."""
    err_console.print(line, highlight=False, markup=False)


def bench_for(bench: str | None, loopback: bool) -> str | None:
    """The service a run goes to: ``--bench``, else ``$HIL_BENCH`` unless ``--loopback`` asks for a local run."""
    return bench or (None if loopback else os.environ.get("HIL_BENCH") or None)


def ordinal(n: int) -> str:
    """1st, 2nd, 3rd, 4th, ..., 11th, 12th, 13th, ..., 21st."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def duration(seconds: float) -> str:
    """A time left in words: ``40 s``, ``4 min``, ``2.5 h``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def waiting_line(name: str, url: str, view: dict[str, Any]) -> str:
    """A queued item's view in words: ``demo.yaml: waiting in URL's queue: 2nd of 3; the lease is ana's (4 min
    left)``, and why the queue is stopped, if it is."""
    line = f"{name}: waiting in {url}'s queue"
    if view.get("place"):
        line += f": {ordinal(int(view['place']))} of {view['waiting']}"
        ahead = int(view.get("ahead") or 0)
        if ahead != int(view["place"]) - 1:
            line += f", {ahead} item{'s' if ahead != 1 else ''} to run before it"
    if view.get("lease_holder"):
        left = view.get("lease_remaining_s")
        line += f"; the lease is {view['lease_holder']}'s" + (f" ({duration(float(left))} left)" if left is not None
                                                              else "")
    stopped = view.get("queue_stopped")
    if stopped:
        line += f"; the queue is stopped ({stopped}): `hil queue start --bench {url}` starts it"
    return line


def run_on_bench(url: str, file: Path, out: Path | None, json_out: bool, *, kind: str = "session",
                 options: dict[str, Any] | None = None) -> tuple[RunResult, dict[str, Any]]:
    """Submit ``file`` to the service, follow it with a progress bar, download the log; the RunResult and the
    item's history record. The client owns its item: Ctrl-C takes it off the queue or stops it, a second Ctrl-C
    aborts it, and the item's end still comes back (:meth:`hil.service.Bench.follow`)."""
    from rich.markup import escape  # noqa: PLC0415  (the terminal UI: loaded only when it draws)
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    bench = client(url)
    with Progress(TextColumn("[bold]{task.fields[what]}[/]"), BarColumn(), TimeRemainingColumn(),
                  console=err_console, transient=True, disable=no_progress(json_out)) as bar:
        task = bar.add_task("run", total=None, what=escape(f"{file.name} on {bench.url}"))

        def on_view(view: dict[str, Any]) -> None:
            if view["state"] == "queued":
                bar.update(task, what=escape(waiting_line(file.name, bench.url, view)))
            elif view.get("total"):
                bar.update(task, total=view["total"], completed=view.get("cycles", 0),
                           what=escape(f"{file.name} on {bench.url}"))

        result, record = call(bench.run_item, file, out=out, on_view=on_view, kind=kind, options=options, say=say)
    if not json_out:
        ran = "submitted to" if record["status"] == "removed" else "ran on"
        note(f"{ran} {bench.url} as {bench.user} (item {record['uid']})")
    return result, record
