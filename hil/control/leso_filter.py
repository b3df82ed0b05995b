"""Linear extended-state-observer filter of seed 002 (Tan et al., 2019), eqs 26-29, on plain floats.

The filter models any sampled signal as x(k+1) = x(k) + tau x'(k) (eq 25) with the rate x' as the extended
state, and runs the discrete LESO (eq 26)

    e1(k)    = z1(k) - y(k)
    z1(k+1)  = z1(k) + tau z2(k) - beta01 e1(k)
    z2(k+1)  = z2(k)             - beta02 e1(k)

with [beta01, beta02]^T = Phi Lc (eq 27), i.e. Z(k+1) = Phi Z(k) - Phi Lc e1(k) (eq 28), where (eq 29)

    Phi = [[1, tau], [0, 1]],  Lc = [1 - beta^2, (1 - beta)^2 / tau]^T,  beta = exp(-omega_o tau),

so beta01 = 2 (1 - beta) and beta02 = (1 - beta)^2 / tau. The error dynamics Phi - Phi Lc C have a double
pole at z = beta.

Reading of the paper (what it leaves open, and what is chosen here):

* tau is a *pseudo* sample period (the paper: "an adjustable parameter similar to the sampling period"); it
  is not the real sample period T_s, which the filter never sees. In Table 1 tau = 0.5 while the data are
  sampled at 100 Hz (T_s = 0.01 s). The real-time bandwidth of the double pole is -ln(beta)/T_s =
  omega_o tau / T_s (5 rad/s for tau = 0.5, omega_o = 0.1 at 100 Hz).
* Only the product omega_o tau matters for the filtered value: with w = tau z2 (the rate in units per
  sample) eq 26 becomes z1 += w - 2(1 - beta) e1, w -= (1 - beta)^2 e1. tau alone only rescales z2.
* The paper does not say which of z1(k) (prior), the "current" estimate or z1(k+1) (one-step prediction)
  it plots. L_d = Phi Lc is the current-observer factorisation (Miklosovic et al. 2006, its ref. 14):
  Zbar(k) = Z(k) - Lc e1(k), Z(k+1) = Phi Zbar(k). ``step`` returns zbar1(k), the estimate of x(k) that
  uses y(k); it had the lowest error of the three on the paper's test. The state Z(k+1) of eq 28 is kept
  as ``z1``, ``z2``.
"""

from __future__ import annotations

import math

DEFAULT_TAU_S = 0.5
DEFAULT_OMEGA_O_RAD_S = 0.1


class LesoFilter:
    """Seed 002 LESO filter (eqs 26-29). ``step(y) -> filtered y``; units of y are the caller's (deg, px, ...).

    Attributes after each step: ``value`` (current estimate zbar1(k)), ``rate_per_sample`` (tau zbar2(k),
    the estimated change of y per sample; divide by the real sample period for a derivative per second),
    ``z1``, ``z2`` (the eq 28 state Z(k+1)). ``beta``, ``beta01``, ``beta02`` are the eq 27/29 gains.
    """

    def __init__(self, *, tau_s: float = DEFAULT_TAU_S, omega_o_rad_s: float = DEFAULT_OMEGA_O_RAD_S) -> None:
        if tau_s <= 0 or omega_o_rad_s <= 0:
            raise ValueError("tau_s and omega_o_rad_s must be positive")
        self.tau_s = float(tau_s)
        self.omega_o_rad_s = float(omega_o_rad_s)
        beta = math.exp(-self.omega_o_rad_s * self.tau_s)  # eq 29
        self.beta = beta
        self.lc1 = 1.0 - beta * beta  # Lc, eq 29
        self.lc2 = (1.0 - beta) ** 2 / self.tau_s
        self.beta01 = self.lc1 + self.tau_s * self.lc2  # Phi Lc, eq 27: = 2 (1 - beta)
        self.beta02 = self.lc2
        self.z1 = 0.0
        self.z2 = 0.0
        self.value = 0.0
        self.rate_per_sample = 0.0

    def reset(self, value: float = 0.0, rate_per_sample: float = 0.0) -> None:
        """Restart from ``value`` with slope ``rate_per_sample`` (units per sample). Start at the first
        measurement to skip the start-up transient."""
        self.z1 = float(value)
        self.z2 = float(rate_per_sample) / self.tau_s
        self.value = self.z1
        self.rate_per_sample = float(rate_per_sample)

    def step(self, y_meas: float) -> float:
        """Take sample y(k); return the filtered value zbar1(k) = z1(k) - (1 - beta^2) e1(k)."""
        z1 = self.z1
        z2 = self.z2
        e1 = z1 - y_meas  # eq 26
        self.value = z1 - self.lc1 * e1
        self.z1 = z1 + self.tau_s * z2 - self.beta01 * e1
        z2 -= self.beta02 * e1
        self.z2 = z2
        self.rate_per_sample = self.tau_s * z2
        return self.value
