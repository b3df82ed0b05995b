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
import itertools
import struct
from binascii import crc_hqx
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

from hil.protocol.messages import CATALOGUE, PROTOCOL_VERSION, Board
from hil.protocol.wire import Catalogue, EncodeError, MessageSpec

SYNC = b"\xeb\x90"
HEADER_SIZE = 9  # sync included
CRC_SIZE = 2
MAX_PAYLOAD = 240
MAX_FRAME = HEADER_SIZE + MAX_PAYLOAD + CRC_SIZE
BITS_PER_BYTE = 10  # 8N1 on the wire: a start bit, 8 data bits, a stop bit
LINE_RATE_BAUD = 6_000_000  # every link's default line rate (docs/protocol.md, "Link budget"; docs/emulator.md)


def frame_size(spec: MessageSpec) -> int:
    """Bytes of one frame of ``spec`` on the wire: header (sync included), payload, CRC."""
    return HEADER_SIZE + spec.payload_size + CRC_SIZE


def wire_time_s(spec: MessageSpec, baudrate: float) -> float:
    """Seconds from a frame's first bit on the wire to its last, at ``baudrate`` (8N1)."""
    return frame_size(spec) * BITS_PER_BYTE / baudrate
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
    _check_nodes(spec.name, src, dst)
    return _pack_frame(catalogue.protocol_version, spec, spec.raw_values(message), src=src, dst=dst, seq=seq)


def _check_nodes(name: str, src: Any, dst: Any) -> None:
    for what, node in (("src", src), ("dst", dst)):
        if not (isinstance(node, int) and 0 <= node <= 0xFF):
            raise EncodeError(f"{name} frame {what} = {node!r}: a node id is a byte, 0..255")


def _pack_frame(version: int, spec: Any, raw: list[Any], *, src: int, dst: int, seq: int) -> bytes:
    header = SYNC + _HEADER.pack(version, src, dst, spec.msg_id, seq & 0xFFFF, spec.payload_size)
    body = header + spec.payload_struct.pack(*raw)
    return body + crc16(memoryview(body)[2:]).to_bytes(2, "little")


class Encoder:
    """Frames messages from one sender on one link, numbering them 0, 1, ... 65535, 0, ...

    A number is taken (:meth:`take_seq`) in one C call, ``next()`` of an ``itertools.count``, which the GIL makes
    atomic: the realtime loop thread (DRIVE_CMD, :class:`FramePacker`) and the event loop (commands, HOST_ALIVE)
    send on the same driver link and never share a number. A message that fails to encode takes none.
    """

    def __init__(self, src: int, catalogue: Catalogue = CATALOGUE) -> None:
        self.src = int(src)
        self.catalogue = catalogue
        self.next_seq = 0

    @property
    def next_seq(self) -> int:
        """The number the next frame will carry (informational while another thread may be sending)."""
        return self._next

    @next_seq.setter
    def next_seq(self, value: int) -> None:
        self._count = itertools.count(value & 0xFFFF)
        self._next = value & 0xFFFF

    def take_seq(self) -> int:
        seq = next(self._count) & 0xFFFF
        self._next = (seq + 1) & 0xFFFF
        return seq

    def encode(self, message: Any, dst: int) -> bytes:
        """One frame; its sequence number is ``frame[6:8]`` (little-endian), see :func:`frame_seq`."""
        spec = self.catalogue.spec(message)
        _check_nodes(spec.name, self.src, dst)
        raw = spec.raw_values(message)  # EncodeError here takes no number
        return _pack_frame(self.catalogue.protocol_version, spec, raw, src=self.src, dst=dst, seq=self.take_seq())


def frame_seq(frame: bytes | bytearray) -> int:
    """The sequence number of an encoded frame."""
    return frame[6] | (frame[7] << 8)


