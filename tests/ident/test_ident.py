"""Frequency-sweep identification (hil.analysis): the chirp, the indirect closed-loop FRF, the fit, session logs.

A synthetic loop (k_m/s under a zero-order hold, first-order gyro at 200 Hz, 0.5 ms delay, white gyro noise, P
controller) checks the estimator and the fit against known values; the emulated plant (firmware_stub.plant) under a
registry controller checks the whole chain, through a real session log, against the plant's configured k_m.
"""

from __future__ import annotations

import inspect
import math
import time
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from firmware_stub.plant import RIGID_PLANT_CONFIG, CarrierMotion, Plant, load_plant_config
from hil.analysis import (
    Frf,
    PlantFit,
    SweptSine,
    bode_plot,
    estimate_frf,
    fit_caption,
    fit_plant,
    identify_log,
    plant_response,
    welch_layout,
)
from hil.control.registry import build_controller
from hil.log import SCHEMA, LogData, SessionLog, read_log
from hil.log.schema import group_by_name

DT = 1e-3
K_M = 0.023
LOOP_CHANNELS = [c.name for c in group_by_name(SCHEMA)["loop"].channels]


# --- (a) the chirp ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["log", "linear"])
def test_sweep_frequency_at_start_middle_and_end(kind: str) -> None:
    sw = SweptSine(f_start_hz=2.0, f_stop_hz=300.0, duration_s=2.0, kind=kind, settle_s=0.5, taper_s=0.2)
    t0, t1 = sw.window_s
    assert (t0, t1) == (0.5, 2.5)
    assert sw.frequency_hz(t0) == pytest.approx(2.0)
    assert sw.frequency_hz(t1) == pytest.approx(300.0)
    mid = math.sqrt(2.0 * 300.0) if kind == "log" else 151.0
    assert sw.frequency_hz(0.5 * (t0 + t1)) == pytest.approx(mid)
    assert sw.frequency_hz(0.0) == 2.0 and sw.frequency_hz(9.0) == pytest.approx(300.0)
    # the signal does what frequency_hz says: zero crossings since the start = 2 x the integral of the frequency
    t = np.arange(t0, t1, 1e-5)
    x = np.array([sw.rate_dps(v) for v in t.tolist()])
    crossings = np.cumsum(np.signbit(x[1:]) != np.signbit(x[:-1]))
    f = np.array([sw.frequency_hz(v) for v in t[1:].tolist()])
    cycles = np.cumsum(f) * 1e-5
    for i in np.linspace(1000, t.size - 2, 25).astype(int):
        assert abs(crossings[i] - 2.0 * cycles[i]) <= 1.5, (t[i], crossings[i], 2.0 * cycles[i])
    # the last 5 ms: 300 Hz
    last = t[1:] > t1 - 0.005
    assert np.count_nonzero(np.diff(crossings[last])) == pytest.approx(2 * 300 * 0.005, abs=1)


@pytest.mark.parametrize("offset", [0.0, 5.0])
def test_sweep_is_continuous_bounded_and_starts_and_ends_at_zero(offset: float) -> None:
    sw = SweptSine(f_start_hz=0.5, f_stop_hz=300.0, duration_s=2.0, amplitude_dps=2.0, offset_dps=offset)
    h = 1e-5
    t = np.arange(-0.01, sw.total_s + 0.01, h)
    x = np.array([sw.rate_dps(v) for v in t.tolist()])
    assert np.all(x[t <= 0.0] == 0.0)
    assert np.all(x[t >= sw.total_s] == 0.0)
    if offset == 0.0:
        assert np.all(x[t <= sw.settle_s] == 0.0)
        assert np.all(x[t >= sw.window_s[1]] == 0.0)
    assert np.max(np.abs(x - offset)) <= 2.0 + offset + 1e-12  # never beyond the amplitude (plus the offset)
    assert np.max(np.abs(x[(t > sw.settle_s) & (t < sw.window_s[1])] - offset)) <= 2.0 + 1e-12
    assert np.max(np.abs(x)) > 1.99 + offset
    # continuous: no step larger than the steepest slope allows
    slope = 2.0 * (2.0 * math.pi * 300.0 + math.pi / sw.taper_s) + offset * math.pi / (2.0 * sw.settle_s)
    assert np.max(np.abs(np.diff(x))) <= slope * h * 1.01
    assert sw(1.234) == sw.rate_dps(1.234)


