"""Sessions with a hexapod driver that is not the protocol one: everything goes through the driver interface, the
bench's hexapod link is never opened, and once the session disarms nothing reaches the driver's load or start."""

from __future__ import annotations

import asyncio
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.boards import GuardedHexapod, Interlock, InterlockClosed
from hil.config import SessionConfig
from hil.link import LinkError
from hil.log.reader import read_log
from hil.protocol import HexAxis
from hil.protocol.swing import Segment
from hil.session import Session, SessionResult, sim_ports
from tests import factories
from tests.boards.drivers import RecordingHexapod, RecordingOptions
from tests.factories import run_session, session_config
from tests.session.helpers import logged_events

SEGMENT = Segment(HexAxis.PITCH, 0.0, 10.0, 1.0, 1.0)


def sim_session(config: SessionConfig, out: Path, *, hooks: dict[str, Any] | None = None,
                ports_without_hexapod: bool = True) -> tuple[Session, SessionResult]:
    """A ``sim`` session whose Session object the test keeps; ``hooks(session)`` fills the driver's."""
    ports = sim_ports()
    if ports_without_hexapod:
        del ports["hexapod"]  # a driver without the bench's link needs no hexapod port at all

    def prepare(session: Session) -> None:
        if hooks is not None:
            RecordingHexapod.hooks.update(hooks)
            for name, hook in hooks.items():  # hooks that need the session get it
                if getattr(hook, "wants_session", False):
                    RecordingHexapod.hooks[name] = lambda drv, hook=hook: hook(drv, session)

    return factories.sim_session(config, out, ports=ports, prepare=prepare)


def with_session(fn: Any) -> Any:
    fn.wants_session = True
    return fn


def safe_event(log_path: Path) -> dict[str, Any]:
    return next(d for k, d in logged_events(log_path) if k == "state" and d.get("state") == "safe")


def test_the_guard_refuses_load_and_start_once_the_session_has_disarmed(test_drivers: type[RecordingHexapod]) -> None:
    interlock = Interlock()
    inner = RecordingHexapod(RecordingOptions())
    guard = GuardedHexapod(inner, interlock, "recording")

    async def main() -> None:
        await guard.identify()
        await guard.load([SEGMENT])
        await guard.start()
        assert guard.running and guard.state == "running"
        interlock.close("session completed")
        for action in (lambda: guard.load([SEGMENT]), guard.start):
            with pytest.raises(InterlockClosed, match=r"refused: the session has disarmed \(session completed\)"):
                await action()
        await guard.stop()  # what makes it safe still goes through
        assert await guard.wait_home(0.5) is True and guard.state == "idle"
        await guard.close()

    asyncio.run(main())
    assert inner.calls == ["identify", "load", "start", "stop", "close"]
    assert inner.segments == (SEGMENT,)  # the refused second upload never reached the driver


def test_a_drivers_own_exception_becomes_a_link_error_naming_it(test_drivers: type[RecordingHexapod]) -> None:
    guard = GuardedHexapod(RecordingHexapod(RecordingOptions()), Interlock(), "recording")

    def busy(drv: RecordingHexapod) -> None:
        raise RuntimeError("controller busy:\n  try later")

    test_drivers.hooks["load"] = busy
    with pytest.raises(LinkError, match=r"^hexapod driver 'recording': load: RuntimeError: controller busy: try "
                                         r"later$"):
        asyncio.run(guard.load([SEGMENT]))


