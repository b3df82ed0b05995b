"""The dask engine: a campaign's cells on a dask.distributed cluster (a real LocalCluster of two worker processes)
give the local engine's results cell for cell, resume as the local engine does, and survive a worker killed in the
middle of a cell; bad engine options are one-line errors before anything is written."""

from __future__ import annotations

import contextlib
import functools
import operator
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

import hil
from hil.campaign import CellResult, load_results
from hil.campaign.engines import DaskEngine, EngineError, LocalEngine
from hil.log.truth import truth_path
from tests.campaign.test_campaign import write_campaign
from tests.session.helpers import assert_same_channels

distributed = pytest.importorskip("distributed")
psutil = pytest.importorskip("psutil")

HIL = [sys.executable, "-m", "hil"]
LocalRun = tuple[Path, Path, dict[str, CellResult]]


def exact(metrics: dict[str, float]) -> dict[str, float]:
    """The control metrics a seed reproduces exactly (the loop latency is the host's own)."""
    return {k: v for k, v in metrics.items() if k != "latency_p99_us"}


def log_of(out: Path, cell: CellResult) -> Path:
    assert cell.log is not None
    return out / cell.log


@pytest.fixture(scope="module")
def cluster() -> Iterator[distributed.LocalCluster]:
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as c:
        yield c


@pytest.fixture(scope="module")
def local_run(tmp_path_factory: pytest.TempPathFactory) -> LocalRun:
    """The small lag campaign (2 seeds, 2 s) on the local engine: the reference every dask run is held to."""
    tmp = tmp_path_factory.mktemp("local")
    path = write_campaign(tmp)
    run = hil.run_campaign(path, out=tmp / "out", jobs=2, write_report=False)
    assert run.result.complete and all(c.status == "completed" for c in run.result.cells)
    return path, run.out_dir, {c.cell_id: c for c in run.result.cells}


def assert_same_cells(out: Path, cells: list[CellResult], local_out: Path, local: dict[str, CellResult]) -> None:
    assert cells and {c.cell_id for c in cells} <= set(local)
    for cell in cells:
        ref = local[cell.cell_id]
        assert cell.status == "completed", cell.message
        assert exact(cell.metrics) == exact(ref.metrics) and cell.metrics.keys() == ref.metrics.keys()
        # the first-order 150 Hz low-pass at 1 kHz lags (1 - a)/a = 0.64 samples at low frequency
        assert 0.55 < cell.metrics["lag_lpf_cycles"] < 0.75
        # where the local engine puts them: the log under cells/ID, beside the same files
        assert Path(cell.log or "").parent == Path("cells") / cell.cell_id
        here, there = out / "cells" / cell.cell_id, local_out / "cells" / cell.cell_id
        for cell_dir, run in ((here, cell), (there, ref)):  # the log, the sim clock's truth file, the cell's files
            log = log_of(cell_dir.parents[1], run)
            assert sorted(p.name for p in cell_dir.iterdir()) == sorted(
                [log.name, truth_path(log).name, "result.json", "session.yaml", "stderr.txt"])
        assert CellResult.model_validate_json((here / "result.json").read_text()) == cell
        session = yaml.safe_load((here / "session.yaml").read_text())
        assert session["logging"]["dir"] == str(here)  # this machine's path: the file re-runs by hand here
        assert assert_same_channels(log_of(out, cell), log_of(local_out, ref), 2000) > 1900


@pytest.mark.slow
def test_the_dask_engine_on_its_own_local_cluster_gives_the_local_engines_cells(local_run: LocalRun,
                                                                                 tmp_path: Path) -> None:
    path, local_out, local = local_run
    seen: list[str] = []
    run = hil.run_campaign(path, out=tmp_path / "out", jobs=2, engine="dask", write_report=False,
                           on_cell=lambda c: seen.append(c.cell_id))
    assert run.result.complete and run.result.jobs == 2 and sorted(seen) == sorted(local)
    assert sorted(c.cell_id for c in run.result.cells) == sorted(local)
    assert_same_cells(run.out_dir, run.result.cells, local_out, local)
    assert load_results(run.out_dir) == run.result  # campaign.json as the local engine writes it


def test_resume_with_the_dask_engine_runs_only_the_missing_cell(cluster: distributed.LocalCluster,
                                                                 local_run: LocalRun, tmp_path: Path) -> None:
    path, local_out, local = local_run
    out = tmp_path / "out"
    shutil.copytree(local_out, out)  # a campaign the local engine ran, one cell of it lost
    first, other = sorted(local)
    (out / "cells" / first / "result.json").unlink()
    kept = {p.name: p.stat().st_mtime_ns for p in (out / "cells" / other).iterdir()}
    seen: list[str] = []
    run = hil.run_campaign(path, out=out, resume=True, engine="dask", scheduler=cluster.scheduler_address,
                           write_report=False, on_cell=lambda c: seen.append(c.cell_id))
    assert run.result.complete and sorted(seen) == sorted(local)
    assert {p.name: p.stat().st_mtime_ns for p in (out / "cells" / other).iterdir()} == kept  # not run again
    assert next(c for c in run.result.cells if c.cell_id == other) == local[other]
    assert_same_cells(out, [c for c in run.result.cells if c.cell_id == first], local_out, local)
    with pytest.raises(hil.ConfigError, match="resume=True"):
        hil.run_campaign(path, out=out, engine="dask", scheduler=cluster.scheduler_address)


