"""A fitted value is `fitted` only within its target accuracy (docs/fit.md, "What the logs determine"); wider, it
is `weak`, and a weak value or a prior kept names the recording that would resolve it."""

from __future__ import annotations

import numpy as np
import pytest

from hil.fit.ranges import param_range
from hil.fit.twin import Estimate, FrfFit, correlation_inflation, grade, pole_doubts


def est(name: str, value: float, sigma: float | None, status: str = "fitted") -> Estimate:
    return Estimate(name, value, sigma, "", status, "test", prior=value)  # type: ignore[arg-type]


def test_a_sigma_wider_than_the_target_is_weak_and_names_the_recording() -> None:
    k_m = "motor_el.k_m_dps2_per_count"
    got = grade([est(k_m, 0.02, 0.0009), est(k_m, 0.02, 0.0011)])  # the target: 5 % of 0.02 = 0.001
    assert [e.status for e in got] == ["fitted", "weak"]
    assert "`hil ident SESSION` with axis=el" in got[1].note and "0.0011" in got[1].note
    delay = grade([est("gyro.delay_s", 5e-4, 0.8e-4), est("gyro.delay_s", 5e-4, 1.3e-4)])  # the target: 0.1 ms
    assert [e.status for e in delay] == ["fitted", "weak"]
    noise = grade([est("gyro.noise_std_dps.y", 0.03, 0.002)])  # the family's 5 %: 0.0015
    assert noise[0].status == "weak" and "static session" in noise[0].note


def test_a_prior_kept_names_the_recording_and_a_value_without_a_target_stays_fitted() -> None:
    got = grade([est("gyro.bandwidth_hz", 200.0, None, "prior"),
                 est("friction.az.viscous_n_m_s_per_rad", 0.01, 0.05)])
    assert got[0].status == "prior" and got[0].note.startswith("record `hil ident SESSION`")
    assert got[1].status == "fitted"  # no target: its sigma is reported, not judged
    assert param_range("friction.az.viscous_n_m_s_per_rad") is not None
    assert param_range("friction.az.viscous_n_m_s_per_rad").tolerance(0.01) is None


def test_residuals_correlated_from_bin_to_bin_widen_the_sigma_as_ar1_predicts() -> None:
    """An FRF fit's sigmas count independent bins only after ``(1 + rho) / (1 - rho)`` (hil.fit.twin): white
    residuals leave them as they are, AR(1) ones with rho = 0.8 widen the variance about 9 times."""
    rng = np.random.default_rng(7)
    n = 4000
    white = rng.standard_normal(2 * n)
    assert correlation_inflation(white) == pytest.approx(1.0, abs=0.1)
    halves = []
    for _ in range(2):
        e = rng.standard_normal(n)
        x = np.empty(n)
        x[0] = e[0]
        for k in range(1, n):
            x[k] = 0.8 * x[k - 1] + e[k]
        halves.append(x)
    assert correlation_inflation(np.concatenate(halves)) == pytest.approx(9.0, rel=0.15)
    # anti-correlated residuals never narrow it, and a constant half is left out
    assert correlation_inflation(np.tile([1.0, -1.0], n)) == 1.0
    assert correlation_inflation(np.concatenate([np.ones(n), white[:n]])) == pytest.approx(1.0, abs=0.15)


def pole(axis: str, bandwidth_hz: float, sigma_hz: float) -> FrfFit:
    return FrfFit(axis=axis, k_m=0.02, bandwidth_hz=bandwidth_hz, delay_s=1e-3, mode_hz=None, damping=None,
                  spring_q=None, sigma={"bandwidth_hz": sigma_hz}, rms_db=0.0, rms_deg=0.0,
                  f_range_hz=(2.0, 320.0), log=f"ident-{axis}")


def test_a_pole_the_logs_disagree_on_is_doubted() -> None:
    """One gyro for both axes: two ident logs that pin its pole 2 combined sigmas apart make the bandwidth and delay
    weak, with the reason (hil.fit.twin.pole_doubts)."""
    assert pole_doubts([]) == ""
    assert pole_doubts([pole("el", 300.0, 15.0), pole("az", 340.0, 15.0)]) == ""  # 40 Hz < 2 x 21.2 Hz
    why = pole_doubts([pole("el", 300.0, 15.0), pole("az", 355.0, 20.0)])  # 55 Hz > 2 x 25 Hz
    assert why.startswith("the logs disagree") and "300 +- 15 Hz (ident-el)" in why and "ident-az" in why
