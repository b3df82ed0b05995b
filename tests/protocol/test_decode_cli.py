"""`hil protocol decode`: streamed in chunks, so any capture decodes in bounded memory."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from hil.cli import app
from hil.protocol import Board, DriveStatus, Encoder, GyroSample

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[2]


def servo_frames(n: int, start_seq: int = 0) -> list[bytes]:
    encoder = Encoder(Board.SERVO)
    encoder.next_seq = start_seq
    return [encoder.encode(GyroSample(i, i, 0.001, -0.002, 0.5, 10.0, -3.0), Board.HOST) for i in range(n)]


def counter(output: str, name: str) -> str:
    found = re.search(rf"│ {name} +│ (.+?) +│", output)
    assert found, output[-2000:]
    return found[1]


def test_a_capture_larger_than_a_chunk_decodes_whole(tmp_path: Path) -> None:
    frames = servo_frames(5000)  # 195 kB: frames straddle the 64 KiB reads
    frames.insert(2000, frames[1999])  # a duplicate
    del frames[3000:3004]  # a gap of 4
    capture = tmp_path / "servo.bin"
    capture.write_bytes(b"".join(frames) + frames[0][:10])  # and an incomplete frame at the end
    result = runner.invoke(app, ["protocol", "decode", str(capture), "--limit", "3"])
    assert result.exit_code == 0, result.output
    out = result.stdout
    assert "4997 frames" in out and "... 4994 more (raise --limit)" in out
    assert "tick=2, " in out and "tick=3, " not in out
    assert counter(out, "frames_ok") == "4997" and counter(out, "bytes") == str(capture.stat().st_size)
    assert counter(out, "duplicates") == "{16: 1}" and counter(out, "frames_lost") == "{16: 4}"
    assert counter(out, r"pending \(incomplete frame\)") == "10"


def test_hex_on_stdin_is_streamed_and_checked_against_a_link(tmp_path: Path) -> None:
    frames = servo_frames(3000)
    stray = Encoder(Board.DRIVER).encode(DriveStatus(0, 0, 0, 0, 0, 0, 0), Board.HOST)
    text = "\n".join(f.hex(" ") for f in [*frames[:1500], stray, *frames[1500:]])  # ~350 kB of text
    result = runner.invoke(app, ["protocol", "decode", "--hex", "-", "--link", "servo", "--limit", "0"], input=text)
    assert result.exit_code == 0, result.output
    out = result.stdout
    assert "3000 frames" in out and counter(out, "misaddressed") == "1" and counter(out, "crc_errors") == "0"


def test_bad_hex_on_stdin_names_its_byte_offset() -> None:
    result = runner.invoke(app, ["protocol", "decode", "--hex", "-"], input="eb 90 01\n0x10")
    assert result.exit_code == 2
    assert "stdin: not hex text: 'x' at byte 10" in result.output


@pytest.mark.slow
def test_a_50_mb_capture_decodes_in_bounded_memory(tmp_path: Path) -> None:
    block = b"".join(servo_frames(65536))  # one turn of the sequence number, 2.6 MB
    capture = tmp_path / "big.bin"
    with capture.open("wb") as f:
        for _ in range(20):
            f.write(block)
    n_frames = 20 * 65536
    # a fresh child measures only its own child (RUSAGE_CHILDREN is the largest of the children it waited for)
    probe = (
        "import resource, subprocess, sys\n"
        "out = subprocess.run([sys.executable, '-m', 'hil', 'protocol', 'decode', sys.argv[1], '--limit', '2'],"
        " capture_output=True, text=True)\n"
        "print(out.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
        "print(out.stdout)\n"
    )
    done = subprocess.run([sys.executable, "-c", probe, str(capture)], capture_output=True, text=True, cwd=ROOT,
                          timeout=120, env={"COLUMNS": "120", "PATH": "/usr/bin:/bin"}, check=False)
    head, _, out = done.stdout.partition("\n")
    code, peak_kb = map(int, head.split())
    assert code == 0, done.stdout + done.stderr
    assert f"{n_frames} frames" in out and counter(out, "frames_ok") == str(n_frames)
    assert counter(out, "bytes") == str(capture.stat().st_size) and counter(out, "seq_gaps") == "{}"
    assert peak_kb < 100_000, f"peak RSS {peak_kb / 1000:.0f} MB"


def write_capture(path: Path, n: int) -> Path:
    """A capture of ``n`` servo samples (rx) each answered by a DRIVE_CMD (tx) 50 us later, 1 ms apart."""
    from hil.link import Capture
    from hil.protocol import DriveCmd

    driver = Encoder(Board.HOST)
    with Capture(path, meta={"session": "decode-test"}) as cap:
        t0 = cap.meta["created_monotonic_ns"]
        for i, frame in enumerate(servo_frames(n)):
            cap.link("servo").rx(frame, t_ns=t0 + 1_000_000 * (i + 1))
            drive = driver.encode(DriveCmd(i, 3 * i, -i), Board.DRIVER)
            cap.link("driver").tx(drive, t_ns=t0 + 1_000_000 * (i + 1) + 50_000)
    return path


def capture_counter(output: str, link: str, direction: str) -> list[str]:
    """The cells of a capture's link-counters row after link and direction."""
    found = re.search(rf"│ {link} +│ {direction} +│(.+)│", output[output.index("link counters"):])
    assert found, output[-2000:]
    return [cell.strip() for cell in found[1].split("│")]


