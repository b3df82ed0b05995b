"""ESO + Kalman filter of Wang et al. (Sensors 2023, seed 000): a scalar KF on the disturbance-compensated rate model.

Structure (paper Figs 5 and 10): the gyro rate goes through the KF; the KF's filtered rate is what the ESO observes
and what the rate loop feeds back; the ESO's disturbance estimate completes the KF's process model.

Process model (eqs 14-16 and 43-44): with the compensated law ``u = u0 - z2/b0`` the plant is
``rate' = b0 (u + d) = b0 u0 + b0 (d - z2/b0)``. Eq 44 predicts with ``T k_m u_{k-1}``, ``u`` there being the
drive before compensation (``u0``); written with the applied drive and the ESO's disturbance estimate this is::

    x^-_k = x_{k-1} + h (b0 u_applied + z2_{k-1})        (eq 44/31: A = 1, B = h b0, D d_hat = h z2)
    P^-_k = P_{k-1} + S + Q                              (eqs 30, 44: S process noise, Q disturbance-estimate error)
    K_k   = P^-_k / (P^-_k + R)                          (eqs 24, 45, C = 1)
    x_k   = x^-_k + K_k (y_k - x^-_k),   P_k = (1 - K_k) P^-_k        (eq 45)

then the ESO is stepped with ``x_k`` as its measurement (Fig 5). Using the applied (saturated) drive keeps the
model right when the drive saturates. ``x^-`` is exactly the ESO's own ZOH prediction of the rate, applied to the
KF state. S, Q, R are variances per sample in (deg/s)^2; only ``S + Q`` matters to the filter (the paper does not
say how it splits them or give values).

Steady state (``steady_state=True``): with ``W = S + Q`` the scalar discrete Riccati equation
``M = M R / (M + R) + W`` for the prior variance M has the positive root ``M = (W + sqrt(W^2 + 4 W R)) / 2``,
hence ``K = M / (M + R)`` and ``P = (1 - K) M``.

"High-gain ESO + KF" (paper Fig 15) is this class with a larger ``omega_o_rad_s``.

Behaviour (measured in tests/control/test_kalman.py, K = 0.089 i.e. S + Q = 1e-5, R = 0.034^2): static white gyro
noise falls to 0.26 / 0.35 / 0.52 of its std at omega_o = 100 / 300 / 1000 rad/s (a first-order 150 Hz low-pass
at 1 kHz: 0.66). Motion explained by the drive is tracked with no lag; motion the ESO must discover (a disturbance)
lags by 0.17 / 0.08 / 0.007 periods of a 15 Hz input for those omega_o (the low-pass: 0.0095). The ESO and the KF form a
3-state loop (the ESO measures the KF, the KF predicts with the ESO) with a lightly damped complex pole pair, so
the disturbance estimate overshoots a step by 15-60 %, more with larger omega_o.
"""

from __future__ import annotations

import math

from hil.control.eso import LinearESO

__all__ = ["EsoKalman", "RandomWalkKalman", "steady_state_kalman"]


def steady_state_kalman(*, w_dps2: float, r_dps2: float) -> tuple[float, float, float]:
    """Closed-form scalar steady state ``(K, P_prior, P_post)`` for a random-walk model with process noise
    ``w_dps2`` (= S + Q) and measurement noise ``r_dps2`` per sample."""
    if w_dps2 < 0.0 or r_dps2 <= 0.0:
        raise ValueError("need w_dps2 >= 0 and r_dps2 > 0")
    m = 0.5 * (w_dps2 + math.sqrt(w_dps2 * w_dps2 + 4.0 * w_dps2 * r_dps2))
    k = m / (m + r_dps2)
    return k, m, (1.0 - k) * m


