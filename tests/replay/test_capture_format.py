"""The capture file: what goes in comes out with its time, link and direction; a file cut anywhere (a killed or
crashed writer) reads up to its last whole record; a damaged record stops the reading there, and says so."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hil.link import (
    MAGIC,
    RECORD_OVERHEAD,
    RX,
    Capture,
    CaptureDecode,
    CaptureError,
    CaptureReader,
    decode_capture,
    find_capture,
    is_capture,
)
from hil.protocol import Board, DriveCmd, DriveStatus, Encoder, GyroSample
from hil.session import capture_for_session
from tests.factories import session_config

ROOT = Path(__file__).resolve().parents[2]


def gyro_frames(n: int) -> list[bytes]:
    enc = Encoder(Board.SERVO)
    return [enc.encode(GyroSample(1000 * (i + 1), i, 0.001 * i, -0.002, 0.5, 10.0, -3.0), Board.HOST)
            for i in range(n)]


def drive_frames(n: int) -> list[bytes]:
    enc = Encoder(Board.HOST)
    return [enc.encode(DriveCmd(i, 10 * i, -i), Board.DRIVER) for i in range(n)]


def write_capture(path: Path, n: int) -> list[int]:
    """``n`` servo samples (rx) each answered by a DRIVE_CMD (tx); returns each record's offset in the file."""
    with Capture(path, meta={"session": "unit"}) as cap:
        servo, driver = cap.link("servo"), cap.link("driver")
        for i, (g, d) in enumerate(zip(gyro_frames(n), drive_frames(n), strict=True)):
            servo.rx(g, t_ns=1_000_000 * i)
            driver.tx(d, t_ns=1_000_000 * i + 40_000)
    data = path.read_bytes()
    first = CaptureReader(path).data_offset
    offsets, pos = [], first
    while pos < len(data):
        offsets.append(pos)
        pos += RECORD_OVERHEAD + int.from_bytes(data[pos + 8 : pos + 12], "little")
    return offsets


def test_records_come_back_with_their_time_link_direction_and_bytes(tmp_path: Path) -> None:
    path = tmp_path / "a.hilcap"
    gyro, drive = gyro_frames(300), drive_frames(300)
    with Capture(path, meta={"session": "unit", "seed": 7}, flush_interval_s=0.005) as cap:
        servo, driver = cap.link("servo"), cap.link("driver")

        def loop_thread() -> None:  # what hil.session._loop_thread queues: (t_ns, link id, direction, bytes)
            for i, g in enumerate(gyro):
                cap.append((2_000_000 * i, servo.id, RX, g))
                time.sleep(0.0001)

        worker = threading.Thread(target=loop_thread)
        worker.start()
        for i, d in enumerate(drive):
            driver.tx(d, t_ns=2_000_000 * i + 1_000)
            time.sleep(0.0001)
        worker.join()
        give_up = time.monotonic() + 60  # the writer thread writes while the capture is open, whenever it is run
        while not cap.stats.flushes and time.monotonic() < give_up:
            time.sleep(0.001)
        driver.note(event="open", port="/dev/null")
    assert cap.stats.records == 601 and cap.stats.dropped == 0 and cap.stats.flushes > 1
    reader = CaptureReader(path)
    assert reader.meta["session"] == "unit" and reader.meta["seed"] == 7
    assert reader.links == ("servo", "driver", "image", "hexapod")
    records = list(reader)
    assert reader.end == "complete" and reader.records == 601
    servo_rx = [r for r in records if r.link == "servo"]
    driver_tx = [r for r in records if r.link == "driver" and r.direction == "tx"]
    assert [r.data for r in servo_rx] == gyro and {r.direction for r in servo_rx} == {"rx"}
    assert [r.t_ns for r in servo_rx] == [2_000_000 * i for i in range(300)]
    assert [r.data for r in driver_tx] == drive and driver_tx[7].t_ns == 14_001_000
    assert records[-1].direction == "note" and records[-1].note() == {"event": "open", "port": "/dev/null"}
    size = reader.data_offset + sum(RECORD_OVERHEAD + len(r.data) for r in records)
    assert path.stat().st_size == size == cap.stats.file_bytes + reader.data_offset == cap.stats.bytes
    assert cap.path == path and cap.summary() == {"path": str(path), "records": 601, "bytes": size, "dropped": 0,
                                                  "error": ""}


