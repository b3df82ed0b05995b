"""`hil protocol docs` and `hil protocol decode`: the catalogue's docs tables, and decoding what a link carried (a
capture of every link, hil.link, or raw bytes of one)."""

from __future__ import annotations

import enum
import re
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any, Literal

import typer
from rich.table import Table

from hil.cli._common import console, err_console, fail, print_json, protocol_app


@protocol_app.command("docs")
def protocol_docs(
    write: Annotated[bool, typer.Option("--write", help="Rewrite the generated blocks of the file.")] = False,
    path: Annotated[Path | None, typer.Option(help="The protocol document (default: docs/protocol.md).")] = None,
) -> None:
    """Check (or with --write, regenerate) the catalogue tables in docs/protocol.md."""
    from hil.config import read_text_file  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.protocol import docgen  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    path = path or docgen.DOC_PATH
    try:
        old = read_text_file(path, 16 << 20)
    except ValueError as exc:
        raise fail(str(exc)) from None
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
    from hil.link import CaptureError, find_capture, is_capture  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    path = Path(capture)
    if capture != "-" and not hex_input and (path.is_dir() or is_capture(path)):
        if side is not None:
            raise fail("--side: a capture knows each record's direction; choose it with --direction rx|tx")
        try:
            found = find_capture(path)
        except CaptureError as exc:
            raise fail(str(exc)) from None
        _decode_capture(found, limit, link, direction, json_out)
        return
    if direction is not None:
        raise fail(f"--direction: {capture} is not a capture file (.hilcap); for raw bytes use --link and --side")
    _decode_raw(capture, hex_input, limit, link, side=side or "host", json_out=json_out)


def _message_json(msg: Any) -> dict[str, Any]:
    """A message's fields as JSON values: enums by name, arrays as lists."""
    out: dict[str, Any] = {}
    for name, value in msg._asdict().items():
        if isinstance(value, enum.Enum):
            out[name] = value.name if value.name is not None else int(value)
        else:
            out[name] = list(value) if isinstance(value, tuple) else value
    return out


def _frame_json(frame: Any) -> dict[str, Any]:
    from hil.protocol import CATALOGUE  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    return {"src": frame.src, "dst": frame.dst, "seq": frame.seq, "message": CATALOGUE.spec(frame.message).name,
            "fields": _message_json(frame.message)}


def _decode_capture(path: Path, limit: int, link: str | None, direction: str | None, json_out: bool) -> None:
    from hil.link import CaptureDecode, CaptureError, CaptureReader, TimedFrame, decode_capture  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    try:
        result = CaptureDecode(CaptureReader(path))
    except (CaptureError, OSError) as exc:
        raise fail(str(exc)) from None
    if link is not None and link not in result.reader.links:
        raise fail(f"--link: {link!r} is not in this capture (links: {', '.join(result.reader.links)})")
    shown: list[TimedFrame] = []
    n_frames = 0
    try:
        for tf in decode_capture(path, links=None if link is None else [link],
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
                        **_frame_json(tf.frame)} for tf in shown],
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

    from hil.link import board_of  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)
    from hil.protocol import Decoder, Frame  # noqa: PLC0415  (the API loads on first use: `hil --help` stays fast)

    chunk_bytes = 1 << 16
    if link is None:
        decoder = Decoder()
    else:
        board = board_of(link)
        if board is None:
            raise fail(f"--link: {link!r} is not servo, driver, image or hexapod")
        decoder = Decoder.for_link(board, "host" if side == "host" else "board")
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

    def hex_blocks() -> Iterator[bytes]:
        """Hex text to bytes, block by block; spaces, newlines and ':' between digits are ignored."""
        carry, offset = b"", 0
        for text in blocks():
            bad = re.search(rb"[^0-9a-fA-F \t\r\n:]", text)
            if bad:
                raise fail(f"{where}: not hex text: {bad[0].decode('latin-1')!r} at byte {offset + bad.start()}")
            offset += len(text)
            digits = carry + text.translate(None, b" \t\r\n:")
            cut = len(digits) & ~1
            carry = digits[cut:]
            yield bytes.fromhex(digits[:cut].decode("ascii"))
        if carry:
            raise fail(f"{where}: not hex text: an odd number of hex digits")

    shown: list[Frame] = []
    n_frames = 0
    try:
        for block in hex_blocks() if hex_input else blocks():
            frames = decoder.feed(block)
            n_frames += len(frames)
            if len(shown) < limit:
                shown += frames[: limit - len(shown)]
    except OSError as exc:
        raise fail(f"{where}: cannot read: {exc.strerror or exc}") from None
    finally:
        if source is not None and source is not sys.stdin.buffer:
            source.close()
    if json_out:
        print_json({"source": where, "frames_total": n_frames, "frames": [_frame_json(fr) for fr in shown],
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
