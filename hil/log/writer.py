"""Crash-safe session log: HDF5 in SWMR mode, written by a child process; this module is that process's side.

Design (measurements: docs/log-format.md, ``benchmarks/bench_log.py``):

* ``SessionLog.append`` (the 1 kHz hot path) packs the row with a precompiled ``struct.Struct``
  (little-endian, the group's HDF5 row layout) onto a per-group ``bytearray``: ~0.3 us, no I/O,
  no numpy, no GC-tracked objects piling up. A value the format refuses (NaN in an integer
  channel, out of range, None, text) is coerced on a slow path and counted in ``bad_values``.
* A flusher thread in the bench process wakes every ``flush_interval_s`` (100 ms), cuts the
  bytes off the buffers (a memcpy: a few microseconds of GIL) and sends them through a pipe to a
  **writer child process**, then sleeps on the reply with the GIL released.
* The child owns the HDF5 file. It views the bytes as a structured array (``np.frombuffer``),
  appends each column to its 1-D dataset, flushes (H5Fflush: from now on the rows survive a
  crash of both processes), acknowledges with the rows now in the file (``SessionLog.rows``) and
  fsyncs in a background thread (``flush()`` and ``close()`` wait for the fsync).

Why a child process and not a writer thread: h5py holds the GIL (and its own global lock) for
every HDF5 call, and appending one 100 ms batch to the 64 datasets takes ~3 ms of such calls, so
a writer *thread* stalls the 1 kHz loop thread by milliseconds at every flush. In a child the HDF5
work runs in another interpreter.

What survives what:
* the bench process dies (exception, SIGKILL): the child reads EOF on its pipe, has already
  written every batch it received, and closes the file normally. Rows still in the bench's
  buffers are lost (<= flush_interval_s).
* both die (power loss, OOM killer, ``kill -9`` of the process group): the file stays a SWMR file
  holding every batch flushed before the kill (after a power loss: every batch fsynced); read it with
  ``h5py.File(p, 'r', swmr=True)`` or ``read_log``, repair it with ``recover_log``
  (``hil recover LOG``).

This module: the file's attributes as HDF5 stores them (``prepare_attrs``), the HDF5 side (``H5Sink``, which the
benchmark also runs in a thread) and the writer process's loop (``_child_main``). The bench's side, which packs
rows and ships them through the pipe, is ``hil.log.session_log`` (``SessionLog``).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import re
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from hil._version import __version__
from hil.log.ipc import recv, send
from hil.log.schema import (
    LOG_FORMAT_VERSION,
    REQUIRED_ATTRS,
    Group,
    schema_from_json,
    schema_to_json,
)

JSON_ATTRS_ALWAYS = ("config", "ident")  # stored as JSON text even when the caller passes a string
_WRITER_OWNED = (
    "log_format_version",
    "schema",
    "json_attrs",
    "log_created_unix_ns",
    "log_created_monotonic_ns",
    "writer_host",
    "writer_pid",
    "recovered",
)
_WRITER_NICE = 10  # the writer needs ~4 % of a core; it must not preempt the 1 kHz loop
# After each dataset append (64 per flush) the writer yields the CPU: on an EEVDF kernel a fair task
# may finish its 1.4 ms slice before a waking task runs, so one ~2 ms flush burst delayed the loop or
# the emulator sharing its core; 64 short bursts do not (docs/performance.md, issue 5).
_yield_cpu = getattr(os, "sched_yield", lambda: None)


class LogError(Exception):
    """A session log cannot be created, read or recovered. The message is one line naming the file."""


def describe_error(exc: BaseException) -> str:
    """One line for an OS or HDF5 error: the cause, without HDF5's internal call chain."""
    text = str(exc)
    mo = re.search(r"error message = '([^']*)'", text)  # HDF5's wording of a failed system call
    if mo:
        cause = mo.group(1)
    elif isinstance(exc, OSError) and exc.strerror:
        cause = exc.strerror
    else:
        cause = text.splitlines()[0] if text else type(exc).__name__
    errno_ = getattr(exc, "errno", None)
    if errno_ is None:
        mo = re.search(r"errno = (\d+)", text)
        errno_ = int(mo.group(1)) if mo else None
    return f"{cause} (errno {errno_})" if errno_ else cause


