"""The start pose phase (docs/control.md, "The start pose"): a session starts from the pose on its encoders, the swing
and the tracking from there; logged as a phase; reproducible on lockstep and sim alike; rebuilt by the replay."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np

from hil.analysis import summarize_log
from hil.log.reader import read_log
from hil.replay import replay_log
from hil.session import run_sim_session
from tests.factories import run_session, session_config
from tests.session.helpers import logged_events

POSE = {"az_deg": -2.0, "el_deg": 6.0}


def _phase(log: Path) -> dict[str, object]:
    phases = [detail for kind, detail in logged_events(log) if kind == "phase"]
    assert len(phases) == 1, phases
    return phases[0]


def test_a_session_away_from_its_pose_goes_there_first_then_swings_and_sim_equals_lockstep(tmp_path: Path) -> None:
    config = session_config(duration_s=1.0, seed=4, start_pose=POSE, tracking={"enabled": False})
    (tmp_path / "lockstep").mkdir()
    lock = run_session(config, tmp_path / "lockstep")
    sim, _ = asyncio.run(run_sim_session(config, tmp_path / "sim"))
    assert lock.result.status == sim.status == "completed", (lock.result.message, sim.message)
    assert lock.result.log_path is not None and sim.log_path is not None
    phase = _phase(lock.result.log_path)
    assert phase == _phase(sim.log_path)
    assert phase["outcome"] == "reached" and phase["from_el_deg"] == 0.0 and phase["error_deg"] <= 0.05
    took_s = float(phase["took_s"])  # type: ignore[arg-type]
    assert 0.3 < took_s < 3.0, took_s  # 6 deg at up to 20 deg/s, then the 50 ms hold
    a, b = read_log(lock.result.log_path), read_log(sim.log_path)
    for group in ("loop", "image", "hexapod"):  # every row, the swing started mid-stream at the same tick
        assert set(a.groups[group]) == set(b.groups[group])
        for channel in set(a.groups[group]) - {"t_host_ns", "latency_us"}:
            np.testing.assert_array_equal(a.groups[group][channel], b.groups[group][channel],
                                          err_msg=f"/{group}/{channel}")
    loop, hexapod = a.groups["loop"], a.groups["hexapod"]
    end_s = float(phase["to_t_s"])  # type: ignore[arg-type]
    at_end = int(np.searchsorted(loop["t_s"], end_s))
    assert abs(loop["el_deg"][at_end] - 6.0) <= 0.05 and abs(loop["az_deg"][at_end] + 2.0) <= 0.05
    run_rows = int(np.count_nonzero(loop["t_s"] >= end_s))
    assert run_rows >= 1000  # duration_s counts from the phase's end
    # the table stood still through the phase (POSE reports exist but show home), and swung after it
    pitch = np.abs(hexapod["pitch_deg"])
    assert np.all(pitch[: int(took_s * 100) - 5] == 0.0) and pitch.max() > 0.5
    summary = summarize_log(lock.result.log_path)
    assert summary["start_pose"]["outcome"] == "reached"
    assert summary["cycles"] == len(loop["t_s"])


def test_a_pose_not_reached_in_time_ends_the_session_as_a_fault_before_anything_swings(tmp_path: Path) -> None:
    config = session_config(duration_s=1.0, seed=4, tracking={"enabled": False},
                            start_pose={**POSE, "timeout_s": 0.1})
    run = run_session(config, tmp_path)
    assert run.result.status == "fault" and run.result.exit_code == 1
    assert run.result.message.startswith("start pose not reached within 0.1 s"), run.result.message
    assert "el 6 +- 0.05 deg" in run.result.message
    assert run.result.log_path is not None
    kinds = [kind for kind, _ in logged_events(run.result.log_path)]
    states = [detail.get("state") for kind, detail in logged_events(run.result.log_path) if kind == "state"]
    assert "phase" in kinds and "swing started" not in states
    hexapod = read_log(run.result.log_path).groups["hexapod"]
    assert np.all(np.asarray(hexapod["pitch_deg"]) == 0.0) and np.all(np.asarray(hexapod["t_profile_s"]) == 0.0)


def test_the_replay_rebuilds_the_phase_and_the_run_exactly(tmp_path: Path) -> None:
    config = session_config(duration_s=1.5, seed=9, start_pose=POSE)
    run = run_session(config, tmp_path)
    assert run.result.log_path is not None and run.result.status in ("completed", "lost_target")
    result = replay_log(run.result.log_path, settle_s=0.5)
    assert result.inputs.get("command_mismatches_az", 0) == result.inputs.get("command_mismatches_el", 0) == 0
    phase = _phase(run.result.log_path)
    assert result.inputs["start_pose_rows"] > 300  # the phase's rows, replayed as the position hold
    for axis in ("el", "az"):
        assert result.axes[axis].drive_diff_max_counts == 0.0
    # the metric window starts settle_s after the phase's end
    assert abs(result.window_s[0] - (float(phase["took_s"]) + 0.5)) < 0.003, (result.window_s, phase)  # type: ignore[arg-type]
    json.dumps(result.inputs)


def test_without_a_start_pose_phase_the_swing_starts_with_the_stream(tmp_path: Path) -> None:
    config = session_config(duration_s=0.5, seed=4, start_pose={"enabled": False})
    run = run_session(config, tmp_path)
    assert run.result.status == "completed" and run.result.log_path is not None
    kinds = [kind for kind, _ in logged_events(run.result.log_path)]
    assert "phase" not in kinds
    assert len(read_log(run.result.log_path).groups["loop"]["t_s"]) >= 500
