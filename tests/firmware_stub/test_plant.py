"""The emulator's plant (firmware_stub.plant): physics against independent solutions, noise, frames and signs,
calibration against the paper (seed 000), config errors."""

from __future__ import annotations

import math
from decimal import Decimal, localcontext
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from firmware_stub.plant import (
    DEFAULT_PLANT_CONFIG,
    RIGID_PLANT_CONFIG,
    CarrierMotion,
    Plant,
    PlantConfig,
    PlantConfigError,
    axis_matrices,
    axis_zoh,
    carrier_state,
    imbalance_torques,
    load_plant_config,
)
from hil.control.pos_kinematics import azel_los_inertial_rate, azel_rot_body_to_el, rot_x, rot_y, rot_z
from tests.firmware_stub.closed_loop import (
    filter_lag,
    run_closed_loop,
    static_filters,
    static_gyro_peak,
    swing_carrier,
)
from tests.firmware_stub.plant_helpers import D2R, G0, REST, assert_config_error, ideal, with_


def linear_axis(cfg: PlantConfig, axis: str) -> tuple[np.ndarray, np.ndarray]:
    """Continuous (A, B) of one axis with friction off: state (i [A], w [deg/s]), input V [V]."""
    m = getattr(cfg, f"motor_{axis}")
    r, ll, kt, ke, j = (m.resistance_ohm, m.inductance_h, m.torque_constant_n_m_per_a, m.back_emf_v_s_per_rad,
                        m.inertia_kg_m2)
    a = np.array([[-r / ll, -ke / ll * D2R], [kt / j / D2R, 0.0]])
    b = np.array([1.0 / ll, 0.0])
    return a, b


# --- motor model ------------------------------------------------------------------------------------------------


def test_k_m_is_the_papers_and_the_current_is_fast(rigid: PlantConfig) -> None:
    for axis in ("az", "el"):
        k_m = rigid.k_m_dps2_per_count(axis)
        tau_e = rigid.electrical_time_constant_s(axis)
        print(f"{axis}: k_m = {k_m:.5f} deg/s^2 per count (eq 38: 0.023), L/R = {tau_e * 1e3:.3f} ms")
        assert k_m == pytest.approx(0.023, rel=1e-3)
        assert tau_e < 0.2e-3


@pytest.mark.parametrize(("axis", "inductance_h"), [("az", None), ("el", None), ("el", 1e-7), ("el", 0.05)])
def test_open_loop_step_follows_the_exact_linear_solution(
    rigid: PlantConfig, axis: str, inductance_h: float | None
) -> None:
    """Constant drive, friction and imbalance off, at rest: current and rate equal the exact solution of the linear
    (i, w) system at every tick, for the default inductance and for L/R = 10 ns (stiff) and 5 ms (slow)."""
    cfg = ideal(rigid)
    if inductance_h is not None:
        cfg = with_(cfg, **{f"motor_{axis}__inductance_h": inductance_h})
    plant = Plant(cfg, seed=0)
    u0 = 1500.0
    m = getattr(cfg, f"motor_{axis}")
    v0 = u0 * m.volts_per_count
    a, b = linear_axis(cfg, axis)
    lam, vec = np.linalg.eig(a)  # independent of the plant's expm: x(t) = A^-1 (e^{At} - I) B V0
    inv_a_b = np.linalg.solve(a, b) * v0
    rates, currents = [], []
    for _ in range(200):
        plant.step_tick(u0 if axis == "az" else 0.0, u0 if axis == "el" else 0.0, REST)
        tr = plant.truth()
        rates.append(tr[f"{axis}_rate_dps"])
        currents.append(tr[f"current_{axis}_a"])
    t = np.arange(1, 201) * 1e-3
    exact = np.array([(vec @ np.diag(np.exp(lam * tk)) @ np.linalg.inv(vec)).real @ inv_a_b - inv_a_b for tk in t])
    # exact up to rounding: 1e-8 of full scale
    assert np.max(np.abs(np.array(currents) - exact[:, 0])) < 1e-8 * np.max(np.abs(exact[:, 0]))
    assert np.max(np.abs(np.array(rates) - exact[:, 1])) < 1e-8 * np.max(np.abs(exact[:, 1]))
    # the paper's k_m / s model (eq 38): the back-EMF pole (J R / (K_t K_e) ~ 6.7 s) bends it by ~1.5 % at 0.2 s
    k_m = cfg.k_m_dps2_per_count(axis)
    if inductance_h is None:
        assert rates[-1] == pytest.approx(k_m * u0 * 0.2, rel=0.02)
    # the encoder integrates the rate (trapezoidal sub-steps), to its resolution
    angle = plant.encoders_deg()[0 if axis == "az" else 1]
    exact_angle = np.trapezoid(np.concatenate([[0.0], exact[:, 1]]), dx=1e-3)
    assert angle == pytest.approx(exact_angle, abs=2 * 360 / cfg.encoder.counts_per_rev)


def test_sine_drive_matches_the_analytic_response(rigid: PlantConfig) -> None:
    """A 5 Hz drive (held each tick: the analytic input is the sine delayed by half a tick) on the elevation axis;
    the full analytic solution (steady state + the transient of the zero initial state) to 0.1 %."""
    cfg = ideal(rigid)
    plant = Plant(cfg, seed=0)
    f, amp, n = 5.0, 2000.0, 600
    w = 2 * math.pi * f
    v_amp = amp * cfg.motor_el.volts_per_count
    a, b = linear_axis(cfg, "el")
    # input v(t) = V sin(w (t - T/2)) = Im(V e^{-jwT/2} e^{jwt}); steady state x_ss = Im(X e^{jwt})
    x_c = np.linalg.solve(1j * w * np.eye(2) - a, b) * v_amp * np.exp(-1j * w * 0.5e-3)
    lam, vec = np.linalg.eig(a)
    x0 = -np.imag(x_c)  # x(0) = 0 = x_ss(0) + homogeneous(0)

    def exact(t: float) -> float:
        hom = (vec @ np.diag(np.exp(lam * t)) @ np.linalg.inv(vec)).real @ x0
        return float(np.imag(x_c * np.exp(1j * w * t))[1] + hom[1])

    errs, peak = [], 0.0
    for k in range(n):
        plant.step_tick(0.0, amp * math.sin(w * k * 1e-3), REST)  # sampled at the tick start, held
        rate = plant.truth()["el_rate_dps"]
        e = exact((k + 1) * 1e-3)
        errs.append(rate - e)
        peak = max(peak, abs(e))
    assert peak > 1.0
    assert max(abs(x) for x in errs) < 1e-3 * peak


