"""Read, recover and export session logs (closed, live or left behind by a crash).

* ``read_log``: every group as numpy arrays, units, decoded attributes. Opens a cleanly closed
  file normally and anything else (a live SWMR file, a file whose writer was killed) with
  ``swmr=True``. Rows past the last flush that the file's extent already covers read as zeros:
  they are trimmed (see ``_trim``).
* ``recover_log``: copies a crashed file through a SWMR reader into a new file with the same
  layout and attributes, trimmed, and puts it in the original's place (the original is kept as
  ``<name>.crashed.h5``). ``hil recover LOG``.
* ``read_attrs``: only the file attributes (quick on a long log).
* ``export_log``: one Parquet or CSV file per group, units included. ``hil export LOG``.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import re
import socket
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import h5py
import numpy as np

from hil.log.schema import LOG_FORMAT_VERSION, schema_from_json
from hil.log.writer import LogError, describe_error

TRUNCATED_FRACTION = 0.9  # a file with less of its superblock's bytes is refused as truncated (see _open)
_COPY_ROWS = 1 << 20  # recover copies this many rows per dataset at a time


class NotASessionLog(LogError):
    """An HDF5 file that is not a session log (it has no ``/loop`` group)."""


@dataclass
class LogData:
    """A session log in memory.

    ``groups[g][channel]`` is a 1-D numpy array with the file's dtype, except the events' ``kind``
    and ``detail``, which are decoded to numpy str arrays. ``attrs``: the file attributes, JSON
    ones decoded. ``trimmed[g]``: rows of the file's extent dropped as never written.
    """

    path: Path
    attrs: dict[str, Any]
    groups: dict[str, dict[str, np.ndarray]]
    units: dict[str, dict[str, str]]
    docs: dict[str, dict[str, str]] = field(default_factory=dict)
    rates: dict[str, str] = field(default_factory=dict)
    trimmed: dict[str, int] = field(default_factory=dict)
    closed_cleanly: bool = True

    def rows(self, group: str) -> int:
        cols = self.groups[group]
        return len(next(iter(cols.values()))) if cols else 0


@dataclass
class RecoverReport:
    path: Path  # the file given
    output: Path | None  # the recovered file (None if nothing was done)
    backup: Path | None  # where the crashed original went (None if untouched)
    already_clean: bool
    rows: dict[str, int]  # rows per group in the recovered (or clean) file
    trimmed: dict[str, int]  # rows of the crashed file's extent that held no data
    message: str

    def __str__(self) -> str:
        return self.summary()

    def summary(self) -> str:
        """The message, then the rows per group (and what was trimmed): what ``hil recover`` prints."""
        lines = [self.message]
        for g, n in self.rows.items():
            cut = self.trimmed.get(g, 0)
            lines.append(f"  {g:<8} {n:>10} rows" + (f"  ({cut} unwritten rows trimmed)" if cut else ""))
        return "\n".join(lines)


# --- opening ---------------------------------------------------------------------------------


def _open(path: Path) -> tuple[h5py.File, bool]:
    """The file open for reading, and whether it was closed cleanly (opens without SWMR)."""
    if not path.is_file():
        raise LogError(f"cannot read session log {path}: no such file")
    try:
        return h5py.File(path, "r"), True
    except OSError as exc:
        cut = re.search(r"truncated file: eof = (\d+).*stored_eof = (\d+)", str(exc))
        if cut and int(cut[1]) < TRUNCATED_FRACTION * int(cut[2]):
            # much of what the superblock counts is gone (a copy cut short): HDF5's SWMR reader retries reads of
            # the missing index blocks for minutes. A write that failed at the end (a full disk) loses a few
            # blocks, and its flushed rows are read as a crashed log's are.
            raise LogError(f"cannot read session log {path}: truncated file ({int(cut[1])} of {int(cut[2])} bytes: "
                           "the end of the file is missing)") from None
    try:
        return h5py.File(path, "r", swmr=True), False
    except OSError as exc:
        raise LogError(f"cannot read session log {path}: {describe_error(exc)}") from None


def _require_session_log(f: h5py.File, path: Path) -> None:
    """Every session log has the 1 kHz ``loop`` group from its creation on (the writer makes every group first)."""
    if not isinstance(f.get("loop"), h5py.Group):
        groups = [name for name, obj in f.items() if isinstance(obj, h5py.Group)]
        has = f"it has {', '.join(groups)}" if groups else "it has no groups"
        raise NotASessionLog(f"{path}: not a session log (no /loop group; {has})")


def _decode_attrs(raw: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in raw.items():
        if isinstance(value, bytes):
            out[key] = value.decode("utf-8", "replace")
        elif isinstance(value, np.generic):
            out[key] = value.item()
        else:
            out[key] = value
    try:
        json_names = json.loads(out.get("json_attrs", "[]"))
    except (TypeError, ValueError):
        json_names = []
    for key in json_names:
        if isinstance(out.get(key), str):
            with contextlib.suppress(ValueError):  # not JSON after all: keep the text
                out[key] = json.loads(out[key])
    return out


def _channel_order(f: h5py.File) -> dict[str, list[str]]:
    """Groups and channels in schema order (the file's own schema attribute), else as stored."""
    try:
        schema = schema_from_json(f.attrs["schema"])
        order = {g.name: [c.name for c in g.channels] for g in schema}
    except (KeyError, ValueError, TypeError):
        order = {}
    out: dict[str, list[str]] = {}
    for name in order:
        if isinstance(f.get(name), h5py.Group):
            out[name] = [c for c in order[name] if isinstance(f[name].get(c), h5py.Dataset)]
    for name, obj in f.items():
        if isinstance(obj, h5py.Group) and name not in out:
            out[name] = [c for c, ds in obj.items() if isinstance(ds, h5py.Dataset)]
    return out


def _trim(cols: dict[str, np.ndarray]) -> int:
    """Rows to keep: up to the last row that was written.

    The writer resizes a dataset before it writes the rows, and its flushes are not atomic
    across datasets, so after a crash the extent can cover rows whose data never reached the
    file: they read as the fill value, 0. A trailing row is dropped when every channel is 0,
    or when its ``t_host_ns`` (a monotonic clock, never 0 in a written row) is 0.
    """
    if not cols:
        return 0
    n = len(next(iter(cols.values())))
    written = np.zeros(n, dtype=bool)
    for col in cols.values():
        written |= col != (b"" if col.dtype.kind == "S" else 0)
    if "t_host_ns" in cols:
        written &= cols["t_host_ns"] != 0
    idx = np.flatnonzero(written)
    return int(idx[-1]) + 1 if idx.size else 0


def _extent(f: h5py.File, group: str, channels: list[str]) -> tuple[int, int]:
    """Rows of the group that hold data, and rows of its largest extent that do not.

    Looks only at the tail (growing the window while it is all unwritten), so recovering a long
    session does not load it whole.
    """
    dsets = [f[group][c] for c in channels]
    lengths = [ds.shape[0] for ds in dsets]
    if not lengths:
        return 0, 0
    n = min(lengths)  # a crash between two datasets' resizes leaves them ragged
    window = min(n, 4096)
    while True:
        keep = n - window + _trim({c: ds[n - window : n] for c, ds in zip(channels, dsets, strict=True)})
        if keep > n - window or window == n:
            return keep, max(lengths) - keep
        window = min(n, window * 8)


def read_log(path: str | Path, *, groups: Iterable[str] | None = None) -> LogData:
    """Read a session log: closed, live (SWMR writer still running) or left by a crash."""
    path = Path(path)
    f, clean = _open(path)
    with f:
        _require_session_log(f, path)
        order = _channel_order(f)
        wanted = list(order) if groups is None else list(groups)
        unknown = [g for g in wanted if g not in order]
        if unknown:
            raise LogError(f"{path}: no group {', '.join(unknown)} (has {', '.join(order)})")
        data = LogData(path=path, attrs=_decode_attrs(dict(f.attrs)), groups={}, units={}, closed_cleanly=clean)
        for g in wanted:
            keep, cut = _extent(f, g, order[g])
            cols = {}
            for c in order[g]:
                v = f[g][c][:keep]
                cols[c] = np.strings.decode(v, "ascii", "replace") if v.dtype.kind == "S" else v
            data.groups[g] = cols
            data.units[g] = {c: _text(f[g][c].attrs.get("unit", "")) for c in order[g]}
            data.docs[g] = {c: _text(f[g][c].attrs.get("doc", "")) for c in order[g]}
            data.rates[g] = _text(f[g].attrs.get("rate", ""))
            data.trimmed[g] = cut
    return data


def read_attrs(path: str | Path) -> dict[str, Any]:
    """The file attributes of a session log (JSON ones decoded), without reading any rows.

    Like ``read_log``, it opens a closed, live or crashed log. Raises ``LogError`` if the file is
    missing or unreadable, ``NotASessionLog`` if it is HDF5 but not a session log.
    """
    path = Path(path)
    f, _ = _open(path)
    with f:
        _require_session_log(f, path)
        return _decode_attrs(dict(f.attrs))


def _text(v: Any) -> str:
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)


