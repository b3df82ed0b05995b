"""`hil doctor`: is the hardware ready? Ports, their holder, a USB-serial adapter's latency timer on a fake sysfs
tree, and the baud rate against the link budget (hil.link.check_port); each board's IDENT and its catalogue
fingerprint, and a listen to the servo stream (hil.boards.check_boards), against the emulator in real time and a
pseudo-terminal nobody answers on (docs/service.md)."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil import api
from hil.boards import check_boards
from hil.config import SessionConfig
from hil.link import check_port, claim_ports, wire_delay
from hil.protocol import CATALOGUE, Decoder, IdentRequest
from hil.session import EmulatorProcess
from tests.factories import session_config, session_data, write_yaml

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


@pytest.mark.realtime
def test_the_command_checks_a_session_s_ports(tmp_path: Path) -> None:
    with EmulatorProcess(clock="lockstep") as emulator:
        ports = {n: p for n, p in emulator.ports.items() if n != "control"}
        good = write_yaml(tmp_path / "lab.yaml", session_data(ports={n: {"port": p} for n, p in ports.items()}))
        slow = write_yaml(tmp_path / "slow.yaml", session_data(ports={
            n: {"port": p, "baudrate": 115_200 if n == "servo" else 921_600} for n, p in ports.items()}))
        ok = subprocess.run([sys.executable, "-m", "hil", "doctor", str(good), "--json", "--no-boards"], cwd=REPO,
                            capture_output=True, text=True, timeout=120, check=False)
        bad = subprocess.run([sys.executable, "-m", "hil", "doctor", str(slow), "--no-boards"], cwd=REPO,
                             capture_output=True, text=True, timeout=120, check=False,
                             env={**os.environ, "COLUMNS": "250"})
    assert ok.returncode == 0, ok.stdout + ok.stderr
    report = json.loads(ok.stdout)
    links = {"servo", "driver", "image", "hexapod", "loop", "host"}
    assert report["ok"] and {f["link"] for f in report["findings"]} == links
    assert len(report["findings"]) == 18 and report["findings"][-1]["check"] == "realtime scheduling"
    # a session whose line cannot carry the link budget does not load (hil.config): the same check, bad input
    line = " ".join(bad.stderr.split())
    assert bad.returncode == 2 and "ports: servo.baudrate: 115200 baud carries 115.2 kbit/s" in line, bad.stderr
    assert "433.0 kbit/s" in line and "use at least 921600 baud" in line


# --- the boards: IDENT and the servo stream ---------------------------------------------------------------------------

def emulated_lab(tmp_path: Path, emulator: EmulatorProcess) -> Path:
    """A session file on the emulator's ports (at the default 921 600 baud)."""
    ports = {n: p for n, p in emulator.ports.items() if n != "control"}
    return write_yaml(tmp_path / "lab.yaml", session_data(ports={n: {"port": p} for n, p in ports.items()}))


def records(fault_log: Path, kind: str) -> list[dict]:  # type: ignore[type-arg]
    """The emulator's records of one kind (read once it has stopped)."""
    lines = fault_log.read_text().splitlines() if fault_log.exists() else []
    return [r for r in map(json.loads, lines) if r["kind"] == kind]