def _expm_50_digits(a: np.ndarray) -> np.ndarray:
    """Reference matrix exponential in 50-digit decimal arithmetic: scaling to a norm under 0.01, 40 Taylor terms
    (truncation < 1e-80), squaring back; rounding to float64 only at the end."""
    n = a.shape[0]
    squarings = max(0, math.ceil(math.log2(float(np.max(np.sum(np.abs(a), axis=1))) / 0.01)))

    def mul(x: list[list[Decimal]], y: list[list[Decimal]]) -> list[list[Decimal]]:
        return [[sum((x[i][k] * y[k][j] for k in range(n)), Decimal(0)) for j in range(n)] for i in range(n)]

    with localcontext(prec=50):
        m = [[Decimal(float(v)) / Decimal(2) ** squarings for v in row] for row in a]
        term = [[Decimal(int(i == j)) for j in range(n)] for i in range(n)]
        total = [row[:] for row in term]
        for k in range(1, 41):
            term = [[v / k for v in row] for row in mul(term, m)]
            total = [[t + v for t, v in zip(tr, vr, strict=True)] for tr, vr in zip(total, term, strict=True)]
        for _ in range(squarings):
            total = mul(total, total)
        return np.array([[float(v) for v in row] for row in total])


@pytest.mark.parametrize("path", [RIGID_PLANT_CONFIG, DEFAULT_PLANT_CONFIG], ids=["rigid", "default"])
def test_zoh_matrices_are_exact_in_every_entry(path: Path) -> None:
    """Phi and Gamma of each axis against a 50-digit matrix exponential of ``[[A, B], [0, 0]] h``, every entry to
    1e-12 relative: the structural mode's augmented matrix has entries ten decades apart, and the smallest entries
    of its exponential (current into angle, ~1e-10) are the ones a plain float64 expm gets wrong first (~1e-9)."""
    cfg = load_plant_config(path)
    h = cfg.internal_step_s
    for axis in ("az", "el"):
        a, b = axis_matrices(cfg, axis)
        n = 3 if cfg.structure_of(axis) is None else 5
        aug = np.zeros((n + 4, n + 4))
        aug[:n, :n], aug[:n, n:] = a[:n, :n] * h, b[:n] * h
        ref = _expm_50_digits(aug)
        phi, gam = axis_zoh(cfg, axis, h)
        got = np.hstack([phi[:n, :n], gam[:n]])
        want = ref[:n]
        assert np.count_nonzero(want) > 2 * n
        nonzero = want != 0
        assert np.all(got[~nonzero] == 0.0), axis
        rel = np.abs(got[nonzero] - want[nonzero]) / np.abs(want[nonzero])
        assert rel.max() < 1e-12, (path.name, axis, rel.max())
        if n == 3:  # rigid: the load rows are the motor's, bit for bit
            assert np.array_equal(phi[3:5], phi[1:3]) and np.array_equal(gam[3:5], gam[1:3])
        else:
            assert np.min(np.abs(want[nonzero])) < 1e-9  # the small entries are there to be checked


def test_internal_step_converges(rigid: PlantConfig) -> None:
    """With friction and imbalance on, 0.2 ms and 0.1 ms internal steps give the same trajectory (to 1 %)."""
    fine = with_(rigid, internal_step_s=1e-4)
    runs = []
    for cfg in (rigid, fine):
        plant = Plant(cfg, seed=3)
        rates = []
        for k in range(1500):
            u = 20000.0 * math.sin(2 * math.pi * 2.0 * k * 1e-3)
            plant.step_tick(u, u, swing_carrier((k + 0.5) * 1e-3, 1.0, 1.0, True, True))
            tr = plant.truth()
            rates.append((tr["az_rate_dps"], tr["el_rate_dps"]))
        runs.append(np.array(rates))
    scale = np.max(np.abs(runs[1]), axis=0)
    assert np.all(scale > 5.0)
    assert np.all(np.max(np.abs(runs[0] - runs[1]), axis=0) < 0.01 * scale)


# --- gyro ---------------------------------------------------------------------------------------------------------


def test_gyro_transfer_function_is_eq3(rigid: PlantConfig) -> None:
    """Seed 000 eq 3: k_a w_c / (s + w_c) e^{-T_d s}; a 20 Hz elevation motion, amplitude and phase of the gyro
    against the true rate (noise, bias, quantisation off; a delay that is not a whole number of ticks)."""
    cfg = with_(ideal(rigid), gyro__delay_s=2.3e-3, gyro__bandwidth_hz=150.0, gyro__scale_factor=1.02)
    plant = Plant(cfg, seed=0)
    f = 20.0
    w = 2 * math.pi * f
    t, true, meas = [], [], []
    for k in range(1500):
        plant.step_tick(0.0, 3000.0 * math.cos(w * k * 1e-3), REST)
        if k >= 500:
            t.append(plant.t_s)
            true.append(plant.truth()["los_rate_y_dps"])
            meas.append(plant.gyro_dps()[1])
    basis = np.column_stack([np.sin(w * np.array(t)), np.cos(w * np.array(t)), np.ones(len(t))])
    ct = np.linalg.lstsq(basis, np.array(true), rcond=None)[0]
    cm = np.linalg.lstsq(basis, np.array(meas), rcond=None)[0]
    # a sin + b cos = Im((a + jb) e^{jwt}): a + jb is the phasor, and the gyro's is H(jw) times the true one
    z_true, z_meas = complex(ct[0], ct[1]), complex(cm[0], cm[1])
    ratio = z_meas / z_true
    wc = 2 * math.pi * 150.0
    expected = 1.02 * wc / (1j * w + wc) * np.exp(-1j * w * 2.3e-3)
    assert abs(ratio) == pytest.approx(abs(expected), rel=2e-3)
    assert np.angle(ratio) == pytest.approx(np.angle(expected), abs=2e-3)


def test_static_gyro_noise_bias_and_quantisation(rigid: PlantConfig) -> None:
    """20 s at rest (imbalance off: the smoothed Coulomb term lets an unbalanced gimbal creep slowly)."""
    cfg = with_(rigid, imbalance__mass_kg=0.0, gyro__noise_std_dps=(0.02, 0.0315, 0.05),
                gyro__bias_dps=(0.02, -0.03, 0.015))
    plant = Plant(cfg, seed=5)
    n = 20000
    g = np.empty((n, 3))
    for k in range(n):
        plant.step_tick(0.0, 0.0, REST)
        g[k] = plant.gyro_dps()
    assert plant.t_s == pytest.approx(20.0)
    std, mean = g.std(axis=0), g.mean(axis=0)
    print(f"gyro std {std}, mean {mean}")
    assert std == pytest.approx([0.02, 0.0315, 0.05], rel=0.03)
    assert mean == pytest.approx([0.02, -0.03, 0.015], abs=1e-3)  # 4.5 sigma of the mean of 20000 samples
    lsb = cfg.gyro.quantisation_lsb_dps
    q = g / lsb
    assert np.max(np.abs(q - np.round(q))) < 1e-6
    assert len(np.unique(g[:, 1])) > 10  # noise spans many LSBs
    # white: no correlation between successive samples, nor between axes
    y = g[:, 1] - mean[1]
    assert abs(np.dot(y[1:], y[:-1]) / np.dot(y, y)) < 0.03
    corr = np.corrcoef(g.T)
    assert np.max(np.abs(corr - np.eye(3))) < 0.03


