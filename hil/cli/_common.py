"""What every `hil` command shares: the typer apps, the consoles, verbosity, and the one-line error."""

from __future__ import annotations

import functools
import json
import logging
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import typer
from rich.console import Console

CONTEXT = {"help_option_names": ["-h", "--help"]}

app = typer.Typer(
    name="hil",
    help="Hardware-in-the-loop bench for electro-optical stabilized platforms.",
    no_args_is_help=True,
    add_completion=True,
    pretty_exceptions_enable=False,
    context_settings=CONTEXT,
    rich_markup_mode="markdown",  # a docstring's lines are one paragraph, as in --help of any tool
)
protocol_app = typer.Typer(help="The framed serial protocol: docs and capture decoding.", no_args_is_help=True,
                           context_settings=CONTEXT, rich_markup_mode="markdown")
app.add_typer(protocol_app, name="protocol")

console = Console()
err_console = Console(stderr=True, soft_wrap=True)


class Verbosity:
    """``-q`` (-1): results and errors only, no progress bars or notes; ``-v`` (1): INFO logging on stderr,
    ``-vv`` (2): DEBUG."""

    level = 0

    @classmethod
    def set(cls, quiet: bool, verbose: int) -> None:
        cls.level = -1 if quiet else verbose
        if verbose:
            from rich.logging import RichHandler  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

            logging.basicConfig(level=logging.DEBUG if verbose > 1 else logging.INFO, format="%(name)s: %(message)s",
                                handlers=[RichHandler(console=err_console, show_path=False)], force=True)

    @classmethod
    def quiet(cls) -> bool:
        return cls.level < 0


def note(message: str) -> None:
    """An informational line (stdout), left out with ``-q``."""
    if not Verbosity.quiet():
        console.print(message, highlight=False)


def no_progress(json_out: bool = False) -> bool:
    """Progress bars are off with ``--json`` and ``-q``."""
    return json_out or Verbosity.quiet()


def print_json(data: Any) -> None:
    """Results as JSON on stdout (NaN and infinities as null, paths and other objects as strings)."""
    try:  # plain data (a service's answer) as it is, without loading the analysis for it
        text = json.dumps(data, allow_nan=False)
    except (TypeError, ValueError):
        from hil.api import json_safe  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

        text = json.dumps(json_safe(data), default=str)
    console.print_json(text)


# a library parameter as its errors write it: name=value, the value a repr, a number or a word
PARAMETER = re.compile(r"(?<![\w.\-])([a-z][a-z0-9_]*)=(True\b|'[^']*'|\"[^\"]*\"|[^\s;,:)'\"]+)?")
PARAMETER_FLAGS = {"out_dir": "--out", "record_dir": "--out", "out_plant": "--out", "ports": "--port",
                   "settle_s": "--settle", "constraints": "--constraint"}


@functools.cache
def option_names() -> frozenset[str]:
    """Every long option of every `hil` command."""
    def walk(command: Any) -> Iterator[str]:  # a click command or group, as typer builds it
        for param in command.params:
            yield from (o for o in (*param.opts, *param.secondary_opts) if o.startswith("--"))
        for sub in getattr(command, "commands", {}).values():
            yield from walk(sub)

    return frozenset(walk(typer.main.get_command(app)))


def as_flags(message: str) -> str:
    """A library error in the command's words: each ``name=value`` of a parameter that is a `hil` option becomes
    ``--name value`` (``name=True`` or a bare ``name=``: ``--name``), e.g. ``jobs=0: need at least 1`` ->
    ``--jobs 0: need at least 1``. Other ``name=value`` text (a config field, a plant parameter) is left as it is."""
    options = option_names()

    def flag(match: re.Match[str]) -> str:
        name, value = match.groups()
        option = PARAMETER_FLAGS.get(name, "--" + name.replace("_", "-"))
        if option not in options:
            return match.group(0)
        if value is None or value == "True":
            return option
        if value[0] in "'\"" and value[-1] == value[0]:
            value = value[1:-1]
        return f"{option} {value}"

    return PARAMETER.sub(flag, message)


def fail(message: str, code: int = 2) -> typer.Exit:
    """Print one line naming what is wrong (stderr) and return the Exit to raise (the message is shown as is: a
    file name or value holding ``[...]`` is not taken for markup). A library error's parameters are shown as the
    command's options (:func:`as_flags`)."""
    from rich.markup import escape  # noqa: PLC0415  (the terminal UI: loaded only when it draws)

    err_console.print(f"[bold red]error:[/] {escape(' '.join(as_flags(message).split()))}", highlight=False)
    return typer.Exit(code)


def finite(option: str, value: float | None) -> None:
    """NaN and infinities are refused for every float option (click's ranges let NaN through)."""
    if value is not None and not math.isfinite(value):
        raise fail(f"{option}: {value!r} is not a finite number")


def check_out_dir(path: Path, option: str) -> None:
    """``path`` is a directory we may write into, or one we may create (nothing is created here); exit 2
    naming the option otherwise. Checked before anything starts, so a bad one never reaches a board."""
    from hil.config import ConfigError, require_writable_dir  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    try:
        require_writable_dir(path, option)
    except ConfigError as exc:
        raise fail(str(exc)) from None


def check_input_file(path: Path) -> None:
    """``path`` names a regular file (a FIFO, device or directory is refused unopened); exit 2 otherwise."""
    from hil.config import require_regular_file  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    try:
        require_regular_file(path)
    except ValueError as exc:
        raise fail(str(exc)) from None
