"""Bench sessions end to end over real ptys against the emulator: the log channel by channel, safety, faults."""

from __future__ import annotations

import asyncio
import math
import os
import signal
import subprocess

import h5py
import numpy as np
import pytest

from firmware_stub.control import ControlClient
from hil.analysis import summarize_log
from hil.log import read_log
from hil.session import EmulatorProcess, Session
from tests.factories import Run, run_session, session_config
from tests.session.helpers import logged_events, wait_cycles


@pytest.fixture(scope="module")
def lockstep_session(tmp_path_factory: pytest.TempPathFactory) -> Run:
    out = tmp_path_factory.mktemp("lockstep")
    return run_session(session_config(duration_s=3.0, seed=4), out)


def test_lockstep_session_completes_and_logs_every_channel(lockstep_session) -> None:  # type: ignore[no-untyped-def]
    res = lockstep_session.result
    assert res.status == "completed" and res.exit_code == 0, res.message
    with h5py.File(res.log_path, "r") as f:  # closed cleanly: opens without SWMR
        assert f["loop/gyro_y_dps"].attrs["unit"] == "deg/s"
    log = read_log(res.log_path)
    loop = log.groups["loop"]
    n = loop["tick"].size
    assert n >= 3000  # the run, then the swing's wind-down
    assert np.all(np.diff(loop["tick"].astype(np.int64)) == 1) and loop["tick"][0] == 0
    np.testing.assert_allclose(np.diff(loop["t_s"]), 1e-3, atol=1e-9)
    assert not loop["tick_gap"].any()
    np.testing.assert_allclose(loop["rate_err_el_dps"], loop["rate_cmd_el_dps"] - loop["gyro_y_dps"], atol=1e-5)
    np.testing.assert_allclose(loop["rate_err_az_dps"], loop["rate_cmd_az_dps"] - loop["gyro_z_dps"], atol=1e-5)
    assert np.all(np.abs(loop["drive_el_counts"]) <= 30000) and np.std(loop["drive_el_counts"]) > 100
    assert np.all(loop["latency_us"] > 0) and np.median(loop["latency_us"]) < 1000
    assert np.all(np.abs(loop["gyro_y_dps"]) < 10) and np.std(loop["gyro_y_dps"][1000:3000]) > 0.03
    assert np.std(loop["dist_el_counts"][1000:3000]) > 100  # the ESO sees the swing's disturbance
    # camera: 100 Hz, consecutive frames, tracking kept the target in view
    image = log.groups["image"]
    assert abs(image["frame"].size - n / 10) <= 5
    assert np.all(np.diff(image["frame"].astype(np.int64)) == 1)
    assert image["track_valid"][20:].all() and np.all(np.abs(image["miss_y_px"]) < 512)
    # hexapod: the 1 deg / 1 Hz pitch, after its 1 s ramp
    hexa = log.groups["hexapod"]
    t, pitch = hexa["t_profile_s"], hexa["pitch_deg"]
    steady = (t > 1.2) & (t < 2.9)
    np.testing.assert_allclose(pitch[steady], np.sin(2 * math.pi * t[steady]), atol=0.02)
    # board timing (lockstep: the modelled wire and host delay, 134 us at the default 6 000 000 baud: 65 + 37 + 32;
    # nothing missing while running) and link counters
    timing = log.groups["timing"]
    latency = timing["board_latency_us"]
    assert timing["tick"].size >= n - 30 and set(np.unique(latency[~np.isnan(latency)])) == {134}
    links = log.groups["links"]
    assert abs(links["t_host_ns"].size - n / 100) <= 2
    assert links["servo_frames_ok"][-1] > n and links["servo_crc_errors"][-1] == 0
    kinds = [str(k) for k in log.groups["events"]["kind"]]
    assert kinds.count("fault") == 0 and "summary" in kinds and kinds.count("state") >= 4
    report = summarize_log(res.log_path)
    assert report["complete"] is True and "incomplete" not in report
    # the file says what ran: config, every board's IDENT, seed, version
    assert log.attrs["config"]["name"] == "swing-1deg-1hz-eso" and log.attrs["seed"] == 4
    assert set(log.attrs["ident"]) == {"servo", "driver", "image", "hexapod"}
    assert log.attrs["ident"]["servo"]["firmware_version"] == "emu-1.0.0"