def test_gyro_is_read_once_per_tick_and_deterministic(rigid: PlantConfig) -> None:
    def swing(k: int) -> CarrierMotion:
        return swing_carrier((k + 0.5) * 1e-3, 1.0, 1.0, True, True)

    def run(plant: Plant, read_twice: bool) -> list[tuple[float, ...]]:
        out = []
        for k in range(1500):  # past one block of noise (1000 ticks)
            plant.step_tick(3000.0, -3000.0, swing(k))
            out.append((*plant.gyro_dps(), *plant.encoders_deg()))
            if read_twice:
                assert plant.gyro_dps() == out[-1][:3]
                plant.miss_px()
                plant.truth()
        return out

    a = run(Plant(rigid, seed=7), True)
    assert a == run(Plant(rigid, seed=7), False)  # what is read does not change the sequence
    assert a != run(Plant(rigid, seed=8), False)
    plant = Plant(rigid, seed=7)
    for k in range(50):
        plant.step_tick(100.0, -100.0, swing(k + 300))
    plant.reset()
    assert plant.t_s == 0.0
    assert run(plant, False) == a


def _reference_run(cfg: PlantConfig, drive: np.ndarray, carriers: list[CarrierMotion]) -> np.ndarray:
    """An independent reference: the continuous model (friction, shaft, cable, imbalance evaluated continuously)
    integrated by scipy's Radau per tick, the drive and the carrier's rate held at its mid-tick value as the plant
    specifies. Returns per tick (load rate az, el, motor rate az, el, current az, el, load angle az, el) in SI."""
    from scipy.integrate import solve_ivp

    axes = ("az", "el")
    prm = []
    for axis in axes:
        m = getattr(cfg, f"motor_{axis}")
        fr = getattr(cfg.friction, axis)
        st = cfg.structure_of(axis)
        cab = cfg.cable_of(axis)
        f = 1.0 if st is None else st.motor_inertia_fraction
        jm, jl = f * m.inertia_kg_m2, (1.0 - f) * m.inertia_kg_m2
        ks = cs = 0.0
        if st is not None:
            mu = jm * jl / m.inertia_kg_m2
            ks, cs = (2 * math.pi * st.mode_hz) ** 2 * mu, 2 * st.damping_ratio * 2 * math.pi * st.mode_hz * mu
        prm.append((m, fr, st is not None, jm, jl, ks, cs, (0.0, 0.0) if cab is None else
                    (cab.stiffness_n_m_per_rad, cab.damping_n_m_s_per_rad)))
    piv = np.array(cfg.pivot_offset_m())
    x = np.zeros(10)
    x[[2, 4]] = cfg.initial_az_deg * D2R
    x[[7, 9]] = cfg.initial_el_deg * D2R
    out = []
    for u, car in zip(drive, carriers, strict=True):
        cs_ = carrier_state(car)
        p, q, r = cs_.pqr
        w, wd = np.array(cs_.pqr), np.array(cs_.pqr_dot)
        f_b = tuple(np.array(cs_.f_body) + np.cross(wd, piv) + np.cross(w, np.cross(w, piv)))

        def rhs(_t: float, y: np.ndarray, u: np.ndarray = u, p: float = p, q: float = q, r: float = r,  # noqa: PLR0917
                f_b: tuple = f_b) -> np.ndarray:
            dy = np.empty(10)
            t_imb = imbalance_torques(cfg.imbalance, f_b, y[4], y[9])
            c_axis = (r, math.cos(y[4]) * q - math.sin(y[4]) * p)
            for ax in range(2):
                m, fr, two, jm, jl, ks, cs, (kc, cc) = prm[ax]
                i, wm, thm, wl, thl = y[5 * ax: 5 * ax + 5]
                c = c_axis[ax]
                v = max(-m.bus_voltage_v, min(m.bus_voltage_v, u[ax] * m.volts_per_count))
                vr = wm - c
                t_f = fr.coulomb_n_m * math.tanh(vr / (fr.smoothing_rate_dps * D2R)) + fr.viscous_n_m_s_per_rad * vr
                t_m = m.torque_constant_n_m_per_a * i - t_f - kc * thm - cc * vr
                di = (v - m.resistance_ohm * i - m.back_emf_v_s_per_rad * vr) / m.inductance_h
                if two:
                    shaft = ks * (thm - thl) + cs * (wm - wl)
                    dwm, dwl = (t_m - shaft) / jm, (shaft + t_imb[ax]) / jl
                else:
                    dwm = dwl = (t_m + t_imb[ax]) / jm
                dy[5 * ax: 5 * ax + 5] = (di, dwm, wm - c, dwl, wl - c)
            return dy

        x = solve_ivp(rhs, (0.0, 1e-3), x, method="LSODA", rtol=1e-9, atol=1e-12).y[:, -1]
        out.append((x[3], x[8], x[1], x[6], x[0], x[5], x[4], x[9]))
    return np.array(out)


