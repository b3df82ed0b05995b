"""The documented Python API (docs/api.md), used as a notebook would: from inside a running event loop."""

from __future__ import annotations

import asyncio
import importlib
import pkgutil
import threading
import types
from pathlib import Path

import pytest
import yaml

import hil
from hil.config import PROFILES
from tests.factories import session_config
from tests.session.helpers import assert_same_channels

CAMPAIGNS = PROFILES / "campaigns"


def test_run_async_inside_a_running_loop_returns_a_log_read_as_dataframes(tmp_path: Path) -> None:
    config = session_config(duration_s=2.0)
    progress: list[int] = []

    async def notebook_cell() -> hil.RunResult:
        return await hil.run_async(config, clock="sim", out=tmp_path, progress=lambda n, _t: progress.append(n))

    result = asyncio.run(notebook_cell())
    assert result.status == "completed" and result.exit_code == 0 and result.clock == "sim"
    assert result.log_path is not None and result.log_path.parent == tmp_path
    summary = result.summary()
    # reported about ten times a second while it runs (the sim clock may finish between two reports)
    assert progress and progress == sorted(progress) and progress[-1] <= summary["cycles"]
    log = result.log
    assert len(log.loop) == summary["cycles"] >= 1990  # 2 s at 1 kHz, less the stream's start
    units = log.loop.attrs["units"]
    assert set(units) == set(log.loop.columns)
    assert "deg/s" in units.values()
    assert log.config["name"] == config.name and log.config["duration_s"] == 2.0
    assert log.provenance["controller"]["name"] == "eso"
    assert len(log.image) > 0  # tracking on: miss distance at camera rate


def test_run_blocks_inside_a_running_loop_without_reentering_it_and_lockstep_equals_sim(tmp_path: Path) -> None:
    config = session_config(duration_s=2.0)
    threads: list[str] = []

    async def notebook_cell() -> tuple[hil.RunResult, hil.RunResult]:
        ticking = asyncio.get_running_loop()
        threads.append(threading.current_thread().name)
        lockstep = hil.run(config, clock="lockstep", out=tmp_path / "lockstep")  # blocks this cell, as in Jupyter
        sim = hil.run(config, clock="sim", out=tmp_path / "sim")
        assert asyncio.get_running_loop() is ticking
        return lockstep, sim

    lockstep, sim = asyncio.run(notebook_cell())
    assert (lockstep.status, sim.status) == ("completed", "completed")
    assert lockstep.clock == "lockstep" and lockstep.emulator  # the emulator process's own summary
    assert lockstep.log_path and sim.log_path
    assert assert_same_channels(lockstep.log_path, sim.log_path, 2000) > 1900


def test_bad_input_is_a_config_error_naming_the_field(tmp_path: Path) -> None:
    config = session_config(duration_s=2.0)
    with pytest.raises(hil.ConfigError, match=r"^clock: 'warp'"):
        hil.run(config, clock="warp", out=tmp_path)  # type: ignore[arg-type]
    with pytest.raises(hil.ConfigError, match=r"^ports: not set"):
        hil.run(config, loopback=False, out=tmp_path)
    with pytest.raises(hil.ConfigError, match="no such file"):
        hil.load_session(tmp_path / "missing.yaml")
    (tmp_path / "file").write_text("")
    with pytest.raises(hil.ConfigError, match=r"^out='.*': exists and is not a directory"):
        hil.run(config, clock="sim", out=tmp_path / "file")
    assert list(tmp_path.iterdir()) == [tmp_path / "file"]  # nothing was started or written


def small_campaign(tmp_path: Path) -> Path:
    data = yaml.safe_load((CAMPAIGNS / "filter-lag-15hz.yaml").read_text())
    data.update(session=str(CAMPAIGNS / data["session"]), duration_s=2.0, seeds=[1, 2])
    for p in data["profiles"]:
        p["path"] = str((CAMPAIGNS / p["path"]).resolve())
    path = tmp_path / "campaign.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.slow
def test_run_campaign_and_report_inside_a_running_loop(tmp_path: Path) -> None:
    path = small_campaign(tmp_path)
    seen: list[str] = []

    async def notebook_cell() -> hil.CampaignRun:
        return hil.run_campaign(path, out=tmp_path / "out", jobs=2, on_cell=lambda c: seen.append(c.cell_id))

    run = asyncio.run(notebook_cell())
    assert run.result.complete and len(seen) == 2
    table = run.table()
    assert list(table["seed"]) == sorted(table["seed"]) or set(table["seed"]) == {1, 2}
    assert len(table) == 2 and table["status"].eq("completed").all()
    # the first-order 150 Hz low-pass at 1 kHz lags (1 - a)/a = 0.64 samples at low frequency
    assert table["lag_lpf_cycles"].between(0.55, 0.75).all()
    assert run.report is not None and run.report.html.is_file() and run.report.markdown.is_file()
    again = hil.report(run.out_dir)  # the report written again, with the campaign's results
    assert again.report.html == run.report.html and again.table().equals(table)
    log = run.out_dir / run.result.cells[0].log
    summary = hil.report(log)
    assert summary["cycles"] >= 1990 and summary["controller"] == run.result.cells[0].controller_name
    with pytest.raises(hil.ConfigError, match="resume=True"):
        hil.run_campaign(path, out=tmp_path / "out")