# --- attributes ----------------------------------------------------------------------------


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "model_dump"):  # pydantic models
        return obj.model_dump(mode="json")
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (Path, _dt.datetime, _dt.date)):
        return str(obj)
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def prepare_attrs(attrs: dict[str, Any]) -> tuple[dict[str, str | int | float], list[str]]:
    """File attributes as HDF5 will store them, and the names of those holding JSON text."""
    missing = [k for k in REQUIRED_ATTRS if k not in attrs]
    if missing:
        raise ValueError(f"session log attrs lack {', '.join(missing)} (required: {', '.join(REQUIRED_ATTRS)})")
    reserved = [k for k in attrs if k in _WRITER_OWNED]
    if reserved:
        raise ValueError(f"session log attrs {', '.join(reserved)} are written by the log itself")
    out: dict[str, str | int | float] = {}
    json_names: list[str] = []
    for key, given in attrs.items():
        if not isinstance(key, str) or not key or "/" in key:
            raise ValueError(f"bad attribute name {key!r}")
        value = given.item() if isinstance(given, np.generic) else given
        if key in JSON_ATTRS_ALWAYS or not (
            isinstance(value, str) or type(value) is float or (type(value) is int and -(2**63) <= value < 2**63)
        ):
            if isinstance(value, str):  # config / ident given as JSON text already
                try:
                    json.loads(value)
                except ValueError:
                    raise ValueError(f"attr {key!r} is a string but not JSON text") from None
                out[key] = value
            else:
                try:
                    out[key] = json.dumps(value, default=_json_default)
                except (TypeError, ValueError) as exc:
                    raise ValueError(f"attr {key!r}: {exc}") from None
            json_names.append(key)
        else:
            out[key] = value
    out.setdefault("software_version", _software_version())
    now_unix, now_mono = time.time_ns(), time.monotonic_ns()
    out.setdefault(
        "start_time_utc", _dt.datetime.fromtimestamp(now_unix / 1e9, _dt.UTC).isoformat(timespec="milliseconds")
    )
    out["log_created_unix_ns"] = now_unix
    out["log_created_monotonic_ns"] = now_mono
    out["log_format_version"] = LOG_FORMAT_VERSION
    out["writer_host"] = socket.gethostname()
    return out, json_names


def _software_version() -> str:
    return str(__version__)


# --- the HDF5 side (runs in the writer child; the benchmark also runs it in a thread) ---------


def chunk_rows(group: Group) -> int:
    """Chunk length of the group's datasets: about a second of data, at most ~32 KB per chunk."""
    per_row = max(np.dtype(c.dtype).itemsize for c in group.channels)
    by_rate = {"loop": 1024, "timing": 1024, "image": 128, "hexapod": 128, "drive": 128,
               "links": 16}.get(group.name, 64)
    return max(1, min(by_rate, 32768 // per_row))


def row_dtype(group: Group) -> np.dtype:
    """The little-endian, unpadded structured dtype of a packed row of ``group``."""
    return np.dtype([(c.name, np.dtype(c.dtype).newbyteorder("<")) for c in group.channels])


class _Syncer:
    """fsync in a thread of the writer, so a slow disk does not hold up the next batch.

    A SIGKILL cannot lose what H5Fflush handed to the kernel; fsync only matters for a power
    loss. Requests made while an fsync runs are served by one more fsync after it.
    """

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.error: str | None = None
        self._cv = threading.Condition()
        self._requested = self._done = 0
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="hil.log fsync", daemon=True)
        self._thread.start()

    def request(self) -> None:
        with self._cv:
            self._requested += 1
            self._cv.notify_all()

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._stop or self._requested > self._done)
                if self._requested == self._done:
                    return
                target = self._requested
            try:
                os.fsync(self.fd)
            except OSError as exc:
                self.error = describe_error(exc)
            with self._cv:
                self._done = target
                self._cv.notify_all()

    def stop(self) -> None:
        """Wait for the fsyncs requested so far, then end the thread."""
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        self._thread.join()