def kill_a_worker_in_a_cell(address: str, killed: list[int], stop: threading.Event) -> None:
    """Wait until a worker runs a cell's session (its process, `hil run` or a warm worker, has a log writer), then
    SIGKILL that worker and everything it started."""
    with distributed.Client(address, set_as_default=False) as client:
        deadline = time.monotonic() + 120.0
        while not stop.is_set() and time.monotonic() < deadline:
            for pid in client.run(os.getpid).values():
                with contextlib.suppress(psutil.Error):
                    worker = psutil.Process(pid)
                    cells = worker.children(recursive=True)
                    if any("hil.log.writer" in " ".join(p.cmdline()) for p in cells):
                        worker.kill()
                        for cell in cells:
                            with contextlib.suppress(psutil.Error):
                                cell.kill()
                        killed.append(pid)
                        return
            time.sleep(0.05)


def test_a_cell_whose_worker_dies_runs_again_and_the_campaign_loses_nothing(
        cluster: distributed.LocalCluster, local_run: LocalRun, tmp_path: Path) -> None:
    path, local_out, local = local_run
    shared = tmp_path / "shared"
    shared.mkdir()
    killed: list[int] = []
    stop = threading.Event()
    killer = threading.Thread(target=kill_a_worker_in_a_cell, args=(cluster.scheduler_address, killed, stop),
                              daemon=True)
    killer.start()
    try:
        run = hil.run_campaign(path, out=tmp_path / "out", engine="dask", scheduler=cluster.scheduler_address,
                               shared_dir=shared, write_report=False)
    finally:
        stop.set()
        killer.join(30)
    assert len(killed) == 1  # a worker died with a cell half run
    assert run.result.complete and run.result.passed
    assert sorted(c.cell_id for c in run.result.cells) == sorted(local)
    assert_same_cells(run.out_dir, run.result.cells, local_out, local)
    assert list(shared.iterdir()) == []  # every attempt's files moved or removed, the killed one's too


@pytest.mark.parametrize("engine", ["local", "dask"])
def test_engines_map_lazily_in_completion_order_and_turn_failures_into_results(
        engine: str, cluster: distributed.LocalCluster) -> None:
    asked: list[int] = []

    def items() -> Iterator[int]:  # as an ask-and-tell optimiser feeds an engine: one item at a time
        for i in (4, 0, 2, 1):
            asked.append(i)
            yield i

    divide = functools.partial(operator.truediv, 12)
    runner = LocalEngine(2) if engine == "local" else DaskEngine(cluster.scheduler_address, workers=2, retries=1)
    with runner:
        assert runner.slots == 2
        out, asked_when_yielded = {}, []
        for item, result in runner.map_cells(divide, items(), in_flight=1,
                                             on_error=lambda item, exc: type(exc).__name__):
            out[item] = result
            asked_when_yielded.append(len(asked))
        assert asked_when_yielded == [2, 3, 4, 4]  # one item running, the next asked before a result is handed on
        assert out == {4: 3.0, 0: "ZeroDivisionError", 2: 6.0, 1: 12.0}
        with pytest.raises(ZeroDivisionError):
            dict(runner.map_cells(divide, [1, 0]))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_bad_engine_options_are_one_line_errors_before_anything_is_written(tmp_path: Path) -> None:
    path = write_campaign(tmp_path)
    out = tmp_path / "out"
    port = free_port()
    cases = [
        ({"engine": "dask", "scheduler": "localhost:8786"}, r"^scheduler='localhost:8786': not a scheduler add"),
        ({"engine": "dask", "scheduler": f"tcp://127.0.0.1:{port}"}, rf"^scheduler='tcp://127.0.0.1:{port}': cannot"),
        ({"engine": "dask", "shared_dir": path}, r"^shared_dir='.*': not a directory"),
        ({"engine": "dask", "workers": 0}, r"^workers=0: need at least 1"),
        ({"scheduler": "tcp://lab:8786"}, r"^scheduler='tcp://lab:8786': only with engine='dask'"),
        ({"engine": "dask", "hardware": True}, r"^engine='dask': hardware=True"),
        ({"engine": "slurm"}, r"^engine='slurm': not local or dask"),
    ]
    for options, message in cases:
        with pytest.raises(hil.ConfigError, match=message):
            hil.run_campaign(path, out=out, **options)  # type: ignore[arg-type]
        assert not out.exists()
    proc = subprocess.run([*HIL, "campaign", str(path), "--out", str(out), "--engine", "dask", "--scheduler",
                           f"tcp://127.0.0.1:{port}"], capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and f"--scheduler tcp://127.0.0.1:{port}" in proc.stderr
    assert not out.exists()


def test_a_worker_that_fails_the_shared_dir_check_is_logged_and_left_out(cluster: distributed.LocalCluster,
                                                                        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                        caplog: pytest.LogCaptureFixture) -> None:
    """The shared directory is checked on every worker when the engine opens. A worker that goes away during the
    check (its answer an exception) is logged and left out, and the engine opens; a worker that answers that it
    cannot write there is a one-line error naming it."""
    answers: dict[str, object] = {}
    monkeypatch.setattr(distributed.Client, "run", lambda self, fn, *args, **kw: dict(answers))
    answers.update({"tcp://10.0.0.1:1": None, "tcp://10.0.0.2:2": OSError("comm closed")})
    with caplog.at_level("WARNING", logger="hil.campaign"), DaskEngine(cluster.scheduler_address,
                                                                       shared_dir=tmp_path) as engine:
        assert engine.client is not None
    assert any("tcp://10.0.0.2:2" in r.getMessage() and "comm closed" in r.getMessage() for r in caplog.records)
    answers["tcp://10.0.0.3:3"] = "not writable here"
    with pytest.raises(EngineError, match=r"^shared_dir='.*': not writable here \(worker tcp://10.0.0.3:3\)"):
        DaskEngine(cluster.scheduler_address, shared_dir=tmp_path).open()