def test_lockstep_sessions_are_reproducible(lockstep_session, tmp_path) -> None:  # type: ignore[no-untyped-def]
    again = run_session(session_config(duration_s=3.0, seed=4), tmp_path)
    a, b = read_log(lockstep_session.result.log_path).groups["loop"], read_log(again.result.log_path).groups["loop"]
    n = min(a["tick"].size, b["tick"].size, 3000)
    for channel in ("gyro_y_dps", "gyro_z_dps", "drive_el_counts", "drive_az_counts", "el_deg", "rate_cmd_el_dps"):
        np.testing.assert_array_equal(a[channel][:n], b[channel][:n], err_msg=channel)


@pytest.mark.slow
@pytest.mark.realtime
def test_watchdog_zeroes_the_drive_within_5_ms_of_a_stall(tmp_path) -> None:
    async def stall(emu: EmulatorProcess, session: Session) -> None:
        await wait_cycles(session, 500)
        while not (session.loop_ and session.loop_.armed):  # not inside a recovery from a spurious trip
            await asyncio.sleep(0.001)
        with ControlClient(emu.ports["control"]) as ctl:
            ctl.call("inject", link="servo", kind="stall", duration_ms=50)

    # the watchdog trips watchdog_ms after the last sample, then trip -> DISABLE -> driver takes ~0.5 ms.
    # 3 ms leaves room within the 5 ms the bench promises, and for the one more watchdog_ms it allows when
    # the host delayed the watchdog's own look by more than 1 ms (Watchdog); 'recover' keeps the run alive
    # if a loaded CI machine delays a sample by more than that before the stall we inject
    safety = {"watchdog_ms": 3, "on_fault": "recover", "max_recoveries": 20, "recover_after_ms": 100}
    run = run_session(session_config(duration_s=3.0, safety=safety), tmp_path, clock="realtime", during=stall)
    assert any("watchdog" in f for f in run.result.stats.faults)
    stall = next(r for r in run.records if r["kind"] == "stall")
    disable = next(r for r in run.records if r["kind"] == "drive_disable" and r["tick"] >= stall["tick"])
    # by the emulator's own record (its tick count and wall clock). On an idle machine this is 4.3-4.8 ms;
    # CI machines stall processes for milliseconds (docs/performance.md), so the bound asserted here is
    # 10 ms, and the 5 ms figure is tracked in issue 5's benchmark rather than asserted
    assert disable["tick"] - stall["tick"] <= 10 and disable["wall_s"] - stall["wall_s"] <= 0.010, (stall, disable)
    assert disable["detail"]["cause"] == "host"
    kinds = [str(k) for k in read_log(run.result.log_path).groups["events"]["kind"]]
    assert "fault" in kinds and "recovered" in kinds
    reasons = summarize_log(run.result.log_path)["fault_reasons"]  # what `hil run` prints under its table
    assert reasons == run.result.stats.faults and any(r.startswith("watchdog: no GYRO_SAMPLE for") for r in reasons)


@pytest.mark.slow
@pytest.mark.realtime
def test_a_bench_the_host_stopped_while_the_board_was_stopped_too_does_not_trip(tmp_path) -> None:
    """A VM's vCPU taken away from the bench and an emulator that share it: both freeze; the bench comes
    back first, its watchdog finds 60 ms of silence on a late look and gives the board one watchdog_ms.

    The board is released 5 ms after the bench is back, when the watchdog (whose wait ran out during the stop)
    has looked. A sample the board wrote just before the stop and the bench had not read yet reaches the
    bench when it resumes and feeds the watchdog first; that stop is then no stall at all, which is also
    right, so the test asks for at least one stall of the three and no trip. A loaded host may stall the bench
    on its own as well, even as long as a stop: those are counted too and never tripped on."""
    stops = 3

    async def freeze(emu: EmulatorProcess, session: Session) -> None:
        assert emu.proc is not None
        await wait_cycles(session, 500)
        me, board = os.getpid(), emu.proc.pid
        for _ in range(stops):
            freezer = subprocess.Popen(["sh", "-c", f"kill -STOP {board} {me}; sleep 0.06; kill -CONT {me}"])
            while freezer.poll() is None:  # this coroutine runs again: the bench is back
                await asyncio.sleep(0.001)
            await asyncio.sleep(0.005)  # the watchdog's late look
            os.kill(board, signal.SIGCONT)
            assert freezer.wait(timeout=5) == 0
            await asyncio.sleep(0.3)

    # 20 ms: the watchdog's look again gives the board 20 ms to show its first catch-up sample
    run = run_session(session_config(duration_s=2.5), tmp_path, clock="realtime", during=freeze, watchdog_ms=20)
    assert run.result.status == "completed", run.result.message
    summary = summarize_log(run.result.log_path)
    assert summary["faults"] == 0 and run.result.stats.faults == []
    assert summary["host_stalls"] == run.result.stats.host_stalls
    stalls_ms = [d["silent_ms"] for k, d in logged_events(run.result.log_path) if k == "host_stall"]
    # seen as stalls, none a trip (a loaded host may add stalls of its own as long as the stops: not bounded here)
    assert len([ms for ms in stalls_ms if ms >= 60.0]) >= 1, stalls_ms
    assert 60.0 <= summary["host_stall_max_ms"] < 1000.0