def test_sweep_hot_path_is_plain_float_math() -> None:
    sw = SweptSine()
    assert type(sw.rate_dps(3.21)) is float
    assert type(sw.rate_dps(0.0)) is float
    src = inspect.getsource(SweptSine.rate_dps)
    assert "np." not in src and "numpy" not in src
    n = 20000
    t0 = time.perf_counter()
    for k in range(n):
        sw.rate_dps(k * 1e-3)
    per_call = (time.perf_counter() - t0) / n
    assert per_call < 20e-6, f"{per_call * 1e6:.1f} us per call"


def test_sweep_config_is_strict() -> None:
    with pytest.raises(ValidationError):
        SweptSine(f_start=1.0)  # type: ignore[call-arg]
    with pytest.raises(ValidationError):
        SweptSine(kind="sine")  # type: ignore[arg-type]
    with pytest.raises(ValidationError):
        SweptSine(f_start_hz=5.0, f_stop_hz=5.0)
    with pytest.raises(ValidationError):
        SweptSine(duration_s=0.1, taper_s=0.1)
    assert SweptSine().axis == "el"
    assert SweptSine.model_validate({"axis": "az", "kind": "linear"}).kind == "linear"


# --- (b), (c) a synthetic loop with known parameters -------------------------------------------------------------


