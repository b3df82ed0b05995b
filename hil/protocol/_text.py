"""Frames and bytes as text: hex text read into bytes block by block, and a decoded frame as JSON values (what
``hil protocol decode`` reads and prints)."""

from __future__ import annotations

import enum
import re
from collections.abc import Iterable, Iterator
from typing import Any

from hil.protocol.framing import Frame
from hil.protocol.messages import CATALOGUE

_NOT_HEX = re.compile(rb"[^0-9a-fA-F \t\r\n:]")


def hex_bytes(blocks: Iterable[bytes], where: str) -> Iterator[bytes]:
    """Hex text to bytes, block by block (a digit pair may straddle two blocks); spaces, tabs, newlines and ':'
    between digits are ignored. ValueError naming ``where`` (the text's source) for a character that is not hex, or
    an odd number of digits at the end."""
    carry, offset = b"", 0
    for text in blocks:
        bad = _NOT_HEX.search(text)
        if bad:
            raise ValueError(f"{where}: not hex text: {bad[0].decode('latin-1')!r} at byte {offset + bad.start()}")
        offset += len(text)
        digits = carry + text.translate(None, b" \t\r\n:")
        cut = len(digits) & ~1
        carry = digits[cut:]
        yield bytes.fromhex(digits[:cut].decode("ascii"))
    if carry:
        raise ValueError(f"{where}: not hex text: an odd number of hex digits")


def message_json(msg: Any) -> dict[str, Any]:
    """A message's fields as JSON values: enums by name, arrays as lists."""
    out: dict[str, Any] = {}
    for name, value in msg._asdict().items():
        if isinstance(value, enum.Enum):
            out[name] = value.name if value.name is not None else int(value)
        else:
            out[name] = list(value) if isinstance(value, tuple) else value
    return out


def frame_json(frame: Frame) -> dict[str, Any]:
    """A frame as JSON values: its addresses, sequence number, message name (the catalogue's) and fields."""
    return {"src": frame.src, "dst": frame.dst, "seq": frame.seq, "message": CATALOGUE.spec(frame.message).name,
            "fields": message_json(frame.message)}
