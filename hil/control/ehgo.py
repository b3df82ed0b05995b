"""Extended high-gain observer of seed 003 (Mohd Nor et al.), eqs 2-7, discretised exactly by zero-order hold.

Continuous observer (eqs 2-3), with y the measured position and xhat = (position, velocity, acceleration):

    d/dt xhat1 = xhat2 + (alpha1 / eps)   (y - xhat1)
    d/dt xhat2 = xhat3 + (alpha2 / eps^2) (y - xhat1)
    d/dt xhat3 =         (alpha3 / eps^3) (y - xhat1)

s^3 + alpha1 s^2 + alpha2 s + alpha3 Hurwitz (eq 4; paper: alpha = 9, 9, 3, eps = 0.01, T_s = 0.05). In the
scaled variables q = (xhat1, eps xhat2, eps^2 xhat3) (eq 5) this is (eq 6)

    dq/dt = (1/eps) [[-alpha1, 1, 0], [-alpha2, 0, 1], [-alpha3, 0, 0]] q + (1/eps) [alpha1, alpha2, alpha3]^T y

and xhat = diag(1, 1/eps, 1/eps^2) q (eq 7). The paper prints the input vector of eq 6 as [alpha1, alpha2,
alpha3]^T without the 1/eps that eqs 2-3 and 5 imply (as printed the position estimate would settle at
eps y); the 1/eps is used here. Eigenvalues of eq 6: the roots of eq 4 divided by eps.

Discretisation: exact zero-order hold of eq 6 at dt_s, q(k+1) = Phi q(k) + Gamma y(k) with
[[Phi, Gamma], [0, 1]] = expm([[A, B], [0, 0]] dt) (the "c2d" of the paper), computed once in the constructor
by scaling and squaring with a Taylor series (:func:`expm`), then carried to the physical coordinates of
eq 7 and stored as plain floats for ``step``. ``step(y(k))`` returns the state after the update, i.e. the
observer at t_k + dt having seen y(k) held over [t_k, t_k + dt).

Caveat (measured, see ``ramp_velocity_gain``): a ZOH-discretised observer only sees a staircase. When eps
is not several times dt, its fast transients finish inside one hold interval and the sampled velocity no
longer tracks: the steady-state velocity estimate for a ramp of unit slope depends only on eps/dt and is
-0.25 at the paper's eps/T_s = 0.01/0.05, 0.61 at 1, 0.97 at 5, 0.993 at 10. Choose eps >~ 5 dt.

Units are generic: position in the measurement's unit u (encoder deg, miss distance px, ...), velocity in
u/s, acceleration in u/s^2; eps and dt in seconds.
"""

from __future__ import annotations

import math

import numpy as np

DEFAULT_EPSILON_S = 0.01
DEFAULT_ALPHAS = (9.0, 9.0, 3.0)


def expm(m: np.ndarray) -> np.ndarray:
    """Matrix exponential by scaling and squaring: Taylor series of degree 20 on m / 2^s, ||m / 2^s||_1 <= 1/2.

    The truncation error of the series is below 0.5^21 / 21! ~ 1e-26 relative, far under double precision.
    """
    m = np.asarray(m, dtype=float)
    norm = float(np.abs(m).sum(axis=0).max()) if m.size else 0.0
    s = max(0, math.ceil(math.log2(norm / 0.5))) if norm > 0.5 else 0
    x = m / 2.0**s
    term = np.eye(m.shape[0])
    result = term.copy()
    for k in range(1, 21):
        term = term @ x / k
        result += term
    for _ in range(s):
        result = result @ result
    return result


