"""Session log: round trip, live (SWMR) reading, crash survival and recovery, flush cadence, export, errors."""

from __future__ import annotations

import json
import math
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

import hil.log.session_log as session_log_mod
from hil import __version__
from hil.log import (
    ATTRS,
    LOG_FORMAT_VERSION,
    SCHEMA,
    LogError,
    SessionLog,
    docgen,
    export_log,
    read_log,
    recover_log,
    units_path,
)
from hil.log.schema import DETAIL_LEN, group_by_name, schema_from_json, schema_to_json
from tests.log.crash_writer import ATTRS as CRASH_ATTRS
from tests.log.crash_writer import EVERY, expected_columns, pattern_row

ROOT = Path(__file__).resolve().parents[2]
G = group_by_name(SCHEMA)
BIG_CONFIG = {"session": "t", "plant": {"inertia": [0.01, 0.02], "notes": "x" * 5000}, "nan": None}
ATTRS_IN = {
    "config": BIG_CONFIG,
    "ident": {"servo": {"board": "SERVO", "firmware_version": "1.2.3", "catalogue_fingerprint": 123}},
    "seed": 42,
    "operator": "bench-test",
    "gain": 0.125,
    "flags": [1, 2, 3],
}


def make_log(path: Path, **kw) -> SessionLog:
    return SessionLog(path, attrs=ATTRS_IN, **kw)


