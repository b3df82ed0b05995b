"""How the sweep's FRF estimator reads the plant (hil.fit.twin.sweep_reading): Welch's segments cut a chirp's
response, so the estimate of an exactly linear, noise-free plant is off near a lightly damped mode; the fit divides
that reading out before it compares the kernel's response (docs/fit.md, "What the estimator reads")."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hil.fit.logs import load_fit_log
from hil.fit.ranges import dump_plant, k_m_of
from hil.fit.record import record, recording_plan, session_on_plant
from hil.fit.twin import fit_frequency_response, lab_wire_delay_s, linear_frf, sweep_reading
from tests.fit.helpers import drawn_plant


def _linear(plant: dict) -> dict:
    """``plant`` made linear and noise-free: viscous friction only, no cable, imbalance, ripple or reachable current
    limit, no gyro noise or quantisation."""
    c = {k: v for k, v in plant.items() if k not in ("cable", "ripple")}
    c["friction"] = {ax: {"coulomb_n_m": 0.0, "model": "tanh", "smoothing_rate_dps": 0.1,
                          "viscous_n_m_s_per_rad": fr["viscous_n_m_s_per_rad"]} for ax, fr in c["friction"].items()}
    c["imbalance"] = {**c["imbalance"], "mass_kg": 0.0}
    c["drive"] = {ax: {**d, "current_limit_a": 20.0} for ax, d in c["drive"].items()}
    c["gyro"] = {**c["gyro"], "noise_std_dps": [0.0] * 3, "noise_psd": [], "random_walk": 0.0,
                 "quantisation_lsb_dps": 0.0}
    return c


@pytest.mark.slow
def test_a_linear_noise_free_plant_is_fitted_exactly_once_the_estimators_reading_is_divided_out(
        tmp_path: Path) -> None:
    """Hidden plant 54 made linear and noise-free, its default levelled elevation sweep (a 190 Hz mode damped at
    4.5 %, inside the band), fitted with that plant as the prior. The estimator reads it 0.3 dB low near the mode;
    with that reading divided out, k_m, the gyro's pole and the total loop delay come back exactly (measured: the
    total delay -0.1 us, +3.1 us before)."""
    hidden, _ = drawn_plant(54, tmp_path)
    plant = _linear(hidden)
    path = dump_plant(plant, tmp_path / "linear.yaml", "draw_plant(54), linear and noise-free")
    base = session_on_plant(path, tmp_path, name="p54-linear", swing=None)
    log = load_fit_log(record([r for r in recording_plan(base) if r.name == "fit-ident-el"], loopback=True)[0])
    wire_s = lab_wire_delay_s([log])
    g = plant["gyro"]

    lin = linear_frf(log, motor=plant["motor_el"])
    reading_db = 20 * np.log10(np.abs(sweep_reading(plant, "el", lin, drive_delay_s=wire_s)))
    f = lin.frf.freq_hz
    near_mode = (f > 170.0) & (f < 210.0) & (lin.frf.coherence >= 0.8)
    away = (f > 40.0) & (f < 120.0) & (lin.frf.coherence >= 0.8)
    assert near_mode.any() and away.any()
    assert np.max(np.abs(reading_db[near_mode])) > 0.2
    assert np.max(np.abs(reading_db[away])) < 0.1

    fit = fit_frequency_response(log, prior=plant, spring_q=0.0, drive_delay_s=wire_s)
    total_error_us = (1 / (2 * math.pi * fit.bandwidth_hz) + fit.delay_s
                      - 1 / (2 * math.pi * g["bandwidth_hz"]) - g["delay_s"] - wire_s) * 1e6
    assert abs(fit.k_m / k_m_of(plant, "el") - 1.0) < 0.001
    assert abs(fit.bandwidth_hz / g["bandwidth_hz"] - 1.0) < 0.01
    assert abs(total_error_us) < 1.0