class FramePacker:
    """A precompiled encoder for one message type from ``encoder``'s sender to ``dst``: one ``struct.pack`` of header
    and payload, then the CRC, with the sequence number taken from ``encoder`` (so both share one count).

    For the 1 kHz DRIVE_CMD (``packer(tick, az_counts, el_counts)``): no per-field range checks, because the caller
    has bounded the values (the session's clamp); ``struct`` still refuses a value beyond its field's width
    (``struct.error``), so nothing wraps silently. Only messages whose fields are all unscaled integer scalars
    qualify (ValueError otherwise). The bytes equal :meth:`Encoder.encode`'s for the same values and number.
    """

    def __init__(self, cls: type, encoder: Encoder, dst: int) -> None:
        catalogue = encoder.catalogue
        spec = next((s for s in catalogue if s.cls is cls), None)
        if spec is None:
            raise ValueError(f"{cls.__name__} is not a message of this catalogue")
        for f in spec.fields:
            w = f.wire
            if w.kind in ("char", "bool") or w.count != 1 or w.scale != 1 or w.primitive.is_float:
                raise ValueError(f"{spec.name}.{f.name}: a precompiled frame takes unscaled integer fields only")
        _check_nodes(spec.name, encoder.src, dst)
        self.spec = spec
        pack = struct.Struct("<2s" + _HEADER.format.lstrip("<") + spec.payload_struct.format.lstrip("<")).pack
        head = (SYNC, catalogue.protocol_version, encoder.src, dst, spec.msg_id)
        length = spec.payload_size
        take_seq = encoder.take_seq

        def packer(*values: int) -> bytes:
            body = pack(*head, take_seq(), length, *values)
            return body + crc_hqx(body[2:], CRC_INIT).to_bytes(2, "little")

        self.pack = packer


@dataclass
class LinkCounters:
    """What a decoder saw on one link (docs/protocol.md, "Receiving"); all counts since the last reset.

    Invariant: bytes = bytes_in_frames + bytes_discarded + pending. ``frames_ok`` counts the frames
    delivered; a frame with a good CRC that addressing refuses (``misaddressed``, ``wrong_link``)
    is consumed whole (its bytes are in ``bytes_in_frames``) but not delivered. The per-source
    sequence counters (dicts keyed by source node id) see every frame with a good CRC.
    """

    bytes: int = 0
    frames_ok: int = 0  # frames delivered
    bytes_in_frames: int = 0  # bytes of every frame with a good CRC, delivered or refused by addressing
    crc_errors: int = 0
    bad_versions: int = 0  # headers whose version byte is not the catalogue's (rejected at the header)
    bad_lengths: int = 0  # claimed length > MAX_PAYLOAD, or not the catalogue's length for the id
    unknown_ids: int = 0  # headers with an id this catalogue does not define (rejected at the header)
    misaddressed: int = 0  # good frames from another source node, or for another destination node
    wrong_link: int = 0  # good frames of a message that this link does not carry (e.g. DRIVE_STATUS on servo)
    resyncs: int = 0  # times the decoder lost frame alignment and had to hunt for a sync word
    bytes_discarded: int = 0
    seq_gaps: dict[int, int] = field(default_factory=dict)  # per source id: forward jumps in the sequence
    frames_lost: dict[int, int] = field(default_factory=dict)  # per source id: frames the gaps skipped
    duplicates: dict[int, int] = field(default_factory=dict)  # per source id: same seq again (a resend)
    reordered: dict[int, int] = field(default_factory=dict)  # per source id: steps back (late frames)
    restarts: dict[int, int] = field(default_factory=dict)  # per source id: count restarted at 0 (board reset)

    def errors(self) -> int:
        """Sum of every error counter (a clean link reads 0).

        Counts each rejected frame, each sequence gap (not the frames it skipped) and each
        reordered frame. Duplicates and restarts are left out: a resend and a board reset lose no
        data and are expected (retries, power cycles); they have their own counters.
        """
        return (
            self.crc_errors + self.bad_versions + self.bad_lengths + self.unknown_ids + self.rejected()
            + sum(self.seq_gaps.values()) + sum(self.reordered.values())
        )

    def rejected(self) -> int:
        """Frames with a good CRC refused by addressing: misaddressed plus wrong_link."""
        return self.misaddressed + self.wrong_link

    def bad_frames(self) -> int:
        """Candidates refused at the header: bad version, bad length or unknown id."""
        return self.bad_versions + self.bad_lengths + self.unknown_ids

    def totals(self) -> dict[str, int]:
        """Whole-link totals, per-source counters summed: the session log's links columns
        (hil.log.schema.LINK_COUNTERS, same names and order)."""
        return {
            "frames_ok": self.frames_ok,
            "crc_errors": self.crc_errors,
            "bad_frames": self.bad_frames(),
            "bytes_discarded": self.bytes_discarded,
            "frames_lost": sum(self.frames_lost.values()),
            "duplicates": sum(self.duplicates.values()),
            "reordered": sum(self.reordered.values()),
            "restarts": sum(self.restarts.values()),
            "rejected": self.rejected(),
        }

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


