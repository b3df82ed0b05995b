"""A session with ``capture_dir``: the capture holds what the log says was exchanged, frame for frame, on the event
loop's links (lockstep) and on the loop thread's (realtime); the sim clock, which has no bytes, refuses it."""

from __future__ import annotations

import asyncio
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from hil.capture import CaptureDecode, CaptureReader, decode_capture
from hil.config import PortConfig
from hil.log import read_log
from hil.protocol import CATALOGUE, Ack, DriveCmd, GyroSample
from hil.session import Session
from hil.sim import SimLab, run_sim_session, sim_ports
from tests.capture.conftest import CapturedRun
from tests.session.helpers import session_config


def exchanged(run: CapturedRun) -> tuple[CaptureDecode, list]:
    result = CaptureDecode(CaptureReader(run.capture))
    return result, list(decode_capture(run.capture, result=result))


def check_against_log(run: CapturedRun) -> dict[str, np.ndarray]:
    """The checks both clocks pass; returns the log's loop group."""
    result, frames = exchanged(run)
    assert result.reader.end == "complete"
    assert run.session.capture is not None and run.session.capture.closed
    assert run.session.capture.stats.records == result.reader.records and run.session.capture.stats.dropped == 0
    loop = read_log(run.log).groups["loop"]
    samples = [f for f in frames if type(f.frame.message) is GyroSample]
    drives = [f for f in frames if type(f.frame.message) is DriveCmd]
    assert {f.link for f in samples} == {"servo"} and {f.direction for f in samples} == {"rx"}
    assert {f.link for f in drives} == {"driver"} and {f.direction for f in drives} == {"tx"}
    # every sample the loop logged is one the capture holds, with the same values
    assert len(samples) == len(loop["tick"])
    ticks = np.array([f.frame.message.tick for f in samples])
    np.testing.assert_array_equal(ticks, loop["tick"])
    for axis in "xyz":
        got = np.array([getattr(f.frame.message, f"rate_{axis}_dps") for f in samples], dtype=np.float32)
        np.testing.assert_array_equal(got, loop[f"gyro_{axis}_dps"])
    # one DRIVE_CMD per cycle the loop drove, carrying the logged drive of its tick
    drive_ticks = np.array([f.frame.message.tick for f in drives])
    last = int(np.flatnonzero(np.isin(loop["tick"], drive_ticks))[-1])
    np.testing.assert_array_equal(drive_ticks, loop["tick"][: last + 1])
    np.testing.assert_array_equal([f.frame.message.az_counts for f in drives], loop["drive_az_counts"][: last + 1])
    np.testing.assert_array_equal([f.frame.message.el_counts for f in drives], loop["drive_el_counts"][: last + 1])
    # each answered in time: sent after its sample arrived
    rx_at = {f.frame.message.tick: f.t_ns for f in samples}
    assert all(f.t_ns > rx_at[f.frame.message.tick] for f in drives)
    # every command the bench sent got its ACK, on its own link
    acks = {(f.link, f.frame.message.msg_id, f.frame.message.seq) for f in frames if type(f.frame.message) is Ack}
    commands = [(f.link, CATALOGUE.spec(f.frame.message).msg_id, f.frame.seq) for f in frames
                if f.direction == "tx" and CATALOGUE.spec(f.frame.message).reply in ("ACK", "ACK/NACK")]
    assert commands and set(commands) <= acks
    # the links were clean both ways, and the capture's rx decoders agree with the bench's own last count
    assert all(c.errors() == 0 for c in result.counters().values())
    links = read_log(run.log).groups["links"]
    assert result.counters()[("servo", "rx")].frames_ok >= int(links["servo_frames_ok"][-1]) > 0
    notes = Counter((r.link, r.note().get("event")) for r in result.notes)
    assert notes == Counter({(name, event): 1 for name in ("servo", "driver", "image", "hexapod")
                             for event in ("open", "close")})
    return loop