@pytest.mark.slow
@pytest.mark.realtime
def test_every_board_answers_with_the_bench_s_fingerprint_and_the_stream_runs_near_1_khz(tmp_path: Path) -> None:
    fault_log = tmp_path / "emulator.jsonl"
    with EmulatorProcess(clock="realtime", extra_args=["--fault-log", str(fault_log)]) as emulator:
        lab = emulated_lab(tmp_path, emulator)
        done = subprocess.run([sys.executable, "-m", "hil", "doctor", str(lab), "--json"], cwd=REPO,
                              capture_output=True, text=True, timeout=120, check=False)
        report = json.loads(done.stdout)
        with claim_ports({n: p for n, p in emulator.ports.items() if n != "control"}, "the next session"):
            pass  # the doctor let go of every port
    rows = {(f["link"], f["check"]): f for f in report["findings"]}
    assert len(rows) == len(report["findings"]) == 23  # 4 checks of each port, 4 idents, the stream, the wire, the host
    assert [f["check"] for f in report["findings"] if f["link"] == "servo"] == [
        "port", "holder", "latency timer", "baud rate", "ident", "servo stream"]
    fingerprint = f"{CATALOGUE.fingerprint:#010x}"
    for link in ("servo", "driver", "image", "hexapod"):
        ident = rows[link, "ident"]
        assert ident["ok"], ident
        assert ident["detail"].startswith(f"{link} board, firmware 'emu-1.0.0', serial ")
        assert ident["detail"].endswith(f"catalogue {fingerprint} (protocol v1) as this bench expects")
        assert ident["values"]["catalogue_fingerprint"] == ident["values"]["expected_fingerprint"] == fingerprint
    stream = rows["servo", "servo stream"]
    values = stream["values"]
    assert stream["ok"] and report["ok"] and done.returncode == 0, stream
    assert 990 <= values["board_rate_hz"] <= 1010, stream  # the emulator's servo board ticks at 1 kHz ...
    assert 800 <= values["received_rate_hz"] <= 1200, stream  # ... and a loaded PC delivers it bunched, a bit late
    assert 0.5 <= values["span_s"] <= 4 and values["lost"] == 0 and values["stopped"], stream  # a 2 s listen
    assert values["samples"] - 1 == pytest.approx(values["received_rate_hz"] * values["span_s"], rel=0.01)
    assert 0 < values["gap_us_p50"] <= values["gap_us_p99"] <= values["max_gap_ms"] * 1000, stream
    assert values["jitter_us"] == pytest.approx(values["gap_us_p99"] - values["gap_us_p50"], abs=0.2)
    assert stream["detail"].startswith(f"{values['board_rate_hz']:.1f} Hz by the board's clock, received at "
                                       f"{values['received_rate_hz']:.1f} Hz ({values['samples']} samples in ")
    assert "the arrivals are not judged" in stream["detail"]  # the emulator's ptys share this PC's CPUs
    # the doctor started the stream once and stopped it itself (not the board's host timer); the driver stayed off
    assert [(r["detail"]["streaming"], r["detail"]["cause"]) for r in records(fault_log, "servo_stream")] == [
        (True, "host"), (False, "host")]
    assert records(fault_log, "drive_enable") == [] and records(fault_log, "hexapod_state") == []


