"""Extended high-gain observer (seed 003, eqs 2-7): the ZOH discretisation, the poles, and velocity/acceleration
from a noisy sampled sine.

Measured (RMS error of the velocity against the true derivative at the time of the latest sample, after the
first quarter of the record; first differencing (y_k - y_{k-1}) / dt for comparison):

    dt 1 ms, eps 0.01, sin(2 pi 1 Hz t), noise std 1e-3, 4 s:   EHGO 0.070   differencing 1.43  (amplitude 6.28)
        acceleration: RMS error 4.6 against an amplitude of 39.5, correlation 0.986
    dt 0.05 s, sin(2 pi 0.1 Hz t), noise std 1e-2, 60 s:
        eps 0.2:          EHGO 0.046   differencing 0.29  (amplitude 0.63); acceleration RMS error 0.10 of 0.39
        eps 0.01 (paper): EHGO 0.56    differencing 0.29; acceleration uncorrelated (0.01)
    (seeds 0-4 give the same ratios to within 5 %)

At the paper's T_s = 0.05 with eps = 0.01 the ZOH observer's poles (-790, -55 +/- 28j rad/s) settle inside
one hold interval, so it only sees steps and its sampled velocity is wrong (ramp gain -0.25, see
``HighGainObserver.ramp_velocity_gain``); eps ~ 4-5 T_s restores it.
"""

from __future__ import annotations

import math
from decimal import Decimal, localcontext

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hil.control.ehgo import HighGainObserver, expm, scaled_matrices, zoh

ALPHAS = (9.0, 9.0, 3.0)


def taylor_float(m: np.ndarray, terms: int = 60) -> np.ndarray:
    term = np.eye(len(m))
    out = term.copy()
    for k in range(1, terms):
        term = term @ m / k
        out += term
    return out


def taylor_decimal(m: list[list[Decimal]], tol: Decimal = Decimal("1e-40")) -> list[list[Decimal]]:
    """exp(m) by its plain Taylor series in the current Decimal context, summed until the terms fall below tol."""
    n = len(m)
    term = [[Decimal(int(i == j)) for j in range(n)] for i in range(n)]
    out = [row[:] for row in term]
    k = 0
    while True:
        k += 1
        term = [[sum(term[i][p] * m[p][j] for p in range(n)) / k for j in range(n)] for i in range(n)]
        out = [[out[i][j] + term[i][j] for j in range(n)] for i in range(n)]
        if k > 10 and max(abs(v) for row in term for v in row) < tol:
            return out


