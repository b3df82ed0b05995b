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

import dataclasses
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
    for name, node in (("src", src), ("dst", dst)):
        if not (isinstance(node, int) and 0 <= node <= 0xFF):
            raise EncodeError(f"{spec.name} frame {name} = {node!r}: a node id is a byte, 0..255")
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
    bad_lengths: int = 0  # claimed length > MAX_PAYLOAD, or not the catalogue's length for the id
    unknown_ids: int = 0  # headers with an id this catalogue does not define (rejected at the header)
    resyncs: int = 0  # times the decoder lost frame alignment and had to hunt for a sync word
    bytes_discarded: int = 0
    seq_gaps: dict[int, int] = field(default_factory=dict)  # per source id: gaps seen
    frames_lost: dict[int, int] = field(default_factory=dict)  # per source id: frames the gaps skipped

    def errors(self) -> int:
        """Sum of every error counter (a clean link reads 0)."""
        return self.crc_errors + self.bad_lengths + self.unknown_ids + sum(self.seq_gaps.values())

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


class Decoder:
    """Streaming frame decoder: feed it any byte chunks, get frames back. Never raises.

    Receiver rules (docs/protocol.md, "Receiving"):
    - hunt for the sync word; bytes before it are discarded;
    - reject a header at once (without waiting for its payload) when the version is wrong, the
      id is not in the catalogue, or the claimed length is not that message's length (so a
      claimed length beyond MAX_PAYLOAD is always dropped at once);
    - on a bad header or CRC, discard only the first sync byte and rescan from the next byte,
      so a false sync never swallows a real frame that starts inside its claimed span.
    A false sync therefore holds back the next real frame by at most ``max_frame`` bytes (the
    catalogue's longest frame), and that is also the most memory kept between calls.
    """

    def __init__(self, catalogue: Catalogue = CATALOGUE) -> None:
        self.catalogue = catalogue
        self.counters = LinkCounters()
        self._buf = bytearray()
        self._last_seq: list[int] = [-1] * 256
        self._aligned = True
        # per-id tables for the hot loop: payload size (-1 = unknown id) and payload decoder
        self._size_of = [-1] * 256
        self._decoder_of: list[Any] = [None] * 256
        for spec in catalogue:
            self._size_of[spec.msg_id] = spec.payload_size
            self._decoder_of[spec.msg_id] = spec.payload_decoder

    @property
    def max_frame(self) -> int:
        """Longest frame of the catalogue: the most a false sync can make the decoder wait for."""
        return HEADER_SIZE + max(self._size_of) + CRC_SIZE

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
        """Append ``data`` and return every frame it completed, in order."""
        buf = self._buf
        buf += data
        c = self.counters
        c.bytes += len(data)
        size_of = self._size_of
        decoder_of = self._decoder_of
        version = self.catalogue.protocol_version
        last_seq = self._last_seq
        unpack_header = _HEADER.unpack_from
        new_frame = tuple.__new__
        out: list[Frame] = []
        n = len(buf)
        pos = 0
        frames_ok = bytes_ok = 0  # kept local in the hot loop, added to the counters at the end
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
            size = size_of[msg_id]  # -1 for an id this catalogue does not define
            if length != size or ver != version:
                if ver == version:
                    if size < 0 and length <= MAX_PAYLOAD:
                        c.unknown_ids += 1
                    else:
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
            out.append(new_frame(Frame, (src, dst, seq, decoder_of[msg_id](buf, pos + HEADER_SIZE))))
            frames_ok += 1
            bytes_ok += end - pos
            pos = end
        c.frames_ok += frames_ok
        c.bytes_in_frames += bytes_ok
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
