"""The motor's torque ripple in an ident sweep's frequency response (hil.fit.twin.drive_with_ripple): the torque is
``K_t i (1 + a sin(N th_m))``, so over a sweep that turns the axis a few ripple periods the loop's gain wanders by
``+-a``; the FRF takes the drive whose torque the motor made (docs/fit.md, "The motor's torque ripple")."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from firmware_stub.plant import Plant, PlantConfig
from hil.fit.logs import load_fit_log
from hil.fit.record import record, recording_plan, session_on_plant
from hil.fit.twin import drive_with_ripple, fit_frequency_response, lab_wire_delay_s, sweep_spring_q
from tests.fit.helpers import drawn_plant


def _linear_elevation(plant: dict) -> dict:
    """``plant`` with the elevation's friction viscous only, no cable, imbalance, current limit or gyro noise: what is
    left besides the ripple is linear."""
    c = {k: v for k, v in plant.items() if k not in ("cable", "drive")}
    c["friction"] = {**c["friction"], "el": {"coulomb_n_m": 0.0, "model": "tanh", "smoothing_rate_dps": 0.1,
                                             "viscous_n_m_s_per_rad": c["friction"]["el"]["viscous_n_m_s_per_rad"]}}
    c["imbalance"] = {**c["imbalance"], "mass_kg": 0.0}
    c["gyro"] = {**c["gyro"], "noise_std_dps": [0.0] * 3, "noise_psd": [], "random_walk": 0.0,
                 "quantisation_lsb_dps": 0.0}
    return c


def test_the_drive_with_ripple_moves_a_ripple_free_plant_as_the_ripple_moved_the_plant(tmp_path: Path) -> None:
    """Hidden plant 54's elevation (a = 2 %, N = 48), its nonlinear parts off, driven to ~40 deg/s (five ripple
    periods in 2 s) with a 37 Hz wobble on top: the same plant without the ripple, driven by the drive with the ripple
    taken in (from the first run's encoder and gyro), follows the first run's gyro within a few % of what the
    ripple does to it; driven by the commanded drive, it misses by all of it."""
    hidden, _ = drawn_plant(54, tmp_path)
    rippled = _linear_elevation(hidden)
    ripple = rippled["ripple"]["el"]
    assert ripple["amplitude_fraction"] > 0.01
    smooth = {k: v for k, v in rippled.items() if k != "ripple"}
    n = 2000
    t_s = np.arange(n) * 1e-3
    u_counts = 3000.0 + 1500.0 * np.sin(2 * math.pi * 37.0 * t_s)
    zero, carrier = np.zeros(n), np.zeros((n, 18))
    out = Plant(PlantConfig.model_validate(rippled), seed=1).run(zero, u_counts, carrier,
                                                                 outputs=["gyro_y_dps", "encoder_el_deg"])
    assert out["gyro_y_dps"][-1] > 30.0  # the axis turned through several ripple periods
    # the drive over tick k follows the encoder and gyro read at the end of tick k - 1
    angle_deg = np.concatenate([[hidden["initial_el_deg"]], out["encoder_el_deg"][:-1]])
    rate_dps = np.concatenate([[0.0], out["gyro_y_dps"][:-1]])
    taken_in = drive_with_ripple(u_counts, rate_dps, angle_deg, hidden["motor_el"], ripple)
    assert not np.allclose(taken_in, u_counts)

    def miss(u: np.ndarray) -> float:
        y = Plant(PlantConfig.model_validate(smooth), seed=1).run(zero, u, carrier, outputs=["gyro_y_dps"])
        return float(np.sqrt(np.mean((y["gyro_y_dps"] - out["gyro_y_dps"]) ** 2)))

    commanded, received = miss(u_counts), miss(taken_in)
    assert commanded > 0.05  # deg/s: what the ripple does to the rate
    assert received < 0.05 * commanded


@pytest.mark.slow
def test_the_ripple_taken_in_takes_its_bias_out_of_the_loop_delay(tmp_path: Path) -> None:
    """Hidden plant 54's default levelled elevation sweep (sim clock, session seed 1), fitted with the hidden plant
    itself as the prior, once with the ripple taken into the drive and once without (the prior's ripple removed).
    Read without it, the gyro's total delay (1 / 2 pi bandwidth + delay) is ~4 us longer: over nine session seeds
    the shift was -4.4 +- 0.3 us (docs/fit.md)."""
    hidden, path = drawn_plant(54, tmp_path)
    base = session_on_plant(path, tmp_path, name="p54", swing=None)
    log = load_fit_log(record([r for r in recording_plan(base) if r.name == "fit-ident-el"], loopback=True)[0])
    wire_s = lab_wire_delay_s([log])
    limit_a = hidden["drive"]["el"]["current_limit_a"]
    q = sweep_spring_q(hidden, "el", [log])

    def total_s(prior: dict) -> float:
        f = fit_frequency_response(log, prior=prior, spring_q=q, drive_delay_s=wire_s, current_limit_a=limit_a)
        return 1.0 / (2 * math.pi * f.bandwidth_hz) + f.delay_s

    shift_us = (total_s({k: v for k, v in hidden.items() if k != "ripple"}) - total_s(hidden)) * 1e6
    assert 3.0 < shift_us < 6.0
