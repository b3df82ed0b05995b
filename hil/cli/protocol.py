"""`hil protocol docs` and `hil protocol decode`: the catalogue's docs tables, and decoding what a link carried (a
capture of every link, hil.link, or raw bytes of one)."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import typer
from rich.table import Table

from hil.cli._common import console, err_console, fail, print_json, protocol_app

if TYPE_CHECKING:
    from hil.api import Frame, TimedFrame


@protocol_app.command("docs")
def protocol_docs(
    write: Annotated[bool, typer.Option("--write", help="Rewrite the generated blocks of the file.")] = False,
    path: Annotated[Path | None, typer.Option(help="The protocol document (default: docs/protocol.md).")] = None,
) -> None:
    """Check (or with --write, regenerate) the catalogue tables in docs/protocol.md."""
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.config import read_text_file  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    path = path or api.PROTOCOL_DOC
    try:
        old = read_text_file(path, 16 << 20)
    except ValueError as exc:
        raise fail(str(exc)) from None
    try:
        new = api.protocol_docs(old)
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


LinkOption = Literal["servo", "driver", "image", "hexapod"]


@protocol_app.command("decode")
def protocol_decode(  # noqa: PLR0917 (typer maps parameters to options)
    capture: Annotated[str, typer.Argument(
        help="A capture file (.hilcap) or a directory holding one (hil run --capture), a raw binary capture of "
             "one link, '-' for stdin, or hex text with --hex.")],
    hex_input: Annotated[bool, typer.Option("--hex", help="The input is hex text (spaces allowed).")] = False,
    limit: Annotated[int, typer.Option(min=0, help="Print at most this many frames.")] = 50,
    link: Annotated[LinkOption | None, typer.Option(
        help="A capture: only this link. Raw input: check addressing as on this board's link.")] = None,
    direction: Annotated[Literal["rx", "tx"] | None, typer.Option(
        help="A capture: only what the bench received (rx) or sent (tx).")] = None,
    side: Annotated[Literal["host", "board"] | None, typer.Option(
        help="Raw input with --link: the receiving end, host (the bytes are what the board sent; default) or "
             "board.")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Frames and counters as JSON.")] = False,
) -> None:
    """Decode what a link carried: a capture's frames with their times (every link, both directions), or a raw
    capture of one link; then the link counters. Streams: memory stays bounded."""
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    path = Path(capture)
    if capture != "-" and not hex_input and (path.is_dir() or api.is_capture(path)):
        if side is not None:
            raise fail("--side: a capture knows each record's direction; choose it with --direction rx|tx")
        try:
            found = api.find_capture(path)
        except api.CaptureError as exc:
            raise fail(str(exc)) from None
        _decode_capture(found, limit, link, direction, json_out)
        return
    if direction is not None:
        raise fail(f"--direction: {capture} is not a capture file (.hilcap); for raw bytes use --link and --side")
    _decode_raw(capture, hex_input, limit, link, side=side or "host", json_out=json_out)


def _decode_capture(path: Path, limit: int, link: str | None, direction: str | None, json_out: bool) -> None:
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    try:
        result = api.open_capture(path)
    except (api.CaptureError, OSError) as exc:
        raise fail(str(exc)) from None
    if link is not None and link not in result.reader.links:
        raise fail(f"--link: {link!r} is not in this capture (links: {', '.join(result.reader.links)})")
    shown: list[TimedFrame] = []
    n_frames = 0
    try:
        for tf in api.decode_capture(path, links=None if link is None else [link],
                                 directions=None if direction is None else [direction], result=result):
            n_frames += 1
            if len(shown) < limit:
                shown.append(tf)
    except OSError as exc:
        raise fail(f"{path}: cannot read: {exc.strerror or exc}") from None
    reader = result.reader
    t0 = reader.meta.get("created_monotonic_ns")  # times from the capture's opening, whatever is selected
    t0 = t0 if isinstance(t0, int) else result.first_t_ns or 0
    ended = reader.end if reader.end == "complete" else f"{reader.end}: {reader.problem}"
    if json_out:
        print_json({
            "capture": str(path), "meta": reader.meta, "records": reader.records, "end": reader.end,
            "problem": reader.problem, "trailing_bytes": reader.trailing_bytes, "frames_total": n_frames,
            "first_t_ns": result.first_t_ns, "last_t_ns": result.last_t_ns,
            "frames": [{"t_ns": tf.t_ns, "t_s": (tf.t_ns - t0) / 1e9, "link": tf.link, "direction": tf.direction,
                        **api.frame_json(tf.frame)} for tf in shown],
            "counters": {f"{name} {d}": {**dec.counters.as_dict(), "errors": dec.counters.errors(),
                                         "pending": dec.pending}
                         for (name, d), dec in result.decoders.items()},
        })
        return
    table = Table("#", "t (ms)", "link", "dir", "src", "dst", "seq", "message",
                  title=f"{n_frames} frames, {reader.records} records ({ended})")
    for i, tf in enumerate(shown):
        fr = tf.frame
        table.add_row(str(i), f"{(tf.t_ns - t0) / 1e6:.3f}", tf.link, tf.direction, f"{fr.src:#04x}",
                      f"{fr.dst:#04x}", str(fr.seq), repr(fr.message))
    console.print(table)
    if n_frames > limit:
        console.print(f"... {n_frames - limit} more (raise --limit)")
    counters = Table("link", "dir", "frames", "bytes", "errors", "discarded", "lost", "pending",
                     title="link counters (every counter: --json)")
    for (name, d), dec in result.decoders.items():
        c = dec.counters
        if c.bytes:
            counters.add_row(name, d, str(c.frames_ok), str(c.bytes), str(c.errors()), str(c.bytes_discarded),
                             str(sum(c.frames_lost.values())), str(dec.pending))
    console.print(counters)
    if reader.end != "complete":
        err_console.print(f"{path}: {reader.problem}", highlight=False)


def _decode_raw(capture: str, hex_input: bool, limit: int, link: str | None, *, side: str, json_out: bool) -> None:
    from hil import api  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    chunk_bytes = 1 << 16
    if link is None:
        decoder = api.Decoder()
    else:
        board = api.board_of(link)
        if board is None:
            raise fail(f"--link: {link!r} is not servo, driver, image or hexapod")
        decoder = api.Decoder.for_link(board, "host" if side == "host" else "board")
    if capture == "-":
        source, where = sys.stdin.buffer, "stdin"
    elif hex_input:
        source, where = None, "the --hex text"
    else:
        p = Path(capture)
        if not p.is_file():
            raise fail(f"{capture}: no such file (pass --hex to decode hex text given on the command line)")
        try:
            source, where = p.open("rb"), capture
        except OSError as exc:
            raise fail(f"{capture}: cannot read: {exc.strerror}") from None

    def blocks() -> Iterator[bytes]:
        if source is None:
            yield capture.encode()
            return
        while block := source.read(chunk_bytes):
            yield block

    shown: list[Frame] = []
    n_frames = 0
    try:
        for block in api.hex_bytes(blocks(), where) if hex_input else blocks():
            frames = decoder.feed(block)
            n_frames += len(frames)
            if len(shown) < limit:
                shown += frames[: limit - len(shown)]
    except OSError as exc:
        raise fail(f"{where}: cannot read: {exc.strerror or exc}") from None
    except ValueError as exc:  # not hex text
        raise fail(str(exc)) from None
    finally:
        if source is not None and source is not sys.stdin.buffer:
            source.close()
    if json_out:
        print_json({"source": where, "frames_total": n_frames, "frames": [api.frame_json(fr) for fr in shown],
                    "counters": {**decoder.counters.as_dict(), "errors": decoder.counters.errors(),
                                 "pending": decoder.pending}})
        return
    table = Table("#", "src", "dst", "seq", "message", title=f"{n_frames} frames")
    for i, fr in enumerate(shown):
        table.add_row(str(i), f"{fr.src:#04x}", f"{fr.dst:#04x}", str(fr.seq), repr(fr.message))
    console.print(table)
    if n_frames > limit:
        console.print(f"... {n_frames - limit} more (raise --limit)")
    counters = Table("counter", "value", title="link counters")
    for name, value in decoder.counters.as_dict().items():
        counters.add_row(name, str(value))
    counters.add_row("pending (incomplete frame)", str(decoder.pending))
    console.print(counters)
