"""A real host death: the emulator runs as users run it (realtime, its own process), a small host process
(tests/firmware_stub/alive_host.py) drives it, and the test SIGKILLs that host. The emulator's fault log
must then show every board protecting itself one host timeout after the last frame it heard."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from hil.session import EmulatorProcess

pytestmark = pytest.mark.realtime

REPO = Path(__file__).resolve().parents[2]
HOST_TIMEOUT_S = 0.5  # the documented default (profiles/emulator/default.yaml)
ALIVE_PERIOD_S = 0.1  # how often the host sends HOST_ALIVE on its quiet links
CLOCK_LAG_S = 0.1  # the realtime board clock (world ticks) may lag wall time this much, then catch up
UPPER_BOUND_S = 1.5  # generous: a loaded machine


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    records = []
    for line in path.read_text().splitlines():
        try:
            records.append(json.loads(line))
        except ValueError:  # a line being written
            break
    return records


@pytest.mark.slow
def test_boards_protect_themselves_after_the_host_is_sigkilled(tmp_path: Path) -> None:
    fault_log, sent_log, ports_file = tmp_path / "faults.jsonl", tmp_path / "sent.log", tmp_path / "ports.json"
    emulator = EmulatorProcess(clock="realtime", extra_args=["--fault-log", str(fault_log)])
    host: subprocess.Popen[str] | None = None
    try:
        ports_file.write_text(json.dumps(emulator.start()))
        host = subprocess.Popen([sys.executable, "-m", "tests.firmware_stub.alive_host", str(ports_file),
                                 str(sent_log)], cwd=REPO, stdout=subprocess.PIPE, text=True)
        assert host.stdout is not None and host.stdout.readline().strip() == "ready"
        time.sleep(0.3)  # a few HOST_ALIVE periods of normal service
        host.send_signal(signal.SIGKILL)
        killed_s = time.time()
        host.wait(5)
        give_up = time.monotonic() + 10
        while not any(r["kind"] == "hexapod_state" and r["detail"]["state"] == "LOADED" and r["wall_s"] > killed_s
                      for r in read_jsonl(fault_log)):
            assert time.monotonic() < give_up, "the hexapod never came home"
            time.sleep(0.1)
    finally:
        if host is not None and host.poll() is None:
            host.kill()
            host.wait(5)
        summary = emulator.stop()
    records = read_jsonl(fault_log)
    last_sent: dict[str, float] = {}
    for line in sent_log.read_text().splitlines():
        link, t = line.split()
        last_sent[link] = float(t)
    timeouts = {r["link"]: r for r in records if r["kind"] == "host_timeout"}
    # while the host lived, no board timed out; after the kill, each one did, once
    assert sorted(timeouts) == ["driver", "hexapod", "image", "servo"]
    assert len([r for r in records if r["kind"] == "host_timeout"]) == 4
    for link, r in timeouts.items():
        assert r["detail"] == {"silence_ms": 500, "timeout_ms": 500}, r  # by the board's own clock
        assert last_sent[link] <= killed_s
        assert last_sent[link] + HOST_TIMEOUT_S - CLOCK_LAG_S <= r["wall_s"], (link, r, last_sent[link])
        assert r["wall_s"] <= killed_s + HOST_TIMEOUT_S + UPPER_BOUND_S, (link, r, killed_s)

    def after_timeout(link: str, kind: str) -> list[dict[str, Any]]:
        return [r["detail"] for r in records if r["link"] == link and r["kind"] == kind
                and r["wall_s"] >= timeouts[link]["wall_s"]]

    assert after_timeout("driver", "drive_disable") == [{"axes": 3, "cause": "host_timeout"}]
    assert after_timeout("hexapod", "hexapod_state") == [{"state": "STOPPING"}, {"state": "LOADED"}]
    assert after_timeout("servo", "servo_stream") == [{"streaming": False, "cause": "host_timeout"}]
    assert summary["driver"]["enabled"] == 0 and summary["hexapod"]["state"] == "LOADED"
    assert summary["streaming"] is False and summary["host_timeouts"] == 4