def test_kernel_matches_an_independent_reference(rigid: PlantConfig) -> None:
    """The compiled kernel (exact-ZOH matrices, friction held per sub-step, imbalance held per tick) against the
    continuous model integrated by scipy (tests/firmware_stub/test_plant.py::_reference_run), 0.3 s with a drive,
    a swing, imbalance (pivot 0.3 m above the table's centre), smoothed friction, a two-mass elevation axis and a
    cable on azimuth: with friction and imbalance off every state within 1e-6 of its peak (the ZOH is exact), with
    them on within 0.5 % (what holding the nonlinear torques over a sub-step or a tick costs: ~0.1 %)."""
    n = 300
    k = np.arange(n)
    drive = np.column_stack([30000 * np.sin(2 * math.pi * 7 * k * 1e-3), 20000 * np.sin(2 * math.pi * 11 * k * 1e-3)])
    carriers = [swing_carrier((j + 0.5) * 1e-3, 3.0, 2.0, True, True) for j in range(n)]
    for nonlinear, tol in ((False, 1e-6), (True, 5e-3)):
        cfg = with_(rigid, friction__az__smoothing_rate_dps=5.0, friction__el__smoothing_rate_dps=5.0,
                    imbalance__eccentricity_mm=(3.0, 0.5, 2.0), initial_az_deg=10.0, initial_el_deg=-5.0)
        if not nonlinear:  # the linear part alone is exact (ZOH), up to the carrier rate held over the tick
            cfg = with_(cfg, friction__az__coulomb_n_m=0.0, friction__el__coulomb_n_m=0.0, imbalance__mass_kg=0.0)
        d = cfg.model_dump()
        d["structure"] = {"el": {"mode_hz": 60.0, "damping_ratio": 0.1, "motor_inertia_fraction": 0.5}}
        d["cable"] = {"az": {"stiffness_n_m_per_rad": 2.0, "damping_n_m_s_per_rad": 0.02}}
        d["mount"] = {"pivot_offset_m": (0.05, -0.1, -0.3)}
        cfg = PlantConfig.model_validate(d)
        ref = _reference_run(cfg, drive, carriers)
        plant = Plant(cfg, seed=0)
        got = []
        for (ua, ue), car in zip(drive, carriers, strict=True):
            plant.step_tick(ua, ue, car)
            tr = plant.truth()
            got.append([tr[key] * (D2R if key.endswith(("dps", "deg")) else 1.0) for key in (
                "az_rate_dps", "el_rate_dps", "az_motor_rate_dps", "el_motor_rate_dps", "current_az_a",
                "current_el_a", "az_deg", "el_deg")])
        got_a = np.array(got)
        scale = np.max(np.abs(ref), axis=0)
        err = np.max(np.abs(got_a - ref), axis=0) / scale
        print(f"nonlinear {nonlinear}: relative errors {err}")
        assert np.all(scale[:6] > 0.05)
        assert np.all(err < tol)
    # the elevation's two masses really differ (the mode is excited), the azimuth's are one body
    assert np.max(np.abs(got_a[:, 1] - got_a[:, 3])) > 0.05 * scale[1]
    assert np.array_equal(got_a[:, 0], got_a[:, 2])


def test_run_is_step_tick_bit_for_bit() -> None:
    """The batch API and step_tick compute the same floats (default.yaml: every mechanism on), across noise blocks,
    mixed: 700 ticks stepped, 1600 by run(), 200 stepped; outputs are plain Python floats."""
    from firmware_stub.plant import DEFAULT_PLANT_CONFIG

    cfg = load_plant_config(DEFAULT_PLANT_CONFIG)
    n = 2500
    t = (np.arange(n) + 0.5) * 1e-3
    drive = 8000.0 * np.sin(2 * math.pi * 3.0 * t)
    cars = [swing_carrier(tk, 1.0, 1.0, True, True) for tk in t]
    arr = np.array([[*c.pose, *c.rate, *c.accel] for c in cars])
    a = Plant(cfg, seed=3)
    rec_a = []
    for j in range(n):
        a.step_tick(drive[j], -drive[j], cars[j])
        rec_a.append((*a.gyro_dps(), *a.encoders_deg(), *a.currents_a(), *a.miss_px()[:2]))
    assert all(type(v) is float for v in rec_a[-1])
    assert type(a.miss_px()[2]) is bool and all(type(v) is float for v in a.truth().values())
    b = Plant(cfg, seed=3)
    rec_b = []
    for j in range(700):
        b.step_tick(drive[j], -drive[j], cars[j])
        rec_b.append((*b.gyro_dps(), *b.encoders_deg(), *b.currents_a(), *b.miss_px()[:2]))
    res = b.run(drive[700:2300], -drive[700:2300], arr[700:2300])
    cols = ("gyro_x_dps", "gyro_y_dps", "gyro_z_dps", "encoder_az_deg", "encoder_el_deg", "current_az_a",
            "current_el_a", "miss_x_px", "miss_y_px")
    rec_b.extend(zip(*(res[c].tolist() for c in cols), strict=True))
    assert res["t_s"][0] == pytest.approx(0.701) and res["t_s"][-1] == pytest.approx(2.3)
    assert b.gyro_dps() == rec_b[-1][:3] and b.t_s == pytest.approx(2.3)
    for j in range(2300, n):
        b.step_tick(drive[j], -drive[j], cars[j])
        rec_b.append((*b.gyro_dps(), *b.encoders_deg(), *b.currents_a(), *b.miss_px()[:2]))
    assert rec_a == rec_b
    assert a.truth() == b.truth()
    with pytest.raises(ValueError, match="carrier"):
        a.step_tick(0.0, 0.0, ((0.0,) * 6, (0.0,) * 5, (0.0,) * 6))
    with pytest.raises(ValueError, match="run"):
        a.run(np.zeros(3), np.zeros(3), np.zeros((3, 17)))


def test_run_outputs_selects_columns_only() -> None:
    """``run(..., outputs=...)`` computes and returns only the named columns (plus t_s), the same floats as a full
    run, and leaves the physics, the noise and the final state unchanged; an unknown name is refused."""
    from firmware_stub.plant import DEFAULT_PLANT_CONFIG, RUN_COLUMNS

    cfg = load_plant_config(DEFAULT_PLANT_CONFIG)
    n = 1500  # across a noise refill
    t = (np.arange(n) + 0.5) * 1e-3
    drive = 8000.0 * np.sin(2 * math.pi * 3.0 * t)
    arr = np.array([[*c.pose, *c.rate, *c.accel] for c in (swing_carrier(tk, 1.0, 1.0, True, True) for tk in t)])
    full = Plant(cfg, seed=5)
    ref = full.run(drive, -drive, arr)
    assert tuple(ref) == ("t_s", *RUN_COLUMNS)
    for sel in (("gyro_x_dps",), ("track_valid", "encoder_el_deg"), ("miss_y_px", "voltage_az_v", "az_deg"), ()):
        part = Plant(cfg, seed=5)
        got = part.run(drive, -drive, arr, outputs=sel)
        assert tuple(got) == ("t_s", *sel)
        for name in got:
            assert np.array_equal(got[name], ref[name]), name
        assert part.truth() == full.truth() and part.gyro_dps() == full.gyro_dps()
        assert part.miss_px() == full.miss_px()
    assert Plant(cfg, seed=5).run(drive, -drive, arr, outputs=RUN_COLUMNS)["track_valid"].dtype == bool
    with pytest.raises(ValueError, match="unknown output 'gyro_w_dps'"):
        Plant(cfg, seed=5).run(drive, -drive, arr, outputs=("gyro_w_dps",))


