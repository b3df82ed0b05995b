"""The `hil` command line (typer). Exit codes: 0 ok, 1 a check failed, 2 bad input."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from hil import __version__

app = typer.Typer(
    name="hil",
    help="Hardware-in-the-loop bench for electro-optical stabilized platforms.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
protocol_app = typer.Typer(help="The framed serial protocol: docs and capture decoding.", no_args_is_help=True)
app.add_typer(protocol_app, name="protocol")

console = Console()
err_console = Console(stderr=True, soft_wrap=True)


def fail(message: str, code: int = 2) -> typer.Exit:
    """Print one line naming what is wrong and return the Exit to raise."""
    err_console.print(f"[bold red]error:[/] {message}", highlight=False)
    return typer.Exit(code)


@app.callback(invoke_without_command=True)
def _main(
    version: Annotated[bool, typer.Option("--version", help="Print the version and exit.")] = False,
) -> None:
    if version:
        console.print(f"hil {__version__}")
        raise typer.Exit(0)


@protocol_app.command("docs")
def protocol_docs(
    write: Annotated[bool, typer.Option("--write", help="Rewrite the generated blocks of the file.")] = False,
    path: Annotated[Path | None, typer.Option(help="The protocol document (default: docs/protocol.md).")] = None,
) -> None:
    """Check (or with --write, regenerate) the catalogue tables in docs/protocol.md."""
    from hil.protocol import docgen

    path = path or docgen.DOC_PATH
    if not path.is_file():
        raise fail(f"{path}: no such file")
    old = path.read_text()
    try:
        new = docgen.apply(old)
    except ValueError as exc:
        raise fail(str(exc)) from None
    if new == old:
        console.print(f"{path}: up to date with the catalogue")
        return
    if write:
        path.write_text(new)
        console.print(f"{path}: regenerated")
        return
    raise fail(f"{path} differs from the catalogue; run `hil protocol docs --write`", code=1)


@protocol_app.command("decode")
def protocol_decode(
    capture: Annotated[str, typer.Argument(help="A raw binary capture file, '-' for stdin, or hex text with --hex.")],
    hex_input: Annotated[bool, typer.Option("--hex", help="The input is hex text (spaces allowed).")] = False,
    limit: Annotated[int, typer.Option(help="Print at most this many frames.")] = 50,
) -> None:
    """Decode a capture of one link: frames, then the link counters."""
    from hil.protocol import Decoder

    if capture == "-":
        data = sys.stdin.buffer.read()
    elif hex_input:
        data = capture.encode()
    else:
        p = Path(capture)
        if not p.is_file():
            raise fail(f"{capture}: no such file (pass --hex to decode hex text given on the command line)")
        data = p.read_bytes()
    if hex_input:
        try:
            data = bytes.fromhex(data.decode("ascii", "replace").replace(":", " "))
        except ValueError as exc:
            raise fail(f"not hex text: {exc}") from None
    decoder = Decoder()
    frames = decoder.feed(data)
    table = Table("#", "src", "dst", "seq", "message", title=f"{len(frames)} frames")
    for i, fr in enumerate(frames[:limit]):
        table.add_row(str(i), f"{fr.src:#04x}", f"{fr.dst:#04x}", str(fr.seq), repr(fr.message))
    console.print(table)
    if len(frames) > limit:
        console.print(f"... {len(frames) - limit} more (raise --limit)")
    counters = Table("counter", "value", title="link counters")
    for name, value in decoder.counters.as_dict().items():
        counters.add_row(name, str(value))
    counters.add_row("pending (incomplete frame)", str(decoder.pending))
    console.print(counters)


def main() -> None:  # pragma: no cover - console-script shim
    app()
