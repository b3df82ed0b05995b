"""ESO tests against analytic truth: ZOH plant simulation, pole locations, closed-form gains, Euler divergence."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.control.eso import LinearESO, NonlinearESO, current_observer_gains, fal

H_S = 1e-3  # 1 kHz rate loop
KM = 0.023  # paper eq 38: deg/s^2 per DAC count
GYRO_SIGMA_DPS = 0.034  # paper Fig 12: +-0.102 deg/s peak ~ 3 sigma


def simulate_plant(u_counts: np.ndarray, d_counts: np.ndarray, rate0_dps: float = 0.0) -> np.ndarray:
    """Exact ZOH solution of d(rate)/dt = KM (u + d), u and d held over each interval: rate[k+1] = rate[k] + ..."""
    rate = np.empty(len(u_counts) + 1)
    rate[0] = rate0_dps
    rate[1:] = rate0_dps + np.cumsum(H_S * KM * (u_counts + d_counts))
    return rate


def run_observer(eso, rate_meas: np.ndarray, u_counts: np.ndarray) -> np.ndarray:
    """Feed samples 1..N: measurement k with the drive held over [k-1, k]. Returns disturbance_counts per step."""
    eso.reset(float(rate_meas[0]))
    out = np.empty(len(u_counts))
    for k in range(len(u_counts)):
        eso.step(float(rate_meas[k + 1]), float(u_counts[k]))
        out[k] = eso.disturbance_counts
    return out


def error_matrix(eso) -> np.ndarray:
    """(I - L C) Phi of the current observer, built from the class's gains."""
    l1, l2 = eso.gains
    phi = np.array([[1.0, H_S], [0.0, 1.0]])
    lc = np.array([[l1], [l2]]) @ np.array([[1.0, 0.0]])
    return (np.eye(2) - lc) @ phi


def crossing_time_s(err: np.ndarray, threshold: float) -> float:
    """First time (sample k -> k*h, disturbance switched on at t = 0) at which |err| <= threshold."""
    return (int(np.argmax(np.abs(err) <= threshold)) + 1) * H_S


def solve_continuous_step_error(level: float) -> float:
    """omega*t at which (1 + omega t) exp(-omega t) = level (double pole at -omega), by bisection."""
    lo, hi = 0.0, 50.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if (1.0 + mid) * math.exp(-mid) > level else (lo, mid)
    return lo


# ---------------------------------------------------------------------------------------------- LinearESO


@pytest.mark.parametrize("omega_o", [50.0, 100.0, 200.0])
def test_step_disturbance_converges_at_the_two_pole_rate(omega_o: float) -> None:
    rng = np.random.default_rng(7)
    n, d = 1000, 500.0
    u = rng.uniform(-1000.0, 1000.0, n)  # arbitrary known drive: the error dynamics must not depend on it
    rate = simulate_plant(u, np.full(n, d), rate0_dps=3.0)
    est = run_observer(LinearESO(omega_o_rad_s=omega_o, b0_dps2_per_count=KM, dt_s=H_S), rate, u)
    err = (d - est) / d

    # Exact discrete truth: e2_k / e2_0 = q^k (1 + k (1 - q)), q = exp(-omega h) (double pole of (I - LC) Phi).
    q = math.exp(-omega_o * H_S)
    k = np.arange(1, n + 1)
    np.testing.assert_allclose(err, q**k * (1.0 + k * (1.0 - q)), rtol=1e-7, atol=1e-9)
    assert abs(est[-1] - d) < 1e-6 * d

    # Continuous truth (1 + w t) e^{-w t}: 63 % and 95 % times within 3 % + one sample.
    for level in (math.exp(-1.0), 0.05):
        t_expected = solve_continuous_step_error(level) / omega_o
        assert crossing_time_s(err, level) == pytest.approx(t_expected, rel=0.03, abs=H_S)


def test_crossing_times_of_the_continuous_double_pole() -> None:
    # 63 %: omega t = 2.146; 95 %: omega t = 4.744 (21.5 ms and 47.4 ms at 100 rad/s)
    assert solve_continuous_step_error(math.exp(-1.0)) == pytest.approx(2.1462, abs=1e-4)
    assert solve_continuous_step_error(0.05) == pytest.approx(4.7439, abs=1e-4)


