"""Frames on the wire: CRC, encoder, and the streaming decoder (docs/protocol.md, "Framing").

Frame layout, all multi-byte fields little-endian::

    offset  size  field
    0       2     sync word EB 90
    2       1     protocol version (1)
    3       1     source node id
    4       1     destination node id
    5       1     message id
    6       2     sequence number (per sender and link, wraps at 65535)
    8       1     payload length N (<= MAX_PAYLOAD)
    9       N     payload
    9+N     2     CRC-16/CCITT-FALSE over bytes 2 .. 8+N (header after sync, and payload)
"""

from __future__ import annotations

import struct
from binascii import crc_hqx
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from hil.protocol.messages import CATALOGUE, PROTOCOL_VERSION
from hil.protocol.wire import Catalogue, EncodeError

SYNC = b"\xeb\x90"
HEADER_SIZE = 9  # sync included
CRC_SIZE = 2
MAX_PAYLOAD = 240
MAX_FRAME = HEADER_SIZE + MAX_PAYLOAD + CRC_SIZE
CRC_INIT = 0xFFFF
_HEADER = struct.Struct("<BBBBHB")  # version, src, dst, msg_id, seq, length (after the sync)


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, xorout 0; check("123456789") = 0x29B1."""
    return crc_hqx(data, CRC_INIT)


class Frame(NamedTuple):
    """A decoded frame: header fields and the message it carried."""

    src: int
    dst: int
    seq: int
    message: Any


def encode_frame(message: Any, *, src: int, dst: int, seq: int, catalogue: Catalogue = CATALOGUE) -> bytes:
    """Encode one message as a complete frame. Raises EncodeError naming the field on bad values."""
    spec = catalogue.spec(message)
    raw = spec.raw_values(message)
    header = SYNC + _HEADER.pack(catalogue.protocol_version, src, dst, spec.msg_id, seq & 0xFFFF, spec.payload_size)
    body = header + spec.payload_struct.pack(*raw)
    return body + crc16(memoryview(body)[2:]).to_bytes(2, "little")


class Encoder:
    """Frames messages from one sender on one link, numbering them 0, 1, ... 65535, 0, ..."""

    def __init__(self, src: int, catalogue: Catalogue = CATALOGUE) -> None:
        self.src = int(src)
        self.catalogue = catalogue
        self.next_seq = 0

    def encode(self, message: Any, dst: int) -> bytes:
        frame = encode_frame(message, src=self.src, dst=dst, seq=self.next_seq, catalogue=self.catalogue)
        self.next_seq = (self.next_seq + 1) & 0xFFFF
        return frame


@dataclass
class LinkCounters:
    """What a decoder saw on one link. Invariant: bytes = bytes_in_frames + bytes_discarded + pending."""

    bytes: int = 0
    frames_ok: int = 0
    bytes_in_frames: int = 0
    crc_errors: int = 0
    bad_lengths: int = 0  # claimed length > MAX_PAYLOAD, or not the catalogue's length for a known id
    unknown_ids: int = 0  # frames with a good CRC and an id this catalogue does not define (skipped)
    resyncs: int = 0  # times the decoder lost frame alignment and had to hunt for a sync word
    bytes_discarded: int = 0
    seq_gaps: dict[int, int] = field(default_factory=dict)  # per source id: gaps seen
    frames_lost: dict[int, int] = field(default_factory=dict)  # per source id: frames the gaps skipped

    def errors(self) -> int:
        """Sum of every error counter (a clean link reads 0)."""
        return self.crc_errors + self.bad_lengths + self.unknown_ids + sum(self.seq_gaps.values())

    def as_dict(self) -> dict[str, Any]:
        return {
            "bytes": self.bytes,
            "frames_ok": self.frames_ok,
            "crc_errors": self.crc_errors,
            "bad_lengths": self.bad_lengths,
            "unknown_ids": self.unknown_ids,
            "resyncs": self.resyncs,
            "bytes_discarded": self.bytes_discarded,
            "seq_gaps": dict(self.seq_gaps),
            "frames_lost": dict(self.frames_lost),
        }


class Decoder:
    """Streaming frame decoder: feed it any byte chunks, get frames back. Never raises.

    Receiver rules (docs/protocol.md, "Receiving"):
    - hunt for the sync word; bytes before it are discarded;
    - reject a header at once (without waiting for its payload) when the version is wrong, the
      claimed length exceeds MAX_PAYLOAD, or a known id claims a length other than its own;
    - on a bad header or CRC, discard only the first sync byte and rescan from the next byte,
      so a false sync never swallows a real frame that starts inside its claimed span;
    - a frame with a good CRC but an unknown id is counted and skipped whole.
    Memory is bounded: between calls at most MAX_FRAME - 1 bytes are kept.
    """

    def __init__(self, catalogue: Catalogue = CATALOGUE) -> None:
        self.catalogue = catalogue
        self.counters = LinkCounters()
        self._buf = bytearray()
        self._last_seq: list[int] = [-1] * 256
        self._aligned = True

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget partial input and sequence history (after a reconnect or a board reset)."""
        self._discard(len(self._buf))
        self._buf.clear()
        self._last_seq = [-1] * 256

    def _discard(self, n: int) -> None:
        if n:
            self.counters.bytes_discarded += n
            if self._aligned:
                self.counters.resyncs += 1
                self._aligned = False

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        buf = self._buf
        buf += data
        c = self.counters
        c.bytes += len(data)
        by_id = self.catalogue.by_id
        version = self.catalogue.protocol_version
        last_seq = self._last_seq
        unpack_header = _HEADER.unpack_from
        out: list[Frame] = []
        n = len(buf)
        pos = 0
        while True:
            start = buf.find(SYNC, pos)
            if start < 0:
                # keep a trailing first sync byte: it may begin the next frame
                keep_from = n - 1 if n > pos and buf[n - 1] == SYNC[0] else n
                self._discard(keep_from - pos)
                pos = keep_from
                break
            if start != pos:
                self._discard(start - pos)
                pos = start
            if n - pos < HEADER_SIZE:
                break
            ver, src, dst, msg_id, seq, length = unpack_header(buf, pos + 2)
            spec = by_id.get(msg_id)
            if ver != version or length > MAX_PAYLOAD or (spec is not None and length != spec.payload_size):
                if ver == version:
                    c.bad_lengths += 1
                self._discard(1)
                pos += 1
                continue
            end = pos + HEADER_SIZE + length + CRC_SIZE
            if end > n:
                break
            if crc_hqx(buf[pos + 2 : end - 2], CRC_INIT) != buf[end - 2] | (buf[end - 1] << 8):
                c.crc_errors += 1
                self._discard(1)
                pos += 1
                continue
            self._aligned = True
            last = last_seq[src]
            if last >= 0 and seq != (last + 1) & 0xFFFF:
                c.seq_gaps[src] = c.seq_gaps.get(src, 0) + 1
                c.frames_lost[src] = c.frames_lost.get(src, 0) + ((seq - last - 1) & 0xFFFF)
            last_seq[src] = seq
            if spec is None:
                c.unknown_ids += 1
                c.bytes_discarded += end - pos
            else:
                out.append(Frame(src, dst, seq, spec.decode_payload(buf, pos + HEADER_SIZE)))
                c.frames_ok += 1
                c.bytes_in_frames += end - pos
            pos = end
        del buf[:pos]
        return out


__all__ = [
    "CRC_INIT",
    "HEADER_SIZE",
    "MAX_FRAME",
    "MAX_PAYLOAD",
    "PROTOCOL_VERSION",
    "SYNC",
    "Decoder",
    "EncodeError",
    "Encoder",
    "Frame",
    "LinkCounters",
    "crc16",
    "encode_frame",
]
