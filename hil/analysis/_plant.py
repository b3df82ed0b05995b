"""Frequency-sweep identification of the rate-loop plant (seed 000 Figs 8-9, eqs 33-38): the model and its fit.

* :func:`fit_plant`: ``P(s) = k_m / s * 1 / (1 + s / omega_c) * exp(-s T_d)`` (deg/s per count, ``k_m`` in
  deg/s^2 per count) by weighted least squares on ``ln P = ln|P| + j arg P`` over the coherent bins. For a fixed
  ``omega_c`` the problem is linear (``ln k_m`` from the magnitude, ``T_d`` from the phase); ``omega_c`` is searched
  (a grid, then ``scipy.optimize.minimize_scalar``, bounded, on log frequency).
  By default the integrator is the exact sampled one the 1 ms loop sees, ``k_m dt / (e^{j w dt} - 1)`` (= ``k_m /
  (j w)`` times a half-sample delay and ``(w dt/2) / sin(w dt/2)``), so ``T_d`` is the gyro + transport delay
  without the zero-order hold's half sample.
* :func:`fit_caption`: the fitted figures, the Bode plot's heading.
* :func:`resonance_hz`: the first resonance the rigid model lacks, third octave by third octave.

Docs: docs/ident.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from hil.analysis._frf import LEVELS_PER_OCTAVE, Frf, octave_share

TWO_PI = 2.0 * math.pi


def plant_response(
    freq_hz: ArrayLike,
    k_m_dps2_per_count: float,
    *,
    bandwidth_hz: float | None = None,
    delay_s: float = 0.0,
    dt_s: float | None = None,
) -> np.ndarray:
    """``k_m / s * 1 / (1 + s/omega_c) * exp(-s T_d)`` at ``s = j 2 pi f``.

    With ``dt_s``: what a loop sampling every ``dt_s`` sees of it, the drive held over each period (zero-order
    hold) and the output sampled at the period's start, i.e. the exact ZOH equivalent (alias sum
    ``1/dt sum_k P(s_k) (1 - e^{-s_k dt}) / s_k``, ``s_k = j(w + 2 pi k / dt)``; closed form without the lag).
    Below Nyquist it is ``k_m / (j w)`` times a half-sample delay and ``(w dt/2) / sin(w dt/2)`` (+1.3 dB at 300 Hz
    for 1 ms), so ``T_d`` stays the continuous delay (gyro + transport) without the hold's half sample.
    """
    w = TWO_PI * np.atleast_1d(np.asarray(freq_hz, dtype=float))
    return k_m_dps2_per_count * SweepShapes(w, dt_s).shape(bandwidth_hz, delay_s)


_ALIASES = 16  # alias terms each side: with the lag they fall off as 1/k^3 (tail < 1e-5 below Nyquist)


class SweepShapes:
    """The model with k_m = 1 on fixed frequencies; per bandwidth, the delay-free alias terms are cached."""

    def __init__(self, w: np.ndarray, dt_s: float | None) -> None:
        self.w, self.dt = w, dt_s
        self._cache: dict[float, np.ndarray] = {}
        if dt_s:
            self.k = np.arange(-_ALIASES, _ALIASES + 1)
            self.s_k = 1j * (w[:, None] + TWO_PI / dt_s * self.k[None, :])
            self._hold = (1.0 - np.exp(-1j * w * dt_s))[:, None] / self.s_k / dt_s

    def shape(self, bandwidth_hz: float | None, delay_s: float) -> np.ndarray:
        w, dt = self.w, self.dt
        if not dt:
            lag = 1.0 if bandwidth_hz is None else 1.0 / (1.0 + 1j * w / (TWO_PI * bandwidth_hz))
            return lag * np.exp(-1j * w * delay_s) / (1j * w)
        n = math.floor(delay_s / dt + 1e-12)
        frac = delay_s / dt - n
        if bandwidth_hz is None:  # rate linear over each period: the sample is an interpolation of two ticks
            z1 = np.exp(-1j * w * dt)
            return dt * z1 ** (n + 1) * ((1.0 - frac) + frac * z1) / (1.0 - z1)
        terms = self._cache.get(bandwidth_hz)
        if terms is None:
            terms = self._hold / self.s_k / (1.0 + self.s_k / (TWO_PI * bandwidth_hz))
            self._cache[bandwidth_hz] = terms
        phase = np.exp(-1j * TWO_PI * self.k * frac)  # e^{-j w_k T_d} = e^{-j w T_d} e^{-j 2 pi k T_d / dt}
        return np.exp(-1j * w * delay_s) * (terms @ phase)


@dataclass(frozen=True)
class PlantFit:
    """The fitted ``k_m / s * 1/(1 + s/omega_c) * exp(-s T_d)``; ``None`` where not identifiable from the data."""

    k_m_dps2_per_count: float
    gyro_bandwidth_hz: float | None
    delay_ms: float | None
    rms_error_db: float  # RMS magnitude residual over the fitted bins
    rms_phase_deg: float  # RMS phase residual over the fitted bins
    n_bins: int
    f_range_hz: tuple[float, float]
    model_bandwidth_hz: float | None  # what the model curve uses (== gyro_bandwidth_hz)
    model_delay_s: float  # what the model curve uses, even when delay_ms is None
    dt_s: float | None  # the sampled integrator's period (None: continuous k_m / s)

    def response(self, freq_hz: ArrayLike) -> np.ndarray:
        return plant_response(
            freq_hz,
            self.k_m_dps2_per_count,
            bandwidth_hz=self.model_bandwidth_hz,
            delay_s=self.model_delay_s,
            dt_s=self.dt_s,
        )

    def lag_and_delay(self) -> str:
        """The gyro's bandwidth and the delay as the fit resolved them, never a figure from outside the fitted band:
        without the pole in the band, the bandwidth is "above" the band's top and the delay is the loop's (the
        gyro's lag, its delay and the wire's together, which the band cannot tell apart)."""
        hi = self.f_range_hz[1]
        if self.gyro_bandwidth_hz is not None:
            td = "n/a" if self.delay_ms is None else f"{self.delay_ms:.2f} ms"
            return f"gyro bandwidth {self.gyro_bandwidth_hz:.0f} Hz, delay {td}"
        td = "n/a" if self.delay_ms is None else f"{self.delay_ms:.2f} ms (the gyro's lag included)"
        return f"gyro bandwidth above {hi:.3g} Hz, loop delay {td}"

    def describe(self) -> str:
        lo, hi = self.f_range_hz
        return (
            f"k_m = {self.k_m_dps2_per_count:.5g} deg/s^2 per count, {self.lag_and_delay()} "
            f"(rms {self.rms_error_db:.2f} dB / {self.rms_phase_deg:.1f} deg over {self.n_bins} bins, "
            f"{lo:.3g}-{hi:.3g} Hz)"
        )


@dataclass(frozen=True)
class _Lin:
    cost: float
    ln_k: float
    delay_s: float
    res_mag: np.ndarray
    res_ph: np.ndarray


def _fit_linear(shapes: SweepShapes, p: np.ndarray, wt: np.ndarray, bandwidth_hz: float | None) -> _Lin:
    """For a fixed bandwidth: ln k_m = weighted mean of ln|P/shape|, T_d from the LS slope (through 0) of the phase
    residual; the sampled shape depends weakly on T_d beyond e^{-j w T_d}, so a few fixed-point passes."""
    w = shapes.w
    td = 0.0
    for _ in range(8 if shapes.dt else 2):
        ratio = p / shapes.shape(bandwidth_hz, td)
        b = np.unwrap(np.angle(ratio))
        b -= TWO_PI * round(float(b[0]) / TWO_PI)  # the phase starts near 0 at low frequency
        step = float(-np.sum(wt * w * b) / np.sum(wt * w * w))
        if abs(step) < 1e-9 or (td == 0.0 and step < 0.0):
            break
        td = max(0.0, td + step)
    ratio = p / shapes.shape(bandwidth_hz, td)
    a = np.log(np.abs(ratio))
    b = np.unwrap(np.angle(ratio))
    b -= TWO_PI * round(float(b[0]) / TWO_PI)
    ln_k = float(np.sum(wt * a) / np.sum(wt))
    ra = a - ln_k
    return _Lin(float(np.sum(wt * (ra * ra + b * b))), ln_k, td, ra, b)


def fit_plant(
    frf: Frf,
    *,
    coherence_min: float = 0.8,
    f_min_hz: float | None = None,
    f_max_hz: float | None = None,
    lag: bool = True,
    sampled_integrator: bool = True,
    pole_max_ratio: float = 2.0,
    pole_min_gain: float = 0.0,
) -> PlantFit:
    """Weighted least squares of the plant model on the bins with ``coherence >= coherence_min`` in the range.

    Residual ``ln(P_data / P_model)`` (log-magnitude and phase in radians alike), weights ``g / (1 - g)`` (the
    inverse variance of a Welch estimate, capped at g = 0.99) times ``1/f`` (each decade counts the same, so ``k_m``
    comes mostly from the low-frequency magnitude where ``|P| ~ k_m / w``). ``lag=False``: integrator + delay only.
    The gyro bandwidth is reported only if its pole is within ``pole_max_ratio`` times the highest fitted frequency
    (2: >= 1 dB of roll-off in the band, otherwise it cannot be told from a delay and the integrator + delay model is
    reported; ``hil ident`` asks for 1, no figure from outside the coherent band) and it lowers the cost by more than
    ``pole_min_gain`` (a fraction; ``hil ident`` asks for 0.3: a pole that barely helps is the residual of something
    else, a mode's skirt, not a lag);
    the delay only if its 1-sigma uncertainty (RMS phase residual over the top frequency) is under
    max(0.1 ms, 25 %).
    """
    f = frf.freq_hz
    sel = np.isfinite(frf.response) & (np.abs(frf.response) > 0) & (frf.coherence >= coherence_min)
    if f_min_hz is not None:
        sel &= f >= f_min_hz
    if f_max_hz is not None:
        sel &= f <= f_max_hz
    n = int(np.count_nonzero(sel))
    if n < 4:
        raise ValueError(f"only {n} bins with coherence >= {coherence_min} in the range: nothing to fit")
    fs, p = f[sel], frf.response[sel]
    w = TWO_PI * fs
    g = np.minimum(frf.coherence[sel], 0.99)
    wt = g / (1.0 - g) / fs
    dt = frf.dt_s if sampled_integrator else None
    f_hi = float(fs.max())

    best_bw: float | None = None
    shapes = SweepShapes(w, dt)
    best = _fit_linear(shapes, p, wt, None)
    if lag:
        from scipy.optimize import minimize_scalar  # noqa: PLC0415  (heavy: loaded only when this computation runs)

        def cost(log_fc: float) -> _Lin:
            return _fit_linear(shapes, p, wt, 10.0**log_fc)

        grid = np.linspace(math.log10(max(float(fs.min()), 0.05 * f_hi)), math.log10(50.0 * f_hi), 31)
        costs = [cost(x).cost for x in grid]
        i = int(np.argmin(costs))
        bounds = (float(grid[max(i - 1, 0)]), float(grid[min(i + 1, grid.size - 1)]))
        x = float(minimize_scalar(lambda v: cost(v).cost, bounds=bounds, method="bounded",
                                  options={"xatol": 1e-5}).x)  # Brent on log10(fc) around the grid's best
        cand = cost(x)
        fc = float(10.0**x)
        if cand.cost < (1.0 - pole_min_gain) * best.cost and fc <= pole_max_ratio * f_hi:
            best, best_bw = cand, fc

    rms_ph = float(np.sqrt(np.mean(best.res_ph**2)))
    sigma_td = rms_ph / (TWO_PI * f_hi)
    delay_ok = sigma_td < max(1e-4, 0.25 * best.delay_s)
    return PlantFit(
        k_m_dps2_per_count=math.exp(best.ln_k),
        gyro_bandwidth_hz=best_bw,
        delay_ms=best.delay_s * 1e3 if delay_ok else None,
        rms_error_db=float(np.sqrt(np.mean((best.res_mag * (20.0 / math.log(10.0))) ** 2))),
        rms_phase_deg=math.degrees(rms_ph),
        n_bins=n,
        f_range_hz=(float(fs.min()), f_hi),
        model_bandwidth_hz=best_bw,
        model_delay_s=best.delay_s,
        dt_s=dt,
    )


def fit_caption(fit: PlantFit) -> str:
    """The fitted figures, each once, on two lines: the model's parameters, then the fit's band and residuals (the
    Bode plot's heading; :meth:`PlantFit.describe` is the one-line form)."""
    lo, hi = fit.f_range_hz
    return (f"k_m = {fit.k_m_dps2_per_count:.5g} deg/s\u00b2 per count, {fit.lag_and_delay()}\n"
            f"rms error {fit.rms_error_db:.2f} dB / {fit.rms_phase_deg:.1f} deg over {fit.n_bins} bins, "
            f"{lo:.3g}\u2013{hi:.3g} Hz")


def resonance_hz(frf: Frf, fit: PlantFit, *, f_min_hz: float, f_max_hz: float, coherence_min: float = 0.8,
                 excess_db: float = 6.0) -> float | None:
    """The first resonance the rigid model ``fit`` does not have, between ``f_min_hz`` and ``f_max_hz``: the lowest
    third octave whose coherent bins stand a median ``excess_db`` or more above the model, at its largest bin; None
    without one. (A structural mode with the gyro on the load peaks 1/(2 zeta), 14 dB at zeta = 0.1; the gyro's lag,
    which the rigid fit below it may lack, only lowers the data.)"""
    ok = (frf.coherence >= coherence_min) & np.isfinite(frf.response) & (np.abs(frf.response) > 0)
    f = frf.freq_hz
    excess = np.full(f.size, -np.inf)
    excess[ok] = 20.0 * np.log10(np.abs(frf.response[ok]) / np.abs(fit.response(f[ok])))
    for fc in np.geomspace(f_min_hz, f_max_hz, max(2, round(math.log2(f_max_hz / f_min_hz) * LEVELS_PER_OCTAVE) + 1)):
        there = octave_share(f, fc) & ok
        if np.count_nonzero(there) >= 3 and float(np.median(excess[there])) >= excess_db:
            return float(f[there][np.argmax(excess[there])])
    return None
