"""The wire in the emulated lab (docs/emulator.md, "The wire"): frames take their wire time at the link's baud rate,
and a DRIVE_CMD acts when its last byte arrives, inside the tick's hold.

Realtime bounds are physical (nothing arrives before its wire time), so they hold on a loaded machine; lockstep
reports the modelled delay exactly; a sim session's rate loop loses the delay's phase at 100 Hz."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from firmware_stub.config import ConfigError, load_emulator_config
from hil.config import PROFILES
from hil.protocol import CATALOGUE, NO_LATENCY_US, DriveCmd, GyroSample, LoopTiming, wire_time_s
from hil.session import emulator_for_plant, run
from tests.factories import session_config
from tests.firmware_stub.host import Host, running_emulator
from tests.firmware_stub.test_emulator import start_session, stream

SLOW_WIRE = dict.fromkeys(("servo", "driver", "image", "hexapod"), 921_600)  # profiles/emulator/slow-wire.yaml's
SAMPLE_WIRE_US = wire_time_s(CATALOGUE.by_type[GyroSample], 921_600) * 1e6  # 423 us
COMMAND_WIRE_US = wire_time_s(CATALOGUE.by_type[DriveCmd], 921_600) * 1e6  # 206 us


def latencies_us(host: Host) -> list[int]:
    return [v for f in host["servo"].frames if isinstance(f.message, LoopTiming)
            for v in f.message.latency_us if v != NO_LATENCY_US]


# --- the emulator ------------------------------------------------------------------------------------------------


@pytest.mark.realtime
def test_realtime_commands_arrive_no_sooner_than_the_two_wire_times() -> None:
    slow = load_emulator_config(clock="realtime", baudrates=SLOW_WIRE)  # wire times a pty alone never takes
    with running_emulator(slow) as emu:
        host = Host(emu.ports(), host_alive_period_s=0.1)
        start_session(host)
        stream(host, 400)
        host.close()
        with_wire = latencies_us(host)
    with running_emulator(slow.model_copy(update={"links": slow.links.model_copy(update={"wire_time": False})})) as emu:
        host = Host(emu.ports(), host_alive_period_s=0.1)
        start_session(host)
        stream(host, 400)
        host.close()
        without = latencies_us(host)
    assert len(with_wire) > 300 and len(without) > 300
    # from the sample's first byte to the command's last: never less than both frames' wire times
    assert min(with_wire) >= int(SAMPLE_WIRE_US + COMMAND_WIRE_US)
    assert min(without) < SAMPLE_WIRE_US + COMMAND_WIRE_US  # a pty alone is faster than that


@pytest.mark.parametrize(("baud", "wire", "expected_us"), [
    (921_600, True, 666), (2_000_000, True, 327), (6_000_000, True, 134), (921_600, False, 0)])
def test_lockstep_loop_timing_reports_the_modelled_delay(baud: int, wire: bool, expected_us: int) -> None:
    config = load_emulator_config(clock="lockstep", baudrates={"servo": baud, "driver": baud})
    config = config.model_copy(update={"links": config.links.model_copy(update={"wire_time": wire})})
    with running_emulator(config) as emu:
        host = Host(emu.ports())
        start_session(host)
        stream(host, 60)
        host.close()
    got = latencies_us(host)
    assert len(got) >= 30 and set(got) == {expected_us}


def test_an_emulated_line_slower_than_its_periodic_load_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"links: servo\.baudrate: 115200 baud cannot carry"):
        load_emulator_config(baudrates={"servo": 115_200})


# --- what the wire costs a session -------------------------------------------------------------------------------


def phase_at_deg(x: np.ndarray, y: np.ndarray, freq_hz: float) -> float:
    """Phase of y against x at freq_hz (deg; negative: y lags), from one DFT bin over whole periods."""
    n = len(x) - len(x) % round(1000 / freq_hz)
    e = np.exp(-2j * np.pi * freq_hz * np.arange(n) / 1000.0)
    return float(np.degrees(np.angle(np.sum(y[:n] * e) / np.sum(x[:n] * e))))


def drive_to_gyro_phase_deg(tmp_path: Path, wire: bool, baud: int = 921_600) -> float:
    lab = emulator_for_plant(PROFILES / "plant" / "default.yaml", tmp_path, wire_time=wire)
    ports = {name: {"port": f"/dev/null-{name}", "baudrate": baud} for name in ("servo", "driver", "image", "hexapod")}
    config = session_config(duration_s=3.0, seed=4, profile=str(PROFILES / "swing" / "static.yaml"),
                            tracking={"enabled": False}, ports=ports,
                            excitation={"axis": "el", "amplitude_dps": 5.0, "freq_hz": 100.0},
                            emulator={"config": lab, "clock": "sim"})
    result = run(config, clock="sim", out=tmp_path / f"out-{wire}-{baud}")
    assert result.status == "completed", result.message
    loop = result.log.loop
    keep = slice(500, None)  # after the start
    return phase_at_deg(loop["drive_el_counts"].to_numpy(float)[keep], loop["gyro_y_dps"].to_numpy()[keep], 100.0)


def test_the_wire_costs_the_rate_loop_its_delay_in_phase_at_100_hz(tmp_path: Path) -> None:
    """drive -> gyro is the plant with the wire in front: the wire adds 360 f D of lag (24.0 deg at 921 600 baud,
    11.8 deg at 2 000 000), the rest of the plant is the same."""
    off = drive_to_gyro_phase_deg(tmp_path, wire=False)
    on = drive_to_gyro_phase_deg(tmp_path, wire=True)
    fast = drive_to_gyro_phase_deg(tmp_path, wire=True, baud=2_000_000)
    assert off - on == pytest.approx(360 * 100 * 666.3e-6, abs=1.0)
    assert off - fast == pytest.approx(360 * 100 * 327.0e-6, abs=1.0)
