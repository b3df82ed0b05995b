"""Recovery restores the whole session: a bench frozen long enough for the boards to protect themselves (the hexapod
parks at home) comes back, re-arms, and puts the swing back where the profile would be now; the span the table did
not swing is an event and is left out of the summary (docs/reliability.md, "Faults")."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hil.analysis import summarize_log
from hil.log import LogError, read_log
from tests.factories import session_data, write_yaml
from tests.session.helpers import logged_events

REPO = Path(__file__).resolve().parents[2]
FREEZE_S = 2.0  # four times the boards' host timeout
HOST_TIMEOUT_S = 0.5  # profiles/emulator/default.yaml
# long enough that the freeze lands mid-swing even when the log the test watches runs seconds behind the session
# (a busy machine starves the log's writer: a freeze meant for profile time 2 s once landed at 8.8 s)
DURATION_S = 16.0


def profile_time_logged(log_path: Path) -> float:
    """The hexapod's latest profile time in a log being written (0 before the first POSE, or while the file is
    still being laid out and cannot be opened yet)."""
    try:
        t = np.asarray(read_log(log_path).groups["hexapod"]["t_profile_s"], dtype=float)
    except LogError:
        return 0.0
    return float(t.max()) if t.size else 0.0


@pytest.mark.slow
def test_a_bench_frozen_past_the_host_timeout_resumes_the_swing_at_the_profile_s_time(tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    session = write_yaml(tmp_path / "s.yaml", session_data(
        name="frozen", duration_s=DURATION_S, logging={"dir": str(logs)},
        safety={"watchdog_ms": 5, "on_fault": "recover", "emulator_stall_grace_ms": 500, "max_recoveries": 10}))
    bench = subprocess.Popen([sys.executable, "-m", "hil", "run", str(session), "--loopback", "--json"], cwd=REPO,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        give_up = time.monotonic() + 60
        while not list(logs.glob("*.h5")):
            assert bench.poll() is None, bench.communicate()
            assert time.monotonic() < give_up, "the session never started"
            time.sleep(0.05)
        while profile_time_logged(next(logs.glob("*.h5"))) < 2.0:  # swinging (the 1 s ramp-in is over)
            assert bench.poll() is None, bench.communicate()
            assert time.monotonic() < give_up, "the swing never started"
            time.sleep(0.1)
        os.kill(bench.pid, signal.SIGSTOP)
        time.sleep(FREEZE_S)
        os.kill(bench.pid, signal.SIGCONT)
        out, err = bench.communicate(timeout=120)
    finally:
        if bench.poll() is None:
            os.kill(bench.pid, signal.SIGCONT)
            bench.kill()
            bench.wait()
    result = json.loads(out)
    assert bench.returncode == 0 and result["status"] == "completed", (result["message"], err)
    log_path = Path(result["log"])
    events = logged_events(log_path)
    gaps = [d for k, d in events if k == "swing_gap"]
    assert gaps and all(g["to_t_s"] is not None for g in gaps), events
    assert any(k == "recovered" for k, _ in events)
    # the table swings again after the gap, on the profile's own clock: pitch = 1 deg sin(2 pi t) once the
    # resumed segment has ramped in again (1 s), with t the original profile's time
    pose = read_log(log_path).groups["hexapod"]
    t_profile = np.asarray(pose["t_profile_s"], dtype=float)
    pitch = np.asarray(pose["pitch_deg"], dtype=float)
    # the freeze's gap is the longest; on a busy machine the 5 ms watchdog may add short ones, whose ramps are
    # left out of the comparison (each resumed segment ramps in again over 1 s)
    freeze = max(gaps, key=lambda g: g["to_t_s"] - g["from_t_s"])
    resumed_at = freeze["profile_s"]
    after = (t_profile > resumed_at + 1.2) & (t_profile < DURATION_S - 0.5)
    for g in gaps:
        after &= ~((t_profile > g["profile_s"] - (g["to_t_s"] - g["from_t_s"]) - 0.05)
                   & (t_profile < g["profile_s"] + 1.2))
    assert np.count_nonzero(after) > 100, (resumed_at, t_profile[-5:])
    expected = np.sin(2 * math.pi * t_profile[after])
    assert np.max(np.abs(pitch[after] - expected)) < 0.02, np.max(np.abs(pitch[after] - expected))
    # the profile resumed where it would have been: as far along as the servo board's clock went since the swing
    # started (the emulator's world waits while its ptys are full, so its clock ran on only part of the freeze)
    loop_t = np.asarray(read_log(log_path).groups["loop"]["t_s"], dtype=float)
    for gap in gaps:
        assert gap["from_t_s"] - loop_t[0] - 0.5 < gap["profile_s"] <= gap["to_t_s"] - loop_t[0] + 0.01, gap
    # the summary leaves the span out and says so: at least the boards' host timeout (the hexapod parks only then)
    summary = summarize_log(log_path)
    spans = sum(g["to_t_s"] - g["from_t_s"] for g in gaps)
    assert HOST_TIMEOUT_S <= summary["swing_gap_s"] <= spans + 0.002, (summary["swing_gaps"], spans)
    assert result["swing_gap_s"] == summary["swing_gap_s"]