@pytest.mark.parametrize("omega_o", [10.0, 100.0, 1000.0, 2000.0, 5000.0, 20000.0])
def test_discrete_observer_poles_are_exp_minus_omega_h(omega_o: float) -> None:
    eso = LinearESO(omega_o_rad_s=omega_o, b0_dps2_per_count=KM, dt_s=H_S)
    m = error_matrix(eso)
    q = math.exp(-omega_o * H_S)
    np.testing.assert_allclose(np.poly(m), [1.0, -2.0 * q, q * q], atol=1e-12)
    # a double (defective) eigenvalue is only determined to ~sqrt(eps) numerically
    np.testing.assert_allclose(np.linalg.eigvals(m), [q, q], atol=1e-6)


@pytest.mark.parametrize("omega_o", [100.0, 1000.0, 5000.0])
def test_gains_match_ackermann_for_the_current_estimator(omega_o: float) -> None:
    # Current estimator: error matrix Phi - L C Phi, i.e. observer pole placement for the pair (Phi, C Phi).
    # Ackermann: L = alpha(Phi) [C Phi; C Phi^2]^-1 [0, 1]^T with alpha(z) = (z - q)^2.
    phi = np.array([[1.0, H_S], [0.0, 1.0]])
    c = np.array([[1.0, 0.0]])
    q = math.exp(-omega_o * H_S)
    alpha_phi = phi @ phi - 2.0 * q * phi + q * q * np.eye(2)
    obs = np.vstack([c @ phi, c @ phi @ phi])
    l_ackermann = alpha_phi @ np.linalg.solve(obs, np.array([0.0, 1.0]))

    eso = LinearESO(omega_o_rad_s=omega_o, b0_dps2_per_count=KM, dt_s=H_S)
    np.testing.assert_allclose(eso.gains, l_ackermann, rtol=1e-9)
    # and the textbook closed form (Miklosovic et al. 2006): l1 = 1 - q^2, l2 = (1 - q)^2 / h
    assert eso.l1 == pytest.approx(1.0 - q * q, rel=1e-12)
    assert eso.l2_per_s == pytest.approx((1.0 - q) ** 2 / H_S, rel=1e-12)


@pytest.mark.parametrize(("beta1", "beta2"), [(300.0, 10_000.0), (100.0, 40_000.0), (3000.0, 1.0e6)])
def test_general_beta_gains_place_matched_poles(beta1: float, beta2: float) -> None:
    # distinct real, complex and real (overdamped) continuous poles map to exp(s_i h)
    eso = NonlinearESO(beta1_per_s=beta1, beta2_per_s2=beta2, b0_dps2_per_count=KM, dt_s=H_S)
    expected = np.sort_complex(np.exp(np.roots([1.0, beta1, beta2]) * H_S))
    np.testing.assert_allclose(np.sort_complex(np.linalg.eigvals(error_matrix(eso))), expected, atol=1e-9)


def euler_eso_error_growth(omega_o: float, n: int, d: float) -> float:
    """Forward-Euler ESO of eq 10 on the same exact plant: max |disturbance error| over the run, relative to d."""
    z1 = z2 = 0.0
    rate, worst = 0.0, 0.0
    for _ in range(n):
        rate += H_S * KM * d
        e = z1 - rate
        z1, z2 = z1 + H_S * (z2 - 2.0 * omega_o * e), z2 + H_S * (-omega_o * omega_o * e)
        worst = max(worst, abs(KM * d - z2) / (KM * d))
    return worst


