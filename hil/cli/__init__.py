"""The `hil` command line (typer): a thin layer over :mod:`hil.api`. Exit codes: 0 ok, 1 a check failed, 2 bad
input. One module per family of commands; each registers its commands on the shared app."""

from __future__ import annotations

from typing import Annotated

import typer

from hil._version import __version__
from hil.cli._common import Verbosity, app, console, err_console, fail


@app.callback(invoke_without_command=True)
def _main(
    version: Annotated[bool, typer.Option("--version", help="Print the version and exit.")] = False,
    quiet: Annotated[bool, typer.Option("-q", "--quiet",
                                        help="Results and errors only: no progress bars or notes.")] = False,
    verbose: Annotated[int, typer.Option("-v", "--verbose", count=True,
                                         help="Log what the bench does on stderr (-vv: more).")] = 0,
) -> None:
    if quiet and verbose:
        raise fail("-q and -v: choose one")
    Verbosity.set(quiet, verbose)
    if version:
        console.print(f"hil {__version__}")
        raise typer.Exit(0)


# each registers its commands, in the order `hil --help` lists them
from hil.cli import session  # noqa: E402, I001
from hil.cli import campaign, tune, fit, logs, check  # noqa: E402
from hil.cli import lab, protocol, replay, service  # noqa: E402

__all__ = ["app", "campaign", "check", "fit", "lab", "logs", "main", "protocol", "replay", "service", "session", "tune"]


def main(argv: list[str] | None = None) -> int:
    """Console-script entry: bad usage is one line on stderr and exit code 2, never a traceback."""
    try:
        code = app(args=argv, prog_name="hil", standalone_mode=False)
    except typer.Abort:
        err_console.print("interrupted")
        return 130
    except Exception as exc:
        # click's UsageError contract (typer vendors click, so match the contract, not the class)
        if getattr(exc, "exit_code", None) != 2 or not hasattr(exc, "format_message"):
            raise
        if not exc.format_message():  # no arguments at all: the help was shown
            return 0
        ctx = getattr(exc, "ctx", None)
        where = f" (see `{ctx.command_path} --help`)" if ctx is not None else ""
        fail(f"{exc.format_message()}{where}")
        return 2
    return code if isinstance(code, int) else 0
