"""Captures of a session's serial links: every byte the bench received and sent, with its time (docs/capture.md).

A capture is one append-only file (``*.hilcap``): a header (magic, version, a JSON description naming the links),
then records, each one read or one write of one link::

    offset  size  field
    0       8     t_ns: time.monotonic_ns() when the bytes were read (rx) or handed to the OS (tx), i64
    8       4     N: length of the data, u32
    12      1     link: index into the header's ``links``, u8
    13      1     direction: 0 rx (the bench received), 1 tx (the bench sent), 2 note (JSON text), u8
    14      2     reserved, 0
    16      N     data: the bytes as read or written
    16+N    4     CRC-32 (zlib.crc32) of bytes 0 .. 16+N-1, u32

All little-endian. Nothing is ever rewritten, so a session killed at any moment leaves a file that reads up to its
last whole record; a record cut short (or torn by a power cut) ends the reading there, and the reader says so.

Producers never block and never format anything: :meth:`Capture.link` gives each link a :class:`LinkCapture` whose
``rx``/``tx`` append one tuple to a shared deque (atomic under the GIL, so the realtime loop thread and the event
loop both append without a lock); a writer thread packs what has accumulated and appends it to the file every
``flush_interval_s``. :class:`CaptureReader` streams a file back; :func:`decode_capture` turns its records into
timed frames with one protocol decoder per link and direction, as the bench and the boards decode them.
"""

from __future__ import annotations

import contextlib
import heapq
import json
import os
import re
import struct
import threading
import time
import zlib
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal, NamedTuple

from hil.protocol import CATALOGUE, LINKS, Board, Decoder, Frame, LinkCounters

MAGIC = b"HILCAP\x1a\n"  # 8 bytes; \x1a\n catch a text-mode transfer, as PNG's signature does
VERSION = 1
SUFFIX = ".hilcap"
RX, TX, NOTE = 0, 1, 2
DIRECTIONS = ("rx", "tx", "note")
Direction = Literal["rx", "tx"]
_FILE_HEAD = struct.Struct("<8sHI")  # magic, version, length of the JSON description
_RECORD = struct.Struct("<qIBBH")  # t_ns, N, link, direction, reserved
RECORD_OVERHEAD = _RECORD.size + 4
MAX_RECORD_DATA = 1 << 24  # a longer claimed length is a corrupt record, never read into memory
MAX_META = 1 << 20
FLUSH_INTERVAL_S = 0.05
READ_CHUNK = 1 << 20
REORDER_WINDOW_NS = 50_000_000  # decoding puts records back in time order within this (see time_ordered)


class CaptureError(ValueError):
    """A file that is not a capture (or not one this version reads), or a capture path that names none."""


# --- writing ---------------------------------------------------------------------------------------------------


class LinkCapture:
    """One link's handle on a :class:`Capture`. ``rx(data)``/``tx(data)`` stamp and queue bytes; the hot path can
    bind ``append`` and ``id`` and queue ``(t_ns, id, RX or TX, data)`` tuples itself (the loop thread does)."""

    __slots__ = ("append", "capture", "id", "name")

    def __init__(self, capture: Capture, name: str, link_id: int) -> None:
        self.capture = capture
        self.name = name
        self.id = link_id
        self.append = capture.append

    def rx(self, data: bytes | bytearray | memoryview, t_ns: int | None = None) -> None:
        """Bytes the bench received on this link (now, or at ``t_ns``)."""
        self.append((time.monotonic_ns() if t_ns is None else t_ns, self.id, RX, bytes(data)))

    def tx(self, data: bytes | bytearray | memoryview, t_ns: int | None = None) -> None:
        """Bytes the bench wrote on this link (now, or at ``t_ns``)."""
        self.append((time.monotonic_ns() if t_ns is None else t_ns, self.id, TX, bytes(data)))

    def note(self, **detail: Any) -> None:
        """A note about the link (opened, closed): JSON text in a record of direction ``note``."""
        text = json.dumps(detail, separators=(",", ":"), default=str).encode()
        self.append((time.monotonic_ns(), self.id, NOTE, text))