def test_white_noise_is_the_documented_draw(rigid: PlantConfig) -> None:
    """The noise scheme the docstring promises (and the pure-Python plant drew): per tick five 16-bit little-endian
    random numbers from random.Random(seed).randbytes, each an index into the table of normal quantiles."""
    import random
    from statistics import NormalDist

    cfg = with_(ideal(rigid), gyro__noise_std_dps=(0.01, 0.02, 0.03), gyro__bias_dps=(0.1, 0.2, 0.3))
    plant = Plant(cfg, seed=11)
    raw = random.Random(11).randbytes(2 * 5 * 1000)
    inv = NormalDist().inv_cdf
    for k in range(20):
        plant.step_tick(0.0, 0.0, REST)
        z = [inv((int.from_bytes(raw[2 * (5 * k + j): 2 * (5 * k + j) + 2], "little") + 0.5) / 65536)
             for j in range(3)]
        assert plant.gyro_dps() == pytest.approx([0.1 + 0.01 * z[0], 0.2 + 0.02 * z[1], 0.3 + 0.03 * z[2]],
                                                 abs=1e-12)

# --- carrier coupling and kinematics -------------------------------------------------------------------------------


def test_body_rates_and_specific_force_from_the_hexapod_pose() -> None:
    """Exact ZYX Euler-rate formula (checked against differentiating the DCM) and the specific force."""
    pose = (10.0, -5.0, 3.0, 7.0, -12.0, 25.0)
    rate = (100.0, 50.0, -80.0, 20.0, 15.0, -30.0)
    accel = (1000.0, -2000.0, 500.0, 0.0, 0.0, 0.0)
    cs = carrier_state(CarrierMotion(pose, rate, accel))

    def dcm(t: float) -> np.ndarray:
        r, p, y = ((a + ad * t) * D2R for a, ad in zip(pose[3:], rate[3:], strict=True))
        return np.array(rot_x(r)) @ np.array(rot_y(p)) @ np.array(rot_z(y))

    dt = 1e-6
    c = dcm(0.0)
    # d/dt C_lab^body = -[w_body x] C_lab^body
    skew = -(dcm(dt) - dcm(-dt)) / (2 * dt) @ c.T
    w_num = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
    assert np.allclose(cs.pqr, w_num, rtol=1e-6, atol=1e-9)
    f_lab = np.array(accel[:3]) * 1e-3 - np.array([0.0, 0.0, G0])
    assert np.allclose(cs.f_body, c @ f_lab, atol=1e-12)
    # derivative of the body rate, against finite differences of the formula with the Euler accelerations
    acc2 = (0.0, 0.0, 0.0, 300.0, -200.0, 100.0)

    def pqr(t: float) -> np.ndarray:
        p2 = tuple(a + ad * t + 0.5 * add * t * t for a, ad, add in zip(pose, rate, acc2, strict=True))
        r2 = tuple(ad + add * t for ad, add in zip(rate, acc2, strict=True))
        return np.array(carrier_state(CarrierMotion(p2, r2, acc2)).pqr)

    cs2 = carrier_state(CarrierMotion(pose, rate, acc2))
    assert np.allclose(cs2.pqr_dot, (pqr(dt) - pqr(-dt)) / (2 * dt), rtol=1e-5, atol=1e-8)


def test_los_rates_match_the_bench_kinematics(rigid: PlantConfig) -> None:
    """The plant's own az-el kinematics against hil.control.pos_kinematics (the bench's), mid-swing, off-axis."""
    cfg = with_(rigid, initial_az_deg=30.0, initial_el_deg=-20.0)
    plant = Plant(cfg, seed=1)
    for k in range(400):
        t = (k + 0.5) * 1e-3
        w = 2 * math.pi
        carrier = CarrierMotion(
            (0.0, 0.0, 0.0, 2 * math.sin(w * t), 3 * math.sin(w * t + 1), 4 * math.sin(w * t + 2)),
            (0.0, 0.0, 0.0, 2 * w * math.cos(w * t), 3 * w * math.cos(w * t + 1), 4 * w * math.cos(w * t + 2)),
            (0.0, 0.0, 0.0, -2 * w * w * math.sin(w * t), -3 * w * w * math.sin(w * t + 1),
             -4 * w * w * math.sin(w * t + 2)),
        )
        plant.step_tick(3000.0, -2000.0, carrier)
    tr = plant.truth()
    pqr = tuple(tr[f"carrier_{c}_dps"] * D2R for c in "pqr")
    expected = azel_los_inertial_rate(pqr, tr["az_deg"] * D2R, tr["el_deg"] * D2R, tr["az_rel_rate_dps"] * D2R,
                                      tr["el_rel_rate_dps"] * D2R)
    got = tuple(tr[f"los_rate_{c}_dps"] * D2R for c in "xyz")
    assert np.allclose(got, expected, atol=1e-12)
    assert abs(tr["carrier_p_dps"]) > 1.0 and abs(tr["carrier_r_dps"]) > 1.0


def test_gyro_reads_the_true_los_rates(rigid: PlantConfig) -> None:
    """With an ideal gyro (no noise, bias, quantisation, delay; a very wide bandwidth) the sample at t_s is the true
    elevation-frame inertial rate at t_s, off-axis and under a 3-axis swing (the hot path against truth())."""
    cfg = with_(ideal(rigid), initial_az_deg=40.0, initial_el_deg=25.0, gyro__delay_s=0.0,
                gyro__bandwidth_hz=1e9)
    plant = Plant(cfg, seed=1)
    w = 2 * math.pi * 2.0
    for k in range(300):
        t = (k + 0.5) * 1e-3
        amp = (2.0, 3.0, 4.0)
        carrier = CarrierMotion(
            (0.0, 0.0, 0.0, *(a * math.sin(w * t + i) for i, a in enumerate(amp))),
            (0.0, 0.0, 0.0, *(a * w * math.cos(w * t + i) for i, a in enumerate(amp))),
            (0.0, 0.0, 0.0, *(-a * w * w * math.sin(w * t + i) for i, a in enumerate(amp))),
        )
        plant.step_tick(2000.0 * math.sin(w * t), -3000.0, carrier)
        tr = plant.truth()
        truth = [tr[f"los_rate_{c}_dps"] for c in "xyz"]
        if k >= 2:  # (the swing starts abruptly; the wide filter still lags 0.16 ns)
            assert plant.gyro_dps() == pytest.approx(truth, abs=1e-6)
    assert min(abs(x) for x in truth) > 0.1


