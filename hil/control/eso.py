"""Second-order extended state observers (ESO) for one rate-loop axis (Wang et al., Sensors 2023, seed 000).

Plant per axis (paper eqs 38-40)::

    d(rate_dps)/dt = b0 * (u + d)       b0 = k_m [deg/s^2 per DAC count] (paper: k_m = 0.023)

with ``u`` the applied (saturated) drive in DAC counts and ``d`` the lumped disturbance in counts.
The extended state is the total disturbance ``x2 = b0 * d`` [deg/s^2] (paper eq 40 keeps ``d`` in counts;
here it is scaled by ``b0`` so that eqs 5-8 apply unchanged)::

    x1' = x2 + b0 * u,   x2' = a(t),   y = x1          (eqs 7 and 40)

The control law compensates with ``u = u0 - z2 / b0`` (eq 43; the paper writes ``u0 - z2`` with z2 in counts).

Discretisation (both observers): the "current observer" of Miklosovic, Radke & Gao (ACC 2006), as in pyadrc and
Herbst's LADRC blockset, instead of the forward-Euler form of eq 10. The plant model is discretised exactly with a
zero-order hold on ``u`` (step ``h = dt_s``)::

    Phi = [[1, h], [0, 1]],   Gamma = [b0*h, 0]

and every step predicts with the drive held over the last interval, then corrects with the current measurement::

    p = Phi @ z + Gamma * u_applied             (predict: the model of eq 40)
    eps = y - p1                                (innovation; eq 41's e1 = z1 - y with the sign flipped)
    z = p + L * eps                             (correct)

The estimation error then obeys ``e_k = (I - L C) Phi e_{k-1}``; with ``L = [l1, l2]`` its characteristic
polynomial is ``z^2 - (2 - l1 - h*l2) z + (1 - l1)``. Matching it to the poles ``exp(s_i h)`` of the continuous
ESO ``s^2 + beta1 s + beta2`` (eq 8; ``beta1 = 2 omega_o``, ``beta2 = omega_o^2`` for bandwidth tuning, a double
pole at ``-omega_o``) gives, for the double pole ``q = exp(-omega_o h)``::

    l1 = 1 - q^2,      l2 = (1 - q)^2 / h          [l1 dimensionless, l2 in 1/s]

Both discrete poles lie inside the unit circle for every ``omega_o * h > 0``, whereas the forward-Euler error
matrix of eq 10 has a double pole at ``1 - omega_o h`` and diverges for ``omega_o * h >= 2`` (2000 rad/s at 1 kHz).

Anti-windup: ``step`` must be given the drive actually applied (after saturation) over the interval that ended
with this measurement. Given the commanded drive instead, the disturbance state absorbs ``sat(u) - u`` and winds
up. ``step`` uses plain Python floats only (it runs on the 1 kHz hot path).
"""

from __future__ import annotations

import math

__all__ = ["LinearESO", "NonlinearESO", "current_observer_gains", "fal"]


def current_observer_gains(*, beta1_per_s: float, beta2_per_s2: float, dt_s: float) -> tuple[float, float]:
    """Gains ``(l1, l2_per_s)`` of the ZOH current observer whose two discrete poles are ``exp(s_i * dt_s)``.

    ``s_i`` are the roots of the continuous ESO polynomial ``s^2 + beta1 s + beta2`` (eq 8, n = 1): the
    pole-matched ("matched z") discretisation, so the observer keeps the continuous design's speed for any
    ``dt_s``. For ``beta1 = 2 w``, ``beta2 = w^2`` this is ``l1 = 1 - q^2``, ``l2 = (1 - q)^2 / dt_s``,
    ``q = exp(-w dt_s)``.
    """
    if dt_s <= 0.0 or beta1_per_s <= 0.0 or beta2_per_s2 <= 0.0:
        raise ValueError("dt_s, beta1_per_s and beta2_per_s2 must be > 0")
    h = dt_s
    det = math.exp(-beta1_per_s * h)  # product of the discrete poles = exp((s1 + s2) h)
    disc = 0.25 * beta1_per_s * beta1_per_s - beta2_per_s2
    root = math.sqrt(abs(disc)) * h
    trace = 2.0 * math.exp(-0.5 * beta1_per_s * h) * (math.cosh(root) if disc >= 0.0 else math.cos(root))
    l1 = 1.0 - det
    l2_per_s = (1.0 + det - trace) / h  # from trace = 2 - l1 - h*l2
    return l1, l2_per_s