@dataclass
class CaptureStats:
    """What a :class:`Capture` wrote (final once it is closed; the writer thread updates it until then)."""

    records: int = 0  # records written to the file
    data_bytes: int = 0  # the bytes they carry (what the links read and wrote, and the notes)
    file_bytes: int = 0  # the records' bytes in the file (data, record headers and CRCs)
    header_bytes: int = 0  # the file's header
    flushes: int = 0
    max_batch: int = 0  # most records written in one flush
    dropped: int = 0  # records lost after a write error
    error: str = ""  # the write error that stopped the file growing, if any

    @property
    def bytes(self) -> int:
        """The file's size: ``header_bytes + file_bytes``."""
        return self.header_bytes + self.file_bytes


class Capture:
    """An open capture file. ``link(name)`` gives a link's handle; :meth:`close` writes what is left.

    ``links``: the link names, in the order of their ids (the header lists them). ``meta``: anything more to put in
    the header's JSON. ``fsync``: fsync the file after every flush (a power cut then loses at most one flush
    interval; a killed process loses nothing already flushed either way)."""

    def __init__(self, path: Path, *, links: Iterable[str] = LINKS, meta: dict[str, Any] | None = None,
                 flush_interval_s: float = FLUSH_INTERVAL_S, fsync: bool = False) -> None:
        self.path = Path(path)
        self.links = tuple(links)
        if len(self.links) > 255 or len(set(self.links)) != len(self.links):
            raise ValueError("capture links: at most 255 distinct names")
        self.meta = {"format": "hil capture", "version": VERSION, "links": list(self.links),
                     "clock": "time.monotonic_ns", "created_unix_ns": time.time_ns(),
                     "created_monotonic_ns": time.monotonic_ns(),
                     "catalogue_fingerprint": f"{CATALOGUE.fingerprint:#010x}", **(meta or {})}
        self.flush_interval_s = flush_interval_s
        self.fsync = fsync
        self.stats = CaptureStats()
        self._queue: deque[tuple[int, int, int, bytes]] = deque()
        self.append = self._queue.append  # the producers' one operation
        self._handles: dict[str, LinkCapture] = {}
        self._lock = threading.Lock()  # between the writer thread and close()/flush()
        self._closed = threading.Event()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND | getattr(os, "O_CLOEXEC", 0),
                           0o644)
        header = _header_bytes(self.meta)
        self._write_all(header)
        self.stats.header_bytes = len(header)
        if fsync:
            os.fsync(self._fd)
        self._thread = threading.Thread(target=self._writer, name="hil-capture", daemon=True)
        self._thread.start()

    @classmethod
    def create(cls, directory: Path, name: str, **kwargs: Any) -> Capture:
        """A new capture in ``directory`` named ``NAME-YYYYmmdd-HHMMSS.hilcap`` (``-2``, ``-3``... if taken)."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        stem = f"{re.sub(r'[^A-Za-z0-9_.-]', '_', name) or 'capture'}-{datetime.now(UTC):%Y%m%d-%H%M%S}"
        for n in range(1, 1000):
            path = directory / f"{stem}{'' if n == 1 else f'-{n}'}{SUFFIX}"
            try:
                return cls(path, **kwargs)
            except FileExistsError:
                continue
        raise FileExistsError(f"{directory}: no free capture name for {stem}")

    def summary(self) -> dict[str, Any]:
        """What the capture wrote, for a session's result: ``path``, ``records``, ``bytes`` (the file's size),
        ``dropped`` (records lost to a write error) and ``error`` (that error, "" if none)."""
        st = self.stats
        return {"path": str(self.path), "records": st.records, "bytes": st.bytes, "dropped": st.dropped,
                "error": st.error}

    def link(self, name: str) -> LinkCapture:
        handle = self._handles.get(name)
        if handle is None:
            if name not in self.links:
                raise ValueError(f"capture: link {name!r} is not one of {', '.join(self.links)}")
            handle = self._handles[name] = LinkCapture(self, name, self.links.index(name))
        return handle

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    @property
    def pending(self) -> int:
        """Records queued and not yet written."""
        return len(self._queue)

    def flush(self) -> None:
        """Write every queued record now (any thread)."""
        with self._lock:
            self._drain()

    def close(self) -> None:
        """Stop the writer, write what is queued, close the file. Idempotent."""
        if self._closed.is_set():
            return
        self._closed.set()
        if self._thread is not threading.current_thread():
            self._thread.join(5.0)
        with self._lock:
            self._drain()
            if self._fd >= 0:
                with contextlib.suppress(OSError):
                    if self.fsync:
                        os.fsync(self._fd)
                    os.close(self._fd)
                self._fd = -1

    def __enter__(self) -> Capture:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the writer thread ---------------------------------------------------------------------------------

    def _writer(self) -> None:
        while not self._closed.wait(self.flush_interval_s):
            with self._lock:
                self._drain()

    def _drain(self) -> None:
        queue, st = self._queue, self.stats
        if not queue:
            return
        out = bytearray()
        pack, crc32, popleft = _RECORD.pack, zlib.crc32, queue.popleft
        n = size = 0
        while True:
            try:
                t_ns, link, direction, data = popleft()
            except IndexError:
                break
            head = pack(t_ns, len(data), link, direction, 0)
            out += head
            out += data
            out += crc32(data, crc32(head)).to_bytes(4, "little")
            n += 1
            size += len(data)
        if self._fd < 0 or st.error:
            st.dropped += n
            return
        try:
            self._write_all(out)
            if self.fsync:
                os.fsync(self._fd)
        except OSError as exc:  # a full disk must not stop the session: the capture stops growing, and says why
            st.error = f"{self.path}: {exc.strerror or exc}"
            st.dropped += n
            return
        st.records += n
        st.data_bytes += size
        st.file_bytes += len(out)
        st.flushes += 1
        st.max_batch = max(st.max_batch, n)

    def _write_all(self, data: bytes | bytearray) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self._fd, view):]


def _header_bytes(meta: dict[str, Any]) -> bytes:
    text = json.dumps(meta, separators=(",", ":"), default=str).encode()
    head = _FILE_HEAD.pack(MAGIC, VERSION, len(text)) + text
    return head + zlib.crc32(head).to_bytes(4, "little")


# --- reading ---------------------------------------------------------------------------------------------------


class Record(NamedTuple):
    """One record of a capture: ``data`` was read (rx) or written (tx) on ``link`` at ``t_ns``; a ``note`` holds
    JSON text about the link."""

    t_ns: int
    link: str
    direction: str  # "rx" | "tx" | "note"
    data: bytes

    def note(self) -> dict[str, Any]:
        """A note's detail (empty for rx/tx records)."""
        if self.direction != "note":
            return {}
        try:
            out = json.loads(self.data)
        except ValueError:
            return {}
        return out if isinstance(out, dict) else {}