def simulate_loop(
    sweep: SweptSine,
    *,
    noise_dps: float,
    kp: float = 3000.0,
    bandwidth_hz: float = 200.0,
    delay_s: float = 0.5e-3,
    seed: int = 1,
    n_sub: int = 10,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """u_k = kp (r_k - y_k) held over each 1 ms tick on k_m / s; the gyro (first-order, delayed) is integrated at
    dt / n_sub and sampled at the ticks, white noise added. Returns r, u, y per tick."""
    h = DT / n_sub
    a = math.exp(-2.0 * math.pi * bandwidth_hz * h)
    nd = round(delay_s / h)
    ring = [0.0] * (nd + 1)  # ring[j] is the gyro output nd sub-steps ago
    n = round(sweep.total_s / DT)
    noise = np.random.default_rng(seed).normal(0.0, noise_dps, n).tolist()
    r_out, u_out, y_out = np.empty(n), np.empty(n), np.empty(n)
    x = g = 0.0
    j = 0
    for k in range(n):
        y = ring[j] + noise[k]
        r = sweep.rate_dps(k * DT)
        u = kp * (r - y)
        r_out[k], u_out[k], y_out[k] = r, u, y
        for _ in range(n_sub):
            x_old = x
            x += K_M * h * u
            g = a * g + (1.0 - a) * 0.5 * (x + x_old)
            j = (j + 1) % (nd + 1)
            ring[j - 1] = g
    return r_out, u_out, y_out


SYNTH_SWEEP = SweptSine(f_start_hz=1.0, f_stop_hz=300.0, duration_s=10.0, amplitude_dps=2.0)


@pytest.fixture(scope="module")
def synth_frf() -> Frf:
    r, u, y = simulate_loop(SYNTH_SWEEP, noise_dps=0.03)
    return estimate_frf(r, u, y, DT, f_min_hz=1.0, f_max_hz=300.0)


def test_frf_matches_the_true_plant(synth_frf: Frf) -> None:
    frf = synth_frf
    assert frf.method == "indirect" and frf.n_segments >= 4
    assert np.iscomplexobj(frf.response) and frf.freq_hz.shape == frf.coherence.shape == frf.response.shape
    true = plant_response(frf.freq_hz, K_M, bandwidth_hz=200.0, delay_s=0.5e-3, dt_s=DT)
    band = (frf.freq_hz >= 2.0) & (frf.freq_hz <= 100.0)
    err_db = frf.magnitude_db()[band] - 20.0 * np.log10(np.abs(true[band]))
    err_deg = np.degrees(np.angle(frf.response[band] / true[band]))
    assert abs(np.median(err_db)) < 0.05 and np.median(np.abs(err_db)) < 0.3  # unbiased, small scatter
    assert abs(np.median(err_deg)) < 0.5 and np.median(np.abs(err_deg)) < 2.0
    assert np.median(frf.coherence[band]) > 0.98
    ph = frf.phase_deg()
    assert ph[frf.freq_hz >= 2.0][0] == pytest.approx(-90.0, abs=3.0)  # an integrator
    assert np.all(np.abs(np.diff(ph[frf.coherence > 0.9])) < 60.0)  # unwrapped


def test_fit_recovers_k_m_bandwidth_and_delay(synth_frf: Frf) -> None:
    fit = fit_plant(synth_frf, f_min_hz=2.0)
    print(fit.describe())
    assert fit.k_m_dps2_per_count == pytest.approx(K_M, rel=0.02)
    assert fit.gyro_bandwidth_hz is not None and fit.gyro_bandwidth_hz == pytest.approx(200.0, rel=0.3)
    assert fit.delay_ms is not None and fit.delay_ms == pytest.approx(0.5, abs=0.2)
    assert fit.rms_error_db < 2.0 and fit.n_bins > 100
    assert fit.f_range_hz[0] >= 2.0 and fit.f_range_hz[1] <= 300.0
    assert "k_m = 0.02" in fit.describe() and "\n" not in fit.describe()
    # integrator + delay only: the lag becomes extra delay, k_m stays close
    fit0 = fit_plant(synth_frf, f_min_hz=2.0, lag=False)
    assert fit0.gyro_bandwidth_hz is None
    assert fit0.k_m_dps2_per_count == pytest.approx(K_M, rel=0.05)
    assert fit0.delay_ms is not None and fit0.delay_ms > fit.delay_ms
    # low band only: the lag is not identifiable, k_m still is
    fit_lo = fit_plant(synth_frf, f_min_hz=2.0, f_max_hz=20.0)
    assert fit_lo.gyro_bandwidth_hz is None
    assert fit_lo.k_m_dps2_per_count == pytest.approx(K_M, rel=0.02)


def test_fit_of_exact_model_data_is_exact() -> None:
    f = np.linspace(1.0, 300.0, 400)
    for bw, td, dt in ((150.0, 0.7e-3, DT), (None, 1.3e-3, DT), (120.0, 0.4e-3, None)):
        frf = Frf(f, plant_response(f, 0.031, bandwidth_hz=bw, delay_s=td, dt_s=dt), np.full(f.size, 0.99), DT, 8)
        fit = fit_plant(frf, lag=bw is not None, sampled_integrator=dt is not None)
        assert fit.k_m_dps2_per_count == pytest.approx(0.031, rel=1e-5)
        assert fit.delay_ms == pytest.approx(td * 1e3, abs=1e-5)
        if bw is None:
            assert fit.gyro_bandwidth_hz is None
        else:  # the bounded search on log10(fc) ends within 1e-5 of the minimum
            assert fit.gyro_bandwidth_hz == pytest.approx(bw, rel=1e-5)
        assert fit.rms_error_db < 1e-4


@pytest.mark.parametrize(("n", "nperseg"), [(11000, 4096), (10997, 4096), (12345, 1024), (6999, 2048), (4096, 4096),
                                            (20, 16)])
def test_welch_segments_cover_the_record_and_end_at_its_end(n: int, nperseg: int) -> None:
    skip, noverlap = welch_layout(n, nperseg)
    step = nperseg - noverlap
    n_seg = (n - skip - noverlap) // step  # what scipy.signal makes of x[skip:]
    starts = skip + step * np.arange(n_seg)
    assert starts[-1] + nperseg == n  # the last segment ends at the last sample
    assert noverlap >= nperseg // 2  # at least 50 % overlap
    assert n_seg == math.ceil((n - nperseg) / (nperseg // 2)) + 1  # as few as cover the record at 50 %
    assert 0 <= skip < max(n_seg, 1)  # at most a few samples left out at the start
    with pytest.raises(ValueError, match="does not fit"):
        welch_layout(nperseg - 1, nperseg)


def test_frf_with_a_few_samples_left_out_at_the_start() -> None:
    """10997 samples: the 5 segments step by 1725 samples, so the first sample is left out; the FRF is as good."""
    r, u, y = simulate_loop(SYNTH_SWEEP, noise_dps=0.03)
    assert welch_layout(10997, 4096) == (1, 4096 - 1725)
    frf = estimate_frf(r[:10997], u[:10997], y[:10997], DT, f_min_hz=1.0, f_max_hz=300.0)
    assert frf.n_segments == 5
    true = plant_response(frf.freq_hz, K_M, bandwidth_hz=200.0, delay_s=0.5e-3, dt_s=DT)
    band = (frf.freq_hz >= 2.0) & (frf.freq_hz <= 100.0)
    err_db = frf.magnitude_db()[band] - 20.0 * np.log10(np.abs(true[band]))
    assert abs(np.median(err_db)) < 0.05 and np.median(np.abs(err_db)) < 0.3
    assert fit_plant(frf, f_min_hz=2.0).k_m_dps2_per_count == pytest.approx(K_M, rel=0.02)


def test_noise_does_not_bias_the_indirect_estimate_but_biases_the_direct_one() -> None:
    r, u, y = simulate_loop(SYNTH_SWEEP, noise_dps=1.0, seed=3)
    err = {}
    for method in ("indirect", "direct"):
        frf = estimate_frf(r, u, y, DT, f_min_hz=1.0, f_max_hz=300.0, method=method)
        err[method] = fit_plant(frf, f_min_hz=2.0).k_m_dps2_per_count / K_M - 1.0
    print(f"k_m error with 1 deg/s gyro noise: indirect {err['indirect']:+.2%}, direct {err['direct']:+.2%}")
    assert abs(err["indirect"]) < 0.04
    assert abs(err["direct"]) > 0.10  # feedback puts the noise in u: S_uy / S_uu drifts towards -1/C


def test_estimate_frf_rejects_bad_input() -> None:
    x = np.zeros(1000)
    with pytest.raises(ValueError, match="same length"):
        estimate_frf(x, x[:-1], x, DT, f_min_hz=1.0, f_max_hz=10.0)
    with pytest.raises(ValueError, match="finite"):
        estimate_frf(np.full(1000, np.nan), x, x, DT, f_min_hz=1.0, f_max_hz=10.0)
    with pytest.raises(ValueError, match="f_min_hz"):
        estimate_frf(x, x, x, DT, f_min_hz=10.0, f_max_hz=1.0)
    with pytest.raises(ValueError, match="nperseg"):
        estimate_frf(x, x, x, DT, f_min_hz=1.0, f_max_hz=10.0, nperseg=4096)
    frf = Frf(np.array([1.0, 2.0]), np.array([1j, 1j]), np.array([0.1, 0.1]), DT, 1)
    with pytest.raises(ValueError, match="nothing to fit"):
        fit_plant(frf)


# --- (d) the emulated plant, through a session log ---------------------------------------------------------------


def run_plant(sweep: SweptSine, *, controller: str = "pi_lpf", pre_s: float = 0.3, post_s: float = 0.3) -> dict:
    """The emulated plant in closed loop (registry controller, both axes), the sweep on ``sweep.axis``' rate
    command, idle ``pre_s`` before and ``post_s`` after; returns the loop-group columns the session would log."""
    plant = Plant(load_plant_config(RIGID_PLANT_CONFIG), seed=1)
    c_az, c_el = build_controller(controller), build_controller(controller)
    rest = CarrierMotion.at_rest()
    n_pre, n = round(pre_s / DT), round((pre_s + sweep.total_s + post_s) / DT)
    cols = {c: np.zeros(n) for c in LOOP_CHANNELS}
    for k in range(n):
        _, gy, gz = plant.gyro_dps()
        exc = sweep.rate_dps((k - n_pre) * DT)
        r_az, r_el = (exc, 0.0) if sweep.axis == "az" else (0.0, exc)
        u_az, u_el = c_az.step(r_az, gz), c_el.step(r_el, gy)
        row = cols
        row["tick"][k], row["t_s"][k], row["t_host_ns"][k] = k, k * DT, 10**9 + k * 10**6  # 0 = never written
        row["gyro_y_dps"][k], row["gyro_z_dps"][k] = gy, gz
        row["rate_cmd_az_dps"][k], row["rate_cmd_el_dps"][k] = r_az, r_el
        row["drive_az_counts"][k], row["drive_el_counts"][k] = u_az, u_el
        plant.step_tick(u_az, u_el, rest)
    return cols


def as_log(cols: dict) -> LogData:
    return LogData(path=Path("mem.h5"), attrs={}, groups={"loop": cols}, units={})


PLANT_SWEEP = SweptSine(f_start_hz=1.0, f_stop_hz=300.0, duration_s=10.0, amplitude_dps=2.0, offset_dps=10.0)


def test_plant_k_m_through_a_session_log(tmp_path: Path) -> None:
    cols = run_plant(PLANT_SWEEP)
    names = LOOP_CHANNELS
    with SessionLog(tmp_path / "sweep.h5", attrs={"config": {}, "ident": {}, "seed": 1}) as log:
        for k in range(cols["tick"].size):
            log.append("loop", [cols[c][k] for c in names])
    data = read_log(tmp_path / "sweep.h5", groups=["loop"])
    frf, fit = identify_log(data, PLANT_SWEEP)
    k_m = load_plant_config(RIGID_PLANT_CONFIG).k_m_dps2_per_count("el")
    print(f"emulated plant, el: {fit.describe()}; k_m error {fit.k_m_dps2_per_count / k_m - 1.0:+.2%}")
    assert fit.k_m_dps2_per_count == pytest.approx(k_m, rel=0.05)
    assert fit.k_m_dps2_per_count == pytest.approx(k_m, rel=0.01)  # what it actually achieves (docs/ident.md)
    assert fit.f_range_hz[0] >= 2.0  # the sweep's first octave is left out
    # the plant's gyro: 200 Hz, 0.5 ms (+ the 0.1 ms L/R current lag, which reads as delay)
    assert fit.gyro_bandwidth_hz is not None and 140.0 < fit.gyro_bandwidth_hz < 260.0
    assert fit.delay_ms is not None and 0.3 < fit.delay_ms < 0.9
    png = bode_plot(frf, fit, tmp_path / "out" / "bode.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plant_az_axis_gaps_and_no_sweep_given() -> None:
    sweep = SweptSine.model_validate({**PLANT_SWEEP.model_dump(), "axis": "az"})
    cols = run_plant(sweep, pre_s=0.7)
    k_m = load_plant_config(RIGID_PLANT_CONFIG).k_m_dps2_per_count("az")
    keep = np.ones(cols["tick"].size, dtype=bool)
    keep[5000:5003] = keep[8000] = False  # samples the bench missed: interpolated on the tick grid
    gappy = {c: v[keep] for c, v in cols.items()}
    _, fit = identify_log(as_log(gappy), sweep)
    assert fit.k_m_dps2_per_count == pytest.approx(k_m, rel=0.05)
    # no sweep given: the active span of the command, the axis by name, band from 2 Hz
    _, fit2 = identify_log(as_log(cols), axis="az", f_min_hz=2.0)
    assert fit2.k_m_dps2_per_count == pytest.approx(k_m, rel=0.05)
    with pytest.raises(ValueError, match="never moves"):
        identify_log(as_log(cols), axis="el")


def test_coulomb_friction_spoils_the_fit_without_a_rate_offset() -> None:
    """Why SweptSine has offset_dps: sweeping around zero rate, the friction relay looks like a pole near
    4 T_c k_m / (pi A) and k_m comes out far too low (docs/ident.md)."""
    sweep = SweptSine(f_start_hz=1.0, f_stop_hz=300.0, duration_s=10.0, amplitude_dps=2.0)
    _, fit = identify_log(as_log(run_plant(sweep)), sweep)
    k_m = load_plant_config(RIGID_PLANT_CONFIG).k_m_dps2_per_count("el")
    print(f"no offset: {fit.describe()}")
    assert fit.k_m_dps2_per_count < 0.7 * k_m


def test_fit_result_types(synth_frf: Frf) -> None:
    fit = fit_plant(synth_frf, f_min_hz=2.0)
    assert isinstance(fit, PlantFit)
    resp = fit.response(synth_frf.freq_hz)
    assert resp.shape == synth_frf.freq_hz.shape and np.iscomplexobj(resp)
    assert isinstance(fit.k_m_dps2_per_count, float) and isinstance(fit.n_bins, int)


def test_bode_plot_is_headed_by_the_name_and_each_fitted_figure_once(
    synth_frf: Frf, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from matplotlib.figure import Figure
    from matplotlib.text import Text
    from PIL import Image

    fit = fit_plant(synth_frf, f_min_hz=2.0)
    assert fit.gyro_bandwidth_hz is not None and fit.delay_ms is not None
    drawn: list[str] = []
    savefig = Figure.savefig

    def spy(self: Figure, *args: object, **kwargs: object) -> None:
        drawn.extend(t.get_text() for t in self.findobj(Text) if t.get_text())
        savefig(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", spy)
    png = bode_plot(synth_frf, fit, tmp_path / "bode.png", title="demo-ident-el")
    text = "\n".join(drawn)
    assert "demo-ident-el" in drawn  # the name alone is the title
    assert text.count("k_m") == 1
    for figure in (f"k_m = {fit.k_m_dps2_per_count:.5g} deg/s", f"gyro bandwidth {fit.gyro_bandwidth_hz:.0f} Hz",
                   f"delay {fit.delay_ms:.2f} ms", f"rms error {fit.rms_error_db:.2f} dB"):
        assert text.count(figure) == 1, (figure, drawn)
    meta = Image.open(png).text  # the same texts in the PNG's metadata
    assert meta["Title"] == "demo-ident-el" and meta["Description"] == fit_caption(fit)
    assert "\n" in fit_caption(fit) and fit_caption(fit).count("k_m = 0.0229") == 1

    # nothing clipped: a title wider than the figure widens the page, and its edges stay background
    wide = np.asarray(Image.open(bode_plot(synth_frf, fit, tmp_path / "wide.png", title="W" * 150)).convert("L"))
    plain = np.asarray(Image.open(png).convert("L"))
    assert wide.shape[1] > plain.shape[1] + 100
    for img in (plain, wide):
        for edge in (img[:3], img[-3:], img[:, :3], img[:, -3:]):
            assert edge.min() == 255
    assert Image.open(bode_plot(synth_frf, None, tmp_path / "nofit.png")).text["Title"] == "plant identification"
