"""Baseline gyro filters: first- and second-order low-pass (seed 000 section 4.3 uses 150 Hz).

Both are per-sample, plain-float filters with ``step(x) -> y`` and ``reset(value)``.
"""

from __future__ import annotations

import math

DEFAULT_DT_S = 1e-3
DEFAULT_CUTOFF_HZ = 150.0


class LowPass1:
    """First-order low-pass 1/(tau s + 1), tau = 1/(2 pi f_c), discretised exactly by zero-order hold.

    y_k = y_{k-1} + (1 - a) (x_k - y_{k-1}),  a = exp(-2 pi f_c h).
    """

    def __init__(self, *, cutoff_hz: float = DEFAULT_CUTOFF_HZ, dt_s: float = DEFAULT_DT_S) -> None:
        if cutoff_hz <= 0 or dt_s <= 0:
            raise ValueError("cutoff_hz and dt_s must be positive")
        self.cutoff_hz = cutoff_hz
        self.dt_s = dt_s
        self.alpha = 1.0 - math.exp(-2.0 * math.pi * cutoff_hz * dt_s)
        self.y = 0.0

    def reset(self, value: float = 0.0) -> None:
        self.y = value

    def step(self, x: float) -> float:
        self.y += self.alpha * (x - self.y)
        return self.y


class LowPass2:
    """Second-order low-pass w_c^2 / (s^2 + 2 zeta w_c s + w_c^2) by the bilinear transform, pre-warped at f_c.

    zeta = 1/sqrt(2) gives a Butterworth response (-3 dB at f_c). Direct form II transposed.
    """

    def __init__(
        self, *, cutoff_hz: float = DEFAULT_CUTOFF_HZ, damping: float = math.sqrt(0.5), dt_s: float = DEFAULT_DT_S
    ) -> None:
        if not 0 < cutoff_hz < 0.5 / dt_s:
            raise ValueError(f"cutoff_hz must lie in (0, Nyquist = {0.5 / dt_s:g} Hz)")
        if damping <= 0:
            raise ValueError("damping must be positive")
        self.cutoff_hz = cutoff_hz
        self.damping = damping
        self.dt_s = dt_s
        k = math.tan(math.pi * cutoff_hz * dt_s)  # pre-warped analogue frequency times h/2
        norm = 1.0 / (1.0 + 2.0 * damping * k + k * k)
        self.b0 = k * k * norm
        self.b1 = 2.0 * self.b0
        self.b2 = self.b0
        self.a1 = 2.0 * (k * k - 1.0) * norm
        self.a2 = (1.0 - 2.0 * damping * k + k * k) * norm
        self._s1 = 0.0
        self._s2 = 0.0
        self.y = 0.0

    def reset(self, value: float = 0.0) -> None:
        """Start in steady state at ``value`` (unity DC gain)."""
        self.y = value
        self._s1 = value - self.b0 * value
        self._s2 = self.b2 * value - self.a2 * value

    def step(self, x: float) -> float:
        y = self.b0 * x + self._s1
        self._s1 = self.b1 * x - self.a1 * y + self._s2
        self._s2 = self.b2 * x - self.a2 * y
        self.y = y
        return y
