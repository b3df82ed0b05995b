"""`python -m firmware_stub` / `hil emulate` as a user runs them: ports map, realtime clock, clean exit."""

from __future__ import annotations

import itertools
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.protocol import NO_LATENCY_US, Ack, AxisMask, DriveCmd, DriveEnable, GyroSample, LoopTiming, ServoMode
from hil.protocol import StreamMode as Mode
from tests.firmware_stub.host import Host


def spawn(*args: str) -> tuple[subprocess.Popen[str], dict[str, str]]:
    proc = subprocess.Popen([sys.executable, "-m", "firmware_stub", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line:
        proc.wait(5)
        pytest.fail(f"emulator did not start: {proc.stderr.read() if proc.stderr else ''}")
    return proc, json.loads(line)


@pytest.mark.realtime
def test_realtime_emulator_serves_a_host_and_leaves_nothing_behind(tmp_path: Path) -> None:
    ports_file = tmp_path / "ports.json"
    proc, ports = spawn("--clock", "realtime", "--ports-file", str(ports_file))
    try:
        assert set(ports) == {"servo", "driver", "image", "hexapod", "control"}
        assert json.loads(ports_file.read_text()) == ports
        host = Host(ports, host_alive_period_s=0.1)
        assert isinstance(host.request("driver", DriveEnable(AxisMask.BOTH, True)), Ack)
        assert isinstance(host.request("servo", ServoMode(Mode.STREAM)), Ack)
        samples: list[GyroSample] = []
        t_end = time.monotonic() + 10
        servo, seen = host["servo"], 0
        while len(samples) < 400 and time.monotonic() < t_end:
            host.pump_all(0.002)
            for frame in servo.frames[seen:]:
                if isinstance(frame.message, GyroSample) and len(samples) < 400:
                    samples.append(frame.message)
                    host["driver"].send(DriveCmd(frame.message.tick, 0, 0))
            seen = len(servo.frames)
        ticks = [s.tick for s in samples]
        assert ticks == list(range(400))
        spacing = {b.t_us - a.t_us for a, b in itertools.pairwise(samples)}
        assert spacing == {1000}  # the board's clock, whatever the host's timing
        reports = [f.message for f in host["servo"].frames if isinstance(f.message, LoopTiming)]
        assert len(reports) >= 30
        measured = [v for r in reports for v in r.latency_us if v != NO_LATENCY_US]
        unanswered = 10 * len(reports) - len(measured)
        # each tick is either measured or counted missing (a loaded machine's host may miss some)
        assert reports[-1].missing_total == unanswered
        assert len(measured) >= 0.5 * 10 * len(reports)
        assert 0 < sorted(measured)[len(measured) // 2] < 5000
        host.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["clock"] == "realtime" and summary["servo"]["samples_sent"] >= 400
    assert not ports_file.exists()
    assert not any(Path(p).exists() for p in ports.values())
    assert not Path(ports["servo"]).parent.exists()


def test_bad_config_is_one_line_and_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "emu.yaml"
    bad.write_text("clock: fast\n")
    proc = subprocess.run([sys.executable, "-m", "firmware_stub", "--config", str(bad)], capture_output=True,
                          text=True, timeout=30, check=False)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "clock" in lines[0] and str(bad) in lines[0]
    bad.write_text("links:\n  servo: {bit_error_rate: 2}\n")
    proc = subprocess.run([sys.executable, "-m", "hil", "emulate", "--config", str(bad)], capture_output=True,
                          text=True, timeout=30, check=False)
    assert proc.returncode == 2 and "links.servo.bit_error_rate" in proc.stderr
