"""ESO + KF tests: Riccati steady state, filterpy cross-check, noise reduction and lag vs a 150 Hz first-order LPF."""

from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from hil.control.kalman import EsoKalman, steady_state_kalman

H_S = 1e-3
KM = 0.023
GYRO_SIGMA_DPS = 0.034  # paper Fig 12a: +-0.102 deg/s peak ~ 3 sigma
R_DPS2 = GYRO_SIGMA_DPS**2
W_DPS2 = 1e-5  # S + Q used in the noise/lag tests (the paper gives no values)
F_HZ = 15.0  # paper Fig 13: 5 deg / 15 Hz
LPF_A = 1.0 - math.exp(-2.0 * math.pi * 150.0 * H_S)  # the paper's 150 Hz low-pass, first order, 1 kHz


def make(omega_o: float, *, w: float = W_DPS2, steady_state: bool = True) -> EsoKalman:
    return EsoKalman(
        omega_o_rad_s=omega_o,
        b0_dps2_per_count=KM,
        dt_s=H_S,
        q_dps2=0.5 * w,
        s_dps2=0.5 * w,
        r_dps2=R_DPS2,
        steady_state=steady_state,
    )


def lpf(x: np.ndarray) -> np.ndarray:
    y, v = np.empty_like(x), 0.0
    for i, xi in enumerate(x):
        v += LPF_A * (xi - v)
        y[i] = v
    return y


def phase_rad(signal: np.ndarray, t: np.ndarray, f_hz: float) -> float:
    """Phase of the f_hz component by least squares on sin, cos and offset."""
    basis = np.column_stack([np.sin(2 * np.pi * f_hz * t), np.cos(2 * np.pi * f_hz * t), np.ones_like(t)])
    s, c, _ = np.linalg.lstsq(basis, signal, rcond=None)[0]
    return math.atan2(c, s)


def lag_periods(reference: np.ndarray, filtered: np.ndarray, t: np.ndarray, skip: int = 2000) -> float:
    """The lag at F_HZ in periods of the F_HZ sine (not 1 ms loop cycles: times 1 / (F_HZ * H_S) for those)."""
    d = phase_rad(reference[skip:], t[skip:], F_HZ) - phase_rad(filtered[skip:], t[skip:], F_HZ)
    return ((d + math.pi) % (2 * math.pi) - math.pi) / (2 * math.pi)


def sine_motion(n: int, rng: np.random.Generator, amp_dps: float = 5.0):
    """Rate = amp sin(2 pi 15 t) exactly at the samples, the drive that makes it (ZOH), and noisy gyro samples."""
    t = np.arange(n + 1) * H_S
    rate = amp_dps * np.sin(2 * np.pi * F_HZ * t)
    u_counts = np.diff(rate) / (H_S * KM)  # u[k] held over [k, k+1]
    gyro = rate + rng.normal(0.0, GYRO_SIGMA_DPS, n + 1)
    return t, rate, u_counts, gyro


def run(kf: EsoKalman, gyro: np.ndarray, u_counts: np.ndarray | None) -> np.ndarray:
    """Filter samples 0..N; sample k is stepped with the drive held over [k-1, k] (zero before the start)."""
    out = np.empty(len(gyro))
    u_prev = 0.0
    for k, y in enumerate(gyro):
        out[k] = kf.step(float(y), u_prev)
        if u_counts is not None and k < len(u_counts):
            u_prev = float(u_counts[k])
    return out


def closed_loop_matrices(kf: EsoKalman) -> tuple[np.ndarray, np.ndarray]:
    """Linear map [x, z1, z2]_{k} = A [x, z1, z2]_{k-1} + B y_k of the steady-state ESO + KF (u = 0), from the
    paper's equations: KF eq 44-45 with prediction x + h z2, then the ESO measuring the KF output."""
    k = kf.gain
    l1, l2 = kf.eso.gains
    x_row, x_in = np.array([1 - k, 0.0, (1 - k) * H_S]), k
    p1 = np.array([0.0, 1.0, H_S])
    a = np.vstack([x_row, p1 + l1 * (x_row - p1), np.array([0.0, 0.0, 1.0]) + l2 * (x_row - p1)])
    b = np.array([x_in, l1 * x_in, l2 * x_in])
    return a, b


# ------------------------------------------------------------------------------------------- gain / Riccati


