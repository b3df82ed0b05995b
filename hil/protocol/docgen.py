"""Generate the catalogue sections of docs/protocol.md from the catalogue itself.

The document keeps hand-written prose around blocks fenced by
``<!-- BEGIN GENERATED: name -->`` / ``<!-- END GENERATED: name -->``; this module renders
each block, and a test fails when the committed document differs from the rendering.
Regenerate with the ``hil protocol docs`` command (its write option).
"""

from __future__ import annotations

import re
from enum import IntEnum, IntFlag
from pathlib import Path
from typing import Any, NamedTuple

from hil.protocol import messages as m
from hil.protocol.budget import direction, loop_wire_delay_s, periodic_load_bits_per_s, periodic_rate_hz
from hil.protocol.framing import (
    CRC_SIZE,
    HEADER_SIZE,
    LINE_RATE_BAUD,
    MAX_PAYLOAD,
    encode_frame,
    frame_size,
    wire_time_s,
)
from hil.protocol.wire import Catalogue, FieldSpec, MessageSpec

DOC_PATH = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"

BOARD_SECTIONS: list[tuple[str, m.Board | None]] = [
    ("Common messages (every board)", None),
    ("Servo-control board", m.Board.SERVO),
    ("Motor driver board", m.Board.DRIVER),
    ("Image-processing board", m.Board.IMAGE),
    ("Hexapod controller", m.Board.HEXAPOD),
]
ENUMS: list[type[IntEnum] | type[IntFlag]] = [
    m.Board,
    m.BoardState,
    m.ErrorCode,
    m.StreamMode,
    m.AxisMask,
    m.DriveFault,
    m.TrackMode,
    m.HexAxis,
    m.HexapodState,
]


class Example(NamedTuple):
    title: str
    src: m.Board
    dst: m.Board
    seq: int
    message: Any


EXAMPLES: list[Example] = [
    Example(
        "GYRO_SAMPLE, servo board to host",
        m.Board.SERVO,
        m.Board.HOST,
        0x0102,
        m.GyroSample(1_000_000, 1000, 0.5, -0.25, 12.0, 30.0, -5.5),
    ),
    Example("DRIVE_CMD, host to motor driver", m.Board.HOST, m.Board.DRIVER, 7, m.DriveCmd(1000, 1200, -350)),
    Example(
        "MISS_DISTANCE, image board to host",
        m.Board.IMAGE,
        m.Board.HOST,
        42,
        m.MissDistance(42, 1_234_567, 3.25, -1.5, True),
    ),
    Example(
        "NACK, hexapod refusing a profile beyond its pitch envelope",
        m.Board.HEXAPOD,
        m.Board.HOST,
        3,
        m.Nack(0x40, 2, m.ErrorCode.ENVELOPE_POSITION, m.HexAxis.PITCH, 12.5, 10.0),
    ),
    Example("HEXAPOD_START (empty payload), host to hexapod", m.Board.HOST, m.Board.HEXAPOD, 0, m.HexapodStart()),
]


def _scaling(f: FieldSpec) -> str:
    w = f.wire
    if w.enum is not None:
        kind = "flags" if issubclass(w.enum, IntFlag) else "enum"
        return f"{kind} {w.enum.__name__}"
    if w.kind == "char":
        return "ASCII, NUL-padded"
    if w.kind == "bool":
        return "0 or 1"
    if w.scale == 1:
        return "1"
    return f"1 LSB = {w.scale:g}"


def _num(x: float) -> str:
    return f"{x:.10g}"