def test_a_capture_decodes_with_times_links_and_directions(tmp_path: Path) -> None:
    write_capture(tmp_path / "run.hilcap", 400)
    result = runner.invoke(app, ["protocol", "decode", str(tmp_path), "--limit", "4"])  # the directory holding it
    assert result.exit_code == 0, result.output
    out = result.stdout
    assert "800 frames, 800 records (complete)" in out
    # times in ms from the capture's opening; each frame with its link, direction and header
    assert re.search(r"│ 1 +│ 1\.050 +│ driver │ tx +│ 0x01 │ 0x20 │ 0 +│ DriveCmd\(tick=0, ", out)
    assert re.search(r"│ 2 +│ 2\.000 +│ servo +│ rx +│ 0x10 │ 0x01 │ 1 +│ GyroSample\(t_us=1, tick=1, ", out)
    # link, dir, frames, bytes, errors, discarded, lost, pending
    assert capture_counter(out, "servo", "rx") == ["400", str(400 * 39), "0", "0", "0", "0"]
    assert capture_counter(out, "driver", "tx") == ["400", str(400 * 19), "0", "0", "0", "0"]
    only = runner.invoke(app, ["protocol", "decode", str(tmp_path / "run.hilcap"), "--link", "driver",
                               "--direction", "tx", "--limit", "0"])
    assert only.exit_code == 0 and "400 frames" in only.stdout and "servo" not in only.stdout


def test_a_capture_decodes_to_json(tmp_path: Path) -> None:
    import json

    path = write_capture(tmp_path / "run.hilcap", 50)
    result = runner.invoke(app, ["protocol", "decode", str(path), "--json", "--limit", "3", "--direction", "rx"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["frames_total"] == 50 and data["records"] == 100 and data["end"] == "complete"
    assert data["meta"]["session"] == "decode-test" and set(data["counters"]) == {
        f"{link} rx" for link in ("servo", "driver", "image", "hexapod")}
    first = data["frames"][0]
    assert first["t_s"] == 0.001 and first["link"] == "servo" and first["direction"] == "rx"
    assert first["message"] == "GYRO_SAMPLE" and first["seq"] == 0 and first["src"] == 0x10
    assert first["fields"] == {"t_us": 0, "tick": 0, "rate_x_dps": 0.001, "rate_y_dps": -0.002, "rate_z_dps": 0.5,
                               "az_deg": 10.0, "el_deg": -3.0}
    assert data["counters"]["servo rx"]["frames_ok"] == 50 and data["counters"]["servo rx"]["errors"] == 0


def test_a_capture_cut_mid_record_decodes_up_to_the_cut_and_says_so(tmp_path: Path) -> None:
    path = write_capture(tmp_path / "run.hilcap", 100)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 19 - 20 - 25])  # the last DRIVE_CMD record gone, the last sample's cut
    result = runner.invoke(app, ["protocol", "decode", str(path), "--limit", "0"])
    assert result.exit_code == 0, result.output
    assert "198 frames, 198 records (truncated: a record cut short at byte" in " ".join(result.stdout.split())
    assert capture_counter(result.stdout, "servo", "rx")[:2] == ["99", str(99 * 39)]
    assert "cut short" in result.stderr


def test_raw_input_decodes_to_json_too(tmp_path: Path) -> None:
    import json

    capture = tmp_path / "servo.bin"
    capture.write_bytes(b"".join(servo_frames(20)))
    result = runner.invoke(app, ["protocol", "decode", str(capture), "--json", "--limit", "2", "--link", "servo"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["frames_total"] == 20 and len(data["frames"]) == 2 and data["frames"][1]["fields"]["tick"] == 1
    assert data["counters"]["frames_ok"] == 20 and data["counters"]["bytes"] == 20 * 39


def test_options_that_do_not_fit_the_input_are_refused(tmp_path: Path) -> None:
    raw = tmp_path / "servo.bin"
    raw.write_bytes(b"".join(servo_frames(3)))
    write_capture(tmp_path / "a.hilcap", 3)
    for args, message in (
        ([str(raw), "--direction", "rx"], "is not a capture file (.hilcap)"),
        ([str(tmp_path / "a.hilcap"), "--side", "board"], "choose it with --direction"),
        ([str(raw), "--link", "gimbal"], "'gimbal' is not one of"),
        ([str(tmp_path / "a.hilcap"), "--direction", "up"], "'up' is not one of"),
    ):
        result = runner.invoke(app, ["protocol", "decode", *args])
        assert result.exit_code == 2, (args, result.output)
        assert message in result.output, (args, result.output)
    write_capture(tmp_path / "b.hilcap", 3)
    result = runner.invoke(app, ["protocol", "decode", str(tmp_path)])
    assert result.exit_code == 2 and "2 captures in this directory (a.hilcap, b.hilcap): name one" in result.output
