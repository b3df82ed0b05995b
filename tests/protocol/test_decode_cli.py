"""`hil protocol decode`: streamed in chunks, so any capture decodes in bounded memory."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

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