@pytest.mark.parametrize(("w", "r"), [(1e-6, R_DPS2), (1e-5, R_DPS2), (1e-3, R_DPS2), (2.0, 0.5), (1e-9, 1.0)])
def test_steady_state_gain_is_the_discrete_riccati_solution(w: float, r: float) -> None:
    p = r  # iterate eqs 44-45 on P alone until it stops moving
    for _ in range(1_000_000):
        m = p + w
        k = m / (m + r)
        p_new = (1.0 - k) * m
        if abs(p_new - p) <= 1e-15 * p:
            break
        p = p_new
    k_closed, m_closed, p_closed = steady_state_kalman(w_dps2=w, r_dps2=r)
    assert k_closed == pytest.approx(k, rel=1e-9)
    assert p_closed == pytest.approx(p, rel=1e-9)
    assert m_closed == pytest.approx(p + w, rel=1e-9)

    kf = EsoKalman(
        omega_o_rad_s=300.0, b0_dps2_per_count=KM, dt_s=H_S, q_dps2=w / 2, s_dps2=w / 2, r_dps2=r, steady_state=True
    )
    assert kf.gain == pytest.approx(k, rel=1e-9)
    assert kf.p_dps2 == pytest.approx(p, rel=1e-9)


def test_time_varying_filter_matches_filterpy_and_converges_to_steady_gain() -> None:
    rng = np.random.default_rng(2)
    ours = make(300.0, steady_state=False)
    ref = KalmanFilter(dim_x=1, dim_z=1, dim_u=1)
    ref.x = np.array([[0.0]])
    ref.P = np.array([[R_DPS2]])
    ref.F, ref.H = np.array([[1.0]]), np.array([[1.0]])
    ref.B = np.array([[H_S * KM]])
    ref.Q, ref.R = np.array([[W_DPS2]]), np.array([[R_DPS2]])
    for _ in range(3000):
        y, u = float(rng.normal(0.0, 1.0)), float(rng.uniform(-100.0, 100.0))
        # eq 44 with the applied drive plus the ESO's disturbance estimate (u0 = u + z2 / b0)
        ref.predict(u=np.array([[u + ours.eso.z2 / KM]]))
        ref.update(np.array([[y]]))
        assert ours.step(y, u) == pytest.approx(float(ref.x[0, 0]), rel=1e-9, abs=1e-12)
        assert ours.p_dps2 == pytest.approx(float(ref.P[0, 0]), rel=1e-9)
    assert ours.gain == pytest.approx(steady_state_kalman(w_dps2=W_DPS2, r_dps2=R_DPS2)[0], rel=1e-9)


@pytest.mark.parametrize("omega_o", [10.0, 100.0, 300.0, 1000.0, 5000.0, 20000.0])
@pytest.mark.parametrize("w", [1e-9, 1e-5, 1e-3, 10.0])
def test_eso_plus_kf_loop_is_stable(omega_o: float, w: float) -> None:
    a, _ = closed_loop_matrices(make(omega_o, w=w))
    assert np.max(np.abs(np.linalg.eigvals(a))) < 1.0


# ------------------------------------------------------------------------------------------- disturbance