def test_frames_decode_as_each_end_decodes_them(tmp_path: Path) -> None:
    path = tmp_path / "b.hilcap"
    stray = Encoder(Board.DRIVER).encode(DriveStatus(0, 0, 0, 0, 0, 0, 0), Board.HOST)  # the driver's, not the servo's
    with Capture(path) as cap:
        servo, driver = cap.link("servo"), cap.link("driver")
        g = gyro_frames(50)
        servo.rx(b"".join(g[:20]) + stray + g[20][:10], t_ns=5)  # a read that ends inside a frame
        servo.rx(g[20][10:] + b"".join(g[21:]), t_ns=6)
        for i, d in enumerate(drive_frames(50)):
            driver.tx(d, t_ns=10 + i)
    result = CaptureDecode(CaptureReader(path))
    frames = list(decode_capture(path, result=result))
    rx = [f for f in frames if f.direction == "rx"]
    assert [f.frame.message.tick for f in rx] == list(range(50))
    assert [f.t_ns for f in rx[19:22]] == [5, 6, 6]  # a frame is timed by the read that completed it
    counters = result.counters()
    assert counters[("servo", "rx")].frames_ok == 50 and counters[("servo", "rx")].misaddressed == 1
    assert counters[("driver", "tx")].frames_ok == 50 and counters[("driver", "tx")].errors() == 0
    only = list(decode_capture(path, links=["driver"], directions=["tx"]))
    assert len(only) == 50 and {f.link for f in only} == {"driver"}
    assert [f.frame.message.az_counts for f in only[:3]] == [0, 10, 20]


@pytest.mark.parametrize("where", ["record header", "data", "crc"])
def test_a_capture_cut_mid_record_decodes_up_to_the_cut(tmp_path: Path, where: str) -> None:
    path = tmp_path / "whole.hilcap"
    offsets = write_capture(path, 200)
    data = path.read_bytes()
    k = 300  # record 300: the 151st servo read, a 39-byte GYRO_SAMPLE
    into = {"record header": 7, "data": 16 + 20, "crc": 16 + 39 + 2}[where]
    cut = tmp_path / "cut.hilcap"
    cut.write_bytes(data[: offsets[k] + into])
    result = CaptureDecode(CaptureReader(cut))
    frames = list(decode_capture(cut, result=result))
    assert result.reader.records == k and result.reader.end == "truncated"
    assert result.reader.trailing_bytes == into and result.reader.problem_offset == offsets[k]
    assert "cut short" in result.reader.problem
    assert len(frames) == k  # every whole record's frame, nothing of the cut one
    ticks = [f.frame.message.tick for f in frames if f.direction == "rx"]
    assert ticks == list(range(150))


def test_a_damaged_record_stops_the_reading_there_and_says_so(tmp_path: Path) -> None:
    path = tmp_path / "d.hilcap"
    offsets = write_capture(path, 100)
    data = bytearray(path.read_bytes())
    data[offsets[120] + 16 + 12] ^= 0x40  # a flipped bit in record 120's data
    path.write_bytes(bytes(data))
    reader = CaptureReader(path)
    records = list(reader)
    assert len(records) == 120 and reader.end == "corrupt"
    assert reader.problem == f"record CRC mismatch at byte {offsets[120]}: reading stopped there"
    assert reader.trailing_bytes == len(data) - offsets[120]