def fal(e: float, alpha: float, delta: float) -> float:
    """Han's fal function, paper eq 42 read as continuous at ``|e| = delta``.

    ``e * delta^(alpha - 1)`` for ``|e| <= delta`` (the paper prints ``e / delta^(b-1)``, which is discontinuous
    at ``|e| = delta``: a typo), ``|e|^alpha * sign(e)`` outside. Its linear-zone slope is ``delta^(alpha-1)``.
    """
    ae = abs(e)
    if ae <= delta:
        return e * delta ** (alpha - 1.0)
    return math.copysign(ae**alpha, e)


class _CurrentObserverESO:
    """Shared state, gains and bookkeeping of the two ESOs (see the module docstring for the discretisation)."""

    __slots__ = ("_b0", "_h", "_hb0", "_l1", "_l2", "dt_s", "z1", "z2")

    def __init__(self, *, l1: float, l2_per_s: float, b0_dps2_per_count: float, dt_s: float) -> None:
        if b0_dps2_per_count == 0.0:
            raise ValueError("b0_dps2_per_count must be non-zero")
        self.dt_s = float(dt_s)
        self._h = self.dt_s
        self._b0 = float(b0_dps2_per_count)
        self._hb0 = self._h * self._b0
        self._l1 = float(l1)
        self._l2 = float(l2_per_s)
        self.z1 = 0.0  # rate estimate [deg/s]
        self.z2 = 0.0  # total disturbance estimate [deg/s^2]

    def reset(self, rate_dps: float = 0.0, disturbance_counts: float = 0.0) -> None:
        """Restart from a known rate (e.g. the first gyro sample) and disturbance (default none)."""
        self.z1 = float(rate_dps)
        self.z2 = float(disturbance_counts) * self._b0

    @property
    def rate_dps(self) -> float:
        """Rate estimate z1 [deg/s]."""
        return self.z1

    @property
    def disturbance_counts(self) -> float:
        """Lumped disturbance estimate in drive counts, ``z2 / b0``: compensate with ``u = u0 - this``."""
        return self.z2 / self._b0

    @property
    def b0_dps2_per_count(self) -> float:
        return self._b0

    @property
    def l1(self) -> float:
        """Rate-state correction gain (dimensionless)."""
        return self._l1

    @property
    def l2_per_s(self) -> float:
        """Disturbance-state correction gain [1/s]: z2 [deg/s^2] += l2 * innovation [deg/s]."""
        return self._l2

    @property
    def gains(self) -> tuple[float, float]:
        """``(l1, l2_per_s)``: the current-observer gain vector L."""
        return self._l1, self._l2


class LinearESO(_CurrentObserverESO):
    """Linear ESO (eqs 5-9 with n = 1; Gao's bandwidth tuning), ZOH current-observer discretisation.

    Both discrete observer poles sit at ``exp(-omega_o_rad_s * dt_s)`` (continuous double pole at
    ``-omega_o``): stable for any ``omega_o_rad_s * dt_s``. States: ``z1`` rate estimate [deg/s], ``z2`` total
    disturbance estimate [deg/s^2].
    """

    __slots__ = ("omega_o_rad_s",)

    def __init__(self, *, omega_o_rad_s: float, b0_dps2_per_count: float, dt_s: float) -> None:
        l1, l2 = current_observer_gains(
            beta1_per_s=2.0 * omega_o_rad_s, beta2_per_s2=omega_o_rad_s * omega_o_rad_s, dt_s=dt_s
        )
        super().__init__(l1=l1, l2_per_s=l2, b0_dps2_per_count=b0_dps2_per_count, dt_s=dt_s)
        self.omega_o_rad_s = float(omega_o_rad_s)

    def step(self, rate_meas_dps: float, u_applied_counts: float) -> float:
        """One sample: ``u_applied_counts`` is the saturated drive held since the previous step. Returns z1."""
        z2 = self.z2
        p1 = self.z1 + self._h * z2 + self._hb0 * u_applied_counts
        e = rate_meas_dps - p1
        self.z1 = z1 = p1 + self._l1 * e
        self.z2 = z2 + self._l2 * e
        return z1