class H5Sink:
    """Owns the HDF5 file: creates the layout, switches SWMR on, appends batches, flushes, closes."""

    def __init__(
        self,
        path: str | Path,
        attrs: dict[str, Any],
        json_attrs: list[str],
        schema: tuple[Group, ...],
        *,
        fsync: bool = True,
        overwrite: bool = False,
    ) -> None:
        import h5py  # noqa: PLC0415  (heavy: loaded only when a log is opened)

        self._h5s = h5py.h5s
        self.path = Path(path)
        self.schema = schema
        self.fsync = fsync
        self.rows = [0] * len(schema)
        self.dtypes = [row_dtype(g) for g in schema]
        self.f = h5py.File(self.path, "w" if overwrite else "w-", libver="latest")
        try:
            attrs = dict(attrs)
            attrs["schema"] = schema_to_json(schema)
            attrs["writer_pid"] = os.getpid()
            attrs["json_attrs"] = json.dumps(sorted({*json_attrs, "schema", "json_attrs"}))
            for key, value in attrs.items():
                self.f.attrs[key] = value
            self.dsets: list[list[Any]] = []
            self.chunks: list[int] = []
            for g in schema:
                grp = self.f.create_group(g.name)
                grp.attrs["rate"] = g.rate
                grp.attrs["doc"] = g.doc
                n_chunk = chunk_rows(g)
                self.chunks.append(n_chunk)
                dsets = []
                for c in g.channels:
                    ds = grp.create_dataset(c.name, shape=(0,), maxshape=(None,), dtype=c.dtype, chunks=(n_chunk,))
                    ds.attrs["unit"] = c.unit
                    ds.attrs["doc"] = c.doc
                    dsets.append(ds)
                self.dsets.append(dsets)
            self.f.flush()
            self.f.swmr_mode = True
            self.fd = self.f.id.get_vfd_handle()
            self.syncer = _Syncer(self.fd) if fsync else None
            if fsync:
                os.fsync(self.fd)
        except BaseException:
            self.abort()
            self.path.unlink(missing_ok=True)  # nothing was logged yet: leave no half-made file
            raise

    def _columns(self, gi: int, packed: bytes | bytearray) -> list[np.ndarray]:
        arr = np.frombuffer(packed, dtype=self.dtypes[gi])
        return [np.ascontiguousarray(arr[name]) for name in arr.dtype.names]  # type: ignore[union-attr]

    def _append(self, ds: Any, n0: int, col: np.ndarray) -> None:
        # the low-level calls: h5py's ds.resize + ds[a:b] = col cost ~4x more per dataset
        k = col.shape[0]
        ds.id.set_extent((n0 + k,))
        fspace = ds.id.get_space()
        fspace.select_hyperslab((n0,), (k,))
        ds.id.write(self._h5s.create_simple((k,)), fspace, col)

    def write(self, batches: dict[int, bytes | bytearray], *, sync: bool = True) -> dict[str, float]:
        """Append the batches (packed rows by group index), flush and fsync. Raises on I/O errors.

        ``sync``: fsync before returning; otherwise the fsync runs in the background (``_Syncer``)
        and the rows are already safe from a crash of the processes, not yet from a power loss.

        A batch larger than a chunk (the writer fell behind) goes in rounds of at most one chunk
        per dataset, each flushed. Within a round nothing is evicted from HDF5's caches and
        H5Fflush writes raw data before metadata, so a writer killed at any point leaves no extent
        on disk that covers unwritten rows (beyond the all-zero tail read_log trims). A failed
        write is different: HDF5 goes on flushing metadata, so the caller rolls back (``rollback``).
        """
        if self.syncer is not None and self.syncer.error:
            raise OSError(f"fsync failed: {self.syncer.error}")
        self.check_still_there()
        t0 = time.perf_counter()
        cols = {gi: self._columns(gi, packed) for gi, packed in batches.items()}
        n_rows = sum(len(c[0]) for c in cols.values())
        flush_s = 0.0
        start = 0
        while True:
            wrote = False
            for gi, gcols in cols.items():
                step = self.chunks[gi]
                a, b = start * step, min((start + 1) * step, len(gcols[0]))
                if a >= b:
                    continue
                n0 = self.rows[gi]
                for ds, col in zip(self.dsets[gi], gcols, strict=True):
                    self._append(ds, n0, col[a:b])
                    _yield_cpu()
                wrote = True
            if not wrote:
                break
            t2 = time.perf_counter()
            self.f.flush()
            for gi, gcols in cols.items():  # this round is in the file now
                step = self.chunks[gi]
                self.rows[gi] += max(0, min((start + 1) * step, len(gcols[0])) - start * step)
            flush_s += time.perf_counter() - t2
            start += 1
        t3 = time.perf_counter()
        if self.syncer is not None:
            if sync:
                os.fsync(self.fd)
            else:
                self.syncer.request()
        t4 = time.perf_counter()
        return {
            "rows": n_rows,
            "rounds": start,
            "write_us": (t3 - t0 - flush_s) * 1e6,
            "flush_us": flush_s * 1e6,
            "fsync_us": (t4 - t3) * 1e6,
            "t_child0": t0,
            "t_child1": t4,
        }

    def check_still_there(self) -> None:
        """OSError if the file being written is no longer at its path (deleted, its directory removed, or replaced):
        the rows would go to a file nobody can open. One stat per batch."""
        try:
            on_disk = os.stat(self.path)
        except FileNotFoundError:
            gone = "its directory was removed" if not self.path.parent.exists() else "the file was deleted"
            raise OSError(f"{gone} while the session ran") from None
        here = os.fstat(self.fd)
        if (on_disk.st_dev, on_disk.st_ino) != (here.st_dev, here.st_ino):
            raise OSError("another file took its place while the session ran")

    def rollback(self) -> None:
        """After a failed write: shrink every dataset back to the rows known to be in the file.

        HDF5 keeps flushing metadata after a raw-data write fails (a full disk refuses new chunks,
        not rewrites of existing metadata), which can leave an extent covering rows that were never
        written. Best effort; shrinking allocates nothing.
        """
        for gi, dsets in enumerate(self.dsets):
            for ds in dsets:
                if ds.shape[0] != self.rows[gi]:
                    ds.id.set_extent((self.rows[gi],))
        self.f.flush()

    def close(self) -> None:
        if self.syncer is not None:
            self.syncer.stop()
        try:
            self.check_still_there()
        finally:
            self.f.close()  # ends SWMR: the file opens normally from now on
        if self.fsync:
            fd = os.open(self.path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)

    def abort(self) -> None:
        """Close after an error, best effort (the file keeps what earlier flushes wrote)."""
        try:
            self.f.close()
        except Exception as exc:  # the disk may still be full
            print(f"hil.log writer: closing {self.path} after an error: {describe_error(exc)}", file=sys.stderr)