class RandomWalkKalman:
    """Scalar Kalman filter on plain floats: x_k = x_{k-1} + w (var q), y_k = x_k + v (var r) (seed 000, n = 1).

    The plain baseline filter: seed 002 compares its LESO filter against this KF (R = 0.1, Q = 0.001).
    """

    def __init__(self, *, q: float, r: float, p0: float = 1.0, x0: float = 0.0) -> None:
        if q < 0 or r <= 0 or p0 < 0:
            raise ValueError("need q >= 0, r > 0, p0 >= 0")
        self.q = q
        self.r = r
        self.p = p0
        self.x = x0

    def step(self, y: float) -> float:
        p = self.p + self.q
        k = p / (p + self.r)
        self.x += k * (y - self.x)
        self.p = (1.0 - k) * p
        return self.x


class EsoKalman:
    """ESO + KF rate estimator (eqs 31-32, 44-45; Figs 5, 10). ``step`` returns the filtered rate [deg/s].

    Parameters (keyword-only): ``omega_o_rad_s``, ``b0_dps2_per_count`` (k_m), ``dt_s`` for the inner
    :class:`~hil.control.eso.LinearESO`; ``q_dps2`` (Q, disturbance-estimate error), ``s_dps2`` (S, process
    noise) and ``r_dps2`` (R, gyro noise) as variances per sample in (deg/s)^2; ``steady_state`` uses the
    closed-form constant gain instead of propagating P; ``p0_dps2`` is the initial posterior variance
    (default R). Attributes: ``rate_dps`` (KF estimate), ``eso`` (inner LinearESO, measures ``rate_dps``),
    ``gain`` (latest K), ``p_dps2`` (posterior variance).
    """

    __slots__ = (
        "_b0h",
        "_h",
        "_p0",
        "_r",
        "_steady",
        "_w",
        "eso",
        "gain",
        "p_dps2",
        "q_dps2",
        "r_dps2",
        "rate_dps",
        "s_dps2",
    )

    def __init__(
        self,
        *,
        omega_o_rad_s: float,
        b0_dps2_per_count: float,
        dt_s: float,
        q_dps2: float,
        r_dps2: float,
        s_dps2: float,
        steady_state: bool = False,
        p0_dps2: float | None = None,
    ) -> None:
        if q_dps2 < 0.0 or s_dps2 < 0.0 or r_dps2 <= 0.0:
            raise ValueError("need q_dps2 >= 0, s_dps2 >= 0, r_dps2 > 0")
        self.eso = LinearESO(omega_o_rad_s=omega_o_rad_s, b0_dps2_per_count=b0_dps2_per_count, dt_s=dt_s)
        self.q_dps2 = float(q_dps2)
        self.r_dps2 = float(r_dps2)
        self.s_dps2 = float(s_dps2)
        self._w = self.q_dps2 + self.s_dps2
        self._r = self.r_dps2
        self._h = float(dt_s)
        self._b0h = float(b0_dps2_per_count) * self._h
        self._steady = bool(steady_state)
        self._p0 = self._r if p0_dps2 is None else float(p0_dps2)
        self.reset()

    def reset(self, rate_dps: float = 0.0) -> None:
        """Restart at a known rate; P back to ``p0_dps2`` (or to its steady-state value)."""
        self.rate_dps = float(rate_dps)
        self.eso.reset(rate_dps)
        if self._steady:
            self.gain, _, self.p_dps2 = steady_state_kalman(w_dps2=self._w, r_dps2=self._r)
        else:
            self.p_dps2 = self._p0
            self.gain = 0.0

    @property
    def disturbance_counts(self) -> float:
        """The inner ESO's lumped-disturbance estimate in drive counts (compensate with ``u0 - this``)."""
        return self.eso.disturbance_counts

    def step(self, rate_meas_dps: float, u_applied_counts: float) -> float:
        """One sample: gyro rate now, saturated drive held since the previous step. Returns the filtered rate."""
        eso = self.eso
        x_pred = self.rate_dps + self._b0h * u_applied_counts + self._h * eso.z2
        if self._steady:
            k = self.gain
        else:
            m = self.p_dps2 + self._w
            k = m / (m + self._r)
            self.p_dps2 = m - k * m
            self.gain = k
        self.rate_dps = x = x_pred + k * (rate_meas_dps - x_pred)
        eso.step(x, u_applied_counts)
        return x
