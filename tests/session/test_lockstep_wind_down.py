"""Lockstep is reproducible to the last row, the wind-down included; the sim clock gives the same whole log.

After the session's duration the bench stops the swing, keeps stabilizing until the hexapod rests, then disarms.
The rows logged meanwhile used to depend on when the host got round to each step (a HEXAPOD_STOP racing the world's
step, the disarm when the event loop noticed the hexapod home): two runs of one seed ended 2500 and 2501 rows long.
Every log group is compared here over the whole log, the host's own clock aside (hil.session.TickWindDown).
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.config import PROFILES
from hil.log.reader import read_log
from hil.session import run_sim_session
from tests.factories import Run, run_session, session_config
from tests.session.helpers import HOST_CLOCK

DURATION_S = 1.5  # then the wind-down: the default emulator ramps the swing home over 1 s
TICKS = round(DURATION_S * 1000)
SEED = 6
SUMMARY_WALL_CLOCK = {"late", "latency_us_p50", "latency_us_p99", "host_stalls"}  # the host's clock in the summary


def _config(profile: str = "swing-1deg-1hz") -> Any:
    return session_config(duration_s=DURATION_S, seed=SEED, profile=str(PROFILES / "swing" / f"{profile}.yaml"))


def _lockstep(out: Path, profile: str = "swing-1deg-1hz") -> Run:
    out.mkdir(parents=True)
    run = run_session(_config(profile), out)
    assert run.result.status == "completed", run.result.message
    assert run.emulator["lockstep_timeouts"] == 0  # the world waited for every answer: the same commands
    return run


def _events(log: Any) -> list[tuple[int, str, dict[str, Any]]]:
    """(tick, kind, detail) of every event, the summary without its wall-clock figures."""
    ev = log.groups["events"]
    out = []
    for tick, kind, detail in zip(ev["tick"], ev["kind"], ev["detail"], strict=True):
        text = detail.decode() if isinstance(detail, bytes) else str(detail)
        try:
            d = json.loads(text)
        except json.JSONDecodeError:  # a detail cut at the log's detail length: compared as its text
            d = {"text": text}
        k = kind.decode() if isinstance(kind, bytes) else str(kind)
        if k == "summary":
            d = {key: v for key, v in d.items() if key not in SUMMARY_WALL_CLOCK}
        out.append((int(tick), k, d))
    return out


def assert_same_logs(a: Path, b: Path) -> dict[str, int]:
    """Every group of two logs: the same number of rows, every value equal but the host's clock (the frames of the
    other boards are handled before the tick's sample in lockstep as in sim: LOCKSTEP_ACK). Returns each group's
    row count."""
    la, lb = read_log(a), read_log(b)
    assert set(la.groups) == set(lb.groups)
    rows = {}
    for group in la.groups:
        ga, gb = la.groups[group], lb.groups[group]
        assert set(ga) == set(gb), group
        if group == "events":  # compared as events first: a difference reads as the events that differ
            assert _events(la) == _events(lb)
        na, nb = {len(v) for v in ga.values()}, {len(v) for v in gb.values()}
        assert na == nb and len(na) == 1, (group, na, nb)
        rows[group] = na.pop()
        if group == "events":
            continue
        for channel in sorted(set(ga) - HOST_CLOCK):
            x, y = np.asarray(ga[channel]), np.asarray(gb[channel])
            np.testing.assert_array_equal(x, y, err_msg=f"/{group}/{channel}")
    return rows


@pytest.mark.slow
def test_two_lockstep_runs_give_the_same_whole_log_wind_down_included(tmp_path: Path) -> None:
    a, b = _lockstep(tmp_path / "a"), _lockstep(tmp_path / "b")
    rows = assert_same_logs(a.result.log_path, b.result.log_path)
    assert rows["loop"] > TICKS + 900  # the wind-down is in the comparison: the swing's 1 s ramp home
    log = read_log(a.result.log_path)
    states = [d.get("state") for _, k, d in _events(log) if k == "state"]
    assert states[-3:] == ["swing stopping", "disarmed", "safe"], states
    pitch = log.groups["hexapod"]["pitch_deg"]
    assert np.abs(pitch[: TICKS // 10]).max() > 0.5 and abs(pitch[-1]) < 1e-3  # logged until the table rests
    drive = log.groups["loop"]["drive_el_counts"]
    assert drive[-1] == 0 and np.count_nonzero(drive[-100:-1]) > 90  # stabilized to the end; the last unanswered


@pytest.mark.slow
def test_two_lockstep_runs_without_a_swing_end_on_the_same_row(tmp_path: Path) -> None:
    a, b = _lockstep(tmp_path / "a", "static"), _lockstep(tmp_path / "b", "static")
    rows = assert_same_logs(a.result.log_path, b.result.log_path)
    hold = 50  # the start pose phase at the pose from its first sample: its 50 ms hold (the 51st runs)
    assert rows["loop"] == hold + TICKS + 1  # the phase, the session's samples, then one unanswered


@pytest.mark.parametrize("profile", ["swing-1deg-1hz", "static"])
def test_a_sim_log_equals_a_lockstep_log_to_the_last_row(tmp_path: Path, profile: str) -> None:
    lock = _lockstep(tmp_path / "lockstep", profile)
    sim, emulator = asyncio.run(run_sim_session(_config(profile), tmp_path / "sim"))
    assert sim.status == "completed", sim.message
    assert emulator["unanswered_samples"] == 0  # the sim world stopped where lockstep's waited
    rows = assert_same_logs(lock.result.log_path, sim.log_path)
    assert rows["loop"] > TICKS