def sine_run(
    obs: HighGainObserver, *, freq_hz: float, noise_std: float, duration_s: float, seed: int = 1
) -> dict[str, float]:
    dt = obs.dt_s
    n = round(duration_s / dt)
    t = np.arange(n) * dt
    w = 2.0 * np.pi * freq_hz
    y = np.sin(w * t) + np.random.default_rng(seed).normal(0.0, noise_std, n)
    obs.reset(position=float(y[0]))
    vel = np.empty(n)
    acc = np.empty(n)
    for k, v in enumerate(y.tolist()):
        vel[k] = obs.step(v)
        acc[k] = obs.acceleration
    diff = np.r_[0.0, np.diff(y) / dt]
    true_v = w * np.cos(w * t)
    true_a = -(w**2) * np.sin(w * t)
    keep = slice(n // 4, None)

    def rms(e: np.ndarray) -> float:
        return float(np.sqrt(np.mean(e[keep] ** 2)))

    return {
        "ehgo": rms(vel - true_v),
        "diff": rms(diff - true_v),
        "acc": rms(acc - true_a),
        "acc_corr": float(np.corrcoef(acc[keep], true_a[keep])[0, 1]),
        "v_amp": w,
        "a_amp": w**2,
    }


# --- discretisation --------------------------------------------------------------------------------------------


def test_expm_known_cases() -> None:
    np.testing.assert_array_equal(expm(np.zeros((3, 3))), np.eye(3))
    np.testing.assert_allclose(expm(np.array([[0.0, 0.5], [0.0, 0.0]])), [[1.0, 0.5], [0.0, 1.0]], atol=1e-16)
    rot = expm(np.array([[0.0, -1.0], [1.0, 0.0]]) * 30.0)
    np.testing.assert_allclose(rot, [[math.cos(30), -math.sin(30)], [math.sin(30), math.cos(30)]], atol=1e-13)


@given(st.lists(st.floats(-1.0, 1.0), min_size=9, max_size=9), st.floats(0.0, 2.0))
def test_expm_matches_a_long_taylor_series(entries: list[float], scale: float) -> None:
    """Random 3x3 matrices with ||m||_1 <= 6 (4 to 8 squarings) against 100 unscaled series terms."""
    m = np.array(entries).reshape(3, 3) * scale
    ref = taylor_float(m, terms=100)
    bound = math.exp(float(np.abs(m).sum(axis=0).max()))
    np.testing.assert_allclose(expm(m), ref, rtol=0, atol=1e-13 * bound)
    np.testing.assert_allclose(expm(m) @ expm(-m), np.eye(3), rtol=0, atol=1e-13 * bound**2)


def test_zoh_at_1khz_equals_a_60_term_taylor_series() -> None:
    a, b = scaled_matrices(epsilon_s=0.01, alphas=ALPHAS)
    dt = 1e-3
    aug = np.zeros((4, 4))
    aug[:3, :3] = a * dt
    aug[:3, 3:] = b * dt
    ref = taylor_float(aug)
    phi, gamma = zoh(a, b, dt)
    np.testing.assert_allclose(phi, ref[:3, :3], rtol=0, atol=1e-14)
    np.testing.assert_allclose(gamma, ref[:3, 3:], rtol=0, atol=1e-14)


def test_zoh_at_paper_ts_equals_a_high_precision_taylor_series() -> None:
    """eps = 0.01, T_s = 0.05: ||[A B] dt||_1 = 105, the series peaks near 1e44 before it converges (plain float
    Taylor is off by ~2 here), so it is summed in 120-digit Decimal arithmetic."""
    with localcontext() as ctx:
        ctx.prec = 120
        eps, dt = Decimal("0.01"), Decimal("0.05")
        a1, a2, a3 = (Decimal(int(x)) for x in ALPHAS)
        zero = Decimal(0)
        aug = [
            [-a1 / eps * dt, dt / eps, zero, a1 / eps * dt],
            [-a2 / eps * dt, zero, dt / eps, a2 / eps * dt],
            [-a3 / eps * dt, zero, zero, a3 / eps * dt],
            [zero, zero, zero, zero],
        ]
        ref = np.array([[float(v) for v in row] for row in taylor_decimal(aug)])
    obs = HighGainObserver(dt_s=0.05, epsilon_s=0.01)
    np.testing.assert_allclose(obs.phi_q, ref[:3, :3], rtol=0, atol=1e-13)
    np.testing.assert_allclose(obs.gamma_q, ref[:3, 3], rtol=0, atol=1e-13)


@pytest.mark.parametrize(("eps", "dt"), [(0.01, 1e-3), (0.01, 0.05), (0.05, 0.05), (0.002, 1e-3)])
def test_poles_are_eq_4_roots_over_eps_mapped_by_exp(eps: float, dt: float) -> None:
    a, _ = scaled_matrices(epsilon_s=eps, alphas=ALPHAS)
    roots = np.roots([1.0, *ALPHAS]) / eps
    eig = np.linalg.eigvals(a)
    np.testing.assert_allclose(np.sort_complex(eig), np.sort_complex(roots), rtol=1e-10)
    poles = np.linalg.eigvals(HighGainObserver(dt_s=dt, epsilon_s=eps).phi_q)
    expected = np.exp(roots * dt)
    for p in expected:
        assert np.min(np.abs(poles - p)) < 1e-9 * max(1.0, abs(p))


def test_constant_input_settles_on_it() -> None:
    """Unity DC gain of the position estimate: the eq 6 input vector carries 1/eps (the paper omits it)."""
    obs = HighGainObserver(dt_s=1e-3)
    for _ in range(3000):
        v = obs.step(5.0)
    assert type(v) is float
    assert obs.position == pytest.approx(5.0, abs=1e-9)
    assert obs.velocity == pytest.approx(0.0, abs=1e-7)
    assert obs.acceleration == pytest.approx(0.0, abs=1e-4)


def test_ramp_velocity_gain_depends_on_eps_over_dt() -> None:
    gains = {r: HighGainObserver(dt_s=0.05, epsilon_s=r * 0.05).ramp_velocity_gain for r in (0.2, 1, 5, 10, 20)}
    assert HighGainObserver(dt_s=1e-3, epsilon_s=5e-3).ramp_velocity_gain == pytest.approx(gains[5], rel=1e-9)
    assert gains[0.2] == pytest.approx(-0.2513, abs=1e-3)  # the paper's eps = 0.01 at T_s = 0.05
    assert gains[1] < gains[5] < gains[10] < gains[20] < 1.0
    assert gains[5] > 0.97
    assert gains[10] > 0.99
    obs = HighGainObserver(dt_s=1e-3)  # and the simulated ramp agrees with the closed form
    for k in range(3000):
        obs.step(2.0 * k * 1e-3)
    assert obs.velocity == pytest.approx(2.0 * obs.ramp_velocity_gain, rel=1e-6)


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError):
        HighGainObserver(dt_s=0.0)
    with pytest.raises(ValueError):
        HighGainObserver(dt_s=1e-3, alpha1=1.0, alpha2=1.0, alpha3=3.0)  # not Hurwitz


# --- velocity and acceleration of a noisy sine ----------------------------------------------------------------


def test_velocity_and_acceleration_at_1khz() -> None:
    r = sine_run(HighGainObserver(dt_s=1e-3, epsilon_s=0.01), freq_hz=1.0, noise_std=1e-3, duration_s=4.0)
    assert r["ehgo"] < 0.1 * r["diff"]
    assert r["ehgo"] < 0.02 * r["v_amp"]
    assert r["acc"] < 0.2 * r["a_amp"]
    assert r["acc_corr"] > 0.98


def test_velocity_at_paper_sample_time_needs_eps_of_a_few_samples() -> None:
    good = sine_run(HighGainObserver(dt_s=0.05, epsilon_s=0.2), freq_hz=0.1, noise_std=1e-2, duration_s=60.0)
    assert good["ehgo"] < 0.25 * good["diff"]
    assert good["ehgo"] < 0.1 * good["v_amp"]
    assert good["acc"] < 0.4 * good["a_amp"]
    assert good["acc_corr"] > 0.9
    # The paper's eps = 0.01 at T_s = 0.05 under ZOH: worse than differencing (see the module docstring).
    paper = sine_run(HighGainObserver(dt_s=0.05, epsilon_s=0.01), freq_hz=0.1, noise_std=1e-2, duration_s=60.0)
    assert paper["ehgo"] > paper["diff"]