class NonlinearESO(_CurrentObserverESO):
    """Han's nonlinear ESO (eqs 41-42), ZOH current-observer discretisation, interchangeable with LinearESO.

    Reading of eq 41 (which prints ``beta_1`` in both lines): ``z1' = z2 - beta1 e1 + b0 u`` and
    ``z2' = -beta2 fal(e1, alpha, delta)``, ``e1 = z1 - y``; fal as in :func:`fal` (eq 42, continuous reading).

    Discretisation: the predict/correct step of LinearESO, with the disturbance correction passed through fal
    normalised to unit slope in its linear zone::

        z2 += l2 * g(eps),   g(eps) = delta^(1-alpha) fal(eps, alpha, delta)
             = eps                               for |eps| <= delta_dps
             = eps * (delta_dps/|eps|)^(1-alpha)  outside

    so ``beta2`` / ``l2`` are the *linear-zone* gains (Han's ``beta02`` equals ``beta2 * delta^(1-alpha)``).
    For errors inside the linear zone the observer is exactly the LinearESO with the same gains; outside it the
    disturbance gain shrinks by ``(delta/|eps|)^(1-alpha)`` (less jitter from gyro spikes, paper sec 4.2). With the
    frozen factor ``c`` in (0, 1] the error matrix has ``det = 1 - l1`` and trace in ``[2q, 1 + q^2]``, inside the
    Jury triangle, for any ``omega_o * h``. The unscaled fal of a forward-Euler Han ESO multiplies the gain by
    ``delta^(alpha-1)`` (x10 for delta = 0.01, alpha = 0.5), which is why it goes unstable near 200 rad/s at 1 kHz.

    Tuning: either ``omega_o_rad_s`` (double pole, as LinearESO) or ``beta1_per_s`` and ``beta2_per_s2``
    (continuous linear-zone gains, pole-matched by :func:`current_observer_gains`). ``delta_dps`` is in the
    error's units (deg/s); the default 0.05 deg/s is ~1.5 sigma of the paper's gyro noise (+-0.102 deg/s peak).
    """

    __slots__ = ("_delta", "_one_minus_alpha", "alpha", "delta_dps")

    def __init__(
        self,
        *,
        b0_dps2_per_count: float,
        dt_s: float,
        omega_o_rad_s: float | None = None,
        beta1_per_s: float | None = None,
        beta2_per_s2: float | None = None,
        alpha: float = 0.5,
        delta_dps: float = 0.05,
    ) -> None:
        if omega_o_rad_s is not None:
            if beta1_per_s is not None or beta2_per_s2 is not None:
                raise ValueError("give omega_o_rad_s or (beta1_per_s, beta2_per_s2), not both")
            beta1_per_s, beta2_per_s2 = 2.0 * omega_o_rad_s, omega_o_rad_s * omega_o_rad_s
        elif beta1_per_s is None or beta2_per_s2 is None:
            raise ValueError("give omega_o_rad_s or both beta1_per_s and beta2_per_s2")
        if not 0.0 < alpha <= 1.0:
            raise ValueError("alpha must be in (0, 1]")
        if delta_dps <= 0.0:
            raise ValueError("delta_dps must be > 0")
        l1, l2 = current_observer_gains(beta1_per_s=beta1_per_s, beta2_per_s2=beta2_per_s2, dt_s=dt_s)
        super().__init__(l1=l1, l2_per_s=l2, b0_dps2_per_count=b0_dps2_per_count, dt_s=dt_s)
        self.alpha = float(alpha)
        self.delta_dps = float(delta_dps)
        self._delta = self.delta_dps
        self._one_minus_alpha = 1.0 - self.alpha

    def step(self, rate_meas_dps: float, u_applied_counts: float) -> float:
        """One sample: ``u_applied_counts`` is the saturated drive held since the previous step. Returns z1."""
        z2 = self.z2
        p1 = self.z1 + self._h * z2 + self._hb0 * u_applied_counts
        e = rate_meas_dps - p1
        ae = abs(e)
        g = e if ae <= self._delta else e * (self._delta / ae) ** self._one_minus_alpha
        self.z1 = z1 = p1 + self._l1 * e
        self.z2 = z2 + self._l2 * g
        return z1
