"""A bench owns its ports: a second bench on the same ports is refused by name before it sends a byte, a port that
cannot be opened is bad input, and a lock left by a dead bench is taken over (hil.link._ports, docs/reliability.md)."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from hil.config import PROFILES
from hil.link import Holder, PortUnavailable, SerialLink, claim_ports, is_exclusive
from hil.session import EmulatorProcess
from tests.factories import session_data, write_yaml
from tests.reliability.helpers import bad_input

REPO = Path(__file__).resolve().parents[2]
HIL = [sys.executable, "-m", "hil"]


@pytest.fixture(autouse=True)
def lock_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Every bench of a test (in-process and the children it starts) locks in a directory of the test's own."""
    locks = tmp_path / "locks"
    monkeypatch.setenv("HIL_LOCK_DIR", str(locks))
    return locks


def lab_session(tmp_path: Path, name: str, ports: dict[str, str], duration_s: float) -> Path:
    """A lab session (no --loopback) on ``ports``: the emulator stands in for the lab's boards. The watchdog is
    long, so a busy host does not end it: what is checked is what another bench does to it."""
    data = session_data(name=name, duration_s=duration_s, ports={n: {"port": p} for n, p in ports.items()},
                        safety={"watchdog_ms": 3000, "on_fault": "stop"}, logging={"dir": str(tmp_path / name)})
    return write_yaml(tmp_path / f"{name}.yaml", data)


def patient_emulator(tmp_path: Path) -> Path:
    """The default emulator, its boards patient with a host that a busy machine holds up (host timeout 5 s)."""
    default = PROFILES / "emulator" / "default.yaml"
    data = yaml.safe_load(default.read_text())
    data["plant"] = str((default.parent / data["plant"]).resolve())
    data["boards"]["host_timeout_ms"] = 5000
    return write_yaml(tmp_path / "emulator.yaml", data)