@pytest.mark.parametrize("omega_o", [300.0, 1000.0])
def test_step_disturbance_estimated_through_the_kf(omega_o: float) -> None:
    rng = np.random.default_rng(4)
    n, d, u_max = 4000, 2500.0, 2000.0
    kf, rate, u_applied = make(omega_o), 0.0, 0.0
    for _ in range(n):  # closed loop, drive saturated (d exceeds the authority): fed the applied drive
        rate += H_S * KM * (u_applied + d)
        kf.step(rate, u_applied)
        u_cmd = 30.0 * (0.0 - kf.rate_dps) / KM - kf.disturbance_counts
        u_applied = min(max(u_cmd, -u_max), u_max)
        # bounded (no windup). The combined ESO + KF has a lightly damped complex pole pair (e.g. 0.94 +- 0.19j at
        # 1000 rad/s, W = 1e-5), so its estimate overshoots a step by 30-50 % whatever drive is applied.
        assert abs(kf.disturbance_counts) <= 1.6 * d
    assert kf.disturbance_counts == pytest.approx(d, rel=1e-6)
    assert kf.rate_dps == pytest.approx(rate, rel=1e-9)
    # unsaturated loop with gyro noise: the rate is held near zero
    kf, rate, u_applied, d_small, rates, est = make(omega_o), 0.0, 0.0, 500.0, [], []
    for _ in range(n):
        rate += H_S * KM * (u_applied + d_small)
        kf.step(rate + float(rng.normal(0.0, GYRO_SIGMA_DPS)), u_applied)
        u_applied = min(max(30.0 * (0.0 - kf.rate_dps) / KM - kf.disturbance_counts, -u_max), u_max)
        rates.append(rate)
        est.append(kf.disturbance_counts)
    assert abs(np.mean(rates[n // 2 :])) < 0.01
    assert np.mean(est[n // 2 :]) == pytest.approx(d_small, rel=0.05)


# ------------------------------------------------------------------------------------------- noise and lag


def test_static_gyro_noise_is_reduced_as_the_lyapunov_equation_predicts() -> None:
    rng = np.random.default_rng(8)
    noise = rng.normal(0.0, GYRO_SIGMA_DPS, 100_000)
    kf = make(300.0)
    out = run(kf, noise, None)[1000:]
    a, b = closed_loop_matrices(kf)
    cov = np.linalg.solve(np.eye(9) - np.kron(a, a), np.outer(b, b).ravel() * R_DPS2).reshape(3, 3)
    ratio, predicted = np.std(out) / GYRO_SIGMA_DPS, math.sqrt(cov[0, 0]) / GYRO_SIGMA_DPS
    assert ratio == pytest.approx(predicted, rel=0.03)
    lpf_ratio = math.sqrt(LPF_A / (2.0 - LPF_A))  # first-order IIR on white noise
    assert np.std(lpf(noise)[1000:]) / GYRO_SIGMA_DPS == pytest.approx(lpf_ratio, rel=0.03)
    # paper Fig 12: 0.102 -> 0.038 (KF), 0.042 (LPF). Here: KF ~0.34, 150 Hz first-order LPF ~0.66 of the raw std
    assert ratio < 0.4
    assert ratio < 0.6 * lpf_ratio


def test_lpf_lag_measurement_matches_its_analytic_phase() -> None:
    t, rate, _, gyro = sine_motion(20_000, np.random.default_rng(9))
    w = 2.0 * math.pi * F_HZ * H_S
    analytic = math.atan2((1.0 - LPF_A) * math.sin(w), 1.0 - (1.0 - LPF_A) * math.cos(w)) / (2.0 * math.pi)
    assert lag_periods(rate, lpf(gyro), t) == pytest.approx(analytic, abs=2e-4)  # ~0.0095 periods, 0.63 ms


@pytest.mark.parametrize("omega_o", [100.0, 300.0, 1000.0])
def test_kf_lags_less_than_lpf_on_commanded_motion(omega_o: float) -> None:
    # Fig 13's case: the platform is driven (closed loop) at 15 Hz, so the drive explains the motion to the KF.
    t, rate, u, gyro = sine_motion(20_000, np.random.default_rng(10))
    kf_lag = lag_periods(rate, run(make(omega_o), gyro, u), t)
    lpf_lag = lag_periods(rate, lpf(gyro), t)
    assert abs(kf_lag) < 1e-3 < lpf_lag


@pytest.mark.parametrize(("omega_o", "kf_lags_less"), [(100.0, False), (300.0, False), (1000.0, True)])
def test_lag_on_unmodelled_motion_depends_on_eso_bandwidth(omega_o: float, kf_lags_less: bool) -> None:
    # Same 15 Hz rate, caused by a disturbance (u = 0): the KF knows it only through the ESO's z2, so its lag
    # falls with omega_o (the paper's "high-gain ESO + KF"); at 100-300 rad/s it lags more than the 150 Hz LPF.
    t, rate, _, gyro = sine_motion(20_000, np.random.default_rng(12))
    kf_lag = lag_periods(rate, run(make(omega_o), gyro, None), t)
    lpf_lag = lag_periods(rate, lpf(gyro), t)
    assert kf_lag > 0.0
    assert (kf_lag < lpf_lag) is kf_lags_less
    if kf_lags_less:  # and it still filters more than the LPF
        noise = np.random.default_rng(13).normal(0.0, GYRO_SIGMA_DPS, 20_000)
        assert np.std(run(make(omega_o), noise, None)[1000:]) < np.std(lpf(noise)[1000:])


def test_random_walk_kalman_matches_filterpy_step_by_step() -> None:
    import random

    from filterpy.kalman import KalmanFilter

    from hil.control.kalman import RandomWalkKalman

    ours = RandomWalkKalman(q=1e-3, r=0.1, p0=1.0)
    ref = KalmanFilter(dim_x=1, dim_z=1)
    ref.x[:] = 0.0
    ref.P[:] = 1.0
    ref.F[:] = 1.0
    ref.H[:] = 1.0
    ref.Q[:] = 1e-3
    ref.R[:] = 0.1
    rng = random.Random(4)
    for k in range(500):
        y = math.sin(0.05 * k) + rng.gauss(0.0, 0.3)
        ref.predict()
        ref.update(y)
        assert ours.step(y) == pytest.approx(float(ref.x[0, 0]), abs=1e-12)
    assert ours.p == pytest.approx(float(ref.P[0, 0]), rel=1e-9)
