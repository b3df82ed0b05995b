"""A session with ``capture_dir``: the capture holds what the log says was exchanged, frame for frame, on the event
loop's links (lockstep) and on the loop thread's (realtime); the sim clock, which has no bytes, refuses it."""

from __future__ import annotations

import asyncio
import os
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from hil.config import PortConfig
from hil.link import CaptureDecode, CaptureReader, PortUnavailable, decode_capture
from hil.log import read_log
from hil.protocol import CATALOGUE, Ack, DriveCmd, GyroSample, LinkCounters
from hil.session import Session, SimLab, run_sim_session, sim_ports
from tests.factories import session_config
from tests.replay.conftest import CapturedRun


def exchanged(run: CapturedRun) -> tuple[CaptureDecode, list]:
    result = CaptureDecode(CaptureReader(run.capture))
    return result, list(decode_capture(run.capture, result=result))


def error_counts(c: LinkCounters) -> dict[str, int]:
    """A decoder's counts of frames out of the ordinary (per-source counts summed)."""
    totals = c.totals()
    return {k: totals[k] for k in ("crc_errors", "bad_frames", "frames_lost", "duplicates", "reordered", "restarts")}


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
    # what the bench received decodes as the bench decoded it, counter for counter; what it sent, as the board did.
    # A loaded machine shows in both: a command answered late is resent (the board counts a repeat or a step back)
    # and a link read late loses what the board's full pty could not take (the emulator counts those bytes). Every
    # such count must be the one the bench or the board reports, and a received one needs bytes the board lost
    counters = result.counters()
    for name, link in run.session.links.items():
        board = run.emulator["links"][name]
        assert counters[(name, "rx")].totals() == link.decoder.counters.totals(), name
        assert counters[(name, "rx")].errors() == 0 or board["tx_overflow_bytes"] > 0, name
        sent, got = error_counts(counters[(name, "tx")]), error_counts(LinkCounters(**board["rx"]))
        if name == "driver" and run.session.use_thread:
            # two threads write it, and one preempted between its stamp and its write puts its frame on the wire
            # after frames stamped later: how the two interleave (gaps, steps back) may differ from the board's view
            for key in ("frames_lost", "reordered"):
                del sent[key], got[key]
        assert sent == got, name
        short_writes = run.result.stats.drive_short_writes if name == "driver" else 0
        assert counters[(name, "tx")].crc_errors == short_writes and counters[(name, "tx")].bad_frames() == 0, name
    links = read_log(run.log).groups["links"]
    assert counters[("servo", "rx")].frames_ok >= int(links["servo_frames_ok"][-1]) > 0
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
    # on the event loop the read is stamped before the loop stamps the sample it holds, and after the DRIVE_CMD that
    # let the world step to it
    t_rx = np.array([f.t_ns for f in frames if type(f.frame.message) is GyroSample])
    t_drive = np.array([f.t_ns for f in frames if type(f.frame.message) is DriveCmd])
    assert (t_rx <= loop["t_host_ns"]).all() and (t_drive < t_rx[1 : len(t_drive) + 1]).all()


@pytest.mark.realtime
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
    # the event loop's frames on the same links: HOST_ALIVE, on every link at each round, however many rounds
    kinds = Counter((f.link, f.direction, CATALOGUE.spec(f.frame.message).name) for f in frames)
    alive = {name: kinds[(name, "tx", "HOST_ALIVE")] for name in ("servo", "driver", "image", "hexapod")}
    assert alive["servo"] > 0 and set(alive.values()) == {alive["servo"]}, alive


def test_the_sim_clock_refuses_a_capture_before_anything_starts(tmp_path: Path) -> None:
    config = session_config(duration_s=0.2)
    with pytest.raises(ValueError, match=r"sim clock's links pass messages, not bytes.*clock='lockstep'"):
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
    ptys = [os.openpty() for _ in range(4)]  # serial ports with no board behind them: nothing answers IDENT_REQ
    try:
        ports = {name: PortConfig(port=os.ttyname(sub))
                 for name, (_, sub) in zip(("servo", "driver", "image", "hexapod"), ptys, strict=True)}
        result = asyncio.run(Session(config, ports, tmp_path / "logs", capture_dir=tmp_path / "capture").run())
    finally:
        for fds in ptys:
            for fd in fds:
                os.close(fd)
    assert result.status == "fault" and "no answer" in result.message
    reader = CaptureReader(next((tmp_path / "capture").glob("*.hilcap")))
    sent = [r for r in reader if r.direction == "tx"]
    assert sent and reader.end == "complete" and reader.meta["session"] == config.name  # the IDENT_REQs it sent


def test_a_session_on_ports_that_do_not_exist_is_refused_before_it_captures_anything(tmp_path: Path) -> None:
    config = session_config(duration_s=0.2)
    ports = {name: PortConfig(port=str(tmp_path / f"no-{name}")) for name in ("servo", "driver", "image", "hexapod")}
    with pytest.raises(PortUnavailable, match=r"servo: .*no-servo: no such port"):
        asyncio.run(Session(config, ports, tmp_path / "logs", capture_dir=tmp_path / "capture").run())
    assert not (tmp_path / "capture").exists() and not (tmp_path / "logs").exists()