def test_a_lockstep_capture_holds_the_frames_the_log_says_were_exchanged(lockstep_run: CapturedRun) -> None:
    loop = check_against_log(lockstep_run)
    _, frames = exchanged(lockstep_run)
    kinds = Counter((f.link, f.direction, CATALOGUE.spec(f.frame.message).name) for f in frames)
    assert kinds[("servo", "rx", "GYRO_SAMPLE")] == len(loop["tick"]) > 1500
    assert kinds[("driver", "tx", "DRIVE_CMD")] == len(loop["tick"]) - 1  # the last sample came once disarmed
    assert kinds[("driver", "tx", "HOST_ALIVE")] == 0  # lockstep sends none
    assert kinds[("servo", "tx", "SERVO_MODE")] == 2 and kinds[("driver", "tx", "DRIVE_ENABLE")] == 1
    # on the event loop the read is stamped before the loop stamps the sample it holds
    samples = [f for f in frames if type(f.frame.message) is GyroSample]
    lead = loop["t_host_ns"] - np.array([f.t_ns for f in samples])
    assert lead.min() >= 0 and np.median(lead) < 2_000_000


def test_the_loop_threads_reads_and_writes_are_captured_with_its_own_times(realtime_run: CapturedRun) -> None:
    loop = check_against_log(realtime_run)
    _, frames = exchanged(realtime_run)
    samples = [f for f in frames if type(f.frame.message) is GyroSample]
    drives = {f.frame.message.tick: f.t_ns for f in frames if type(f.frame.message) is DriveCmd}
    # the loop thread stamps a read once: while it ran (every cycle that drove), the capture's time of a sample's
    # read is the log's t_host_ns; the event loop reads the last samples, after the thread stopped at the disarm
    t_rx = np.array([f.t_ns for f in samples])
    n = len(drives)
    np.testing.assert_array_equal(t_rx[:n], loop["t_host_ns"][:n])
    assert (t_rx[n:] <= loop["t_host_ns"][n:]).all()
    # and DRIVE_CMD k went out within the latency the loop logged for cycle k
    ticks = loop["tick"][: len(drives)]
    sent = np.array([drives[int(k)] for k in ticks]) - loop["t_host_ns"][: len(drives)]
    assert (sent > 0).all() and (sent <= loop["latency_us"][: len(drives)] * 1000 + 1000).all()
    kinds = Counter((f.link, f.direction, CATALOGUE.spec(f.frame.message).name) for f in frames)
    assert kinds[("servo", "tx", "HOST_ALIVE")] >= 10  # the event loop's frames on the same links


def test_the_sim_clock_refuses_a_capture_before_anything_starts(tmp_path: Path) -> None:
    config = session_config(duration_s=0.2)
    with pytest.raises(ValueError, match=r"sim clock's links pass messages, not bytes.*--clock lockstep"):
        asyncio.run(run_sim_session(config, tmp_path / "logs", capture_dir=tmp_path / "capture"))

    async def direct() -> None:
        lab = SimLab(config.emulator.config, seed=0)
        Session(config, sim_ports(), tmp_path / "logs", lockstep=True, open_link=lab.open_link,
                capture_dir=tmp_path / "capture")

    with pytest.raises(ValueError, match="nothing to capture"):
        asyncio.run(direct())
    assert not (tmp_path / "capture").exists() and not (tmp_path / "logs").exists()


def test_a_session_that_never_connects_leaves_a_readable_capture(tmp_path: Path) -> None:
    config = session_config(duration_s=0.2)
    ports = {name: PortConfig(port=str(tmp_path / f"no-{name}")) for name in ("servo", "driver", "image", "hexapod")}
    result = asyncio.run(Session(config, ports, tmp_path / "logs", capture_dir=tmp_path / "capture").run())
    assert result.status == "fault" and "cannot open" in result.message
    reader = CaptureReader(next((tmp_path / "capture").glob("*.hilcap")))
    assert list(reader) == [] and reader.end == "complete" and reader.meta["session"] == config.name
