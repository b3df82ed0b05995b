"""The session sequence of docs/protocol.md section 6.3, as the emulated boards saw it, and TRACK_CMD's gate."""

from __future__ import annotations

from pathlib import Path

import pytest

from firmware_stub.config import load_emulator_config
from firmware_stub.emulator import Emulator
from hil.protocol import MissDistance
from tests.factories import run_session, session_config


@pytest.mark.slow
def test_the_bench_follows_the_documented_session_sequence(tmp_path: Path) -> None:
    run = run_session(session_config(duration_s=0.5, seed=2), tmp_path)
    assert run.result.status == "completed", run.result.message
    steps = []
    for r in run.records:
        kind, detail = r["kind"], r.get("detail", {})
        if kind == "hexapod_state":
            steps.append(f"hexapod {detail['state']}")
        elif kind in ("drive_enable", "drive_disable"):
            steps.append(kind)
        elif kind == "servo_stream":
            steps.append("stream on" if detail["streaming"] else "stream off")
    # 4. profile upload (LOADED) before 5. enable; 6. STREAM, the start pose phase, then START; 7. wind-down: STOP
    # while the loop runs, the bench waits for the ramp; 8. disarm: DRIVE_DISABLE at once and again acknowledged,
    # then (the swing already home) the stream
    assert steps == ["hexapod LOADED", "drive_enable", "stream on", "hexapod RUNNING", "hexapod STOPPING",
                     "hexapod LOADED", "drive_disable", "drive_disable", "stream off"], steps
    (tmp_path / "unposed").mkdir()
    unposed = run_session(session_config(duration_s=0.5, seed=2, start_pose={"enabled": False}), tmp_path / "unposed")
    assert [f"hexapod {r['detail']['state']}" if r["kind"] == "hexapod_state" else r["kind"]
            for r in unposed.records if r["kind"] in ("hexapod_state", "servo_stream")][:3] == [
        "hexapod LOADED", "hexapod RUNNING", "servo_stream"]  # without the phase: START, then STREAM
    disable = next(r for r in run.records if r["kind"] == "drive_disable")
    assert disable["detail"]["cause"] == "host"


def test_track_cmd_gate_0_is_the_whole_field_and_a_gate_invalidates_what_lies_outside() -> None:
    emu = Emulator(load_emulator_config())
    try:
        sent: list[MissDistance] = []
        emu.image.send = lambda m: sent.append(m) or True  # type: ignore[method-assign]
        emu.plant.miss_px = lambda: (50.0, -3.0, True)  # type: ignore[method-assign]
        emu.image.tracking = True
        for gate_px, valid in ((0, True), (60, True), (40, False)):
            emu.image.gate_px = gate_px
            emu.image.pipeline.clear()  # frames of the previous setting still in the camera's latency
            sent.clear()
            for tick in range(0, 200, emu.image.period_ticks):
                emu.image.on_tick(tick)
            frames = [m for m in sent if isinstance(m, MissDistance)]
            assert len(frames) >= 10
            assert all(f.track_valid == valid for f in frames), (gate_px, frames[-1])
            assert all((f.miss_x_px, f.miss_y_px) == ((50.0, -3.0) if valid else (0.0, 0.0)) for f in frames)
    finally:
        emu.close()
