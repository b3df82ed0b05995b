"""The bench's side of the session log: ``SessionLog`` packs rows and ships them to the writer process.

``append`` packs a row into a per-group buffer (no I/O); a flusher thread cuts the buffers every
``flush_interval_s`` and sends them through a pipe to the writer process (``hil.log.writer``, which owns the
HDF5 file), then waits for its reply. The writer process is started here, kept as this process's spare
between logs (``prestart_writer``) and ended here. The design and what survives what: ``hil.log.writer``.
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import math
import os
import pickle
import select
import signal
import struct
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from hil.log.ipc import helper_argv, recv, send, send_bytes, spawn_helper
from hil.log.schema import (
    DETAIL_LEN,
    KIND_LEN,
    SCHEMA,
    Group,
    schema_to_json,
    validate,
)
from hil.log.writer import LogError, describe_error, prepare_attrs, row_dtype

log = logging.getLogger("hil.log")

_STARTUP_TIMEOUT_S = 60.0  # the child imports numpy and h5py: ~0.3 s, much more on a loaded machine
_CLOSE_TIMEOUT_S = 60.0


# --- packing rows (the bench side's hot path) ---------------------------------------------


_F4_MAX = float(np.finfo(np.float32).max)
_STRUCT_CODES = {
    "f8": "d",
    "f4": "f",
    "i8": "q",
    "i4": "i",
    "i2": "h",
    "i1": "b",
    "u8": "Q",
    "u4": "I",
    "u2": "H",
    "u1": "B",
}


def row_struct(group: Group) -> struct.Struct:
    """The struct that packs one row of ``group`` exactly as ``row_dtype`` lays it out."""
    codes = []
    for c in group.channels:
        dt = np.dtype(c.dtype)
        codes.append(f"{dt.itemsize}s" if dt.kind == "S" else _STRUCT_CODES[dt.str[1:]])
    st = struct.Struct("<" + "".join(codes))
    assert st.size == row_dtype(group).itemsize
    return st


class _Coerce(NamedTuple):
    kind: str  # 'f', 'i' (also unsigned) or 'S'
    size: int
    lo: int
    hi: int


def _coercer(dtype: str) -> _Coerce:
    dt = np.dtype(dtype)
    if dt.kind in "iu":
        info = np.iinfo(dt)
        return _Coerce("i", dt.itemsize, int(info.min), int(info.max))
    return _Coerce(dt.kind, dt.itemsize, 0, 0)


def _coerce(value: Any, c: _Coerce) -> tuple[Any, bool]:
    """A value the channel can hold, and whether it had to be changed (NaN, None, overflow, text...)."""
    if c.kind == "S":
        raw = value if isinstance(value, bytes) else str(value).encode("ascii", "backslashreplace")
        return raw[: c.size], False
    if c.kind == "f":
        try:
            x = float(value)
        except (TypeError, ValueError):
            return math.nan, True
        if c.size == 4 and math.isfinite(x) and abs(x) > _F4_MAX:
            return math.copysign(math.inf, x), False  # what numpy does: float32 overflows to inf
        return x, False
    if isinstance(value, (int, np.integer)):
        number = int(value)
    else:
        try:
            x = float(value)
        except (TypeError, ValueError):
            return 0, True
        if math.isnan(x):
            return 0, True
        if math.isinf(x):
            return (c.hi if x > 0 else c.lo), True
        number = int(x)  # truncation toward zero, as numpy casts
    clipped = min(max(number, c.lo), c.hi)
    return clipped, clipped != number


def _writer_argv() -> list[str]:
    """The command that starts the writer child (tests wrap it to limit the file size)."""
    return helper_argv("hil.log.writer:_child_main")


class _Spare:
    """This process's idle writer: one started ahead (:func:`prestart_writer`), or the writer of the last log that
    closed cleanly, waiting for its next ``open``. At most one is kept, and only for the command it was started
    with (tests start writers through a wrapper)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._idle: tuple[list[str], subprocess.Popen[bytes]] | None = None

    def waiting(self, argv: list[str]) -> bool:
        with self._lock:
            return self._idle is not None and self._idle[0] == argv and self._idle[1].poll() is None

    def take(self, argv: list[str]) -> subprocess.Popen[bytes] | None:
        """The idle writer if it runs ``argv`` and is alive (another is ended), else None."""
        with self._lock:
            idle, self._idle = self._idle, None
        if idle is None:
            return None
        if idle[0] == argv and idle[1].poll() is None:
            with contextlib.suppress(OSError):  # the CPUs a new writer would inherit: a past session may have pinned it
                os.sched_setaffinity(idle[1].pid, os.sched_getaffinity(0))
            return idle[1]
        _end_writer(idle[1], kill=False)
        return None

    def keep(self, argv: list[str], proc: subprocess.Popen[bytes]) -> None:
        """Keep ``proc`` (idle, started with ``argv``) unless a live writer already waits; else end it."""
        with self._lock:
            if self._idle is None or self._idle[1].poll() is not None:
                self._idle = (argv, proc)
                return
        _end_writer(proc, kill=False)