def test_imbalance_torque_drives_the_axes(rigid: PlantConfig) -> None:
    """Friction off, drive 0: the axes accelerate at (imbalance torque) / J, in its direction."""
    m = 10.0
    cfg = with_(ideal(rigid), imbalance__mass_kg=m, imbalance__eccentricity_mm=(2.0, 0.0, 0.0))
    lateral = CarrierMotion(REST.pose, REST.rate, (0.0, 3000.0, 0.0, 0.0, 0.0, 0.0))  # 3 m/s^2 to the right

    def run(c: PlantConfig, carrier: CarrierMotion) -> tuple[dict[str, float], float]:
        plant = Plant(c, seed=0)
        for _ in range(20):
            plant.step_tick(0.0, 0.0, carrier)
        tr = plant.truth()
        for axis in ("az", "el"):
            expected = tr[f"imbalance_{axis}_n_m"] / getattr(c, f"motor_{axis}").inertia_kg_m2 * plant.t_s / D2R
            # (back-EMF: < 0.1 %; a torque that only grows as the gimbal turns, < 1e-4 N m, is not constant)
            assert tr[f"{axis}_rate_dps"] == pytest.approx(expected, rel=0.01, abs=1e-4)
        return tr, plant.t_s

    tr, _ = run(cfg, lateral)
    assert tr["imbalance_el_n_m"] == pytest.approx(-m * G0 * 2e-3, rel=1e-3)  # nose-heavy: LOS down
    assert tr["imbalance_az_n_m"] == pytest.approx(-m * 3.0 * 2e-3, rel=1e-3)  # pushed right, the nose lags left
    # general case, against vector algebra done here: tilted, yawed and accelerating hexapod, gimbal off-axis
    rho = np.array([1.5, -0.8, 2.0])
    general = with_(cfg, imbalance__eccentricity_mm=tuple(rho), initial_az_deg=20.0, initial_el_deg=30.0)
    roll, pitch, yaw = 5.0, 10.0, 30.0
    for acc in (np.array([1500.0, -2500.0, 800.0]), np.array([0.0, 0.0, 800.0])):
        tr, _ = run(general, CarrierMotion((0.0, 0.0, 0.0, roll, pitch, yaw), REST.rate, (*acc, 0.0, 0.0, 0.0)))
        c_lb = np.array(rot_x(roll * D2R)) @ np.array(rot_y(pitch * D2R)) @ np.array(rot_z(yaw * D2R))
        f_b = c_lb @ (acc * 1e-3 - np.array([0.0, 0.0, G0]))
        c_be = np.array(rot_y(tr["el_deg"] * D2R)) @ np.array(rot_z(tr["az_deg"] * D2R))
        torque_e = -m * np.cross(rho * 1e-3, c_be @ f_b)
        torque_o = np.array(rot_y(tr["el_deg"] * D2R)).T @ torque_e
        got = (tr["imbalance_az_n_m"], tr["imbalance_el_n_m"])
        assert got == pytest.approx((torque_o[2], torque_e[1]), rel=1e-6)
        assert min(abs(torque_o[2]), abs(torque_e[1])) > 0.01


def test_yaw_swing_drags_the_azimuth_axis(rigid: PlantConfig) -> None:
    """Drive 0, 1 deg / 1 Hz yaw: friction and back-EMF couple the carrier into the azimuth axis, so the LOS
    turns with the carrier (inertial rate nonzero, same sign as r) instead of staying inertially still."""
    plant = Plant(with_(rigid, imbalance__mass_kg=0.0), seed=1)
    los, r = [], []
    for k in range(2000):
        plant.step_tick(0.0, 0.0, swing_carrier((k + 0.5) * 1e-3, 1.0, 1.0, pitch=False, yaw=True))
        tr = plant.truth()
        los.append(tr["los_rate_z_dps"])
        r.append(tr["carrier_r_dps"])
    los_a, r_a = np.array(los[500:]), np.array(r[500:])
    assert np.std(r_a) == pytest.approx(2 * math.pi / math.sqrt(2), rel=0.02)
    assert np.std(los_a) > 0.5 * np.std(r_a)
    assert np.corrcoef(los_a, r_a)[0, 1] > 0.9
    # no Coulomb friction: the back-EMF and viscous friction drag the axis, w / r = H(jw) of the linear model
    # L di/dt = -R i - K_e (w - r), J dw/dt = K_t i - D (w - r)
    d_visc = 0.05
    loose = Plant(with_(ideal(rigid), friction__az__viscous_n_m_s_per_rad=d_visc), seed=1)
    t, los2, r2 = [], [], []
    for k in range(3000):
        loose.step_tick(0.0, 0.0, swing_carrier((k + 0.5) * 1e-3, 1.0, 1.0, pitch=False, yaw=True))
        tr = loose.truth()
        t.append(loose.t_s)
        los2.append(tr["los_rate_z_dps"])
        r2.append(tr["carrier_r_dps"])
    tt = np.array(t)
    w = 2 * math.pi
    basis = np.column_stack([np.sin(w * tt), np.cos(w * tt), np.ones_like(tt), tt])  # + the slow transient
    cl, cr = (np.linalg.lstsq(basis, np.array(v), rcond=None)[0] for v in (los2, r2))
    ratio = complex(cl[0], cl[1]) / complex(cr[0], cr[1])
    m = rigid.motor_az
    a = np.array([[-m.resistance_ohm / m.inductance_h, -m.back_emf_v_s_per_rad / m.inductance_h],
                  [m.torque_constant_n_m_per_a / m.inertia_kg_m2, -d_visc / m.inertia_kg_m2]])
    b_r = [m.back_emf_v_s_per_rad / m.inductance_h, d_visc / m.inertia_kg_m2]
    expected = np.linalg.solve(1j * w * np.eye(2) - a, b_r)[1]
    assert 0.05 < abs(expected) < 0.2
    assert abs(ratio) == pytest.approx(abs(expected), rel=0.03)
    assert np.angle(ratio) == pytest.approx(np.angle(expected), abs=0.03)


def test_roll_reaches_the_elevation_axis_at_az_90(rigid: PlantConfig) -> None:
    """At az = 90 deg the elevation axis is along -x_b: the carrier rate on it is -p (seed 004 style,
    -sin(az) p + cos(az) q). A roll swing with drive 0 drags the elevation axis with rate ~ -p."""
    plant = Plant(with_(rigid, initial_az_deg=90.0, imbalance__mass_kg=0.0), seed=1)
    el, p, q_pitch = [], [], []
    for k in range(1500):
        t = (k + 0.5) * 1e-3
        w = 2 * math.pi
        carrier = CarrierMotion((0.0, 0.0, 0.0, math.sin(w * t), 0.0, 0.0),
                                (0.0, 0.0, 0.0, w * math.cos(w * t), 0.0, 0.0),
                                (0.0, 0.0, 0.0, -w * w * math.sin(w * t), 0.0, 0.0))
        plant.step_tick(0.0, 0.0, carrier)
        tr = plant.truth()
        el.append(tr["los_rate_y_dps"])
        p.append(tr["carrier_p_dps"])
        q_pitch.append(tr["el_rel_rate_dps"])
    el_a, p_a = np.array(el[300:]), np.array(p[300:])
    assert np.corrcoef(el_a, -p_a)[0, 1] > 0.9
    assert np.std(el_a) > 0.5 * np.std(p_a)
    assert np.max(np.abs(q_pitch[300:])) < 0.05 * np.max(np.abs(p_a))  # stuck to the carrier: little relative motion
    assert abs(plant.truth()["az_deg"] - 90.0) < 0.1