# --- recover ---------------------------------------------------------------------------------


def _writer_alive(attrs: dict[str, Any]) -> bool:
    """True if the pid that wrote the file still runs here as a hil.log writer."""

    pid = attrs.get("writer_pid")
    if not isinstance(pid, int) or attrs.get("writer_host") != socket.gethostname():
        return False
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False
    return b"hil.log.writer" in cmdline


def _fsync_path(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def free_path(path: Path) -> Path:
    """``path``, or the first of ``STEM-2.SUFFIX``, ``STEM-3.SUFFIX``, ... that does not exist: two logs of one name
    started in the same second (sim sessions take less) never meet."""
    if not path.exists():
        return path
    for i in range(2, 10_000):
        alt = path.with_name(f"{path.stem}-{i}{path.suffix}")
        if not alt.exists():
            return alt
    raise LogError(f"no free name for {path}")


def recover_log(path: str | Path, *, output: Path | None = None) -> RecoverReport:
    """Make a log left by a crash open normally (``hil recover LOG``).

    Copies every group through a SWMR reader into a new file with the same layout (chunks,
    dtypes, dataset/group/file attributes, plus a ``recovered`` attribute), trimmed like
    ``read_log``. Without ``output`` the copy replaces the original, which is kept as
    ``<stem>.crashed.h5``; with ``output`` the original is left alone. A file that already opens
    normally is reported as such and nothing changes.
    """
    path = Path(path)
    f, clean = _open(path)
    try:
        _require_session_log(f, path)
    except LogError:
        f.close()
        raise
    if clean:
        with f:
            order = _channel_order(f)
            rows: dict[str, int] = {g: _extent(f, g, order[g])[0] for g in order}
        return RecoverReport(path, None, None, True, rows, {}, f"{path}: closed cleanly, nothing to recover")
    target = Path(output) if output is not None else path
    if output is not None and target.exists():
        f.close()
        raise LogError(f"cannot recover {path}: output {target} already exists")
    if not os.access(target.parent, os.W_OK | os.X_OK):
        f.close()
        raise LogError(f"cannot recover {path}: cannot write in {target.parent}")
    tmp = target.with_name(target.name + ".recover-tmp")
    if tmp.exists() or tmp.is_symlink():
        f.close()
        raise LogError(f"cannot recover {path}: {tmp} is in the way (left by an earlier attempt? remove it)")
    rows = {}
    trimmed: dict[str, int] = {}
    backup = None
    try:
        with f, h5py.File(tmp, "w", libver="latest") as out:
            attrs = _decode_attrs(dict(f.attrs))
            if _writer_alive(attrs):
                raise LogError(f"cannot recover {path}: its writer (pid {attrs['writer_pid']}) is still running")
            order = _channel_order(f)
            for g in order:
                src = f[g]
                dst = out.create_group(g)
                for k, v in src.attrs.items():
                    dst.attrs[k] = v
                keep, cut = _extent(f, g, order[g])
                rows[g], trimmed[g] = keep, cut
                for c in order[g]:
                    ds = src[c]
                    new = dst.create_dataset(
                        c, shape=(keep,), maxshape=(None,), dtype=ds.dtype, chunks=ds.chunks or None
                    )
                    for k, v in ds.attrs.items():
                        new.attrs[k] = v
                    for a in range(0, keep, _COPY_ROWS):
                        b = min(a + _COPY_ROWS, keep)
                        new[a:b] = ds[a:b]
            for k, v in f.attrs.items():
                out.attrs[k] = v
            names = set(attrs.get("json_attrs") or [])
            out.attrs["recovered"] = json.dumps(
                {
                    "time_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                    "from": path.name,
                    "trimmed_rows": trimmed,
                }
            )
            out.attrs["json_attrs"] = json.dumps(sorted(names | {"recovered", "json_attrs"}))
        _fsync_path(tmp)
        if output is None:
            backup = free_path(path.with_name(f"{path.stem}.crashed.h5"))
            os.rename(path, backup)
        os.replace(tmp, target)
        _fsync_path(target.parent)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        if backup is not None and not target.exists():  # put the original back where it was
            with contextlib.suppress(OSError):
                os.rename(backup, path)
        if isinstance(exc, OSError):
            raise LogError(f"cannot recover {path}: {describe_error(exc)}") from None
        raise
    where = f"; the crashed file is kept as {backup.name}" if backup else ""
    total = sum(trimmed.values())
    msg = f"{path}: recovered into {target}{where} ({total} unwritten rows trimmed)"
    return RecoverReport(path, target, backup, False, rows, trimmed, msg)


# --- export ----------------------------------------------------------------------------------


def export_log(path: str | Path, fmt: Literal["parquet", "csv"], out_dir: Path | None = None) -> list[Path]:
    """One file per group, ``<stem>.<group>.parquet|csv``, in ``out_dir`` (default: beside the log).

    Returns every file written, in group order (for CSV each group's file, then its units file).

    Parquet: each field carries ``unit`` and ``doc`` metadata; the schema metadata holds
    ``hil.units`` and ``hil.docs`` (JSON by channel), ``hil.group``, ``hil.rate``, ``hil.source``
    and ``hil.attrs`` (the file attributes as JSON), and ``PANDAS_ATTRS``, which pandas restores as
    ``df.attrs``: ``pandas.read_parquet(p).attrs["units"]`` is ``{channel: unit}``. CSV: one header
    row of channel names, then the rows, so a plain ``pandas.read_csv(p)`` reads it; the units go in
    ``<stem>.<group>.units.json`` beside it (``{channel: unit}``, in column order).
    """
    if fmt not in ("parquet", "csv"):
        raise ValueError(f"unknown export format {fmt!r} (parquet or csv)")
    path = Path(path)
    data = read_log(path)
    out_dir = Path(out_dir) if out_dir is not None else path.parent
    created = _missing_dirs(out_dir)
    written: list[Path] = []
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        _write_groups(data, path, fmt, out_dir, written)
    except OSError as exc:  # nothing half-written is left: the files and the directories made for them go
        for done in written:
            with contextlib.suppress(OSError):
                done.unlink(missing_ok=True)
        for d in created:
            with contextlib.suppress(OSError):
                d.rmdir()
        where = getattr(exc, "filename", None) or out_dir
        raise LogError(f"cannot export {path}: {where}: {describe_error(exc)}") from None
    return written


def _missing_dirs(directory: Path) -> list[Path]:
    """``directory`` and its ancestors that do not exist yet, deepest first."""
    missing = []
    d = directory.absolute()
    while not d.exists() and d != d.parent:
        missing.append(d)
        d = d.parent
    return missing


def _write_groups(data: LogData, path: Path, fmt: str, out_dir: Path, written: list[Path]) -> None:
    """One file per group into ``out_dir``; each is added to ``written`` before it is opened."""
    import pyarrow as pa  # noqa: PLC0415  (heavy: loaded only for exports)
    import pyarrow.csv as pacsv  # noqa: PLC0415  (heavy: loaded only for exports)
    import pyarrow.parquet as pq  # noqa: PLC0415  (heavy: loaded only for exports)

    for g, cols in data.groups.items():
        units = data.units[g]
        docs = data.docs[g]
        fields = [
            pa.field(
                c,
                pa.from_numpy_dtype(v.dtype) if v.dtype.kind != "U" else pa.string(),
                metadata={"unit": units[c], "doc": docs[c]},
            )
            for c, v in cols.items()
        ]
        meta = {
            "hil.group": g,
            "hil.rate": data.rates.get(g, ""),
            "hil.units": json.dumps(units),
            "hil.docs": json.dumps(docs),
            "hil.source": path.name,
            "hil.attrs": json.dumps(data.attrs, default=str),
            "hil.log_format_version": str(data.attrs.get("log_format_version", LOG_FORMAT_VERSION)),
        }
        if fmt == "parquet":  # pandas.read_parquet restores this as df.attrs (as read_log_frames sets it)
            meta["PANDAS_ATTRS"] = json.dumps(frame_attrs(g, data))
        table = pa.table([pa.array(v) for v in cols.values()], schema=pa.schema(fields, metadata=meta))
        out = out_dir / f"{path.stem}.{g}.{fmt}"
        written.append(out)
        if fmt == "parquet":
            pq.write_table(table, out)
        else:
            with open(out, "wb") as fh:
                pacsv.write_csv(table, fh)
            sidecar = units_path(out)
            written.append(sidecar)
            sidecar.write_text(json.dumps({c: units[c] for c in cols}, indent=1) + "\n")


def units_path(csv_path: str | Path) -> Path:
    """The units file of an exported CSV: ``<stem>.<group>.units.json`` beside ``<stem>.<group>.csv``."""
    csv_path = Path(csv_path)
    return csv_path.with_name(csv_path.name.removesuffix(".csv") + ".units.json")


def frame_attrs(group: str, data: LogData) -> dict[str, Any]:
    """What a group's DataFrame carries in ``df.attrs``: ``units`` and ``docs`` by column, the group and its rate."""
    return {"units": dict(data.units.get(group, {})), "docs": dict(data.docs.get(group, {})), "group": group,
            "rate": data.rates.get(group, "")}