def test_a_sim_session_drives_a_software_table_only_through_the_interface(tmp_path: Path,
                                                                          test_drivers: type[RecordingHexapod]) -> None:
    config = session_config(duration_s=0.5, seed=4, hexapod={"driver": "recording", "pitch_deg": 0.75,
                                                             "label": "table-9"})
    session, result = sim_session(config, tmp_path)
    assert result.status == "completed", result.message
    (driver,) = test_drivers.instances
    # stop twice: the wind-down's (then it waits home), and the shutdown's, which always stops a started swing
    assert driver.calls == ["identify", "load", "start", "stop", "stop", "close"]
    assert driver.segments == tuple(config.profile.protocol_segments()) and len(driver.segments) == 2
    assert "hexapod" not in session.links  # the bench's hexapod link was never opened
    log = read_log(result.log_path)
    hexapod = log.groups["hexapod"]
    assert np.asarray(hexapod["t_profile_s"]).tolist() == [0.0]
    assert [float(hexapod[c][0]) for c in ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")] == \
        [0.0, 0.0, 0.0, 0.0, 0.75, 0.0]
    assert log.attrs["ident"]["hexapod"] == {"driver": "recording", "label": "table-9"}
    assert log.attrs["config"]["hexapod"] == {"driver": "recording", "pitch_deg": 0.75, "label": "table-9",
                                              "token": None}
    assert safe_event(result.log_path) == {"state": "safe", "driver": "disabled", "hexapod": "stopped",
                                           "stream": "idle"}
    summary = next(d for k, d in logged_events(result.log_path) if k == "summary")
    assert summary["cycles"] >= 500 and set(summary["link_errors"]) == {"servo", "driver", "image"}
    # disarmed for good: the session's hold on the driver refuses anything that would move it again
    for action in (session.hexapod.start, lambda: session.hexapod.load([SEGMENT])):
        with pytest.raises(InterlockClosed, match="session completed"):
            asyncio.run(action())
    assert driver.calls == ["identify", "load", "start", "stop", "stop", "close"]


def test_a_signal_during_the_upload_means_the_table_is_never_started(tmp_path: Path,
                                                                     test_drivers: type[RecordingHexapod]) -> None:
    @with_session
    def interrupt(drv: RecordingHexapod, session: Session) -> None:
        session._on_signal(signal.SIGINT)

    config = session_config(duration_s=0.5, seed=4, hexapod={"driver": "recording"})
    _, result = sim_session(config, tmp_path, hooks={"load": interrupt})
    assert (result.status, result.exit_code, result.message) == ("interrupted", 130, "SIGINT")
    (driver,) = test_drivers.instances
    assert driver.calls == ["identify", "load", "close"]  # no start, and nothing to stop
    assert safe_event(result.log_path)["hexapod"] == "never started"


def test_a_fault_the_driver_reports_disarms_and_stops_the_table(tmp_path: Path,
                                                                test_drivers: type[RecordingHexapod]) -> None:
    def lose_connection_soon(drv: RecordingHexapod) -> None:
        asyncio.get_running_loop().call_later(0.05, lambda: drv.on_fault("connection reset by the controller"))

    config = session_config(duration_s=30.0, seed=4, hexapod={"driver": "recording"})
    session, result = sim_session(config, tmp_path, hooks={"start": lose_connection_soon})
    assert (result.status, result.exit_code) == ("fault", 1)
    assert result.message == "hexapod: connection reset by the controller"
    assert 0 < result.stats.cycles < 30_000
    (driver,) = test_drivers.instances
    assert driver.calls == ["identify", "load", "start", "stop", "close"]
    assert safe_event(result.log_path)["hexapod"] == "stopped"
    with pytest.raises(InterlockClosed):
        asyncio.run(session.hexapod.start())
    assert driver.calls.count("start") == 1


def test_a_driver_that_cannot_stop_is_recorded_and_the_session_still_ends_safe(tmp_path: Path,
                                                                               test_drivers: type[RecordingHexapod]
                                                                               ) -> None:
    def gone(drv: RecordingHexapod) -> None:
        raise ConnectionResetError("peer closed")

    config = session_config(duration_s=0.3, seed=4, hexapod={"driver": "recording"})
    _, result = sim_session(config, tmp_path, hooks={"stop": gone})
    assert result.status == "completed", result.message
    (driver,) = test_drivers.instances
    assert driver.calls == ["identify", "load", "start", "stop", "stop", "close"]  # each refused, then closed
    assert safe_event(result.log_path) == {
        "state": "safe", "driver": "disabled", "stream": "idle",
        "hexapod": "not confirmed: hexapod driver 'recording': stop: ConnectionResetError: peer closed"}


def test_a_lockstep_session_leaves_the_emulators_hexapod_link_alone(tmp_path: Path,
                                                                     test_drivers: type[RecordingHexapod]) -> None:
    config = session_config(duration_s=0.5, seed=6, hexapod={"driver": "recording", "pitch_deg": -1.25})
    run = run_session(config, tmp_path)
    assert run.result.status == "completed", run.result.message
    (driver,) = test_drivers.instances
    assert driver.calls == ["identify", "load", "start", "stop", "stop", "close"]
    hexapod = read_log(run.result.log_path).groups["hexapod"]
    assert float(hexapod["pitch_deg"][0]) == -1.25 and len(hexapod["pitch_deg"]) == 1
    summary = next(d for k, d in logged_events(run.result.log_path) if k == "summary")
    assert summary["cycles"] >= 500 and set(summary["link_errors"]) == {"servo", "driver", "image"}
    # the emulator's own hexapod was never loaded nor started: nothing spoke to it
    assert run.emulator["hexapod"] == {"state": "IDLE", "segments": 0}


def test_the_protocol_driver_keeps_its_state_poses_and_wind_down(tmp_path: Path) -> None:
    config = session_config(duration_s=1.5, seed=4)
    session, result = sim_session(config, tmp_path, ports_without_hexapod=False)
    assert result.status == "completed", result.message
    assert session.hexapod is not None and session.hexapod.state == "LOADED" and not session.hexapod.running
    log = read_log(result.log_path)
    ident = log.attrs["ident"]["hexapod"]
    assert ident["driver"] == "protocol" and ident["board"] == "HEXAPOD" and ident["port"] == "sim:hexapod"
    pitch = np.asarray(log.groups["hexapod"]["pitch_deg"])
    assert len(pitch) >= 150 and 0.2 < np.max(np.abs(pitch)) <= 1.0  # 100 Hz POSEs of the 1 deg swing
    events = logged_events(result.log_path)
    kinds = [d.get("state") for k, d in events if k == "state"]
    assert kinds.index("swing stopping") < kinds.index("disarmed")
    assert not [d for k, d in events if k == "info" and "hexapod" in d]  # home within the wind-down
    assert safe_event(result.log_path)["hexapod"] == "stopped"


def test_a_driver_that_hangs_cannot_keep_the_session_from_ending(tmp_path: Path, test_drivers: type[RecordingHexapod],
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    async def hang(drv: RecordingHexapod) -> None:
        await asyncio.sleep(3600)  # a vendor's TCP link gone quiet

    monkeypatch.setattr(GuardedHexapod, "CALL_TIMEOUT_S", 0.2)
    config = session_config(duration_s=0.3, seed=4, hexapod={"driver": "recording"})
    t0 = time.monotonic()
    _, result = sim_session(config, tmp_path, hooks={"stop": hang, "close": hang})
    assert time.monotonic() - t0 < 30  # two stops and a close, each given up after 0.2 s
    assert result.status == "completed", result.message
    (driver,) = test_drivers.instances
    assert driver.calls == ["identify", "load", "start", "stop", "stop", "close"]
    assert safe_event(result.log_path) == {
        "state": "safe", "driver": "disabled", "stream": "idle",
        "hexapod": "not confirmed: hexapod driver 'recording': stop: no answer within 0.2 s"}