@pytest.mark.slow
@pytest.mark.realtime
def test_disconnect_mid_session_is_recovered(tmp_path) -> None:
    async def unplug(emu: EmulatorProcess, session: Session) -> None:
        await wait_cycles(session, 800)
        with ControlClient(emu.ports["control"]) as ctl:
            ctl.call("inject", link="servo", kind="disconnect", duration_ms=300)

    # a 50 ms watchdog: this test is about the unplugged link, not about a loaded machine's scheduling
    config = session_config(duration_s=3.0, safety={"on_fault": "recover", "recover_after_ms": 100,
                                                    "watchdog_ms": 50, "max_recoveries": 20})
    run = run_session(config, tmp_path, clock="realtime", during=unplug)
    # recovered to the end; with the loop disarmed for the recovery on a swinging table the line of sight may leave
    # the camera's view for good, and the tracking verdict then says so (lost_target, exit 4) instead of completed
    assert run.result.status in ("completed", "lost_target"), run.result.message
    if run.result.status == "lost_target":
        assert run.result.exit_code == 4 and run.result.message.startswith("tracking: the target was lost for ")
    faults = run.result.stats.faults
    # the disconnect is one fault; a loaded machine may add watchdog trips, each recovered too
    assert sum("servo link lost" in f for f in faults) == 1, faults
    assert all("servo link lost" in f or "watchdog" in f for f in faults), faults
    assert run.result.stats.recoveries == len(faults)
    # the stream's on/off records aside, and a host timeout of the board's own: on a loaded machine the bench may
    # fall silent for its host timeout, the board then protects itself and the watchdog trips (recovered too)
    servo = [k for k in run.kinds("servo") if k not in ("servo_stream", "host_timeout")]
    assert servo[:2] == ["disconnect", "reconnect"], servo
    events = read_log(run.result.log_path).groups["events"]
    kinds = [str(k) for k in events["kind"]]
    assert kinds.index("fault") < kinds.index("recovered")
    assert run.result.stats.cycles >= 3000


def test_board_with_another_catalogue_is_refused(tmp_path) -> None:
    run = run_session(session_config(duration_s=1.0), tmp_path, emulator_args=["--fingerprint", "0x12345678"])
    assert run.result.status == "fault" and run.result.exit_code == 1
    msg = run.result.message
    assert "servo" in msg and "0x12345678" in msg and "emu-1.0.0" in msg and "catalogue" in msg
    assert run.result.stats.cycles == 0
    assert "drive_enable" not in run.kinds()  # nothing was armed


def test_garbage_on_every_link_is_counted_and_the_session_completes(tmp_path) -> None:
    emulator_config = tmp_path / "noisy.yaml"
    emulator_config.write_text(
        "plant: " + str(session_config().emulator.config.parent.parent / "plant" / "default.yaml") + "\n"
        "links:\n" + "".join(f"  {link}: {{garbage_rate: 0.05, bit_error_rate: 1.0e-5}}\n"
                             for link in ("servo", "driver", "image", "hexapod")))
    config = session_config(duration_s=2.0, emulator={"config": str(emulator_config), "clock": "lockstep"})
    run = run_session(config, tmp_path)
    assert run.result.status == "completed", run.result.message
    links = read_log(run.result.log_path).groups["links"]
    for link in ("servo", "image", "hexapod"):
        assert links[f"{link}_bytes_discarded"][-1] > 0, link
    garbage = sum(r["detail"]["n_bytes"] for r in run.records if r["kind"] == "garbage" and r["link"] == "servo")
    assert links["servo_bytes_discarded"][-1] >= 0.5 * garbage
    assert run.result.stats.cycles >= 2000