@pytest.mark.parametrize("path", sorted(PROFILES.glob("*/*.yaml")), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_check_file_knows_every_shipped_config(path: Path) -> None:
    folders = {"sessions": "session", "campaigns": "campaign", "controllers": "controller", "swing": "swing",
               "hexapod": "hexapod", "emulator": "emulator", "plant": "plant", "targets": "targets"}
    checked = hil.check_file(path)
    assert checked["kind"] == folders[path.parent.name]
    assert checked["summary"]


def test_check_file_guesses_the_kind_from_the_keys_and_names_the_bad_field(tmp_path: Path) -> None:
    session = yaml.safe_load((PROFILES / "sessions" / "demo.yaml").read_text())
    session["controller"] = str(PROFILES / "controllers" / "eso.yaml")
    session["profile"] = str(PROFILES / "swing" / "swing-1deg-1hz.yaml")
    session["hexapod_limits"] = str(PROFILES / "hexapod" / "default.yaml")
    session["emulator"] = {"config": str(PROFILES / "emulator" / "default.yaml")}
    (tmp_path / "mine.yaml").write_text(yaml.safe_dump(session))
    assert hil.check_file(tmp_path / "mine.yaml")["kind"] == "session"
    (tmp_path / "ctl.yaml").write_text("name: eso\nparams: {omega_o_rad_s: -3}\n")
    with pytest.raises(hil.ConfigError, match="omega_o_rad_s"):
        hil.check_file(tmp_path / "ctl.yaml")
    (tmp_path / "odd.yaml").write_text("colour: blue\nsize: 3\n")
    with pytest.raises(hil.ConfigError, match="match no config kind"):
        hil.check_file(tmp_path / "odd.yaml")


def test_a_session_ends_early_through_interrupt_as_ctrl_c_would(tmp_path: Path) -> None:
    from tests.session.helpers import logged_events

    config = session_config(duration_s=30.0)
    interrupts: list[asyncio.Task[None]] = []

    async def notebook_cell() -> hil.RunResult:
        def on_session(session: object) -> None:
            async def once_swinging() -> None:  # by the session's own progress, not a wall-clock delay
                while getattr(session, "loop_", None) is None or session.loop_.stats.cycles < 500:  # type: ignore[attr-defined]
                    await asyncio.sleep(0.01)
                session.interrupt()  # type: ignore[attr-defined]

            interrupts.append(asyncio.get_running_loop().create_task(once_swinging()))

        return await hil.run_async(config, clock="sim", out=tmp_path, on_session=on_session)

    result = asyncio.run(notebook_cell())
    assert (result.status, result.exit_code) == ("interrupted", 130)
    events = logged_events(result.log_path)
    assert ("signal", {"signal": "SIGINT"}) in events
    safe = next(d for k, d in events if k == "state" and d["state"] == "safe")
    assert (safe["driver"], safe["hexapod"], safe["stream"]) == ("disabled", "stopped", "idle")
    assert result.summary()["cycles"] < 29000  # it did not run its 30 s


def test_a_keyboard_interrupt_in_a_notebook_cell_ends_the_session_safely(tmp_path: Path) -> None:
    import os
    import signal

    config = session_config(duration_s=600.0)  # the sim clock: long enough to interrupt

    async def notebook_cell() -> None:
        threading.Timer(1.5, os.kill, (os.getpid(), signal.SIGINT)).start()  # the kernel's interrupt button
        hil.run(config, clock="sim", out=tmp_path)

    loop = asyncio.new_event_loop()  # a kernel's loop: no asyncio.Runner SIGINT handler of its own
    try:
        with pytest.raises(KeyboardInterrupt):
            loop.run_until_complete(notebook_cell())
    finally:
        loop.close()
    (log_path,) = tmp_path.glob("*.h5")
    log = hil.read_log(log_path)
    kinds = list(log.events["kind"])
    assert "signal" in kinds
    details = [str(d) for d in log.events["detail"]]
    assert any('"safe"' in d and '"disabled"' in d for d in details)
    assert len(log.loop) < 590_000


def test_no_subpackage_shadows_a_public_name() -> None:
    # importing hil.X sets the attribute hil.X to the module: a package named like a public name would hide it
    for info in pkgutil.iter_modules(hil.__path__):
        if not info.name.startswith("_"):  # hil.__main__ would run the CLI
            importlib.import_module(f"hil.{info.name}")
    shadowed = [name for name in hil.__all__ if isinstance(getattr(hil, name), types.ModuleType)]
    assert shadowed == []