def zoh(a: np.ndarray, b: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation of dx/dt = a x + b u: returns (Phi, Gamma) from one augmented expm."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float).reshape(a.shape[0], -1)
    n, m = b.shape
    aug = np.zeros((n + m, n + m))
    aug[:n, :n] = a * dt_s
    aug[:n, n:] = b * dt_s
    e = expm(aug)
    return e[:n, :n], e[:n, n:]


def scaled_matrices(
    *, epsilon_s: float, alphas: tuple[float, float, float] = DEFAULT_ALPHAS
) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) of eq 6 in the scaled variables q of eq 5 (input vector with the 1/eps of eqs 2-3)."""
    a1, a2, a3 = alphas
    a = np.array([[-a1, 1.0, 0.0], [-a2, 0.0, 1.0], [-a3, 0.0, 0.0]]) / epsilon_s
    b = np.array([[a1], [a2], [a3]]) / epsilon_s
    return a, b


class HighGainObserver:
    """Seed 003 EHGO (eqs 2-7), exact ZOH at ``dt_s``. ``step(position) -> velocity``.

    Attributes: ``position`` (u), ``velocity`` (u/s), ``acceleration`` (u/s^2, the extended state);
    ``phi_q``, ``gamma_q`` (numpy, the discrete eq 6 matrices); ``ramp_velocity_gain`` (steady-state velocity
    estimate per unit true slope on a sampled ramp; 1 is ideal, see the module caveat).
    Start with ``reset(position=first_measurement)``: from a wrong initial position a high-gain observer
    peaks (velocity ~ error / eps).
    """

    def __init__(
        self,
        *,
        dt_s: float,
        epsilon_s: float = DEFAULT_EPSILON_S,
        alpha1: float = DEFAULT_ALPHAS[0],
        alpha2: float = DEFAULT_ALPHAS[1],
        alpha3: float = DEFAULT_ALPHAS[2],
    ) -> None:
        if dt_s <= 0 or epsilon_s <= 0:
            raise ValueError("dt_s and epsilon_s must be positive")
        if not (alpha1 > 0 and alpha3 > 0 and alpha1 * alpha2 > alpha3):
            raise ValueError("s^3 + alpha1 s^2 + alpha2 s + alpha3 must be Hurwitz (eq 4)")
        self.dt_s = float(dt_s)
        self.epsilon_s = float(epsilon_s)
        self.alphas = (float(alpha1), float(alpha2), float(alpha3))
        a, b = scaled_matrices(epsilon_s=self.epsilon_s, alphas=self.alphas)
        self.phi_q, gamma = zoh(a, b, self.dt_s)
        self.gamma_q = gamma[:, 0]
        # Physical coordinates (eq 7): xhat = S q, S = diag(1, 1/eps, 1/eps^2).
        s = np.array([1.0, 1.0 / self.epsilon_s, 1.0 / self.epsilon_s**2])
        phi_x = self.phi_q * s[:, None] / s[None, :]
        gamma_x = self.gamma_q * s
        (self._p00, self._p01, self._p02), (self._p10, self._p11, self._p12), (self._p20, self._p21, self._p22) = (
            phi_x.tolist()
        )
        self._g0, self._g1, self._g2 = gamma_x.tolist()
        # Ramp y(k) = k dt: steady state q(k) = c + d k with d = (I - Phi)^-1 Gamma dt, c = -(I - Phi)^-1 d.
        i_phi = np.eye(3) - self.phi_q
        d = np.linalg.solve(i_phi, self.gamma_q * self.dt_s)
        self.ramp_velocity_gain = float(-np.linalg.solve(i_phi, d)[1] / self.epsilon_s)
        self.position = 0.0
        self.velocity = 0.0
        self.acceleration = 0.0

    def reset(self, position: float = 0.0, velocity: float = 0.0, acceleration: float = 0.0) -> None:
        self.position = float(position)
        self.velocity = float(velocity)
        self.acceleration = float(acceleration)

    def step(self, position_meas: float) -> float:
        """Take y(k) (u); return the velocity estimate (u/s). Updates position, velocity, acceleration."""
        x0 = self.position
        x1 = self.velocity
        x2 = self.acceleration
        self.position = self._p00 * x0 + self._p01 * x1 + self._p02 * x2 + self._g0 * position_meas
        v = self._p10 * x0 + self._p11 * x1 + self._p12 * x2 + self._g1 * position_meas
        self.acceleration = self._p20 * x0 + self._p21 * x1 + self._p22 * x2 + self._g2 * position_meas
        self.velocity = v
        return v
