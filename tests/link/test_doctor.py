"""`hil doctor`: is the hardware ready? Ports, their holder, a USB-serial adapter's latency timer on a fake sysfs
tree, and the baud rate against the link budget (hil.link.check_port; docs/service.md)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hil.link import check_port, claim_ports
from hil.session import EmulatorProcess
from tests.reliability.helpers import session_data, write_yaml

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def lock_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    locks = tmp_path / "locks"
    monkeypatch.setenv("HIL_LOCK_DIR", str(locks))
    return locks


@pytest.fixture
def pty() -> str:
    """A terminal device nobody holds (the follower side of a pseudo-terminal)."""
    leader, follower = os.openpty()
    path = os.ttyname(follower)
    os.close(follower)
    yield path
    os.close(leader)


def fake_timer(sysfs: Path, port: str, ms: int) -> Path:
    timer = sysfs / "bus" / "usb-serial" / "devices" / Path(os.path.realpath(port)).name / "latency_timer"
    timer.parent.mkdir(parents=True)
    timer.write_text(f"{ms}\n")
    return timer


def by_check(findings: list) -> dict:  # type: ignore[type-arg]
    return {f.check: f for f in findings}


def test_a_free_serial_port_at_a_fast_enough_baud_rate_passes(pty: str, tmp_path: Path) -> None:
    found = by_check(check_port("servo", pty, baud=921_600, sysfs=tmp_path / "sys"))
    assert list(found) == ["port", "holder", "latency timer", "baud rate"] and all(f.ok for f in found.values())
    assert found["baud rate"].detail == "921600 baud; the periodic load servo → host is 47% of it"


def test_an_ftdi_adapter_left_at_16_ms_fails_and_says_how_to_set_1_ms(pty: str, tmp_path: Path) -> None:
    timer = fake_timer(tmp_path / "sys", pty, 16)
    slow = by_check(check_port("servo", pty, baud=921_600, sysfs=tmp_path / "sys"))["latency timer"]
    assert not slow.ok and "latency timer 16 ms delays every sample by up to 16 ms" in slow.detail
    assert f"echo 1 | sudo tee {timer}" in slow.detail and 'ATTR{latency_timer}="1"' in slow.detail
    timer.write_text("1\n")
    assert by_check(check_port("servo", pty, baud=921_600, sysfs=tmp_path / "sys"))["latency timer"].ok


def test_115200_baud_cannot_carry_the_gyro_stream(pty: str, tmp_path: Path) -> None:
    baud = by_check(check_port("servo", pty, baud=115_200, sysfs=tmp_path))["baud rate"]
    assert not baud.ok
    assert baud.detail == ("115200 baud carries 115.2 kbit/s, and the periodic messages servo → host need 433.0 "
                           "kbit/s (at most 80% of the line, docs/protocol.md link budget); use at least 921600 "
                           "baud on both ends")
    assert by_check(check_port("driver", pty, baud=460_800, sysfs=tmp_path))["baud rate"].ok  # 190 kbit/s


def test_a_missing_port_a_non_tty_and_a_held_port_fail_by_name(pty: str, tmp_path: Path) -> None:
    missing = check_port("servo", "/dev/nonexistent-servo", baud=921_600, sysfs=tmp_path)
    assert [f.check for f in missing] == ["port", "baud rate"] and not missing[0].ok
    assert missing[0].detail.startswith("servo: /dev/nonexistent-servo: no such port")
    null = check_port("image", "/dev/null", baud=921_600, sysfs=tmp_path)[0]
    assert not null.ok and null.detail == "image: /dev/null: not a serial port (not a terminal device)"
    with claim_ports({"servo": pty}, "the other bench"):
        held = by_check(check_port("servo", pty, baud=921_600, sysfs=tmp_path))["holder"]
    assert not held.ok and f"servo: {pty} is in use by pid {os.getpid()}" in held.detail
    assert "session 'the other bench'" in held.detail


def test_the_command_checks_a_session_s_ports(tmp_path: Path) -> None:
    with EmulatorProcess(clock="lockstep") as emulator:
        ports = {n: p for n, p in emulator.ports.items() if n != "control"}
        good = write_yaml(tmp_path / "lab.yaml", session_data(ports={n: {"port": p} for n, p in ports.items()}))
        slow = write_yaml(tmp_path / "slow.yaml", session_data(ports={
            n: {"port": p, "baudrate": 115_200 if n == "servo" else 921_600} for n, p in ports.items()}))
        ok = subprocess.run([sys.executable, "-m", "hil", "doctor", str(good), "--json"], cwd=REPO,
                            capture_output=True, text=True, timeout=120, check=False)
        bad = subprocess.run([sys.executable, "-m", "hil", "doctor", str(slow)], cwd=REPO, capture_output=True,
                             text=True, timeout=120, check=False, env={**os.environ, "COLUMNS": "250"})
    assert ok.returncode == 0, ok.stdout + ok.stderr
    report = json.loads(ok.stdout)
    assert report["ok"] and {f["link"] for f in report["findings"]} == {"servo", "driver", "image", "hexapod"}
    assert len(report["findings"]) == 16
    assert bad.returncode == 1 and "FAIL" in bad.stdout and "433.0 kbit/s" in bad.stdout, bad.stdout
    assert "15 of 16 checks passed" in " ".join(bad.stdout.split())
