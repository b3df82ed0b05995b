"""The FRF fit reads only what the loop passed through linearly (hil.fit.twin.nonlinear_bins): a third octave whose
drive sat at its limit, or whose axis turned against the sweep's offset, is left out; an ident log with no linear
stretch below 50 Hz gives no k_m, and the fit keeps the prior and says what to record instead."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from firmware_stub.plant import DEFAULT_PLANT_CONFIG
from hil.analysis import SweptSine
from hil.fit.logs import load_fit_log
from hil.fit.ranges import draw_plant, dump_plant, get_param, load_plant_dict
from hil.fit.record import record, recording_plan, session_on_plant
from hil.fit.twin import LINEAR_LOW_HZ, fit_frequency_response, fit_logs, lab_wire_delay_s, nonlinear_bins
from tests.fit.helpers import SLOW_WIRE_BAUD

DT_S = 1e-3
SWEEP = SweptSine(f_start_hz=1.0, f_stop_hz=450.0, duration_s=8.0, amplitude_dps=1.5, axis="el", offset_dps=3.0)


def _sweep_log(k0: int = 200) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ticks, the chirp's frequency at each, a drive well inside its limit and a rate that never turns back."""
    n = k0 + round(SWEEP.total_s / DT_S)
    k = np.arange(n)
    f_t = np.array([SWEEP.frequency_hz((i - k0) * DT_S) for i in k])
    u = 1000.0 * np.sin(2 * np.pi * 3.0 * k * DT_S)
    y = 3.0 + 1.5 * np.sin(2 * np.pi * 5.0 * k * DT_S)
    return f_t, u, y


def test_the_third_octaves_where_the_drive_clipped_or_the_axis_reversed_are_left_out() -> None:
    f_t, u, y = _sweep_log()
    bins = np.array([2.0, 7.0, 7.5, 20.0, 100.0, 300.0])
    assert not nonlinear_bins(bins, SWEEP, u, y, DT_S, 200, 30000.0).any()
    clipped = u.copy()
    clipped[(f_t > 6.5) & (f_t < 8.0)] = 30000.0  # the drive at its limit while the chirp crossed 6.5-8 Hz
    assert list(nonlinear_bins(bins, SWEEP, clipped, y, DT_S, 200, 30000.0)) == [False, True, True, False,
                                                                                     False, False]
    few = u.copy()  # under 1 % of a third octave's ticks at the limit: a glancing touch, kept
    few[np.flatnonzero((f_t > 95.0) & (f_t < 105.0))[:1]] = 30000.0
    assert not nonlinear_bins(bins, SWEEP, few, y, DT_S, 200, 30000.0).any()
    turned = y.copy()  # the rate went against the 3 deg/s offset for 20 ms while the chirp was near 20 Hz
    at = np.flatnonzero(f_t >= 20.0)[0]
    turned[at:at + 20] = -0.5
    got = nonlinear_bins(bins, SWEEP, u, turned, DT_S, 200, 30000.0)
    assert list(got) == [False, False, False, True, False, False]


@pytest.mark.slow
def test_an_ident_log_without_a_linear_low_band_keeps_the_prior_and_says_what_to_record(tmp_path: Path) -> None:
    base = session_on_plant(DEFAULT_PLANT_CONFIG, tmp_path, name="clip", swing=None)
    log = record([r for r in recording_plan(base) if r.name == "fit-ident-el"], loopback=True, level=False)[0]
    fit = fit_logs([log])
    good = fit.estimate("motor_el.k_m_dps2_per_count")
    assert good is not None and good.status == "fitted"
    with h5py.File(log, "a") as f:  # the drive at its limit through the sweep's first 4.5 s (1-31 Hz)
        drive = f["loop"]["drive_el_counts"]
        d = drive[...]
        rate_cmd = f["loop"]["rate_cmd_el_dps"][...]
        start = int(np.flatnonzero(np.abs(rate_cmd) > 0)[0])
        d[start:start + 5000] = np.where(np.arange(5000) % 2 == 0, 30000, -30000)
        drive[...] = d
    fit = fit_logs([log])
    e = fit.estimate("motor_el.k_m_dps2_per_count")
    assert e is not None and e.status == "prior" and e.value == pytest.approx(good.prior)
    assert f"not linear below {LINEAR_LOW_HZ:g} Hz" in e.note and "PI + LPF" in e.note and "axis=el" in e.note
    mode = fit.estimate("structure.el.mode_hz")
    assert mode is not None and mode.status == "prior" and "not linear" in mode.source


@pytest.mark.slow
def test_an_ident_sweep_the_eso_cannot_pass_linearly_is_recorded_again_with_pi_lpf(tmp_path: Path) -> None:
    """Hidden plant 15's azimuth (k_m 0.045, twice the ESO's b0): its ESO loop clips the drive through the sweep,
    so `hil fit --record` records that sweep again with PI + LPF, and the log it keeps gives k_m within 5 %."""
    plant, _ = draw_plant(15, load_plant_dict(DEFAULT_PLANT_CONFIG))
    path = dump_plant(plant, tmp_path / "hidden-15.yaml", "hidden plant 15")
    base = session_on_plant(path, tmp_path, name="p15", swing=None, baudrate=SLOW_WIRE_BAUD)  # the slow-wire lab
    said: list[str] = []
    log = record([r for r in recording_plan(base) if r.name == "fit-ident-az"], loopback=True, level=False,
                 progress=said.append)[0]
    assert any("not linear where k_m shows; again with pi_lpf" in s for s in said), said
    fit_log = load_fit_log(log)
    assert fit_log.config["controller"]["name"] == "pi_lpf"
    got = fit_frequency_response(fit_log, prior=plant, drive_delay_s=lab_wire_delay_s([fit_log]))
    assert got.k_m == pytest.approx(get_param(plant, "motor_az.k_m_dps2_per_count"), rel=0.05)