def fill(log: SessionLog, n_ticks: int, start: int = 0) -> None:
    for k in range(start, start + n_ticks):
        for name, every in EVERY.items():
            if k % every == 0:
                log.append(name, pattern_row(G[name], k // every, 1_000_000 + k))


def rows_for(n_ticks: int) -> dict[str, int]:
    return {name: -(-n_ticks // every) for name, every in EVERY.items()}


def assert_pattern(data, name: str, n: int) -> None:
    cols = data.groups[name]
    assert len(cols[next(iter(cols))]) == n, name
    for ch, want in expected_columns(G[name], n).items():
        got = cols[ch]
        assert got.dtype == want.dtype, (name, ch)
        np.testing.assert_array_equal(got, want, err_msg=f"{name}/{ch}")


# --- round trip ------------------------------------------------------------------------------


def test_round_trip_every_group_units_and_attrs(tmp_path):
    p = tmp_path / "s.h5"
    with make_log(p) as log:
        fill(log, 1234)
        log.event("state", 7, {"from": "idle", "to": "track"})
        log.event("fault", 8, "plain text détail")  # non-ASCII is escaped, not lost
        log.event("info", 9, {"long": "y" * 1000})
        log.event("a_kind_that_is_much_longer_than_32_characters", 10)
    assert log.rows == {**rows_for(1234), "events": 4}
    assert log.error is None
    assert log.bad_values == {g.name: 0 for g in SCHEMA}

    with h5py.File(p, "r") as f:  # closed cleanly: opens without SWMR
        assert f["loop/gyro_y_dps"].attrs["unit"] == "deg/s"
        assert f["loop"].attrs["rate"] == "1 kHz"
        assert f["loop/t_s"].attrs["doc"]
        for g in SCHEMA:  # one 1-D, chunked, extendible dataset per channel, in the schema's dtype
            for c in g.channels:
                ds = f[g.name][c.name]
                assert ds.ndim == 1 and ds.maxshape == (None,) and ds.chunks is not None
                assert ds.dtype == np.dtype(c.dtype)
                assert ds.attrs["unit"] == c.unit
        assert f.attrs["seed"] == 42 and f.attrs["gain"] == 0.125 and f.attrs["operator"] == "bench-test"
        assert json.loads(f.attrs["config"]) == BIG_CONFIG
        assert f.attrs["log_format_version"] == LOG_FORMAT_VERSION
        assert schema_from_json(f.attrs["schema"]) == SCHEMA

    data = read_log(p)
    assert data.closed_cleanly
    for name, n in rows_for(1234).items():
        assert_pattern(data, name, n)
        assert data.trimmed[name] == 0
    np.testing.assert_array_equal(data.groups["loop"]["t_host_ns"], 1_000_000 + np.arange(1234))
    ev = data.groups["events"]
    assert list(ev["kind"]) == ["state", "fault", "info", "a_kind_that_is_much_longer_than_"]
    assert json.loads(ev["detail"][0]) == {"from": "idle", "to": "track"}
    assert ev["detail"][1] == "plain text d\\xe9tail"
    assert len(ev["detail"][2]) == DETAIL_LEN and ev["detail"][2].endswith("...")
    np.testing.assert_array_equal(ev["tick"], [7, 8, 9, 10])
    assert np.all(np.diff(ev["t_host_ns"]) >= 0) and ev["t_host_ns"][0] > 0

    assert data.attrs["config"] == BIG_CONFIG and data.attrs["ident"] == ATTRS_IN["ident"]
    assert data.attrs["flags"] == [1, 2, 3] and data.attrs["seed"] == 42
    assert data.attrs["software_version"] == __version__
    assert data.attrs["start_time_utc"].endswith("+00:00")
    for a in ATTRS:
        if a.source not in ("recover", "session"):  # hil.session writes those; a bare SessionLog need not
            assert a.name in data.attrs, a.name
    for g in SCHEMA:
        assert data.units[g.name] == {c.name: c.unit for c in g.channels}
    assert data.units["loop"]["gyro_x_dps"] == "deg/s" and data.units["loop"]["latency_us"] == "us"


def test_read_log_subset_and_unknown_group(tmp_path):
    p = tmp_path / "s.h5"
    with make_log(p) as log:
        fill(log, 100)
    assert set(read_log(p, groups=["image"]).groups) == {"image"}
    with pytest.raises(LogError, match="no group nope"):
        read_log(p, groups=["nope"])


def test_bad_values_are_coerced_counted_and_never_raise(tmp_path):
    p = tmp_path / "s.h5"
    row = list(pattern_row(G["loop"], 0))
    row[0] = math.nan  # tick u4 <- NaN
    row[3] = None  # gyro_x f4 <- None
    row[18] = 12.7  # drive_az_counts i4 <- float: truncated, not bad
    row[21] = -5  # tick_gap u4 <- out of range
    with make_log(p) as log:
        log.append("loop", row)
        log.append("loop", pattern_row(G["loop"], 1))
        log.append("image", (1, 1e40, 5, 1e40, -1e40, True, -1))  # f4 overflow -> inf (as numpy); u4 -1 -> 0
        with pytest.raises(ValueError, match="takes 22 values"):
            log.append("loop", row[:-1])
        with pytest.raises(ValueError, match="unknown log group"):
            log.append("nope", row)
    assert log.bad_values["loop"] == 3 and log.bad_values["image"] == 1
    loop = read_log(p).groups["loop"]
    assert loop["tick"][0] == 0 and math.isnan(loop["gyro_x_dps"][0])
    assert loop["drive_az_counts"][0] == 12 and loop["tick_gap"][0] == 0
    assert loop["tick"][1] == 1
    img = read_log(p).groups["image"]
    assert img["t_exposure_s"][0] == 1e40 and np.isinf(img["miss_x_px"][0]) and img["miss_y_px"][0] < 0
    assert img["loop_tick"][0] == 0 and img["track_valid"][0] == 1


def test_append_after_close_raises(tmp_path):
    log = make_log(tmp_path / "s.h5")
    log.close()
    log.close()  # idempotent
    with pytest.raises(LogError, match="closed"):
        log.append("loop", pattern_row(G["loop"], 0))


# --- live reading ----------------------------------------------------------------------------


def test_live_swmr_reader_sees_rows_grow(tmp_path):
    p = tmp_path / "live.h5"
    with make_log(p, flush_interval_s=10.0) as log:  # only explicit flushes
        fill(log, 300)
        log.flush()
        assert log.rows["loop"] == 300
        with pytest.raises(OSError):
            h5py.File(p, "r")  # a SWMR file being written does not open without swmr=True
        with h5py.File(p, "r", swmr=True) as f:
            ds = f["loop/tick"]
            assert ds.shape == (300,)
            fill(log, 200, start=300)
            ds.refresh()
            assert ds.shape == (300,)  # not flushed yet
            log.flush()
            ds.refresh()
            f["loop/gyro_x_dps"].refresh()
            assert ds.shape == (500,)
            np.testing.assert_array_equal(ds[:], np.arange(500))
        live = read_log(p)
        assert not live.closed_cleanly
        assert_pattern(live, "loop", 500)
        with pytest.raises(LogError, match="still running"):
            recover_log(p)  # never pull a file from under its writer
    assert read_log(p).closed_cleanly


# --- crash -----------------------------------------------------------------------------------


class CrashWriter:
    """The crash writer child (tests/log/crash_writer.py): its process, its log writer's pid, and the loop rows the
    writer has acknowledged as flushed so far (read from the child's stdout by a thread)."""

    def __init__(self, path: Path, seconds: float) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "tests.log.crash_writer", str(path), str(seconds)],
                                     cwd=ROOT, stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        first = self.proc.stdout.readline().split()
        assert first[0] == "writer_pid", first
        assert self.proc.stdout.readline().strip() == "started"
        self.writer_pid = int(first[1])
        self.flushed = 0
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            word, _, n = line.partition(" ")
            if word == "flushed":
                self.flushed = max(self.flushed, int(n))

    def await_flushed(self, rows: int, timeout_s: float = 30.0) -> None:
        """Until the writer has acknowledged ``rows`` loop rows (it is up and flushing: how long it takes to start
        depends on the machine's load, what a kill loses does not)."""
        end = time.monotonic() + timeout_s
        while self.flushed < rows:
            assert time.monotonic() < end, f"the writer acknowledged only {self.flushed} rows in {timeout_s:g} s"
            time.sleep(0.01)

    def killed(self) -> int:
        """After the kill: every loop row the writer acknowledged as flushed (they must all be in the file)."""
        self.proc.wait()
        self._reader.join(10)
        return self.flushed


def _start_crash_writer(path: Path, seconds: float) -> tuple[subprocess.Popen[str], int]:
    child = CrashWriter(path, seconds)
    return child.proc, child.writer_pid


def _wait_gone(pid: int, timeout: float = 10.0) -> None:
    """Wait until pid has exited (it is not our child: poll /proc)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (FileNotFoundError, ProcessLookupError):
            return
        if state in ("Z", "X"):
            return
        time.sleep(0.01)
    raise AssertionError(f"pid {pid} still running")


def _check_crash_file(data, flushed: int) -> int:
    """The rows that survived a kill: the logged pattern, and at least the ``flushed`` rows the writer had
    acknowledged. How long before the kill the newest surviving row was logged is the machine's scheduling (a
    flush every 100 ms, the writer at nice 10): measured, not asserted, in docs/log-format.md."""
    loop = data.groups["loop"]
    n = len(loop["tick"])
    assert n >= flushed > 0, f"{n} rows survived of {flushed} acknowledged as flushed"
    assert_pattern(data, "loop", n)
    for name, every in EVERY.items():  # the slower groups, as far as they got
        m = len(data.groups[name]["t_host_ns" if name != "timing" else "tick"])
        assert (n - 1) // every - 2 <= m <= (n - 1) // every + 2, name
        assert_pattern(data, name, m)
    assert len(data.groups["events"]["tick"]) in range((n - 1) // 250 - 1, (n - 1) // 250 + 3)
    return n


def test_sigkill_of_bench_and_writer_keeps_every_flushed_row_and_recovers(tmp_path):
    p = tmp_path / "crash.h5"
    child = CrashWriter(p, 30.0)
    child.await_flushed(301)
    time.sleep(random.uniform(0.0, 1.0))  # a random moment of the steady state
    os.kill(child.writer_pid, signal.SIGKILL)  # power loss / OOM: both processes die at once
    os.kill(child.proc.pid, signal.SIGKILL)
    flushed = child.killed()
    _wait_gone(child.writer_pid)

    with pytest.raises(OSError):
        h5py.File(p, "r")  # left in SWMR-writing state
    before = read_log(p)
    assert not before.closed_cleanly
    n = _check_crash_file(before, flushed)
    assert before.attrs["seed"] == 1234 and before.attrs["config"] == CRASH_ATTRS["config"]

    report = recover_log(p)
    assert not report.already_clean
    assert report.backup == tmp_path / "crash.crashed.h5" and report.backup.exists()
    assert report.output == p and report.rows["loop"] == n
    assert "recovered" in report.summary() and str(report) == report.summary()
    assert any(line.split()[:2] == ["loop", str(n)] for line in str(report).splitlines())
    with h5py.File(p, "r") as f:  # now opens normally
        assert f["loop/tick"].shape == (n,)
        with h5py.File(report.backup, "r", swmr=True) as orig:
            assert f["loop/tick"].chunks == orig["loop/tick"].chunks
    after = read_log(p)
    assert after.closed_cleanly
    for name, cols in before.groups.items():
        for ch, v in cols.items():
            np.testing.assert_array_equal(after.groups[name][ch], v, err_msg=f"{name}/{ch}")
    assert after.units == before.units
    assert after.attrs["recovered"]["from"] == "crash.h5"
    strip = {"recovered", "json_attrs"}
    assert {k: v for k, v in after.attrs.items() if k not in strip} == {
        k: v for k, v in before.attrs.items() if k not in strip
    }
    again = recover_log(p)
    assert again.already_clean and again.backup is None and "nothing to recover" in again.message


def test_sigkill_of_bench_only_writer_closes_the_file(tmp_path):
    """The writer outlives the bench: it reads EOF, writes what it got and closes the file normally."""
    p = tmp_path / "bench_died.h5"
    child = CrashWriter(p, 30.0)
    child.await_flushed(301)
    time.sleep(random.uniform(0.0, 0.5))
    os.kill(child.proc.pid, signal.SIGKILL)
    flushed = child.killed()
    _wait_gone(child.writer_pid)
    with h5py.File(p, "r"):
        pass  # closed cleanly by the writer
    data = read_log(p)
    assert data.closed_cleanly
    _check_crash_file(data, flushed)
    assert recover_log(p).already_clean


def test_recover_to_output_leaves_the_original(tmp_path):
    p = tmp_path / "c.h5"
    proc, writer_pid = _start_crash_writer(p, 3.0)
    time.sleep(0.5)
    os.kill(writer_pid, signal.SIGKILL)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    _wait_gone(writer_pid)
    out = tmp_path / "fixed.h5"
    report = recover_log(p, output=out)
    assert report.output == out and report.backup is None
    with pytest.raises(OSError):
        h5py.File(p, "r")  # untouched
    with h5py.File(out, "r") as f:
        assert f["loop/tick"].shape == (report.rows["loop"],)
    with pytest.raises(LogError, match="already exists"):
        recover_log(p, output=out)


def test_trim_drops_zero_rows_past_the_last_flush(tmp_path):
    """Extent grown but data never written (a crash between resize and write) reads as 0 and is trimmed."""
    p = tmp_path / "s.h5"
    with make_log(p) as log:
        fill(log, 100)
    with h5py.File(p, "a") as f:
        for ch in G["loop"].channels:
            f["loop"][ch.name].resize((130,))  # 30 rows of fill value
        f["image/frame"].resize((15,))  # ragged: one channel longer than the others
    data = read_log(p)
    assert data.trimmed["loop"] == 30 and data.trimmed["image"] == 5
    assert_pattern(data, "loop", 100)
    assert_pattern(data, "image", 10)


# --- flush cadence ---------------------------------------------------------------------------


@pytest.mark.slow
def test_the_writer_flushes_while_rows_come_never_more_often_than_its_interval(tmp_path):
    # how far the file lags the appends is the machine's (the writer runs at nice 10): benchmarks/bench_log.py
    p = tmp_path / "cadence.h5"
    with make_log(p, flush_interval_s=0.1) as log:
        deadline = time.perf_counter()
        steady = None  # the first row after the writer's first flush: how long it takes to start is the machine's
        for k in range(3000):  # 3 s at 1 kHz, real time
            while (rem := deadline - time.perf_counter()) > 0:
                if rem > 3e-4:
                    time.sleep(rem - 2e-4)
            log.append("loop", pattern_row(G["loop"], k, time.monotonic_ns()))
            if steady is None and log.rows["loop"] > 0:
                steady, t_steady, flushes_before = k, time.perf_counter(), len(log.stats)
            deadline += 1e-3
        flushes = len(log.stats)
        elapsed = time.perf_counter() - t_steady
        on_disk_before_close = log.rows["loop"]
    assert steady is not None and steady < 3000, steady  # the writer flushed while the rows came
    assert 0 < on_disk_before_close <= 3000
    assert flushes - flushes_before <= elapsed / 0.1 + 2  # a flush every ~100 ms, never more often
    assert log.rows["loop"] == 3000  # and close() writes the rest


# --- export ----------------------------------------------------------------------------------


def test_export_parquet_and_csv_round_trip_with_units(tmp_path):
    import pandas as pd
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    p = tmp_path / "sess.h5"
    with make_log(p) as log:
        fill(log, 250)
        log.event("watchdog", 3, {"late_ms": 2.5, "text": 'quote " and, comma'})
    data = read_log(p)

    out = export_log(p, "parquet", out_dir=tmp_path / "pq")
    assert [x.name for x in out] == [f"sess.{g.name}.parquet" for g in SCHEMA]
    for g, path in zip(SCHEMA, out, strict=True):
        table = pq.read_table(path)
        assert table.column_names == [c.name for c in g.channels]
        meta = table.schema.metadata
        assert json.loads(meta[b"hil.units"]) == {c.name: c.unit for c in g.channels}
        assert json.loads(meta[b"hil.attrs"])["seed"] == 42
        assert pd.read_parquet(path).attrs["units"] == {c.name: c.unit for c in g.channels}  # PANDAS_ATTRS
        for c in g.channels:
            field = table.schema.field(c.name)
            assert field.metadata[b"unit"].decode() == c.unit
            got = table.column(c.name).to_numpy()
            want = data.groups[g.name][c.name]
            if want.dtype.kind == "U":
                assert list(got) == list(want)
            else:
                assert got.dtype == want.dtype
                np.testing.assert_array_equal(got, want)

    out = export_log(p, "csv", out_dir=tmp_path / "csv")
    assert [x.name for x in out] == [f"sess.{g.name}.{ext}" for g in SCHEMA for ext in ("csv", "units.json")]
    for g, path, units in zip(SCHEMA, out[::2], out[1::2], strict=True):
        assert units == units_path(path)
        assert json.loads(units.read_text()) == {c.name: c.unit for c in g.channels}
        assert list(json.loads(units.read_text())) == [c.name for c in g.channels]  # column order
        first = path.read_text().splitlines()[0]
        assert first == ",".join(f'"{c.name}"' for c in g.channels)  # one header row, no comment line
        table = pacsv.read_csv(path)
        assert table.column_names == [c.name for c in g.channels]
        for c in g.channels:
            want = data.groups[g.name][c.name]
            got = table.column(c.name).to_numpy(zero_copy_only=False)
            if want.dtype.kind == "U":
                assert list(got) == list(want)
            else:
                np.testing.assert_array_equal(got.astype(want.dtype), want, err_msg=f"{g.name}/{c.name}")
    assert json.loads(read_log(p).groups["events"]["detail"][0])["text"] == 'quote " and, comma'
    with pytest.raises(ValueError, match="format"):
        export_log(p, "xlsx")  # type: ignore[arg-type]


# --- errors ----------------------------------------------------------------------------------


def test_missing_directory_existing_file_and_bad_attrs(tmp_path):
    missing = tmp_path / "no" / "such" / "dir" / "s.h5"
    with pytest.raises(LogError) as ei:
        make_log(missing)
    msg = str(ei.value)
    assert str(missing) in msg and "does not exist" in msg and "\n" not in msg

    p = tmp_path / "s.h5"
    make_log(p).close()
    with pytest.raises(LogError, match="already exists"):
        make_log(p)
    make_log(p, overwrite=True).close()

    with pytest.raises(ValueError, match="lack config"):
        SessionLog(tmp_path / "x.h5", attrs={"ident": {}, "seed": 1})
    with pytest.raises(ValueError, match="written by the log"):
        SessionLog(tmp_path / "x.h5", attrs={**ATTRS_IN, "schema": "x"})
    with pytest.raises(ValueError, match="not JSON"):
        SessionLog(tmp_path / "x.h5", attrs={**ATTRS_IN, "config": "not json {"})
    assert not (tmp_path / "x.h5").exists()

    with pytest.raises(LogError, match="no such file"):
        read_log(tmp_path / "absent.h5")


def test_unwritable_directory_names_path_and_cause(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root writes into read-only directories")
    d = tmp_path / "ro"
    d.mkdir(mode=0o500)
    with pytest.raises(LogError) as ei:
        make_log(d / "s.h5")
    assert str(d / "s.h5") in str(ei.value) and "ermission denied" in str(ei.value)


def test_disk_full_mid_session_sets_error_keeps_flushed_rows(tmp_path, monkeypatch):
    limit = 1_000_000  # bytes: the new file (~100 kB) fits, a few thousand more rows do not
    script = Path(__file__).with_name("limited_writer.py")
    monkeypatch.setattr(session_log_mod, "_writer_argv", lambda: [sys.executable, str(script), str(limit)])
    p = tmp_path / "full.h5"
    log = make_log(p)
    fill(log, 500)
    log.flush()
    assert log.error is None and log.rows["loop"] == 500
    for k in range(500, 60_500):  # ~5.6 MB of loop rows
        log.append("loop", pattern_row(G["loop"], k))
    log.flush()
    assert log.error is not None
    assert str(p) in log.error and "file too large" in log.error.lower(), log.error
    log.append("loop", pattern_row(G["loop"], 0))  # still no exception: rows are dropped
    log.event("info", 1, "dropped")
    log.flush()
    log.close()  # no exception either
    data = read_log(p)
    n = len(data.groups["loop"]["tick"])
    assert n >= 500
    assert_pattern(data, "loop", n)


def test_writer_killed_mid_session_sets_error_and_file_recovers(tmp_path):
    p = tmp_path / "oom.h5"
    log = make_log(p)
    fill(log, 400)
    log.flush()
    os.kill(log.writer_pid, signal.SIGKILL)
    _wait_gone(log.writer_pid)
    fill(log, 100, start=400)
    log.flush()
    assert log.error is not None and "killed (SIGKILL)" in log.error
    fill(log, 100, start=500)  # appends are dropped silently
    log.close()
    assert recover_log(p).rows["loop"] == 400
    assert_pattern(read_log(p), "loop", 400)


def test_one_writer_process_writes_log_after_log_and_one_that_failed_is_not_reused(tmp_path, monkeypatch):
    """A process that runs session after session starts one writer: it writes each log whole and closes it, then
    takes the next. A writer whose log failed ends with it; the next log gets a new one."""
    pids = []
    for i in range(3):
        p = tmp_path / f"s{i}.h5"
        with make_log(p) as log:
            fill(log, 300 + 100 * i)
            pids.append(log.writer_pid)
        assert log.error is None
        data = read_log(p)
        for name, n in rows_for(300 + 100 * i).items():
            assert_pattern(data, name, n)
        with h5py.File(p, "r") as f:  # closed: opens without SWMR
            assert int(f.attrs["writer_pid"]) == pids[-1]
    assert pids[0] == pids[1] == pids[2]
    os.kill(pids[0], 0)  # still there, idle, waiting for the next log
    os.sched_setaffinity(pids[0], {min(os.sched_getaffinity(0))})  # as a session's host.loop_cpu leaves it
    with make_log(tmp_path / "s3.h5") as log:
        assert log.writer_pid == pids[0]
        assert os.sched_getaffinity(log.writer_pid) == os.sched_getaffinity(0)  # what a new writer would inherit

    limit = 1_000_000  # a writer that cannot write past 1 MB: its log fails
    script = Path(__file__).with_name("limited_writer.py")
    monkeypatch.setattr(session_log_mod, "_writer_argv", lambda: [sys.executable, str(script), str(limit)])
    with make_log(tmp_path / "full.h5") as log:
        limited = log.writer_pid
        assert limited != pids[0]  # the spare runs another command: not taken
        fill(log, 60_000)
        log.flush()
        assert log.error is not None
    _wait_gone(limited)  # ended with its failed log
    monkeypatch.undo()
    with make_log(tmp_path / "after.h5") as log:
        fill(log, 100)
        assert log.writer_pid != limited
    assert log.error is None
    assert_pattern(read_log(tmp_path / "after.h5"), "loop", rows_for(100)["loop"])

def test_crash_writer_pattern_is_exact_in_every_dtype():
    """The crash tests compare exactly: every pattern value must survive the cast to its dtype."""
    for g in SCHEMA:
        if g.name == "events":
            continue
        for k in (0, 1, 999, 123_456):
            for ci, c in enumerate(g.channels):
                v = pattern_row(g, k)[ci]
                assert float(np.array(v, dtype=c.dtype)) == v, (g.name, c.name, v)


# --- schema and document ---------------------------------------------------------------------


def test_schema_has_the_specified_channels_and_units():
    names = [g.name for g in SCHEMA]
    assert names == ["loop", "timing", "image", "hexapod", "drive", "links", "events"]
    loop = {c.name: (c.dtype, c.unit) for c in G["loop"].channels}
    assert len(loop) == 22
    assert loop["tick"] == ("u4", "1") and loop["t_host_ns"] == ("i8", "ns") and loop["t_s"] == ("f8", "s")
    assert loop["gyro_z_dps"] == ("f4", "deg/s") and loop["el_deg"] == ("f8", "deg")
    assert loop["drive_el_counts"] == ("i4", "counts") and loop["tick_gap"] == ("u4", "1")
    assert loop["dist_az_counts"] == ("f4", "counts") and loop["latency_us"] == ("f4", "us")
    drive = {c.name: (c.dtype, c.unit) for c in G["drive"].channels}
    assert drive["az_current_a"] == drive["el_current_a"] == ("f4", "A") and drive["bus_voltage_v"] == ("f4", "V")
    assert drive["last_tick"] == ("u4", "1") and drive["faults"] == ("u1", "1")
    links = [c.name for c in G["links"].channels]
    assert len(links) == 37 and links[1] == "servo_frames_ok" and links[-1] == "hexapod_rejected"
    assert {c.name: c.dtype for c in G["events"].channels} == {
        "t_host_ns": "i8",
        "tick": "u4",
        "kind": "S32",
        "detail": "S480",
    }
    assert schema_from_json(schema_to_json()) == SCHEMA
    for g in SCHEMA:
        assert g.doc and all(c.doc and c.unit for c in g.channels)


def test_log_format_document_is_generated_from_the_schema():
    doc = docgen.DOC_PATH.read_text()
    assert docgen.apply(doc) == doc, "docs/log-format.md is stale: run `python -m hil.log.docgen --write`"
    for g in SCHEMA:
        assert f"### `/{g.name}`" in doc
        for c in g.channels:
            assert f"| `{c.name}` |" in doc and f"| `{c.unit}` |" in doc
    for a in ATTRS:
        assert f"| `{a.name}` |" in doc
    for needle in ("h5read", "swmr=True", "hil recover", "hil export", "--format parquet", "SIGKILL"):
        assert needle in doc, needle


def test_a_copy_cut_short_is_refused_at_once(tmp_path):
    """A log file missing most of what its superblock counts (a copy interrupted) is one LogError naming it, at once:
    HDF5's SWMR reader would retry the missing index blocks for minutes."""
    p = tmp_path / "full.h5"
    log = make_log(p)
    fill(log, 20_000)
    log.close()
    data = p.read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[: len(data) // 3])
    t0 = time.monotonic()
    with pytest.raises(LogError, match=r"cut\.h5: truncated file \(\d+ of \d+ bytes"):
        read_log(cut)
    assert time.monotonic() - t0 < 5.0
