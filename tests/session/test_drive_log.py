"""The driver's DRIVE_STATUS reports in the session log (/drive): its state and the currents it measured, beside the
loop that commanded them."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from firmware_stub.plant import DEFAULT_PLANT_CONFIG
from hil.analysis import summarize_log
from hil.config import PROFILES
from hil.fit.ranges import load_plant_dict
from hil.fit.twin import armature_current_a
from hil.log.reader import read_log
from hil.session import run_sim_session
from tests.factories import session_config


def test_the_logged_currents_are_those_the_logged_drive_makes(tmp_path: Path) -> None:
    """Under a 3 deg swing, each report's current is ``(u V_count - K_e w) / R`` of the loop row of the command it
    names (``last_tick``), from the logged drive and encoder rate and the plant file's motor: measured within
    0.4 % rms of the current; one row off, 3.5-4 %."""
    config = session_config(duration_s=3.0, seed=3, profile=str(PROFILES / "swing" / "swing-3deg-1hz.yaml"))
    result, _ = asyncio.run(run_sim_session(config, tmp_path))
    log = read_log(result.log_path)
    drive, loop = log.groups["drive"], log.groups["loop"]
    assert drive["az_current_a"].dtype == np.float32 and log.units["drive"]["az_current_a"] == "A"
    enabled = np.asarray(drive["enabled"]) == 3
    assert enabled.sum() >= 290  # 100 Hz over the 3 s the loop drove both axes
    assert not np.any(np.asarray(drive["faults"])) and np.all(np.asarray(drive["bus_voltage_v"]) > 0)
    plant = load_plant_dict(DEFAULT_PLANT_CONFIG)
    rows = np.searchsorted(np.asarray(loop["tick"]), np.asarray(drive["last_tick"]))
    ok = enabled & (rows > 0) & (rows < loop["tick"].size - 1)
    for axis in ("az", "el"):
        rate_dps = np.degrees(np.gradient(np.unwrap(np.radians(np.asarray(loop[f"{axis}_deg"]))))) / 1e-3
        made = armature_current_a(np.asarray(loop[f"drive_{axis}_counts"], float), rate_dps, plant[f"motor_{axis}"])
        measured = np.asarray(drive[f"{axis}_current_a"])[ok]
        rms = float(np.sqrt(np.mean(measured ** 2)))
        assert rms > 0.5, (axis, rms)  # the swing takes amperes
        assert float(np.sqrt(np.mean((made[rows[ok]] - measured) ** 2))) < 0.015 * rms, axis
        assert float(np.sqrt(np.mean((made[rows[ok] + 1] - measured) ** 2))) > 0.02 * rms, axis
    # the session's summary: the currents over the run (the first settle_s and the wind-down left out)
    summary = summarize_log(result.log_path)
    t_s = np.asarray(loop["t_s"]) - summary["run_from_t_s"]  # from the start pose phase's end
    in_run = (t_s >= summary["settle_s"]) & (t_s < 3.0)
    reports = in_run[np.searchsorted(np.asarray(loop["tick"]), np.asarray(drive["loop_tick"]))] & enabled
    assert 190 <= reports.sum() <= 201  # 100 Hz over the 2 s after the settle
    for axis in ("az", "el"):
        amps = np.abs(np.asarray(drive[f"{axis}_current_a"], dtype=float)[reports])
        got = summary[f"motor_current_{axis}_a"]
        assert got["rms"] == pytest.approx(np.sqrt(np.mean(amps ** 2)), rel=1e-9) and got["rms"] > 0.5
        assert got["peak"] == pytest.approx(amps.max(), rel=1e-9) and got["peak"] > got["rms"]