KILLED_WRITER = """
import os, signal, sys, time
from pathlib import Path
from hil.link import Capture
cap = Capture(Path(sys.argv[1]), flush_interval_s=0.01)
servo = cap.link("servo")
for i in range(1_000_000):
    servo.rx(i.to_bytes(4, "little") * 8, t_ns=i)
    if i % 50 == 0:
        time.sleep(0.001)
    if i == 20_000:
        while cap.stats.records <= 1000:  # flushed while it ran, however slowly the machine ran its writer
            time.sleep(0.001)
        os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_capture_whose_writer_was_killed_reads_up_to_its_last_flush(tmp_path: Path) -> None:
    path = tmp_path / "killed.hilcap"
    done = subprocess.run([sys.executable, "-c", KILLED_WRITER, str(path)], cwd=ROOT, timeout=60, check=False)
    assert done.returncode == -signal.SIGKILL
    reader = CaptureReader(path)
    records = list(reader)
    assert reader.end in ("complete", "truncated")
    assert 1000 < len(records) <= 20_001  # flushed while it ran; the queue's tail died with the process
    assert [r.t_ns for r in records] == list(range(len(records)))  # in order, none lost before the last flush
    assert all(r.data == r.t_ns.to_bytes(4, "little") * 8 for r in records)


def test_what_is_not_a_capture_is_refused_by_name(tmp_path: Path) -> None:
    raw = tmp_path / "raw.bin"
    raw.write_bytes(b"".join(gyro_frames(3)))
    assert not is_capture(raw)
    with pytest.raises(CaptureError, match="not a capture"):
        CaptureReader(raw)
    with pytest.raises(CaptureError, match=r"no \.hilcap capture"):
        find_capture(tmp_path)
    Capture.create(tmp_path, "one").close()
    Capture.create(tmp_path, "one").close()  # the same second: a second name, not an overwrite
    found = sorted(tmp_path.glob("*.hilcap"))
    assert len(found) == 2 and all(is_capture(p) and p.read_bytes()[:8] == MAGIC for p in found)
    with pytest.raises(CaptureError, match="2 captures in this directory"):
        find_capture(tmp_path)
    old = tmp_path / "v2.hilcap"
    old.write_bytes(found[0].read_bytes()[:8] + (2).to_bytes(2, "little") + found[0].read_bytes()[10:])
    with pytest.raises(CaptureError, match="format version 2; this bench reads 1"):
        CaptureReader(old)


def test_a_full_disk_stops_the_capture_growing_not_the_session(tmp_path: Path) -> None:
    cap = Capture(tmp_path / "full.hilcap", flush_interval_s=3600)
    servo = cap.link("servo")
    os.close(cap._fd)  # the file can no longer be written, as on a full or vanished disk
    cap._fd = os.open(os.devnull, os.O_RDONLY)
    for g in gyro_frames(10):
        servo.rx(g)
    cap.flush()
    assert cap.stats.dropped == 10 and cap.stats.records == 0 and "full.hilcap" in cap.stats.error
    servo.rx(gyro_frames(1)[0])  # producers go on appending; nothing raises
    cap.close()
    assert cap.stats.dropped == 11


@pytest.mark.parametrize(("lockstep", "emulated", "emulator"), [
    (True, False, "lockstep"),  # lockstep runs only against the emulator
    (True, True, "lockstep"),
    (False, True, "realtime"),  # the emulator paced in real time (hil run --loopback --clock realtime)
    (False, False, None),  # the lab's boards: no emulator to record
])
def test_a_session_capture_records_the_emulator_it_ran_against(tmp_path: Path, lockstep: bool, emulated: bool,
                                                               emulator: str | None) -> None:
    config = session_config(seed=11)
    kwargs = {"emulated": True} if emulated else {}
    with capture_for_session(tmp_path, config, lockstep=lockstep, **kwargs) as cap:
        pass
    meta = CaptureReader(cap.path).meta
    assert cap.path.parent == tmp_path and cap.path.name.startswith(f"{config.name}-")
    assert meta["session"] == config.name and meta["seed"] == 11 and meta["controller"] == config.controller.name
    assert meta["session_clock"] == ("lockstep" if lockstep else "realtime")
    if emulator is None:
        assert not {"emulator_config", "emulator_clock", "emulator_seed"} & set(meta)
    else:
        assert meta["emulator_config"] == str(config.emulator.config) and Path(meta["emulator_config"]).is_file()
        assert meta["emulator_clock"] == emulator and meta["emulator_seed"] == 11
    assert cap.stats.records == 0 and cap.stats.bytes == cap.path.stat().st_size > 100