def _child_main() -> None:
    """The writer process: messages in on stdin, replies out on the original stdout. It writes one log after
    another (``open`` ... ``close`` each), so a process that runs session after session (a campaign's warm worker, a
    notebook) starts one writer, not one per log; it ends at EOF on stdin, or after a log that failed."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole process group: the bench closes us
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # we exit at EOF on stdin, after closing the file
    with contextlib.suppress(OSError):
        os.nice(_WRITER_NICE)  # on a busy machine the loop process gets the CPU first
    # Not SCHED_IDLE: it halved the emulator's pacing tail on an idle 2-core VM, but any CPU-bound
    # neighbour (a report, a compiler) starved the writer for seconds, so a crash lost far more than
    # 200 ms and a bench-only crash left the file open for >10 s. Nice 10 keeps ~10 % of a core under load.
    out_fd = os.dup(1)
    os.dup2(2, 1)  # a stray print must not corrupt the replies
    in_fd = 0

    def reply(obj: Any) -> None:
        with contextlib.suppress(OSError):  # the bench is gone: carry on to EOF and close the file
            send(out_fd, obj)

    while True:
        msg = recv(in_fd)
        if msg is None or msg[0] != "open":
            os._exit(0)  # no file is open: no interpreter teardown (~0.1 s) for anyone to wait on
        if not _write_one_log(msg, in_fd, reply):
            os._exit(0)  # a log that failed: no HDF5 close, no atexit flush


def _write_one_log(msg: tuple[Any, ...], in_fd: int, reply: Callable[[Any], None]) -> bool:
    """One log, from its ``open`` message to its ``close`` (or EOF): True if it closed cleanly and this writer can
    take the next one."""
    _, path, attrs, json_attrs, schema_text, fsync, overwrite = msg
    try:
        sink = H5Sink(path, attrs, json_attrs, schema_from_json(schema_text), fsync=fsync, overwrite=overwrite)
    except Exception as exc:
        reply(("fail", describe_error(exc)))
        return False
    reply(("ready", os.getpid()))
    failed: str | None = None
    while True:
        msg = recv(in_fd)
        if msg is None or msg[0] == "close":
            break
        if msg[0] == "batch":
            if failed:
                reply(("error", failed))
                continue
            try:
                stats = sink.write(msg[1], sync=msg[2])
            except Exception as exc:
                # Stop touching the file: flushing or closing now would write the extents of a
                # half-written batch. On disk it stays as the last good flush left it, like after a
                # crash (read_log reads it, recover_log repairs it).
                failed = describe_error(exc)
                try:
                    sink.rollback()
                except Exception as exc2:
                    print(f"hil.log writer: {path}: rollback after an error: {describe_error(exc2)}", file=sys.stderr)
                reply(("error", failed))
                continue
            reply(("ack", sink.rows, stats))
    if failed:
        reply(("closed", sink.rows, failed))
        return False
    close_error = None
    try:
        sink.close()
    except Exception as exc:
        close_error = describe_error(exc)
    reply(("closed", sink.rows, close_error))
    return close_error is None and msg is not None