def is_capture(path: Path) -> bool:
    """Whether ``path`` is a file starting with the capture magic."""
    try:
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def find_capture(path: Path) -> Path:
    """The capture ``path`` names: the file itself, or the one ``*.hilcap`` of a directory. CaptureError otherwise."""
    path = Path(path)
    if path.is_dir():
        found = sorted(path.glob(f"*{SUFFIX}"))
        if len(found) == 1:
            return found[0]
        if not found:
            raise CaptureError(f"{path}: no {SUFFIX} capture in this directory")
        names = ", ".join(p.name for p in found[:5]) + (", ..." if len(found) > 5 else "")
        raise CaptureError(f"{path}: {len(found)} captures in this directory ({names}): name one")
    if not path.exists():
        raise CaptureError(f"{path}: no such file or directory")
    if not is_capture(path):
        raise CaptureError(f"{path}: not a capture (no {MAGIC[:6].decode()} header)")
    return path


class CaptureReader:
    """Streams the records of a capture in bounded memory. ``meta`` and ``links`` come from the header (read at
    once; CaptureError if it is not a capture). After iterating, ``end`` says how the file ended: ``complete``
    (at a record boundary), ``truncated`` (a record cut short: ``trailing_bytes`` of it) or ``corrupt`` (a record
    whose CRC or fields are wrong, from ``problem_offset`` on); ``problem`` says what in words."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.end = ""
        self.problem = ""
        self.problem_offset = -1
        self.trailing_bytes = 0
        self.records = 0
        with open(self.path, "rb") as f:
            head = f.read(_FILE_HEAD.size)
            if len(head) < _FILE_HEAD.size or head[:8] != MAGIC:
                raise CaptureError(f"{self.path}: not a capture (no {MAGIC[:6].decode()} header)")
            _, version, meta_len = _FILE_HEAD.unpack(head)
            if version != VERSION:
                raise CaptureError(f"{self.path}: capture format version {version}; this bench reads {VERSION}")
            if meta_len > MAX_META:
                raise CaptureError(f"{self.path}: header claims {meta_len} bytes of description (corrupt)")
            text = f.read(meta_len)
            crc = f.read(4)
        if len(text) < meta_len or len(crc) < 4:
            raise CaptureError(f"{self.path}: header cut short")
        if zlib.crc32(head + text) != int.from_bytes(crc, "little"):
            raise CaptureError(f"{self.path}: header CRC mismatch (corrupt)")
        try:
            self.meta: dict[str, Any] = json.loads(text)
            self.links: tuple[str, ...] = tuple(str(x) for x in self.meta["links"])
        except (ValueError, KeyError, TypeError):
            raise CaptureError(f"{self.path}: header description is not valid JSON with 'links'") from None
        self.data_offset = _FILE_HEAD.size + meta_len + 4

    def __iter__(self) -> Iterator[Record]:
        links, dirs = self.links, DIRECTIONS
        unpack, crc32, head_size = _RECORD.unpack_from, zlib.crc32, _RECORD.size
        buf = b""
        pos = 0  # within buf
        offset = self.data_offset  # of buf[0] in the file
        self.records = 0
        self.end = "complete"
        with open(self.path, "rb") as f:
            f.seek(self.data_offset)
            eof = False
            while True:
                left = len(buf) - pos
                if left >= head_size:
                    t_ns, n, link, direction, reserved = unpack(buf, pos)
                    if n > MAX_RECORD_DATA or link >= len(links) or direction >= len(dirs) or reserved:
                        self._corrupt(offset + pos, f"record fields out of range (length {n}, link {link}, "
                                                    f"direction {direction})")
                        return
                    need = head_size + n + 4
                else:
                    need = head_size
                if left < need:
                    if not eof:
                        chunk = f.read(max(READ_CHUNK, need - left))
                        if chunk:
                            buf = buf[pos:] + chunk
                            offset += pos
                            pos = 0
                            continue
                        eof = True
                    if left:
                        self._cut(offset + pos, left, "a record header" if left < head_size else "a record")
                    return
                end = pos + need
                if crc32(buf[pos : end - 4]) != int.from_bytes(buf[end - 4 : end], "little"):
                    self._corrupt(offset + pos, "record CRC mismatch")
                    return
                data = buf[pos + head_size : end - 4]
                pos = end
                self.records += 1
                yield Record(t_ns, links[link], dirs[direction], data)

    def _cut(self, at: int, n: int, what: str) -> None:
        self.end, self.trailing_bytes, self.problem_offset = "truncated", n, at
        self.problem = f"{what} cut short at byte {at}: {n} bytes after the last whole record"

    def _corrupt(self, at: int, what: str) -> None:
        self.end, self.problem_offset = "corrupt", at
        with contextlib.suppress(OSError):
            self.trailing_bytes = self.path.stat().st_size - at
        self.problem = f"{what} at byte {at}: reading stopped there"


# --- decoding --------------------------------------------------------------------------------------------------


class TimedFrame(NamedTuple):
    """A frame decoded from a capture: the time of the record that completed it, its link and direction."""

    t_ns: int
    link: str
    direction: str  # "rx": the bench received it; "tx": the bench sent it
    frame: Frame


@dataclass
class CaptureDecode:
    """What :func:`decode_capture` decoded: per ``(link, direction)`` its decoder's counters and held bytes, the
    records read, and how the file ended (:class:`CaptureReader`)."""

    reader: CaptureReader
    decoders: dict[tuple[str, str], Decoder] = field(default_factory=dict)
    records: int = 0
    notes: list[Record] = field(default_factory=list)
    first_t_ns: int | None = None
    last_t_ns: int | None = None

    def counters(self) -> dict[tuple[str, str], LinkCounters]:
        return {key: dec.counters for key, dec in self.decoders.items()}


def link_decoder(link: str, direction: str) -> Decoder:
    """The decoder of one end of a link: rx decodes as the bench does (what the board may send the host), tx as the
    board does (what the host may send it); a link that names no board decodes everything."""
    board = Board.__members__.get(link.upper())
    if board is None or board is Board.HOST:
        return Decoder()
    return Decoder.for_link(board, "host" if direction == "rx" else "board")


def time_ordered(records: Iterable[Record], window_ns: int = REORDER_WINDOW_NS) -> Iterator[Record]:
    """``records`` in time order (file order among equal times). Producers stamp and queue in two statements, so
    two threads' records can reach the file a little out of order; a record is held until one ``window_ns`` later
    has been read, which bounds both the memory and the disorder this repairs."""
    heap: list[tuple[int, int, Record]] = []
    for n, rec in enumerate(records):
        heapq.heappush(heap, (rec.t_ns, n, rec))
        while heap and heap[0][0] < rec.t_ns - window_ns:
            yield heapq.heappop(heap)[2]
    while heap:
        yield heapq.heappop(heap)[2]


def decode_capture(path: Path, *, links: Iterable[str] | None = None, directions: Iterable[str] | None = None,
                   result: CaptureDecode | None = None) -> Iterator[TimedFrame]:
    """The frames of a capture in time order (:func:`time_ordered`), each with its record's time. ``links`` and
    ``directions`` select (None: all). Pass ``result`` (``CaptureDecode(CaptureReader(path))``) to read the counters
    once iterated. A note that a link was opened again resets that link's decoders, as the bench's new link starts a
    new decoder."""
    reader = result.reader if result is not None else CaptureReader(path)
    out = result if result is not None else CaptureDecode(reader)
    want_links = None if links is None else set(links)
    want_dirs = {"rx", "tx"} if directions is None else set(directions)
    for name in reader.links:
        if want_links is None or name in want_links:
            for d in ("rx", "tx"):
                if d in want_dirs:
                    out.decoders[(name, d)] = link_decoder(name, d)
    for rec in time_ordered(reader):
        out.records += 1
        if rec.direction == "note":
            out.notes.append(rec)
            if rec.note().get("event") == "open":
                for d in ("rx", "tx"):
                    dec = out.decoders.get((rec.link, d))
                    if dec is not None:
                        dec.reset()
            continue
        dec = out.decoders.get((rec.link, rec.direction))
        if dec is None:
            continue
        if out.first_t_ns is None:
            out.first_t_ns = rec.t_ns
        out.last_t_ns = rec.t_ns
        for frame in dec.feed(rec.data):
            yield TimedFrame(rec.t_ns, rec.link, rec.direction, frame)