@pytest.mark.parametrize("omega_h", [1.0, 2.0, 5.0])
def test_zoh_observer_stable_where_forward_euler_is_not(omega_h: float) -> None:
    omega_o, n, d = omega_h / H_S, 2000, 200.0
    rng = np.random.default_rng(3)
    u = np.zeros(n)
    rate = simulate_plant(u, np.full(n, d))
    eso = LinearESO(omega_o_rad_s=omega_o, b0_dps2_per_count=KM, dt_s=H_S)
    est = run_observer(eso, rate, u)
    assert np.max(np.abs(est)) <= d * (1.0 + 1e-9)  # error (1 + k(1-q)) q^k is monotone: no overshoot
    assert abs(est[-1] - d) < 1e-9 * d
    # with gyro noise it stays bounded too
    noisy = rate + rng.normal(0.0, GYRO_SIGMA_DPS, n + 1)
    est_noisy = run_observer(eso, noisy, u)
    assert np.all(np.isfinite(est_noisy))
    # bounded: white noise reaches z2 through l2 (z2 std ~ 1.4 l2 sigma here), no divergence
    assert np.max(np.abs(est_noisy[n // 2 :] - d)) < 8.0 * eso.l2_per_s * GYRO_SIGMA_DPS / KM

    # Forward Euler: error matrix [[1 - 2wh, h], [-w^2 h, 1]] has a double pole at 1 - wh.
    growth = euler_eso_error_growth(omega_o, n, d)
    if omega_h >= 2.0:
        assert growth > 100.0  # |1 - wh| >= 1: diverges (linearly at wh = 2, geometrically beyond)
    else:
        assert growth < 1.5  # wh = 1 happens to be Euler's deadbeat point (double pole at 0); it diverges from 2


def test_reset_and_disturbance_property() -> None:
    eso = LinearESO(omega_o_rad_s=300.0, b0_dps2_per_count=KM, dt_s=H_S)
    eso.reset(rate_dps=1.5, disturbance_counts=40.0)
    assert eso.z1 == 1.5
    assert eso.rate_dps == 1.5
    assert eso.z2 == pytest.approx(40.0 * KM)
    assert eso.disturbance_counts == pytest.approx(40.0)
    # a consistent measurement leaves the state on the model trajectory
    z1 = eso.step(1.5 + H_S * KM * (40.0 + 10.0), 10.0)
    assert z1 == pytest.approx(1.5 + H_S * KM * 50.0, abs=1e-12)
    assert eso.disturbance_counts == pytest.approx(40.0, abs=1e-9)


# ---------------------------------------------------------------------------------------------- anti-windup


@pytest.mark.parametrize(
    "make",
    [
        lambda: LinearESO(omega_o_rad_s=300.0, b0_dps2_per_count=KM, dt_s=H_S),
        lambda: NonlinearESO(omega_o_rad_s=300.0, b0_dps2_per_count=KM, dt_s=H_S, delta_dps=0.01),
    ],
    ids=["linear", "fal"],
)
def test_saturated_drive_does_not_wind_up_the_disturbance_state(make) -> None:
    u_max, d, kp = 2000.0, 3000.0, 50.0  # the disturbance exceeds the drive authority
    n = 3000

    def closed_loop(feed_applied: bool) -> np.ndarray:
        eso, rate, u_cmd, u_applied, history = make(), 0.0, 0.0, 0.0, np.empty(n)
        for k in range(n):
            rate += H_S * KM * (u_applied + d)  # plant over the last interval with the applied drive
            eso.step(rate, u_applied if feed_applied else u_cmd)
            u_cmd = kp * (0.0 - eso.z1) / KM - eso.disturbance_counts
            u_applied = min(max(u_cmd, -u_max), u_max)
            history[k] = eso.disturbance_counts
        return history

    good = closed_loop(feed_applied=True)
    assert np.all(np.abs(good) <= d * (1.0 + 1e-6))
    assert good[-1] == pytest.approx(d, rel=1e-6)
    wound = closed_loop(feed_applied=False)  # fed the commanded drive: z2 absorbs sat(u) - u and runs away
    assert abs(wound[-1]) > 10.0 * d


# ---------------------------------------------------------------------------------------------- NonlinearESO


def test_fal_is_continuous_odd_with_linear_zone_slope() -> None:
    alpha, delta = 0.5, 0.01
    assert fal(delta, alpha, delta) == pytest.approx(delta**alpha)
    assert fal(delta * (1 + 1e-9), alpha, delta) == pytest.approx(fal(delta, alpha, delta), rel=1e-8)
    assert fal(1e-4, alpha, delta) / 1e-4 == pytest.approx(delta ** (alpha - 1.0))  # x10 for delta = 0.01
    assert fal(-0.3, alpha, delta) == pytest.approx(-(0.3**alpha))
    assert fal(4.0, 1.0, delta) == 4.0


def test_fal_eso_equals_linear_eso_inside_the_linear_zone() -> None:
    rng = np.random.default_rng(11)
    n = 3000
    u = rng.uniform(-500.0, 500.0, n)
    d = np.where(np.arange(n) > 500, 150.0, 0.0)
    meas = simulate_plant(u, d) + rng.normal(0.0, GYRO_SIGMA_DPS, n + 1)
    lin = LinearESO(omega_o_rad_s=400.0, b0_dps2_per_count=KM, dt_s=H_S)
    nl = NonlinearESO(omega_o_rad_s=400.0, b0_dps2_per_count=KM, dt_s=H_S, delta_dps=10.0)  # every error inside
    assert nl.gains == lin.gains
    np.testing.assert_allclose(run_observer(nl, meas, u), run_observer(lin, meas, u), rtol=0, atol=1e-9)


@pytest.mark.parametrize("omega_o", [100.0, 1000.0])
def test_fal_eso_converges_on_a_step_disturbance(omega_o: float) -> None:
    n, d = 3000, 2000.0
    u = np.zeros(n)
    rate = simulate_plant(u, np.full(n, d))
    nl = NonlinearESO(omega_o_rad_s=omega_o, b0_dps2_per_count=KM, dt_s=H_S, delta_dps=1e-3)
    est_nl = run_observer(nl, rate, u)
    est_lin = run_observer(LinearESO(omega_o_rad_s=omega_o, b0_dps2_per_count=KM, dt_s=H_S), rate, u)
    assert np.max(np.abs(est_nl - est_lin)) > 0.01 * d  # the nonlinear zone was exercised
    assert abs(est_nl[-1] - d) < 1e-6 * d
    assert np.max(np.abs(est_nl)) < 1.5 * d


def test_fal_eso_stable_at_1000_rad_s_with_gyro_noise() -> None:
    rng = np.random.default_rng(5)
    n, d = 20000, 300.0
    u = rng.uniform(-200.0, 200.0, n)
    meas = simulate_plant(u, np.full(n, d)) + rng.normal(0.0, GYRO_SIGMA_DPS, n + 1)
    nl = NonlinearESO(omega_o_rad_s=1000.0, b0_dps2_per_count=KM, dt_s=H_S)  # default alpha, delta
    est = run_observer(nl, meas, u)
    tail = est[n // 2 :]
    assert np.all(np.isfinite(est))
    assert abs(np.mean(tail) - d) < 0.05 * d  # unbiased on average
    lin_tail = run_observer(LinearESO(omega_o_rad_s=1000.0, b0_dps2_per_count=KM, dt_s=H_S), meas, u)[n // 2 :]
    assert np.std(tail) < np.std(lin_tail)  # fal shrinks the gain on noise spikes outside the linear zone


@pytest.mark.parametrize("omega_o", [100.0, 1000.0, 5000.0, 20000.0])
def test_fal_eso_frozen_gain_family_is_stable(omega_o: float) -> None:
    # outside the linear zone the disturbance gain is c * l2 with c in (0, 1]: every frozen member is stable
    eso = NonlinearESO(omega_o_rad_s=omega_o, b0_dps2_per_count=KM, dt_s=H_S)
    l1, l2 = eso.gains
    phi = np.array([[1.0, H_S], [0.0, 1.0]])
    for c in np.linspace(1e-3, 1.0, 50):
        m = (np.eye(2) - np.array([[l1, 0.0], [c * l2, 0.0]])) @ phi
        assert np.max(np.abs(np.linalg.eigvals(m))) < 1.0


def test_constructor_validation() -> None:
    with pytest.raises(ValueError):
        NonlinearESO(b0_dps2_per_count=KM, dt_s=H_S)
    with pytest.raises(ValueError):
        NonlinearESO(omega_o_rad_s=100.0, beta1_per_s=1.0, beta2_per_s2=1.0, b0_dps2_per_count=KM, dt_s=H_S)
    with pytest.raises(ValueError):
        NonlinearESO(omega_o_rad_s=100.0, b0_dps2_per_count=KM, dt_s=H_S, delta_dps=0.0)
    with pytest.raises(ValueError):
        current_observer_gains(beta1_per_s=0.0, beta2_per_s2=1.0, dt_s=H_S)
    with pytest.raises(ValueError):
        LinearESO(omega_o_rad_s=100.0, b0_dps2_per_count=0.0, dt_s=H_S)