@pytest.mark.realtime
def test_a_board_from_another_catalogue_is_named_with_both_fingerprints(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    fault_log = tmp_path / "emulator.jsonl"
    with EmulatorProcess(clock="realtime", extra_args=["--fault-log", str(fault_log)]) as emulator:
        lab = emulated_lab(tmp_path, emulator)
        board = f"{CATALOGUE.fingerprint:#010x}"
        monkeypatch.setattr(type(CATALOGUE), "fingerprint", property(lambda _self: 0x0BADF00D))
        findings = api.doctor(lab, sysfs=tmp_path / "sys")
    rows = {(f.link, f.check): f for f in findings}
    for link in ("servo", "driver", "image", "hexapod"):
        ident = rows[link, "ident"]
        assert not ident.ok
        assert ident.detail == (f"{link}: firmware 'emu-1.0.0' speaks catalogue {board} (protocol v1), this bench "
                                "0x0badf00d (protocol v1): update one of them")
        assert ident.values["expected_fingerprint"] == "0x0badf00d"
    stream = rows["servo", "servo stream"]
    assert not stream.ok and stream.detail.startswith("not listened to: the servo board did not identify")
    assert records(fault_log, "servo_stream") == []  # a board that speaks another catalogue is told nothing more


def test_a_port_where_nothing_answers_says_so_within_the_timeout() -> None:
    leader, follower = os.openpty()
    port = os.ttyname(follower)
    os.close(follower)
    try:
        t0 = time.monotonic()
        findings = asyncio.run(check_boards({"servo": port}, {"servo": 921_600}, ident_timeout_s=0.5))
        took_s = time.monotonic() - t0
        os.set_blocking(leader, False)
        sent = os.read(leader, 4096)
        with claim_ports({"servo": port}, "the next session"):
            pass  # released
    finally:
        os.close(leader)
    ident, stream = findings
    assert not ident.ok and ident.detail == (
        f"servo: no answer to IDENT_REQ on {port} within 500 ms: check the wiring (the board powered, its cable on "
        "this port, RS422 pairs the right way round) and that both ends run at 921600 baud; not a byte came "
        "meanwhile")
    assert not stream.ok and stream.detail.startswith("not listened to: the servo board did not identify")
    assert took_s < 10  # 0.5 s of asking, and opening and closing the port; generous for a loaded machine
    # what went out: IDENT_REQ and its 3 resends (one frame, one sequence number), nothing that starts a stream
    frames = list(Decoder().feed(sent))
    assert [type(f.message) for f in frames] == [IdentRequest] * 4 and len({f.seq for f in frames}) == 1


@pytest.mark.realtime
def test_the_stream_is_stopped_and_the_ports_released_when_the_check_is_cancelled(tmp_path: Path) -> None:
    fault_log = tmp_path / "emulator.jsonl"
    with EmulatorProcess(clock="realtime", extra_args=["--fault-log", str(fault_log)]) as emulator:
        ports = {n: p for n, p in emulator.ports.items() if n != "control"}

        async def cancelled_while_listening() -> float:
            task = asyncio.ensure_future(check_boards(ports, dict.fromkeys(ports, 921_600), listen_s=60.0))
            await asyncio.sleep(1.5)  # the boards identified and the stream started
            task.cancel()
            t0 = time.monotonic()
            with pytest.raises(asyncio.CancelledError):
                await task
            return time.monotonic() - t0

        took_s = asyncio.run(cancelled_while_listening())
        with claim_ports(ports, "the next session"):
            pass  # released
    assert took_s < 10  # the stop and the closing, not the 60 s listen
    assert [(r["detail"]["streaming"], r["detail"]["cause"]) for r in records(fault_log, "servo_stream")] == [
        (True, "host"), (False, "host")]
    assert records(fault_log, "drive_enable") == []


def test_the_host_row_says_how_to_grant_realtime_scheduling_where_it_is_refused(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Where the kernel refuses SCHED_FIFO (an unprivileged user without an rtprio limit), the host row fails and
    says how to grant it; the service's worker then runs its loop threads at normal priority and says why."""
    import hil.session._host as host

    def refuse(priority: int) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(host, "set_fifo", refuse)
    findings = api.doctor(None, sysfs=tmp_path)
    row = findings[-1]
    assert (row.link, row.check, row.ok) == ("host", "realtime scheduling", False)
    assert row.detail.startswith("SCHED_FIFO 50 refused (Operation not permitted): the 1 kHz loop then shares")
    assert "`USER - rtprio 80` in /etc/security/limits.d/hil.conf" in row.detail and "cap_sys_nice+ep" in row.detail
    monkeypatch.undo()
    assert api.doctor(None, sysfs=tmp_path)[-1].ok == (os.geteuid() == 0 or host.fifo_refusal() is None)


def test_the_wire_delay_is_a_warning_over_the_budget_and_never_a_failure() -> None:
    slow = wire_delay(921_600, 921_600, 100.0)
    assert slow.ok and slow.warning and slow.link == "loop" and slow.check == "wire delay"
    assert slow.values == {"wire_delay_us": 629.3, "budget_us": 100.0}  # GYRO_SAMPLE 423 us + DRIVE_CMD 206 us
    assert "adds 629 us to every cycle" in slow.detail and "ports.wire_delay_budget_us" in slow.detail
    assert "6000000 baud on both ends adds 97 us" in slow.detail
    default = wire_delay(6_000_000, 6_000_000, 100.0)
    assert default.ok and not default.warning and default.values["wire_delay_us"] == 96.7
    assert not wire_delay(921_600, 921_600, 700.0).warning  # a session may allow its slow wire


def test_doctor_on_a_session_reports_its_wire_delay(tmp_path: Path) -> None:
    session = session_config(ports={n: {"port": f"/dev/nonexistent-{n}", "baudrate": 921_600}
                                    for n in ("servo", "driver", "image", "hexapod")},
                             ).model_dump(mode="json")
    session["ports"]["wire_delay_budget_us"] = 50
    findings = api.doctor(SessionConfig.model_validate(session), boards=False, sysfs=tmp_path)
    delay = next(f for f in findings if f.check == "wire delay")
    assert delay.ok and delay.warning and delay.values["budget_us"] == 50
