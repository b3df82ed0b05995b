"""The notebook API (``read_log_frames``: pandas DataFrames) and the exports read back with plain pandas."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest

from hil.log import SCHEMA, LogError, LogFrames, export_log, read_log, read_log_frames, recover_log, units_path
from hil.log.schema import group_by_name
from tests.log.conftest import SIM_SECONDS
from tests.log.test_log import fill, make_log, rows_for

UNITS = {g.name: {c.name: c.unit for c in g.channels} for g in SCHEMA}


def _wait_gone(pid: int) -> None:
    for _ in range(500):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.01)


def test_read_log_frames_of_a_session_log(sim_log: Path) -> None:
    data = read_log_frames(sim_log)
    assert isinstance(data, LogFrames) and data.path == sim_log and data.closed_cleanly
    assert data.groups == [g.name for g in SCHEMA]
    with h5py.File(sim_log, "r") as f:
        for g in SCHEMA:
            df = getattr(data, g.name)
            assert df is data[g.name] and df is data.frames[g.name]
            assert list(df.columns) == [c.name for c in g.channels]
            assert len(df) == f[g.name][g.channels[0].name].shape[0], g.name  # every row of the file
            assert df.attrs["units"] == UNITS[g.name] and data.units[g.name] == UNITS[g.name]
            assert df.attrs["rate"] == group_by_name()[g.name].rate and df.attrs["group"] == g.name
            for c in g.channels:
                if c.dtype.startswith("S"):
                    assert list(df[c.name]) == [v.decode() for v in f[g.name][c.name][:]]
                else:
                    assert df[c.name].dtype == np.dtype(c.dtype), (g.name, c.name)
                    np.testing.assert_array_equal(df[c.name].to_numpy(), f[g.name][c.name][:])
    loop = data.loop
    assert len(loop) >= SIM_SECONDS * 1000 and loop.attrs["units"]["gyro_y_dps"] == "deg/s"
    assert np.all(np.diff(loop["tick"].to_numpy().astype(np.int64)) == 1)
    assert len(data.image) >= SIM_SECONDS * 100 - 5 and data.image.attrs["units"]["miss_x_px"] == "px"
    assert data.config["duration_s"] == SIM_SECONDS and data.config["controller"]["name"] == "eso_kf_high_gain"
    assert data.provenance["controller"]["params"]["omega_o_rad_s"] == 1000.0
    assert data.attrs["clock"] == "sim" and data.attrs["seed"] == 4
    kinds = list(data.events["kind"])
    assert kinds[0] == "state" and kinds[-1] == "summary"
    (summary,) = data.event_details("summary")
    assert summary["detail"]["cycles"] == len(loop) and summary["tick"] == int(loop["tick"].iloc[-1])

    text = repr(data)
    assert text.startswith(f"<LogFrames {sim_log}: session_name swing-1deg-1hz-eso, controller eso_kf_high_gain")
    for g in SCHEMA:
        assert f".{g.name}" in text and f" {len(data[g.name])} rows x " in text
    assert {"loop", "events", "provenance"} <= set(dir(data))
    with pytest.raises(AttributeError, match="groups: loop, timing"):
        _ = data.nope
    with pytest.raises(KeyError, match="no log group 'nope'"):
        data["nope"]
    assert read_log_frames(sim_log, groups=["image"]).groups == ["image"]


@pytest.mark.slow
def test_read_log_frames_of_a_live_and_of_a_crashed_log(tmp_path: Path) -> None:
    p = tmp_path / "live.h5"
    log = make_log(p, flush_interval_s=10.0)  # only explicit flushes
    fill(log, 300)
    log.flush()
    fill(log, 50, start=300)  # not flushed: not in the file yet
    live = read_log_frames(p)
    assert not live.closed_cleanly
    assert {g: len(live[g]) for g in rows_for(300)} == rows_for(300)
    np.testing.assert_array_equal(live.loop["tick"].to_numpy(), np.arange(300))
    assert live.loop.attrs["units"]["t_host_ns"] == "ns" and live.config == read_log(p).attrs["config"]
    assert live.provenance == {}  # a bare SessionLog records none
    assert ", live or crashed" in repr(live)

    os.kill(log.writer_pid, signal.SIGKILL)  # the writer dies: the file stays as the last flush left it
    _wait_gone(log.writer_pid)
    log.close()
    crashed = read_log_frames(p)
    assert not crashed.closed_cleanly and len(crashed.loop) == 300
    recover_log(p)
    recovered = read_log_frames(p)
    assert recovered.closed_cleanly
    for g in rows_for(300):
        pd.testing.assert_frame_equal(recovered[g], crashed[g])
        assert recovered[g].attrs["units"] == UNITS[g]
    with pytest.raises(LogError, match="no such file"):
        read_log_frames(tmp_path / "absent.h5")


def test_csv_export_reads_with_plain_pandas_and_units_beside_it(sim_log: Path, tmp_path: Path) -> None:
    data = read_log(sim_log)
    written = export_log(sim_log, "csv", out_dir=tmp_path)
    assert len(written) == 2 * len(SCHEMA) and all(p.exists() for p in written)
    for g in SCHEMA:
        path = tmp_path / f"{sim_log.stem}.{g.name}.csv"
        df = pd.read_csv(path)  # nothing to skip, nothing to tell it
        assert list(df.columns) == [c.name for c in g.channels]
        assert len(df) == data.rows(g.name) and len(df) > 0
        units = json.loads(units_path(path).read_text())
        assert units == UNITS[g.name] and units_path(path).name == f"{sim_log.stem}.{g.name}.units.json"
        for c in g.channels:
            want = data.groups[g.name][c.name]
            if want.dtype.kind == "U":
                assert list(df[c.name].fillna("")) == list(want)
            else:  # floats in their shortest exact form, integers (t_host_ns too) exact
                np.testing.assert_array_equal(df[c.name].to_numpy().astype(want.dtype), want, err_msg=c.name)
    # the documented way to apply the units
    p = tmp_path / f"{sim_log.stem}.loop.csv"
    df = pd.read_csv(p)
    df.attrs["units"] = json.loads(p.with_name(p.name.removesuffix(".csv") + ".units.json").read_text())
    assert df.attrs["units"]["gyro_y_dps"] == "deg/s" and df.attrs["units"]["tick"] == "1"
    assert df["t_host_ns"].dtype == np.int64
    assert int(df["t_host_ns"].iloc[-1]) == int(data.groups["loop"]["t_host_ns"][-1])


def test_parquet_export_gives_units_to_pandas(sim_log: Path, tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    written = export_log(sim_log, "parquet", out_dir=tmp_path)
    assert [p.name for p in written] == [f"{sim_log.stem}.{g.name}.parquet" for g in SCHEMA]
    frames = read_log_frames(sim_log)
    for g, path in zip(SCHEMA, written, strict=True):
        df = pd.read_parquet(path)
        assert df.attrs["units"] == UNITS[g.name]  # pandas restores df.attrs from the file
        assert df.attrs == frames[g.name].attrs  # the same attrs as the notebook API gives
        assert list(df.columns) == [c.name for c in g.channels] and len(df) == len(frames[g.name])
        schema = pq.read_schema(path)  # the per-field metadata stays
        for c in g.channels:
            assert schema.field(c.name).metadata[b"unit"].decode() == c.unit
    loop = pd.read_parquet(written[0])
    pd.testing.assert_frame_equal(loop, frames.loop)