_SPARE = _Spare()


def prestart_writer() -> None:
    """Start a writer process now, for the next :class:`SessionLog` of this process to take: its start (an
    interpreter, numpy and h5py: ~0.3-0.6 s) is then off the next session's path. A campaign's warm worker calls it
    between cells (a no-op while the writer of the last log waits as the spare). The spare waits for its ``open``
    like any writer, and ends at EOF when this process does."""
    argv = _writer_argv()
    if _SPARE.waiting(argv):
        return
    with contextlib.suppress(OSError):  # no spare: the next log starts its own writer, as usual
        _SPARE.keep(argv, spawn_helper(argv))


def _writer_process() -> tuple[list[str], subprocess.Popen[bytes]]:
    """The spare writer if one is waiting and alive, else a new one (OSError if it cannot start); and its command."""
    argv = _writer_argv()
    proc = _SPARE.take(argv)
    return argv, proc if proc is not None else spawn_helper(argv)


def _end_writer(proc: subprocess.Popen[bytes], *, kill: bool) -> None:
    """EOF on the writer's stdin (it closes its file, if one is open, and exits), then reap it."""
    for pipe in (proc.stdin, proc.stdout):
        if pipe is not None:
            pipe.close()
    if kill:
        proc.kill()
    try:
        proc.wait(timeout=_CLOSE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


# --- the bench side -------------------------------------------------------------------------


class _Discard:
    """Stands in for a group's buffer once the log has failed: rows are dropped, silently."""

    __slots__ = ()

    def __iadd__(self, data: bytes) -> _Discard:
        return self


class _Closed:
    __slots__ = ()

    def __iadd__(self, data: bytes) -> _Closed:
        raise LogError("the session log is closed")


class SessionLog:
    """One session's log file: HDF5, one group per rate, one 1-D dataset per channel, SWMR.

    ``append`` and ``event`` never block and never raise on I/O trouble: if the writer fails
    (disk full, writer killed) the log records the cause in ``error``, drops further rows and
    keeps everything flushed before. Creating the log raises ``LogError`` if the file cannot be
    made. Close it (or use it as a context manager) for a file that opens without SWMR.

    ``rows``: rows in the file per group (updated at every flush; fsynced in the background).
    ``bad_values``: values per group that had to be coerced (NaN or None in an integer channel
    -> 0, out of range -> clipped, non-numbers in a float channel -> NaN). ``stats``: one dict
    per flush (diagnostics). ``writer_pid``: the writer process.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        attrs: dict[str, Any],
        schema: tuple[Group, ...] = SCHEMA,
        flush_interval_s: float = 0.1,
        fsync: bool = True,
        overwrite: bool = False,
    ) -> None:
        self.path = Path(path).absolute()
        self.flush_interval_s = float(flush_interval_s)
        if not self.flush_interval_s > 0:
            raise ValueError("flush_interval_s must be > 0")
        self._init_buffers(schema)
        self.error: str | None = None
        self.on_error: Callable[[str], None] | None = None  # called once, from any thread, when logging stops
        self.rows: dict[str, int] = {g.name: 0 for g in schema}
        self.stats: collections.deque[dict[str, float]] = collections.deque(maxlen=100_000)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._closed = False
        self._proc: subprocess.Popen[bytes] | None = None
        self._thread: threading.Thread | None = None
        prepared, json_names = prepare_attrs(attrs)  # ValueError for bad attrs, before any file exists

        where = f"cannot create session log {self.path}"
        if not self.path.parent.is_dir():
            raise LogError(f"{where}: directory {self.path.parent} does not exist")
        if self.path.exists() and not overwrite:
            raise LogError(f"{where}: the file already exists")
        try:
            self._argv, self._proc = _writer_process()
        except OSError as exc:
            raise LogError(f"{where}: cannot start the writer process: {describe_error(exc)}") from None
        assert self._proc.stdin is not None and self._proc.stdout is not None
        self._wfd = self._proc.stdin.fileno()
        self._rfd = self._proc.stdout.fileno()
        try:
            send(self._wfd, ("open", str(self.path), prepared, json_names, schema_to_json(schema), fsync, overwrite))
            ready, _, _ = select.select([self._rfd], [], [], _STARTUP_TIMEOUT_S)
            reply = recv(self._rfd) if ready else None
        except OSError:
            reply = None
        if reply is None or reply[0] != "ready":
            cause = reply[1] if reply is not None and reply[0] == "fail" else self._writer_gone()
            self._reap(kill=True)
            raise LogError(f"{where}: {cause}")
        self.writer_pid: int = reply[1]
        self._thread = threading.Thread(target=self._flusher, name=f"hil.log flusher {self.path.name}", daemon=True)
        self._thread.start()

    def _init_buffers(self, schema: tuple[Group, ...]) -> None:
        validate(schema)
        self.schema = schema
        self._names = [g.name for g in schema]
        self._bufs = [bytearray() for _ in schema]
        self._slots: dict[str, tuple[Any, Any]] = {
            g.name: (row_struct(g).pack, buf) for g, buf in zip(schema, self._bufs, strict=True)
        }
        self.bad_values: dict[str, int] = {g.name: 0 for g in schema}
        self._coercers = {g.name: [_coercer(c.dtype) for c in g.channels] for g in schema}
        self._structs = [row_struct(g) for g in schema]
        self._last_rows: dict[int, bytes] = {}  # the last row of each group's last batch shipped (latest())

    # -- hot path --------------------------------------------------------------------------

    def append(self, group: str, row: Sequence[Any]) -> None:
        """Queue one row (values in schema order). ~0.3 us; never blocks, never does I/O.

        Integer channels want ints (a float is truncated, on a slower path), strings want bytes.
        Raises ValueError for an unknown group or a row of the wrong length.
        """
        try:
            pack, buf = self._slots[group]
        except KeyError:
            raise ValueError(f"unknown log group {group!r}") from None
        try:
            buf += pack(*row)
        except (struct.error, OverflowError, TypeError, ValueError):
            buf += self._repack(group, row)

    def _repack(self, group: str, row: Sequence[Any]) -> bytes:
        """The slow path: a row the struct refused, value by value."""
        coercers = self._coercers[group]
        if len(row) != len(coercers):
            raise ValueError(f"log group {group!r} takes {len(coercers)} values, got {len(row)}")
        values = []
        bad = 0
        for v, c in zip(row, coercers, strict=True):
            fixed, changed = _coerce(v, c)
            values.append(fixed)
            bad += changed
        if bad:
            self.bad_values[group] += bad
        return self._slots[group][0](*values)

    def event(self, kind: str, tick: int, detail: dict[str, Any] | str = "") -> None:
        """Log an event now (t_host_ns = time.monotonic_ns()). ``detail``: a dict (stored as JSON) or text."""
        t = time.monotonic_ns()
        text = detail if isinstance(detail, str) else json.dumps(detail, separators=(",", ":"), default=str)
        raw = text.encode("ascii", "backslashreplace")
        if len(raw) > DETAIL_LEN:
            raw = raw[: DETAIL_LEN - 3] + b"..."
        self.append("events", (t, tick, kind.encode("ascii", "replace")[:KIND_LEN], raw))

    def latest(self, group: str) -> dict[str, Any] | None:
        """The last row appended to ``group`` (channel name -> value), or None before the first. For a live view
        (the service's page) from any thread: it reads the buffer's tail, never the hot path's state."""
        gi = self._names.index(group)
        size = self._structs[gi].size
        tail = bytes(self._bufs[gi][-size:])  # one copy: the loop thread may append or the flusher cut meanwhile
        if len(tail) != size:
            tail = self._last_rows.get(gi, b"")
            if len(tail) != size:
                return None
        names = [c.name for c in self.schema[gi].channels]
        return dict(zip(names, self._structs[gi].unpack(tail), strict=True))

    # -- flushing --------------------------------------------------------------------------

    def _take(self) -> dict[int, bytearray]:
        """Cut what the buffers hold (a memcpy per group; rows appended meanwhile stay)."""
        batches = {}
        for gi, buf in enumerate(self._bufs):
            n = len(buf)
            if n:
                batches[gi] = buf[:n]
                del buf[:n]
                size = self._structs[gi].size
                self._last_rows[gi] = bytes(batches[gi][n - n % size - size:n - n % size])
        return batches

    def _flusher(self) -> None:
        next_t = time.monotonic() + self.flush_interval_s
        while not self._stop.wait(max(0.0, next_t - time.monotonic())):
            with self._lock:
                if self._closed:
                    return
                try:
                    self._ship()
                except Exception as exc:  # a bug here must not end logging silently
                    self._fail(f"flusher thread: {exc!r}")
            next_t = max(next_t + self.flush_interval_s, time.monotonic())

    def _ship(self, *, sync: bool = False) -> None:
        """Send what the buffers hold to the writer and wait until it is in the file. Call with _lock held.

        ``sync``: also wait for the fsync (otherwise the writer fsyncs in the background).
        """
        if self.error is not None or self._proc is None:
            return
        t0 = time.perf_counter()
        batches = self._take()
        if not batches:
            return
        data = pickle.dumps(("batch", batches, sync), protocol=pickle.HIGHEST_PROTOCOL)
        t1 = time.perf_counter()
        try:
            send_bytes(self._wfd, data)
            reply = recv(self._rfd)
        except OSError:
            reply = None
        t2 = time.perf_counter()
        if reply is None:
            self._fail(self._writer_gone())
        elif reply[0] == "ack":
            _, rows, stats = reply
            self.rows = dict(zip(self._names, rows, strict=True))
            stats.update(t_start=t0, ship_us=(t1 - t0) * 1e6, roundtrip_us=(t2 - t0) * 1e6, bytes=len(data))
            self.stats.append(stats)
        else:
            self._fail(reply[1])

    def _writer_gone(self) -> str:
        proc = self._proc
        if proc is None:
            return "no writer process"
        try:
            rc = proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            return "the writer process stopped answering"
        if rc < 0:
            try:
                name = signal.Signals(-rc).name
            except ValueError:
                name = f"signal {-rc}"
            return f"the writer process was killed ({name})"
        return f"the writer process exited with status {rc}"

    def _fail(self, cause: str) -> None:
        first = self.error is None
        if first:
            self.error = f"{self.path}: logging stopped: {cause}"
            log.error("%s", self.error)
        for name in self._names:
            pack, _ = self._slots[name]
            self._slots[name] = (pack, _Discard())
        for buf in self._bufs:
            buf.clear()
        if first and self.on_error is not None:
            self.on_error(self.error)  # type: ignore[arg-type]

    def flush(self) -> None:
        """Write everything queued so far to the file (and fsync); returns when it is on disk.

        Blocks for a few ms: call it from the session's control code, not from the 1 kHz loop.
        """
        with self._lock:
            if not self._closed:
                self._ship(sync=True)

    def close(self) -> None:
        """Flush, end SWMR and close: the file then opens with a plain ``h5py.File(p, 'r')``.

        Never raises on I/O trouble; check ``error`` afterwards. Appending after close raises LogError.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            for name in self._names:
                pack, _ = self._slots[name]
                self._slots[name] = (pack, _Closed())
            self._stop.set()
            if self.error is None:
                self._ship(sync=True)
            reply = None
            try:
                send(self._wfd, ("close",))
                reply = recv(self._rfd)
            except OSError:
                pass
            if self.error is None:
                if reply is None or reply[0] != "closed":
                    self._fail(self._writer_gone())
                else:
                    _, rows, close_error = reply
                    self.rows = dict(zip(self._names, rows, strict=True))
                    if close_error:
                        self._fail(close_error)
            if self.error is None and self._proc is not None:  # closed cleanly: the writer can take the next log
                proc, self._proc = self._proc, None
                _SPARE.keep(self._argv, proc)
            else:
                self._reap(kill=False)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()

    def _reap(self, *, kill: bool) -> None:
        if self._proc is not None:
            _end_writer(self._proc, kill=kill)

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> SessionLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else ("failed" if self.error else "open")
        return f"<SessionLog {self.path} {state} rows={self.rows}>"
