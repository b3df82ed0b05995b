"""The one-way door: once a session disarms, nothing enables the driver, starts the stream or the swing again.

A servo stall near the end of a session with ``on_fault: recover`` leaves a recovery pending while the session
winds down; without the interlock, that recovery re-enabled the driver and restarted the stream after the
disarm. The boards' final state is read from the emulator's side, well after the session has returned.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import yaml

from firmware_stub.control import ControlClient
from hil.config import PROFILES
from hil.session import EmulatorProcess
from tests.factories import run_session, session_config
from tests.session.helpers import logged_events

DURATION_S = 0.6
STOP_RAMP_S = 0.3  # the wind-down: the hexapod ramps home over this (simulated) time while the loop still runs
RECOVER_AFTER_MS = 150.0
STALL_MS = 100.0
# the last 300 ms of the session, 10 ms steps: the wind-down, while the loop is armed and the swing ramps home
STALL_STARTS_S = [round(DURATION_S + 0.01 * i, 3) for i in range(31)]


def emulator_with_stall(tmp: Path, at_s: float) -> Path:
    data = yaml.safe_load((PROFILES / "emulator" / "default.yaml").read_text())
    data["plant"] = str((PROFILES / "plant" / "default.yaml").resolve())
    data["boards"]["hexapod"]["stop_ramp_s"] = STOP_RAMP_S
    data["faults"] = [{"at_s": at_s, "link": "servo", "kind": "stall", "duration_ms": STALL_MS}]
    path = tmp / "emulator-stall.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.slow
@pytest.mark.parametrize("stall_at_s", STALL_STARTS_S)
def test_a_stall_during_the_last_300_ms_never_leaves_a_board_moving(tmp_path: Path, stall_at_s: float) -> None:
    config = session_config(
        duration_s=DURATION_S, seed=3,
        safety={"watchdog_ms": 50, "on_fault": "recover", "recover_after_ms": RECOVER_AFTER_MS, "max_recoveries": 5},
        emulator={"config": emulator_with_stall(tmp_path, stall_at_s), "clock": "lockstep"})
    status: dict = {}

    def look_later(emu: EmulatorProcess) -> None:  # after any recovery that was pending could have fired
        time.sleep((RECOVER_AFTER_MS + 200) / 1000)
        with ControlClient(emu.ports["control"]) as ctl:
            status.update(ctl.call("status"))

    run = run_session(config, tmp_path, watchdog_ms=50, after=look_later)
    assert run.result.status in ("completed", "fault"), run.result.message
    # the emulator's own view: nothing enabled, nothing streaming, no swing running
    assert status["driver"]["enabled"] == 0, status["driver"]
    assert status["streaming"] is False
    assert status["hexapod"]["state"] != "RUNNING"
    # its record of the driver: the last enable came before the last disable
    driver = [r["kind"] for r in run.records if r["link"] == "driver" and r["kind"] in ("drive_enable",
                                                                                        "drive_disable")]
    assert driver and driver[-1] == "drive_disable", driver
    # the log says how the session left the boards
    events = logged_events(run.result.log_path)
    safe = [d for k, d in events if k == "state" and d.get("state") == "safe"]
    assert len(safe) == 1 and safe[0]["driver"] == "disabled" and safe[0]["hexapod"] == "stopped", safe
    # a stall that outlasts the stream never ends in lockstep (the world is frozen then): its ACK is lost, and
    # the log says so rather than claiming a confirmation it did not get
    assert safe[0]["stream"] == "idle" or safe[0]["stream"].startswith("not confirmed: servo:"), safe
    kinds = [k for k, _ in events]
    assert kinds[-1] == "summary"
    assert "recovered" not in kinds[kinds.index("summary") - 2:]
