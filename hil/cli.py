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


@app.command()
def selftest(
    ticks: Annotated[int, typer.Option(min=100, help="GYRO_SAMPLEs to stream at 1 kHz.")] = 3000,
    seed: Annotated[int, typer.Option(help="Seed of the injected faults.")] = 1,
    garbage_rate: Annotated[float, typer.Option(min=0, max=1, help="Chance of a garbage burst per frame.")] = 0.01,
    flip_rate: Annotated[float, typer.Option(min=0, max=1, help="Chance of a flipped bit per frame.")] = 0.005,
    json_out: Annotated[bool, typer.Option("--json", help="Print the report as JSON.")] = False,
) -> None:
    """Protocol self-test: the bench against an emulated servo board on a pty, with injected faults."""
    import dataclasses
    import json

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from hil.selftest import main_sync

    with Progress(
        TextColumn("[bold]selftest[/] GYRO_SAMPLE -> DRIVE_CMD"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=err_console,
        transient=True,
        disable=json_out,
    ) as bar:
        task = bar.add_task("frames", total=ticks)
        report = main_sync(
            ticks=ticks,
            seed=seed,
            garbage_rate=garbage_rate,
            flip_rate=flip_rate,
            progress=lambda n: bar.update(task, completed=n),
        )
    if json_out:
        console.print_json(json.dumps(dataclasses.asdict(report) | {"passed": report.passed}))
    else:
        _print_selftest(report)
    if not report.passed:
        raise typer.Exit(1)


def _print_selftest(report) -> None:  # type: ignore[no-untyped-def]
    b, c = report.board, report.counters
    t = Table(title="Protocol self-test: bench <-> emulated servo board on a pty")
    t.add_column("what")
    t.add_column("value", justify="right")
    t.add_column("unit / note")
    if report.ident:
        i = report.ident
        t.add_row("board", f"{i['board']} {i['firmware_version']}", f"fingerprint {i['catalogue_fingerprint']}")
    if b:
        t.add_row("GYRO_SAMPLE sent", str(b["ticks_sent"]), "1 kHz, board clock")
        t.add_row("  bit-flipped", str(len(b["corrupted_ticks"])), "injected")
        t.add_row("  garbage bursts", str(b["garbage_bursts"]), f"{b['garbage_bytes']} bytes injected")
        t.add_row("received by the bench", str(report.frames_received), "")
        t.add_row("uncorrupted lost", str(len(report.lost_untouched)), "must be 0")
        t.add_row("corrupted delivered", str(len(report.corrupted_delivered)), "must be 0")
        t.add_row("CRC errors / bad lengths", f"{c['crc_errors']} / {c['bad_lengths']}", "")
        t.add_row("resyncs / bytes discarded", f"{c['resyncs']} / {c['bytes_discarded']}", "")
        lat = b["latency_us"]
        if lat:
            t.add_row("sample k -> command k", f"{lat['p50']} / {lat['p99']} / {lat['max']}", "us p50/p99/max")
        t.add_row("late (>1 ms) / missing", f"{b['late_commands']} / {b['missing_commands']}", "missing = bit-flipped")
        r = report.bench_reaction_us
        if r:
            t.add_row("bench decode -> write", f"{r['p50']} / {r['p99']}", "us p50 / p99")
        pl = b["pacing_late_us"]
        if pl:
            t.add_row("board pacing lateness", f"{pl['p50']} / {pl['p99']}", "us p50 / p99")
    t.add_row("wall time", f"{report.wall_s:.1f}", "s")
    console.print(t)
    if report.passed:
        console.print("[bold green]PASS[/]: every uncorrupted frame arrived once, in order, and was answered.")
    else:
        for failure in report.failures:
            err_console.print(f"[bold red]FAIL[/]: {failure}", highlight=False)


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
        err_console.print(f"[bold red]error:[/] {exc.format_message()}{where}", highlight=False)
        return 2
    return code if isinstance(code, int) else 0