def _range(f: FieldSpec) -> str:
    w = f.wire
    if w.kind == "char" or w.enum is not None or w.kind == "bool":
        return ""
    if w.primitive.is_float:
        return "finite"
    lo, hi = w.eng_range
    return f"{_num(lo)} … {_num(hi)}"


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def render_message(spec: MessageSpec) -> str:
    lines = [
        f"#### `{spec.msg_id:#04x}` {spec.name}",
        "",
        f"{direction(spec)}; rate: {spec.rate}"
        + (f"; reply: {spec.reply}" if spec.reply else "")
        + f"; payload {spec.payload_size} bytes; fingerprint `{spec.fingerprint:#010x}`.",
        "",
        " ".join(line.strip() for line in spec.doc.splitlines() if line.strip()),
        "",
    ]
    if not spec.fields:
        lines.append("No payload.")
        return "\n".join(lines)
    lines += [
        "| offset | field | type | unit | scaling | range | description |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for f in spec.fields:
        w = f.wire
        lines.append(
            f"| {f.offset} | `{f.name}` | {w.type_label} | {_cell(w.unit)} | {_scaling(f)} | {_range(f)} "
            f"| {_cell(w.doc)} |"
        )
    return "\n".join(lines)


def _belongs(spec: MessageSpec, board: m.Board | None) -> bool:
    if board is None:
        return spec.sender is None or spec.receiver is None
    return board in (spec.sender, spec.receiver)


def render_catalogue(cat: Catalogue) -> str:
    out = [
        f"Protocol version {cat.protocol_version}; catalogue fingerprint **`{cat.fingerprint:#010x}`** "
        "(what IDENT must carry).",
        "",
        "| id | message | direction | rate | reply | payload bytes | fingerprint |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    out += [
        f"| `{s.msg_id:#04x}` | {s.name} | {direction(s)} | {s.rate} | {s.reply} | {s.payload_size} "
        f"| `{s.fingerprint:#010x}` |"
        for s in cat
    ]
    for title, board in BOARD_SECTIONS:
        node = "" if board is None else f" (node id `{board.value:#04x}`)"
        out += ["", f"### {title}{node}", ""]
        out += ["\n\n".join(render_message(s) for s in cat if _belongs(s, board))]
    return "\n".join(out)


def render_enums() -> str:
    out: list[str] = []
    for enum in ENUMS:
        kind = "bit flags" if issubclass(enum, IntFlag) else "values"
        doc = (enum.__doc__ or "").strip()
        doc = "" if doc.startswith(("An enumeration", "Support for integer-based Flags")) else doc
        out += [f"**{enum.__name__}** ({kind}){': ' + doc if doc else ''}", ""]
        out += ["| name | value |", "| --- | --- |"]
        out += [f"| {member.name} | `{member.value:#04x}` ({member.value}) |" for member in enum]
        out.append("")
    return "\n".join(out).rstrip()


def render_examples() -> str:
    out: list[str] = []
    for ex in EXAMPLES:
        frame = encode_frame(ex.message, src=ex.src, dst=ex.dst, seq=ex.seq)
        spec = m.CATALOGUE.spec(ex.message)
        out += [f"**{ex.title}**: `{ex.message!r}`, seq {ex.seq}", "", "```", frame.hex(" "), "```", ""]
        rows = [
            (0, 2, "sync"),
            (2, 1, "version"),
            (3, 1, f"src = {ex.src.name}"),
            (4, 1, f"dst = {ex.dst.name}"),
            (5, 1, f"msg_id = {spec.name}"),
            (6, 2, f"seq = {ex.seq}"),
            (8, 1, f"length = {spec.payload_size}"),
        ]
        for f, value in zip(spec.fields, ex.message, strict=True):
            shown = value.name if hasattr(value, "name") else value
            if f.wire.scale != 1:
                shown = f"{value} {f.wire.unit} (raw {round(value / f.wire.scale)})"
            rows.append((HEADER_SIZE + f.offset, f.wire.size, f"{f.name} = {shown}"))
        crc_at = HEADER_SIZE + spec.payload_size
        rows.append((crc_at, CRC_SIZE, f"CRC-16 = {int.from_bytes(frame[crc_at:], 'little'):#06x}"))
        out += ["| offset | bytes | meaning |", "| --- | --- | --- |"]
        out += [f"| {off} | `{frame[off:off + n].hex(' ')}` | {_cell(text)} |" for off, n, text in rows]
        out.append("")
    return "\n".join(out).rstrip()


def render_layout(cat: Catalogue) -> str:
    return "```\n" + cat.layout_text() + "\n```"


def _baud(rate: int) -> str:
    """A line rate as the docs write it: 921 600, 6 000 000."""
    return f"{rate:,}".replace(",", " ")


def render_limits(cat: Catalogue) -> str:
    longest = max(cat, key=lambda s: s.payload_size)
    frame = HEADER_SIZE + longest.payload_size + CRC_SIZE
    return (
        f"`MAX_PAYLOAD` = {MAX_PAYLOAD} bytes (a frame of at most {HEADER_SIZE + MAX_PAYLOAD + CRC_SIZE} bytes). "
        f"The longest message of this catalogue is {longest.name}: a **{frame}-byte frame**, "
        f"{frame * 10 / LINE_RATE_BAUD * 1e6:.0f} us at {_baud(LINE_RATE_BAUD)} baud (the default line rate), "
        f"{frame * 10 / 921_600 * 1e6:.0f} us at {_baud(921_600)} baud."
    )


BAUDS = (921_600, LINE_RATE_BAUD)  # the slow lab's and the default


def render_link_budget(cat: Catalogue) -> str:
    """Wire time and link load of the periodic messages (8N1: 10 bit times per byte)."""
    head = " | ".join(f"wire time at {b / 1e6:g} Mbaud" for b in BAUDS)
    out = [f"| message | frame bytes | rate | {head} |", "| --- | --- | --- |" + " --- |" * len(BAUDS)]
    for s in cat:
        hz = periodic_rate_hz(s)
        if hz is None:
            continue
        size = frame_size(s)
        times = " | ".join(f"{wire_time_s(s, b) * 1e6:.0f} us" for b in BAUDS)
        out.append(f"| {s.name} | {size} | {hz:g} Hz | {times} |")
    load = periodic_load_bits_per_s(cat)
    out += ["", "Periodic load per link direction (each board has its own full-duplex link; HEARTBEAT adds 36 B/s):"]
    for link, bits in sorted(load.items()):
        share = ", ".join(f"{100 * bits / b:.0f} % of {b / 1e6:g} Mbaud" for b in BAUDS)
        out.append(f"- {link}: {bits / 10 / 1e3:.1f} kB/s ({share})")
    delays = ", ".join(f"{loop_wire_delay_s(b, b, cat) * 1e6:.0f} us at {b / 1e6:g} Mbaud" for b in BAUDS)
    out += ["", f"The 1 kHz loop's wire delay, a GYRO_SAMPLE's wire time plus its DRIVE_CMD's: {delays}."]
    return "\n".join(out)


def render_blocks(cat: Catalogue = m.CATALOGUE) -> dict[str, str]:
    return {
        "limits": render_limits(cat),
        "budget": render_link_budget(cat),
        "catalogue": render_catalogue(cat),
        "enums": render_enums(),
        "examples": render_examples(),
        "layout": render_layout(cat),
    }


_BLOCK = re.compile(r"(<!-- BEGIN GENERATED: (\w+) -->\n)(.*?)(<!-- END GENERATED: \2 -->)", re.S)


def apply(doc: str, blocks: dict[str, str] | None = None) -> str:
    """Return ``doc`` with every generated block replaced by its current rendering."""
    blocks = render_blocks() if blocks is None else blocks
    missing = set(blocks) - {found[1] for found in _BLOCK.findall(doc)}
    if missing:
        raise ValueError(f"docs/protocol.md lacks the generated block(s): {', '.join(sorted(missing))}")
    return _BLOCK.sub(lambda mo: mo.group(1) + blocks[mo.group(2)] + "\n" + mo.group(4), doc)