@pytest.mark.slow
@pytest.mark.realtime
def test_a_second_bench_on_the_same_ports_is_refused_and_the_first_runs_undisturbed(tmp_path: Path) -> None:
    with EmulatorProcess(patient_emulator(tmp_path), clock="realtime") as emulator:
        ports = {n: p for n, p in emulator.ports.items() if n != "control"}
        first = subprocess.Popen([*HIL, "run", str(lab_session(tmp_path, "first", ports, 6.0)), "--json"],
                                 cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            give_up = time.monotonic() + 60
            while not list((tmp_path / "first").glob("*.h5")):  # the first bench is connected and logging
                assert first.poll() is None, first.communicate()
                assert time.monotonic() < give_up, "the first session never started"
                time.sleep(0.1)
            time.sleep(1.0)  # mid-swing
            second = subprocess.run([*HIL, "run", str(lab_session(tmp_path, "second", ports, 2.0))],
                                    check=False, cwd=REPO, capture_output=True, text=True, timeout=120)
            out, err = first.communicate(timeout=120)
        finally:
            if first.poll() is None:
                first.kill()
                first.wait()
        boards = emulator.stop()
    lines = second.stderr.strip().splitlines()
    assert second.returncode == 2, (second.stdout, second.stderr, first.returncode)
    assert len(lines) == 1, second.stderr
    assert "servo" in lines[0] and ports["servo"] in lines[0], lines[0]
    assert f"pid {first.pid}" in lines[0] and "'first'" in lines[0], lines[0]  # the holder, by name
    assert not (tmp_path / "second").exists()  # refused before it made anything
    assert first.returncode == 0, (out, err)
    summary = json.loads(out)
    assert summary["status"] == "completed", summary
    assert summary["faults"] == 0 and summary["cycles"] >= 6000, summary
    # No sample was taken by another reader: a cycle is missed only where this host did not read the servo pty in
    # time (it filled, and the board lost what it could not write, as a UART overruns), and no frame reached the
    # boards from another node.
    overflow = boards["links"]["servo"]["tx_overflow_bytes"]
    assert summary["missed_cycles"] <= overflow, (summary["missed_cycles"], overflow)
    assert boards["misaddressed_frames"] == 0


def test_a_port_claim_names_its_holder_and_a_dead_holder_is_taken_over(tmp_path: Path) -> None:
    main_fd, sub_fd = os.openpty()
    try:
        port = os.ttyname(sub_fd)
        holder = subprocess.Popen(  # another bench: it claims the port, says so, and waits to be killed
            [sys.executable, "-c", "import sys, time; from hil.link import claim_ports; "
             f"c = claim_ports({{'servo': {port!r}}}, 'other-session'); print('held', flush=True); time.sleep(60)"],
            cwd=REPO, stdout=subprocess.PIPE, text=True)
        try:
            assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
            with pytest.raises(PortUnavailable) as refused:
                claim_ports({"servo": port}, "mine")
            assert f"pid {holder.pid}" in str(refused.value) and "'other-session'" in str(refused.value)
            assert str(refused.value).startswith(f"servo: {port} is in use by")
            holder.send_signal(signal.SIGKILL)
            holder.wait(10)
        finally:
            if holder.poll() is None:
                holder.kill()
                holder.wait()
        with claim_ports({"servo": port}, "mine") as claims:  # the kernel let go of the dead one's lock
            dead = claims.taken_over["servo"]
            assert isinstance(dead, Holder) and dead.pid == holder.pid and dead.session == "other-session"
            with pytest.raises(PortUnavailable, match="is in use by pid"):  # held again, by us now
                claim_ports({"image": port}, "third")
        with claim_ports({"servo": port}, "again") as claims:  # released: free, and no dead holder to report
            assert claims.taken_over == {}
    finally:
        os.close(main_fd)
        os.close(sub_fd)


def test_two_names_of_one_device_are_one_port(tmp_path: Path) -> None:
    main_fd, sub_fd = os.openpty()
    try:
        port = os.ttyname(sub_fd)
        alias = tmp_path / "by-id-servo"
        alias.symlink_to(port)
        with claim_ports({"servo": str(alias)}, "a"), pytest.raises(PortUnavailable, match="is in use by"):
            claim_ports({"servo": port}, "b")
        with pytest.raises(PortUnavailable, match=r"driver: .* is also the servo link's port"):
            claim_ports({"servo": port, "driver": str(alias)}, "c")
    finally:
        os.close(main_fd)
        os.close(sub_fd)


def test_an_open_link_holds_the_tty_exclusively_and_lets_go_when_closed() -> None:
    main_fd, sub_fd = os.openpty()

    async def scenario() -> tuple[bool, bool]:
        link = await SerialLink.open("servo", os.ttyname(sub_fd))
        held = is_exclusive(sub_fd)  # TIOCEXCL is the tty's: seen through any of its descriptors
        link.close()
        await asyncio.wait_for(link.closed, 5)
        return held, is_exclusive(sub_fd)

    try:
        assert asyncio.run(scenario()) == (True, False)
    finally:
        os.close(main_fd)
        os.close(sub_fd)


@pytest.mark.parametrize(("port", "reason"), [("/dev/nonexistent-servo", "no such port"),
                                              ("/dev/null", "not a serial port (not a terminal device)"),
                                              ("/", "a directory, not a serial port")])
def test_a_port_that_cannot_be_opened_is_one_line_and_exit_2(capsys: pytest.CaptureFixture[str], tmp_path: Path,
                                                             port: str, reason: str) -> None:
    ptys = [os.openpty() for _ in range(3)]  # the other links are real ttys: the bad one is refused all the same
    try:
        good = [os.ttyname(sub) for _, sub in ptys]
        ports = {"servo": {"port": port}, "driver": {"port": good[0]}, "image": {"port": good[1]},
                 "hexapod": {"port": good[2]}}
        session = write_yaml(tmp_path / "s.yaml", session_data(ports=ports, logging={"dir": str(tmp_path / "logs")}))
        bad_input(capsys, ["run", session], f"servo: {port}: {reason}")
        for main_fd, _ in ptys:  # nothing was sent on the good ports either
            os.set_blocking(main_fd, False)
            with pytest.raises(BlockingIOError):
                os.read(main_fd, 64)
        assert not (tmp_path / "logs").exists()
    finally:
        for fds in ptys:
            for fd in fds:
                os.close(fd)


def test_a_second_emulator_on_the_same_ports_file_is_refused(tmp_path: Path) -> None:
    ports_file = tmp_path / "ports.json"
    with EmulatorProcess(clock="lockstep", extra_args=["--ports-file", str(ports_file)]) as first:
        ports = first.ports
        assert json.loads(ports_file.read_text()) == ports
        second = subprocess.run([sys.executable, "-m", "firmware_stub", "--clock", "lockstep", "--ports-file",
                                 str(ports_file)], check=False, cwd=REPO, capture_output=True, text=True, timeout=120)
        assert second.returncode == 2, second.stderr
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and f"--ports-file {ports_file}: in use by the emulator with pid {first.proc.pid}" \
            in lines[0], second.stderr
        assert json.loads(ports_file.read_text()) == ports  # the first one's map, untouched
        first.stop()
    assert list(tmp_path.iterdir()) == []  # the map and its lock go with the emulator
