"""Warm cell workers (hil.campaign.warm): a sim-clock cell in a worker that outlives it gives what a `hil run` process
gives, a worker runs cell after cell, bad input and a killed worker end only their cell."""

from __future__ import annotations

import math
import signal
import threading
import time
from pathlib import Path

import pytest
import yaml

from hil.campaign import load_campaign, run_campaign
from hil.campaign.metrics import compute_metrics, log_health
from hil.campaign.runner import cell_sessions
from hil.campaign.warm import WarmCell, WorkerDied
from hil.config import PROFILES
from hil.log import read_log

CAMPAIGN = PROFILES / "campaigns" / "tune-eso-kf-miss-3deg.yaml"
WALL_METRICS = ("latency_p99_us", "latency_p50_us")  # host wall time: differs from run to run whatever runs it


def short_campaign(seconds: float = 1.5):  # type: ignore[no-untyped-def]
    return load_campaign(CAMPAIGN).model_copy(update={"duration_s": seconds, "seeds": [1]})


def session_file(tmp_path: Path, name: str = "s", **changes: object) -> Path:
    config = short_campaign()
    sessions = cell_sessions(config, tmp_path / "unused")
    data = next(iter(sessions.values()))
    data.update(changes)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.mark.slow
def test_warm_cells_give_the_metrics_and_logs_of_hil_run_processes(tmp_path: Path) -> None:
    config = short_campaign()
    warm = run_campaign(config, tmp_path / "warm", warm=True)
    cold = run_campaign(config, tmp_path / "cold", warm=False)
    assert [c.status for c in warm.cells] == ["completed"] * 2 == [c.status for c in cold.cells]
    for w, c in zip(warm.cells, cold.cells, strict=True):
        assert w.cell_id == c.cell_id
        deterministic = {k: v for k, v in w.metrics.items() if k not in WALL_METRICS}
        assert deterministic and deterministic == {k: v for k, v in c.metrics.items() if k not in WALL_METRICS}
        loop_w = read_log(tmp_path / "warm" / w.log).groups["loop"]  # type: ignore[operator]
        loop_c = read_log(tmp_path / "cold" / c.log).groups["loop"]  # type: ignore[operator]
        assert loop_w["tick"].size == loop_c["tick"].size > 1000
        for column in ("gyro_x_dps", "rate_err_el_dps", "drive_el_counts", "drive_az_counts"):
            assert (loop_w[column] == loop_c[column]).all(), column


def test_a_worker_runs_cell_after_cell_and_a_bad_session_ends_only_its_cell(tmp_path: Path) -> None:
    good = session_file(tmp_path)
    bad = session_file(tmp_path, "bad", duration_s=-1)
    worker = WarmCell()
    try:
        first = worker.run(good, tmp_path / "a", tmp_path / "a.txt", 300.0, analysis="control", settle_s=1.0)
        refused = worker.run(bad, tmp_path / "b", tmp_path / "b.txt", 300.0)
        second = worker.run(good, tmp_path / "c", tmp_path / "c.txt", 300.0)
        assert worker.alive() and worker.cells == 3
    finally:
        worker.close()
    assert first["status"] == second["status"] == "completed" and first["exit_code"] == 0
    assert Path(first["log"]).parent == tmp_path / "a" and Path(second["log"]).exists()
    assert read_log(first["log"]).groups["loop"]["tick"].size == read_log(second["log"]).groups["loop"]["tick"].size
    # the campaign's metrics, worked out in the worker, are those of the log read here
    here = {k: v for k, v in compute_metrics(first["log"], "control", 1.0).items() if math.isfinite(v)}
    assert first["metrics"] == here and here["miss_std_px"] > 0 and "metrics" not in second
    assert first["health"] == log_health(first["log"], 1.0, 32767.0)  # the registry's default drive limit
    assert refused["exit_code"] == 2 and "duration_s" in refused["message"]
    assert "duration_s" in (tmp_path / "b.txt").read_text()  # the cell's stderr, as `hil run` writes it


@pytest.mark.slow
def test_a_worker_killed_mid_cell_is_named_and_the_next_cell_gets_a_new_one(tmp_path: Path) -> None:
    long = session_file(tmp_path, duration_s=600.0)
    worker = WarmCell()
    threading.Thread(target=lambda: (time.sleep(3.0), worker.send_signal(signal.SIGKILL)), daemon=True).start()
    with pytest.raises(WorkerDied, match="SIGKILL"):
        worker.run(long, tmp_path / "a", tmp_path / "a.txt", 300.0)
    assert not worker.alive()
    worker.close()


def test_sigint_ends_a_warm_cell_the_way_it_ends_hil_run(tmp_path: Path) -> None:
    long = session_file(tmp_path, duration_s=600.0)
    worker = WarmCell()
    try:
        def rows() -> int:
            logs = list((tmp_path / "a").glob("*.h5"))
            try:
                return int(read_log(logs[0]).groups["loop"]["tick"].size) if logs else 0
            except Exception:  # created, not yet readable
                return 0

        def interrupt_when_logging() -> None:
            deadline = time.monotonic() + 300.0
            while rows() < 200 and time.monotonic() < deadline:
                time.sleep(0.2)
            worker.send_signal(signal.SIGINT)

        threading.Thread(target=interrupt_when_logging, daemon=True).start()
        record = worker.run(long, tmp_path / "a", tmp_path / "a.txt", 300.0)
        assert record["status"] == "interrupted" and record["exit_code"] == 130
        assert read_log(record["log"]).groups["loop"]["tick"].size >= 200  # the log kept, closed the safe way
        assert worker.alive()  # and the worker goes on to the next cell
        again = worker.run(session_file(tmp_path, "again"), tmp_path / "b", tmp_path / "b.txt", 300.0)
        assert again["status"] == "completed"
    finally:
        worker.close()


def test_a_stop_sent_as_a_cell_starts_is_held_and_a_finished_cells_handle_signals_nothing(tmp_path: Path) -> None:
    worker = WarmCell()
    try:
        handle = worker.begin()
        handle.send_signal(signal.SIGINT)  # the campaign stops before the worker has even read its cell
        record = worker.run(session_file(tmp_path, "long", duration_s=600.0), tmp_path / "a", tmp_path / "a.txt",
                            300.0)
        assert record["status"] == "interrupted" and record["exit_code"] == 130
        worker.begin()
        handle.send_signal(signal.SIGINT)  # a stop for the cell that ended must not reach the next one
        again = worker.run(session_file(tmp_path), tmp_path / "b", tmp_path / "b.txt", 300.0)
        assert again["status"] == "completed" and worker.alive()
    finally:
        worker.close()