Side = Literal["host", "board"]


def link_message_ids(board: int, side: Side = "host", catalogue: Catalogue = CATALOGUE) -> frozenset[int]:
    """Ids of the messages ``side`` may receive on ``board``'s link, from the catalogue's sender/receiver.

    On the host's side: messages whose sender is ``board`` or any board (None) and whose receiver
    is the host (or None). On the board's side, the mirror: sender the host (or None), receiver
    ``board`` or any board.
    """
    if side not in ("host", "board"):
        raise ValueError(f"side {side!r}: expected 'host' or 'board'")
    near, far = (Board.HOST, board) if side == "host" else (board, Board.HOST)
    return frozenset(s.msg_id for s in catalogue if s.sender in (far, None) and s.receiver in (near, None))


class Decoder:
    """Streaming frame decoder: feed it any byte chunks, get frames back. Never raises.

    Receiver rules (docs/protocol.md, "Receiving"):
    - hunt for the sync word; bytes before it are discarded;
    - reject a header at once (without waiting for its payload) when the version is wrong, the
      id is not in the catalogue, or the claimed length is not that message's length (so a
      claimed length beyond MAX_PAYLOAD is always dropped at once);
    - on a bad header or CRC, discard only the first sync byte and rescan from the next byte,
      so a false sync never swallows a real frame that starts inside its claimed span;
    - track the sequence number per source (``_track_seq``) for every frame with a good CRC;
    - when the decoder knows its link (``src``, ``dst``, ``msg_ids``, or :meth:`for_link`), drop
      a good frame from another source or for another destination (``misaddressed``) or of a
      message the link does not carry (``wrong_link``): consumed, counted, never delivered.
    A false sync therefore holds back the next real frame by at most ``max_frame`` bytes (the
    catalogue's longest frame), and that is also the most memory kept between calls.

    ``Decoder()`` accepts any source, destination and catalogue message (a capture tool).
    """

    def __init__(
        self,
        catalogue: Catalogue = CATALOGUE,
        *,
        src: int | None = None,
        dst: int | None = None,
        msg_ids: Iterable[int] | None = None,
    ) -> None:
        """``src``/``dst``: the only source and destination node ids accepted (None: any);
        ``msg_ids``: the only message ids accepted (None: every id of the catalogue)."""
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
        # addressing: checked only when something is restricted (one boolean test per frame otherwise)
        self.src = src
        self.dst = dst
        self.msg_ids = None if msg_ids is None else frozenset(msg_ids)
        self._on_link = [self.msg_ids is None or i in self.msg_ids for i in range(256)]
        self._src_ok = [src is None or i == src for i in range(256)]
        self._dst_ok = [dst is None or i == dst for i in range(256)]
        self._check_address = src is not None or dst is not None or self.msg_ids is not None
        self.last_misaddressed: tuple[int, int] | None = None  # (src, dst) of the latest misaddressed frame

    @classmethod
    def for_link(cls, board: int, side: Side = "host", catalogue: Catalogue = CATALOGUE) -> Decoder:
        """The decoder of one end of ``board``'s link: ``side="host"`` receives what the board sends
        (src = board, dst = host), ``side="board"`` what the host sends (src = host, dst = board);
        only the messages the catalogue routes that way (:func:`link_message_ids`) are delivered."""
        board = int(board)
        src, dst = (board, int(Board.HOST)) if side == "host" else (int(Board.HOST), board)
        return cls(catalogue, src=src, dst=dst, msg_ids=link_message_ids(board, side, catalogue))

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

    def note_restart(self, src: int) -> None:
        """``src`` restarted its count (it announced IDENT at boot): its next frame starts afresh,
        without counting loss, reordering or a restart."""
        self._last_seq[src] = -1

    def _track_seq(self, src: int, seq: int, last: int) -> int:
        """Count an out-of-step sequence number (``seq`` is not ``last + 1``); returns the new last.

        With d = (seq - last) mod 65536: d == 0 a duplicate; seq == 0 a restart (no loss); a step
        back (d >= 32768) a reordered frame (last stays); otherwise a gap of d - 1 lost frames."""
        c = self.counters
        d = (seq - last) & 0xFFFF
        if d == 0:
            c.duplicates[src] = c.duplicates.get(src, 0) + 1
            return last
        if seq == 0:
            c.restarts[src] = c.restarts.get(src, 0) + 1
            return 0
        if d >= 0x8000:
            c.reordered[src] = c.reordered.get(src, 0) + 1
            return last
        c.seq_gaps[src] = c.seq_gaps.get(src, 0) + 1
        c.frames_lost[src] = c.frames_lost.get(src, 0) + d - 1
        return seq

    def _discard(self, n: int) -> None:
        if n:
            self.counters.bytes_discarded += n
            if self._aligned:
                self.counters.resyncs += 1
                self._aligned = False

    def fast_feed(self, cls: type) -> Callable[[bytes], list[Frame]]:
        """A :meth:`feed` with a fixed-layout fast path for ``cls`` (the loop thread's GYRO_SAMPLE).

        A chunk that starts with one whole, good frame of ``cls`` from this link's source to its destination, while
        nothing is held back, is taken with one prefix compare, one CRC and one payload unpack instead of the sync
        hunt; whatever follows it, and any other chunk, goes to :meth:`feed`. Frames, counters and sequence tracking
        come out exactly as :meth:`feed` gives them (tested). Needs a decoder that knows its link (:meth:`for_link`).
        """
        spec = next((s for s in self.catalogue if s.cls is cls), None)
        if spec is None or self.src is None or self.dst is None or not self._on_link[spec.msg_id]:
            raise ValueError(f"{cls.__name__}: the fast path needs a message this link carries and a decoder that "
                             "knows its source and destination (Decoder.for_link)")
        src, dst, length = self.src, self.dst, spec.payload_size
        prefix = SYNC + bytes((self.catalogue.protocol_version, src, dst, spec.msg_id))
        size = HEADER_SIZE + length + CRC_SIZE
        decode = spec.payload_decoder
        feed, counters, new_frame = self.feed, self.counters, tuple.__new__

        def fast(data: bytes) -> list[Frame]:
            if (self._buf or len(data) < size or data[8] != length or not data.startswith(prefix)
                    or crc_hqx(data[2 : size - 2], CRC_INIT) != data[size - 2] | (data[size - 1] << 8)):
                return feed(data)
            seq = data[6] | (data[7] << 8)
            last_seq = self._last_seq
            last = last_seq[src]
            last_seq[src] = seq if last < 0 or seq == (last + 1) & 0xFFFF else self._track_seq(src, seq, last)
            counters.bytes += size
            counters.frames_ok += 1
            counters.bytes_in_frames += size
            self._aligned = True
            frame = new_frame(Frame, (src, dst, seq, decode(data, HEADER_SIZE)))
            if len(data) == size:
                return [frame]
            return [frame, *feed(data[size:])]

        return fast

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
        check_address, src_ok, dst_ok, on_link = self._check_address, self._src_ok, self._dst_ok, self._on_link
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
                if ver != version:
                    c.bad_versions += 1
                elif size < 0 and length <= MAX_PAYLOAD:
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
            last_seq[src] = seq if last < 0 or seq == (last + 1) & 0xFFFF else self._track_seq(src, seq, last)
            bytes_ok += end - pos
            if check_address and not (src_ok[src] and dst_ok[dst] and on_link[msg_id]):
                if not (src_ok[src] and dst_ok[dst]):
                    c.misaddressed += 1
                    self.last_misaddressed = (src, dst)
                else:
                    c.wrong_link += 1
                pos = end
                continue
            out.append(new_frame(Frame, (src, dst, seq, decoder_of[msg_id](buf, pos + HEADER_SIZE))))
            frames_ok += 1
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
    "FramePacker",
    "LinkCounters",
    "crc16",
    "encode_frame",
    "frame_seq",
    "link_message_ids",
]