# --- imbalance ----------------------------------------------------------------------------------------------------


def test_static_imbalance_torque(rigid: PlantConfig) -> None:
    m, rho = 8.0, 2.0
    cfg = with_(rigid, imbalance__mass_kg=m, imbalance__eccentricity_mm=(rho, 0.0, 0.0))
    plant = Plant(cfg, seed=0)
    plant.step_tick(0.0, 0.0, REST)
    tr = plant.truth()
    # nose-heavy: gravity pulls the LOS down, a negative torque about y_e; magnitude m g |rho|
    assert tr["imbalance_el_n_m"] == pytest.approx(-m * G0 * rho * 1e-3, rel=1e-6)
    assert tr["imbalance_az_n_m"] == pytest.approx(0.0, abs=1e-12)
    # hexapod pitched 10 deg (nose up): the horizontal arm shortens by cos(10 deg)
    pitched = CarrierMotion((0.0, 0.0, 0.0, 0.0, 10.0, 0.0), REST.rate, REST.accel)
    plant = Plant(cfg, seed=0)
    plant.step_tick(0.0, 0.0, pitched)
    assert plant.truth()["imbalance_el_n_m"] == pytest.approx(-m * G0 * rho * 1e-3 * math.cos(10 * D2R), rel=1e-4)
    # pendulous (centre of mass below the pivot): no torque level, -m g rho_z sin(pitch) when pitched
    pend = with_(rigid, imbalance__mass_kg=m, imbalance__eccentricity_mm=(0.0, 0.0, rho))
    plant = Plant(pend, seed=0)
    plant.step_tick(0.0, 0.0, REST)
    assert plant.truth()["imbalance_el_n_m"] == pytest.approx(0.0, abs=1e-12)
    plant = Plant(pend, seed=0)
    plant.step_tick(0.0, 0.0, pitched)
    assert plant.truth()["imbalance_el_n_m"] == pytest.approx(-m * G0 * rho * 1e-3 * math.sin(10 * D2R), rel=1e-4)
    # a forward acceleration of the hexapod (1 m/s^2) on the pendulous gimbal swings its bottom back, which turns
    # the LOS down: -m rho_z a
    accel = CarrierMotion(REST.pose, REST.rate, (1000.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    plant = Plant(pend, seed=0)
    plant.step_tick(0.0, 0.0, accel)
    assert plant.truth()["imbalance_el_n_m"] == pytest.approx(-m * rho * 1e-3 * 1.0, rel=1e-4)


def test_imbalance_torque_against_vector_algebra(rigid: PlantConfig) -> None:
    rng = np.random.default_rng(4)
    imb = rigid.imbalance
    for _ in range(20):
        f_b = rng.normal(size=3) * 5
        az, el = rng.uniform(-math.pi, math.pi), rng.uniform(-1.2, 1.2)
        c_be = np.array(azel_rot_body_to_el(az, el))
        torque_e = -imb.mass_kg * np.cross(np.array(imb.eccentricity_mm) * 1e-3, c_be @ f_b)
        torque_o = np.array(rot_y(el)).T @ torque_e  # elevation -> azimuth frame
        got = imbalance_torques(imb, tuple(f_b), az, el)
        assert got == pytest.approx((torque_o[2], torque_e[1]), abs=1e-12)


# --- camera -------------------------------------------------------------------------------------------------------


def test_camera_signs_follow_the_gimbal_rates(rigid: PlantConfig) -> None:
    """Target fixed on the home LOS: a positive az rate makes miss_x decrease, a positive el rate miss_y."""
    cfg = ideal(rigid)
    for axis, idx in (("az", 0), ("el", 1)):
        plant = Plant(cfg, seed=0)
        plant.step_tick(0.0, 0.0, REST)
        start = plant.miss_px()
        assert start[:2] == pytest.approx((0.0, 0.0), abs=1e-9) and start[2]
        for _ in range(100):
            plant.step_tick(2000.0 if axis == "az" else 0.0, 2000.0 if axis == "el" else 0.0, REST)
        tr = plant.truth()
        assert tr[f"{axis}_rate_dps"] > 1.0
        miss = plant.miss_px()
        assert miss[idx] < -10.0 and abs(miss[1 - idx]) < 1e-6 * abs(miss[idx])
        # small angles: the miss is minus the gimbal angle over the IFOV
        assert miss[idx] == pytest.approx(-tr[f"{axis}_deg"] / cfg.camera.ifov_deg_per_px, rel=1e-3)


def test_camera_geometry_and_field_of_view(rigid: PlantConfig) -> None:
    cfg = ideal(rigid)
    ifov = cfg.camera.ifov_deg_per_px

    def miss(**changes: Any) -> tuple[float, float, bool]:
        carrier = changes.pop("carrier", REST)
        plant = Plant(with_(cfg, **changes), seed=0)
        plant.step_tick(0.0, 0.0, carrier)
        return plant.miss_px()

    x, y, ok = miss(camera__target_az_deg=0.4, camera__target_el_deg=0.3)  # target right and up
    assert ok and x == pytest.approx(0.4 / ifov, rel=1e-3) and y == pytest.approx(0.3 / ifov, rel=1e-3)
    # the hexapod yawed right by 0.2 deg carries the LOS right: the target appears left
    x, _, _ = miss(carrier=CarrierMotion((0.0, 0.0, 0.0, 0.0, 0.0, 0.2), REST.rate, REST.accel))
    assert x == pytest.approx(-0.2 / ifov, rel=1e-3)
    # pitched up 0.2 deg: the target appears down
    _, y, _ = miss(carrier=CarrierMotion((0.0, 0.0, 0.0, 0.0, 0.2, 0.0), REST.rate, REST.accel))
    assert y == pytest.approx(-0.2 / ifov, rel=1e-3)
    half_w = cfg.camera.half_width_px * ifov
    assert miss(camera__target_az_deg=0.99 * half_w)[2]
    assert not miss(camera__target_az_deg=1.01 * half_w)[2]
    assert not miss(camera__target_el_deg=-1.01 * cfg.camera.half_height_px * ifov)[2]
    assert not miss(camera__target_az_deg=180.0)[2]  # behind the camera


def test_camera_centroid_noise(rigid: PlantConfig) -> None:
    cfg = with_(rigid, imbalance__mass_kg=0.0, camera__centroid_noise_std_px=0.5)
    plant = Plant(cfg, seed=2)
    xs = []
    for _ in range(4000):
        plant.step_tick(0.0, 0.0, REST)
        xs.append(plant.miss_px()[0] - plant.truth()["los_error_x_deg"] / cfg.camera.ifov_deg_per_px)
    assert np.std(xs) == pytest.approx(0.5, rel=0.05)


# --- calibration against the paper (docs/emulator.md) --------------------------------------------------------------


def test_static_gyro_peak_is_the_papers(rigid: PlantConfig) -> None:
    """Seed 000 Fig 12a: +-0.102 deg/s static noise, read as the median over 1 s records of max |x - mean|."""
    st = static_gyro_peak(rigid, records=10)
    print(f"static gyro peak {st['peak_dps']:.3f} deg/s, std {st['std_dps']:.4f}")
    assert 0.08 <= st["peak_dps"] <= 0.13


def test_closed_loop_eso_rate_error_is_of_the_papers_order(rigid: PlantConfig) -> None:
    """Seed 000 Table 1, plain ESO under the 1 deg / 1 Hz swing: std 0.32 deg/s, range +-0.72; the emulator must be
    within a factor ~2 (docs/emulator.md has the numbers for all three controllers)."""
    res = run_closed_loop("eso", config=rigid, seconds=5.0)
    for axis in ("el", "az"):
        s = res.axis(axis)
        print(f"eso {axis}: std {s.std_dps:.3f} deg/s, range +-{s.range_dps:.2f}, true std {s.true_std_dps:.3f}")
        assert 0.15 <= s.std_dps <= 0.65
        assert 0.36 <= s.range_dps <= 1.44
    # without the swing the loop only sees gyro noise: the error collapses to the noise level
    quiet = run_closed_loop("eso", config=rigid, seconds=2.0, amplitude_deg=0.0)
    assert quiet.el.std_dps < 0.05


@pytest.mark.parametrize("seed", [1, 4])
def test_paper_ordering_of_rate_error_and_miss_distance(rigid: PlantConfig, seed: int) -> None:
    """Seed 000 Tables 1-2 on a short run: under the 1 deg / 1 Hz swing ESO > ESO + KF > high-gain ESO + KF in the
    rate error (rate command 0) and in the camera's miss distance (tracking on), on both axes. The paper's margin
    (miss std 55 % lower with ESO + KF) is NOT reached: the emulator gives ~7 % (docs/emulator.md says why)."""
    names = ("eso", "eso_kf", "eso_kf_high_gain")
    rate = {n: run_closed_loop(n, config=rigid, seconds=2.0, seed=seed) for n in names}
    miss = {n: run_closed_loop(n, config=rigid, seconds=2.0, tracking=True, seed=seed) for n in names}
    for axis in ("el", "az"):
        r = [rate[n].axis(axis).std_dps for n in names]
        m = [miss[n].axis(axis).miss_std_px for n in names]
        print(f"seed {seed} {axis}: rate std {r[0]:.3f} / {r[1]:.3f} / {r[2]:.3f} deg/s, "
              f"miss std {m[0]:.2f} / {m[1]:.2f} / {m[2]:.2f} px")
        assert r[0] > 1.02 * r[1] > 1.02 * 1.5 * r[2]
        assert m[0] > 1.04 * m[1] > 1.04 * 2.0 * m[2]
        assert 2.0 <= m[0] <= 12.0  # paper 6.02 px (ESO, Table 2)


def test_kalman_filter_is_quieter_than_the_low_pass_and_lags_less(rigid: PlantConfig) -> None:
    """Seed 000 Figs 12-13: at rest the KF's rate is at least as quiet as a 150 Hz low-pass of the raw gyro; under a
    5 deg/s 15 Hz rate command it is off the raw gyro's timing by less than the low-pass is (it predicts with the
    drive, and leads the delayed gyro: a lead counts by its magnitude, as the campaigns compare lags)."""
    st = static_filters(rigid, seconds=4.0)
    lag = filter_lag(rigid, seconds=1.0)
    print(f"peaks raw {st['raw']:.3f} lpf {st['lpf']:.3f} kf {st['kf']:.3f}; lag lpf {lag['lpf']:.2f} "
          f"kf {lag['kf']:.2f} loop cycles (1 ms)")
    assert st["kf"] <= st["lpf"] < 0.8 * st["raw"]
    assert abs(lag["kf"]) < lag["lpf"]
    assert 0.5 < lag["lpf"] < 0.8  # first-order 150 Hz at 1 kHz: (1 - a) / a = 0.64 loop cycles


# --- configuration ------------------------------------------------------------------------------------------------


def test_default_config_file() -> None:
    assert DEFAULT_PLANT_CONFIG.is_file()
    assert Path(__file__).parents[2] / "profiles/plant/default.yaml" == DEFAULT_PLANT_CONFIG
    default = load_plant_config(DEFAULT_PLANT_CONFIG)
    assert default.camera.frame_rate_hz == 100.0 and default.camera.latency_frames == 1
    assert default.hexapod.pitch.angle_deg > 3.0
    for path in (DEFAULT_PLANT_CONFIG, RIGID_PLANT_CONFIG):
        for line in path.read_text().splitlines():  # every parameter line has a comment with its source
            if ":" in line and not line.lstrip().startswith("#") and not line.rstrip().endswith(":"):
                assert "#" in line, line


@pytest.mark.parametrize(
    ("change", "field", "reason"),
    [
        (lambda d: d["motor_el"].update(foo=1.0), "motor_el.foo", "unknown field"),
        (lambda d: d["motor_el"].update(resistance_ohm=-1.0), "motor_el.resistance_ohm", "greater than 0"),
        (lambda d: d["gyro"].update(noise_std_dps=[0.03, -0.1, 0.03]), "gyro.noise_std_dps", ">= 0"),
        (lambda d: d.update(internal_step_s=3e-4), "internal_step_s", "less than or equal"),
        (lambda d: d.update(internal_step_s=0.15e-3), "internal_step_s", "does not divide"),
        (lambda d: d["friction"]["el"].update(smoothing_rate_dps=0.001), "friction.el.smoothing_rate_dps",
         "unstable"),
        (lambda d: d.pop("camera"), "camera", "required"),
    ],
)
def test_config_errors_are_one_line_naming_the_field(tmp_path: Path, change: Any, field: str, reason: str) -> None:
    assert_config_error(tmp_path, RIGID_PLANT_CONFIG, change, field, reason)


def test_config_file_errors(tmp_path: Path) -> None:
    with pytest.raises(PlantConfigError, match="cannot read"):
        load_plant_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("gyro: [1, 2\n")
    with pytest.raises(PlantConfigError, match="not valid YAML"):
        load_plant_config(bad)
    bad.write_text("- 1\n")
    with pytest.raises(PlantConfigError, match="mapping"):
        load_plant_config(bad)
