"""Frequency-sweep identification of the rate-loop plant (seed 000 Figs 8-9, eqs 33-38), as a pure library.

The bench adds a swept sine ``r(t)`` (:class:`SweptSine`) to the rate command of the closed 1 kHz rate loop and logs,
per tick, the command ``r`` (deg/s), the drive ``u`` (signed DAC counts) and the measured gyro rate ``y`` (deg/s).

* :func:`estimate_frf`: Welch cross-spectra (``scipy.signal``: Hann window, 50 % overlap) and the *indirect* closed-loop
  estimate ``P = S_ry / S_ru`` of the plant ``y/u``: both spectra are cross-spectra with the external excitation
  ``r``, which the gyro noise and the disturbances are not correlated with, so neither noise nor feedback bias it
  (the direct ``S_uy / S_uu`` tends to ``-1/C`` where noise dominates, because ``u`` carries the fed-back noise).
* :func:`fit_plant`: ``P(s) = k_m / s * 1 / (1 + s / omega_c) * exp(-s T_d)`` (deg/s per count, ``k_m`` in
  deg/s^2 per count) by weighted least squares on ``ln P = ln|P| + j arg P`` over the coherent bins. For a fixed
  ``omega_c`` the problem is linear (``ln k_m`` from the magnitude, ``T_d`` from the phase); ``omega_c`` is searched
  (a grid, then ``scipy.optimize.minimize_scalar``, bounded, on log frequency).
  By default the integrator is the exact sampled one the 1 ms loop sees, ``k_m dt / (e^{j w dt} - 1)`` (= ``k_m /
  (j w)`` times a half-sample delay and ``(w dt/2) / sin(w dt/2)``), so ``T_d`` is the gyro + transport delay
  without the zero-order hold's half sample.
* :func:`bode_plot`: PNG of data, fit and coherence, headed by the fitted figures (:func:`fit_caption`).
  :func:`identify_log`: the whole chain on a session log.

Docs: docs/ident.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, model_validator

if TYPE_CHECKING:
    from hil.log.reader import LogData

__all__ = [
    "GYRO_CHANNEL",
    "Frf",
    "PlantFit",
    "SweptSine",
    "bode_plot",
    "estimate_frf",
    "estimate_sweep_frf",
    "fit_caption",
    "fit_plant",
    "identify_log",
    "plant_response",
]

TWO_PI = 2.0 * math.pi
GYRO_CHANNEL = {"el": "gyro_y_dps", "az": "gyro_z_dps"}  # the loop-group channel each axis' rate loop feeds back


# --- excitation ----------------------------------------------------------------------------------------------------


class SweptSine(BaseModel):
    """A swept sine added to one axis' rate command, ``t_s`` from the start of the excitation.

    ``[0, settle_s)``: zero (plus the ``offset_dps`` ramp, if any); ``[settle_s, settle_s + duration_s)``: the
    sweep ``amplitude_dps * taper * sin(phase)``, phase continuous and zero at the start, frequency ``f_start_hz ->
    f_stop_hz`` exponentially (``log``) or linearly; a raised-cosine taper of ``taper_s`` at each end; then zero.

    ``offset_dps`` (default 0) adds a constant rate during the sweep, ramped in over ``settle_s`` and out over the
    ``settle_s`` after it (``total_s`` covers both): if it exceeds the rate swing, the axis never reverses, so the
    Coulomb friction stays constant instead of switching at every zero crossing (the relay it makes otherwise looks
    like a pole near ``4 T_c k_m / (pi A)``, A the rate amplitude, and biases the identified ``k_m``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    f_start_hz: float = Field(0.5, gt=0, le=450, description="frequency at the start of the sweep")
    f_stop_hz: float = Field(300.0, gt=0, le=450, description="frequency at the end of the sweep (< 500 Hz Nyquist)")
    duration_s: float = Field(20.0, gt=0, le=3600, description="length of the sweep itself")
    amplitude_dps: float = Field(2.0, gt=0, le=200, description="peak of the sweep")
    kind: Literal["log", "linear"] = Field("log", description="log: exponential chirp; linear: linear chirp")
    axis: Literal["el", "az"] = Field("el", description="the axis whose rate command gets the sweep")
    settle_s: float = Field(0.5, ge=0, le=60, description="zero before the sweep starts (offset ramp, if any)")
    taper_s: float = Field(0.1, ge=0, le=60, description="raised-cosine fade in and out of the sweep amplitude")
    offset_dps: float = Field(0.0, ge=-200, le=200,
                              description="constant rate during the sweep (keeps friction on one side)")

    _c: tuple[float, ...] = PrivateAttr(default=())

    @model_validator(mode="after")
    def _check(self) -> SweptSine:
        if self.f_stop_hz == self.f_start_hz:
            raise ValueError("f_stop_hz must differ from f_start_hz")
        if 2.0 * self.taper_s > self.duration_s:
            raise ValueError("taper_s: the two tapers are longer than duration_s")
        return self

    def model_post_init(self, __context: Any) -> None:
        f0, f1, dur = self.f_start_hz, self.f_stop_hz, self.duration_s
        if f0 == f1:
            return  # refused by _check, which runs after this
        if self.kind == "log":
            rate = math.log(f1 / f0) / dur  # f(tau) = f0 exp(rate tau)
            c1, c2 = TWO_PI * f0 / rate, rate
        else:
            c1, c2 = TWO_PI * f0, math.pi * (f1 - f0) / dur  # phase = c1 tau + c2 tau^2
        self._c = (c1, c2)

    @property
    def total_s(self) -> float:
        """Length of the whole excitation: settle, sweep, and a settle after it."""
        return 2.0 * self.settle_s + self.duration_s

    @property
    def window_s(self) -> tuple[float, float]:
        """Where the sweep is active, relative to the start of the excitation."""
        return (self.settle_s, self.settle_s + self.duration_s)

    def frequency_hz(self, t_s: float) -> float:
        """Instantaneous frequency at ``t_s`` (clamped to the sweep)."""
        tau = min(max(t_s - self.settle_s, 0.0), self.duration_s)
        if self.kind == "log":
            return self.f_start_hz * math.exp(self._c[1] * tau)
        return self.f_start_hz + (self.f_stop_hz - self.f_start_hz) * tau / self.duration_s

    def rate_dps(self, t_s: float) -> float:
        """The rate command to add at ``t_s`` (plain float math: a few microseconds, for the 1 kHz loop)."""
        settle, dur = self.settle_s, self.duration_s
        tau = t_s - settle
        out = 0.0
        if 0.0 < tau < dur:
            c1, c2 = self._c
            phase = c1 * math.expm1(c2 * tau) if self.kind == "log" else tau * (c1 + c2 * tau)
            a = self.amplitude_dps
            tp = self.taper_s
            if tau < tp:
                a *= 0.5 - 0.5 * math.cos(math.pi * tau / tp)
            elif dur - tau < tp:
                a *= 0.5 - 0.5 * math.cos(math.pi * (dur - tau) / tp)
            out = a * math.sin(phase)
        off = self.offset_dps
        if off != 0.0 and 0.0 < t_s < dur + 2.0 * settle:
            if t_s < settle:
                off *= 0.5 - 0.5 * math.cos(math.pi * t_s / settle)
            elif tau > dur:
                off *= 0.5 + 0.5 * math.cos(math.pi * (tau - dur) / settle)
            out += off
        return out

    __call__ = rate_dps


# --- frequency response --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Frf:
    """An estimated frequency response ``y/u`` (deg/s per DAC count) on Welch bins."""

    freq_hz: np.ndarray
    response: np.ndarray  # complex
    coherence: np.ndarray  # in [0, 1]
    dt_s: float  # sample time of the data (the fit's sampled integrator uses it)
    n_segments: int  # Welch averages
    method: Literal["indirect", "direct"] = "indirect"

    def magnitude_db(self) -> np.ndarray:
        return 20.0 * np.log10(np.abs(self.response))

    def phase_deg(self) -> np.ndarray:
        """Phase, unwrapped along frequency."""
        return np.degrees(np.unwrap(np.angle(self.response)))


def welch_layout(n: int, nperseg: int) -> tuple[int, int]:
    """Where the Welch segments of an ``n``-sample record go: ``(skip, noverlap)`` for ``scipy.signal``'s
    ``csd`` / ``welch`` / ``coherence`` on ``x[skip:]``.

    The segments overlap by 50 % or slightly more, as few as cover the whole record at 50 %, and the last one ends
    exactly at ``n`` (a sweep's last frequencies must not fall off the end); the segments step by a whole number
    of samples, so the first ``skip`` samples (fewer than the number of segments) are left out."""
    if not 0 < nperseg <= n:
        raise ValueError(f"nperseg {nperseg} does not fit {n} samples")
    span = n - nperseg
    half = max(nperseg // 2, 1)
    n_steps = math.ceil(span / half)
    if n_steps == 0:
        return 0, nperseg // 2
    step = span // n_steps
    return span - n_steps * step, nperseg - step


def welch_options(nperseg: int, noverlap: int, fs_hz: float) -> dict[str, Any]:
    """The ``scipy.signal`` spectral options shared by the FRF and the campaign report's PSD: periodic Hann
    window, each segment's least-squares line removed (a ramp or slow drift leaks less); scipy's defaults for the
    rest (one-sided, density, mean of the segments)."""
    return {"fs": fs_hz, "window": "hann", "nperseg": nperseg, "noverlap": noverlap, "detrend": "linear"}


def default_nperseg(n: int, dt_s: float, f_min_hz: float) -> int:
    """A power of two giving ~4 bins below ``f_min_hz`` (the Hann lobe spans 2), at most half the record."""
    want = 2 ** math.ceil(math.log2(max(4.0 / (f_min_hz * dt_s), 16.0)))
    cap = 2 ** int(math.log2(max(n // 2, 16)))
    return int(min(want, cap))


def estimate_frf(
    r: Any,
    u: Any,
    y: Any,
    dt_s: float,
    *,
    f_min_hz: float,
    f_max_hz: float,
    nperseg: int | None = None,
    method: Literal["indirect", "direct"] = "indirect",
) -> Frf:
    """Plant ``y/u`` from closed-loop data excited by ``r``: Welch (Hann, 50 % overlap), bins in [f_min, f_max].

    The segments (``nperseg`` long, default: ~4 bins below ``f_min_hz``) overlap by 50 % or slightly more so that
    they end exactly at the end of the record (:func:`welch_layout`); spectra and coherences by ``scipy.signal``.

    ``indirect`` (default): ``S_ry / S_ru``; the coherence is the one whose random error equals the sum of the two
    estimates': ``1 / (1/g_ry + 1/g_ru - 1)``. ``direct``: ``S_uy / S_uu`` with ``g_uy`` (biased under feedback
    with noise; kept for comparison).
    """
    from scipy import signal  # noqa: PLC0415  (heavy: loaded only when this computation runs)

    rr, uu, yy = (np.asarray(v, dtype=float).ravel() for v in (r, u, y))
    n = rr.size
    if not (uu.size == n and yy.size == n):
        raise ValueError(f"r, u, y must have the same length (got {rr.size}, {uu.size}, {yy.size})")
    if not (np.all(np.isfinite(rr)) and np.all(np.isfinite(uu)) and np.all(np.isfinite(yy))):
        raise ValueError("r, u, y must be finite")
    if not 0.0 < f_min_hz < f_max_hz:
        raise ValueError(f"need 0 < f_min_hz < f_max_hz (got {f_min_hz}, {f_max_hz})")
    if method not in ("indirect", "direct"):
        raise ValueError(f"method must be 'indirect' or 'direct' (got {method!r})")
    nper = nperseg or default_nperseg(n, dt_s, f_min_hz)
    if nper < 16 or nper > n:
        raise ValueError(f"nperseg {nper} does not fit {n} samples")
    skip, noverlap = welch_layout(n, nper)
    rr, uu, yy = rr[skip:], uu[skip:], yy[skip:]
    opts = welch_options(nper, noverlap, 1.0 / dt_s)
    n_seg = (rr.size - noverlap) // (nper - noverlap)

    def coherence(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # 0 where a spectrum is exactly zero
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.nan_to_num(signal.coherence(a, b, **opts)[1], nan=0.0, posinf=0.0)

    tiny = np.finfo(float).tiny
    if method == "indirect":
        freq, s_ry = signal.csd(rr, yy, **opts)
        s_ru = signal.csd(rr, uu, **opts)[1]
        resp = s_ry / np.where(s_ru == 0, tiny, s_ru)
        g_ry, g_ru = coherence(rr, yy), coherence(rr, uu)
        coh = 1.0 / (1.0 / np.maximum(g_ry, 1e-12) + 1.0 / np.maximum(g_ru, 1e-12) - 1.0)
    else:
        freq, s_uy = signal.csd(uu, yy, **opts)
        s_uu = signal.welch(uu, **opts)[1]
        resp = s_uy / np.maximum(s_uu, tiny)
        coh = coherence(uu, yy)
    keep = (freq >= f_min_hz) & (freq <= f_max_hz) & (freq > 0)
    if not np.any(keep):
        raise ValueError(f"no frequency bin in [{f_min_hz}, {f_max_hz}] Hz with nperseg {nper}")
    return Frf(
        freq_hz=freq[keep],
        response=resp[keep],
        coherence=np.clip(coh[keep], 0.0, 1.0),
        dt_s=float(dt_s),
        n_segments=int(n_seg),
        method=method,
    )


HI_NPERSEG = 1024  # Welch segment of a sweep's high band (a chirp: longer segments hold more of it, fewer average it)


def estimate_sweep_frf(r: Any, u: Any, y: Any, dt_s: float, *, f_min_hz: float, f_max_hz: float) -> Frf:
    """:func:`estimate_frf` of a swept sine at two resolutions: long segments (~4 bins below ``f_min_hz``) for the
    low band (k_m, a cable's spring), ``HI_NPERSEG`` ones above ``max(20 Hz, 8 bins)``: a chirp crosses each
    high-frequency bin in milliseconds, so the short segments' noise is a fraction of the long ones' and their
    averages many (coherent further up: the lag, the delay and a structural mode live there)."""
    lo = estimate_frf(r, u, y, dt_s, f_min_hz=f_min_hz, f_max_hz=f_max_hz)
    n = np.asarray(r).size
    if n < HI_NPERSEG:
        return lo
    hi = estimate_frf(r, u, y, dt_s, f_min_hz=f_min_hz, f_max_hz=f_max_hz, nperseg=HI_NPERSEG)
    split = max(20.0, 8.0 / (HI_NPERSEG * dt_s))
    lo_sel, hi_sel = lo.freq_hz < split, hi.freq_hz >= split
    return Frf(np.concatenate([lo.freq_hz[lo_sel], hi.freq_hz[hi_sel]]),
               np.concatenate([lo.response[lo_sel], hi.response[hi_sel]]),
               np.concatenate([lo.coherence[lo_sel], hi.coherence[hi_sel]]), dt_s, lo.n_segments)


# --- model and fit -------------------------------------------------------------------------------------------------


def plant_response(
    freq_hz: Any,
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

    def response(self, freq_hz: Any) -> np.ndarray:
        return plant_response(
            freq_hz,
            self.k_m_dps2_per_count,
            bandwidth_hz=self.model_bandwidth_hz,
            delay_s=self.model_delay_s,
            dt_s=self.dt_s,
        )

    def describe(self) -> str:
        bw = "n/a" if self.gyro_bandwidth_hz is None else f"{self.gyro_bandwidth_hz:.0f} Hz"
        td = "n/a" if self.delay_ms is None else f"{self.delay_ms:.2f} ms"
        lo, hi = self.f_range_hz
        return (
            f"k_m = {self.k_m_dps2_per_count:.5g} deg/s^2 per count, gyro bandwidth {bw}, delay {td} "
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
) -> PlantFit:
    """Weighted least squares of the plant model on the bins with ``coherence >= coherence_min`` in the range.

    Residual ``ln(P_data / P_model)`` (log-magnitude and phase in radians alike), weights ``g / (1 - g)`` (the
    inverse variance of a Welch estimate, capped at g = 0.99) times ``1/f`` (each decade counts the same, so ``k_m``
    comes mostly from the low-frequency magnitude where ``|P| ~ k_m / w``). ``lag=False``: integrator + delay only.
    The gyro bandwidth is reported only if its pole is within twice the highest fitted frequency (>= 1 dB of
    roll-off in the band, otherwise it cannot be told from a delay and the integrator + delay model is reported);
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
        if cand.cost < best.cost and fc <= 2.0 * f_hi:
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


# --- plot ----------------------------------------------------------------------------------------------------------


def fit_caption(fit: PlantFit) -> str:
    """The fitted figures, each once, on two lines: the model's parameters, then the fit's band and residuals (the
    Bode plot's heading; :meth:`PlantFit.describe` is the one-line form)."""
    bw = "n/a" if fit.gyro_bandwidth_hz is None else f"{fit.gyro_bandwidth_hz:.0f} Hz"
    td = "n/a" if fit.delay_ms is None else f"{fit.delay_ms:.2f} ms"
    lo, hi = fit.f_range_hz
    return (f"k_m = {fit.k_m_dps2_per_count:.5g} deg/s\u00b2 per count, gyro bandwidth {bw}, delay {td}\n"
            f"rms error {fit.rms_error_db:.2f} dB / {fit.rms_phase_deg:.1f} deg over {fit.n_bins} bins, "
            f"{lo:.3g}\u2013{hi:.3g} Hz")


def bode_plot(
    frf: Frf, fit: PlantFit | None, path: str | Path, *, title: str | None = None, coherence_min: float = 0.8
) -> Path:
    """Magnitude (dB) and phase (deg) against log frequency: data (grey below ``coherence_min``), fit (the fitted
    band shaded), coherence; ``fit`` may be None. ``title`` (e.g. the session's name, default "plant
    identification") heads the plot, the fitted figures (:func:`fit_caption`) under it; the page grows to hold the
    whole heading (constrained layout, tight bounding box), and the PNG's Title and Description hold the same two
    texts. Returns the PNG's path (parent directories are created)."""
    from matplotlib.figure import Figure as MplFigure  # noqa: PLC0415  (heavy: loaded only when a figure is drawn)

    out = Path(path)
    f = frf.freq_hz
    head = title or "plant identification"
    caption = fit_caption(fit) if fit is not None else "no fit"
    fig = MplFigure(figsize=(8.0, 6.5), layout="constrained")
    ax_m, ax_p = fig.subplots(2, 1, sharex=True)
    mag, ph = frf.magnitude_db(), frf.phase_deg()
    model = None
    if fit is not None:  # data phase shown around the model's: no unwrapping through incoherent bins
        model = fit.response(f)
        ph_m = np.degrees(np.unwrap(np.angle(model)))
        ph = ph_m + np.degrees(np.angle(frf.response / model))
    ax_c = ax_m.twinx()
    ax_c.fill_between(f, 0.0, frf.coherence, color="tab:green", alpha=0.12, step="mid", label="coherence")
    ax_c.set_ylim(0.0, 1.05)
    ax_c.set_ylabel("coherence", color="tab:green")
    good = frf.coherence >= coherence_min
    for ax, v in ((ax_m, mag), (ax_p, ph)):
        ax.semilogx(f[good], v[good], ".", ms=2.5, color="tab:blue", label=f"data ({frf.method})")
        ax.semilogx(f[~good], v[~good], ".", ms=2.0, color="0.7", label=f"coherence < {coherence_min:g}")
    if fit is not None and model is not None:
        ax_m.semilogx(f, 20.0 * np.log10(np.abs(model)), "-", color="tab:red", label="fit")
        ax_p.semilogx(f, ph_m, "-", color="tab:red", label="fit")
        lo, hi = fit.f_range_hz
        for ax in (ax_m, ax_p):
            ax.axvspan(lo, hi, color="0.5", alpha=0.06, lw=0)
    ax_m.set_ylabel("|y/u| (dB re 1 deg/s per count)")
    ax_p.set_ylabel("phase (deg)")
    ax_p.set_xlabel("frequency (Hz)")
    for ax in (ax_m, ax_p):
        ax.grid(True, which="both", alpha=0.3)
        ax.patch.set_visible(False)
    ax_m.set_zorder(ax_c.get_zorder() + 1)  # data and legend over the coherence shading
    ax_m.legend(loc="lower left", fontsize=8)
    fig.suptitle(head, fontsize=11, fontweight="bold")
    ax_m.set_title(caption, fontsize=9)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110, format="png", bbox_inches="tight", pad_inches=0.1,
                metadata={"Title": head, "Description": caption})
    return out


# --- session logs --------------------------------------------------------------------------------------------------


def _uniform(tick: np.ndarray, *cols: np.ndarray) -> tuple[np.ndarray, ...]:
    """Columns on a gap-free tick grid: samples the bench missed (tick gaps) are linearly interpolated."""
    t = tick.astype(np.int64)
    grid = np.arange(t[0], t[-1] + 1)
    if grid.size == t.size:
        return cols
    return tuple(np.interp(grid, t, c) for c in cols)


def sweep_start(r: np.ndarray, sweep: SweptSine, dt_s: float) -> int:
    """Index where the excitation starts: the peak of the cross-correlation of the command with the sweep."""
    tpl = np.array([sweep.rate_dps(k * dt_s) for k in range(round(sweep.total_s / dt_s))])
    x = r - r.mean()
    tpl -= tpl.mean()
    nfft = 1 << math.ceil(math.log2(x.size + tpl.size))
    xc = np.fft.irfft(np.fft.rfft(x, nfft) * np.conj(np.fft.rfft(tpl, nfft)), nfft)[: max(x.size - tpl.size, 0) + 1]
    return int(np.argmax(xc))


def identify_log(
    data: LogData,
    sweep: SweptSine | None = None,
    *,
    axis: Literal["el", "az"] | None = None,
    f_min_hz: float | None = None,
    f_max_hz: float | None = None,
    nperseg: int | None = None,
    coherence_min: float = 0.8,
    lag: bool = True,
) -> tuple[Frf, PlantFit]:
    """FRF and fit from a session log (``hil.log.read_log``): one axis' rate command, drive and gyro.

    With ``sweep``: the excitation is located by cross-correlating the logged command with ``sweep.rate_dps``; the
    window is the active sweep plus half of ``settle_s`` each side; FRF band ``f_start..f_stop`` (at most 0.45 / dt);
    the fit skips the sweep's first octave (below ``2 f_start`` the chirp starts at a segment edge and its bins are
    biased by a few tenths of a dB). Without: the span where the command departs from its first value by more than
    5 % of its largest excursion, band 1 Hz .. 0.45 / dt, fitted whole. ``f_min_hz`` / ``f_max_hz`` override the
    band (FRF and fit). ``axis`` defaults to the sweep's, else "el".
    """
    ax = axis or (sweep.axis if sweep is not None else "el")
    loop = data.groups.get("loop")
    if not loop:
        raise ValueError("the log has no 'loop' group")
    names = (f"rate_cmd_{ax}_dps", f"drive_{ax}_counts", GYRO_CHANNEL[ax])
    missing = [c for c in (*names, "t_s") if c not in loop]
    if missing:
        raise ValueError(f"loop group lacks {', '.join(missing)}")
    r, u, y = (np.asarray(loop[c], dtype=float) for c in names)
    t = np.asarray(loop["t_s"], dtype=float)
    if r.size < 64:
        raise ValueError(f"loop group has {r.size} rows: too short")
    dt = float(np.median(np.diff(t)))
    if "tick" in loop:
        r, u, y = _uniform(np.asarray(loop["tick"]), r, u, y)
    if sweep is not None:
        k0 = sweep_start(r, sweep, dt)
        pad = 0.5 * sweep.settle_s
        a, b = k0 + round((sweep.window_s[0] - pad) / dt), k0 + round((sweep.window_s[1] + pad) / dt)
        f_lo, f_hi = min(sweep.f_start_hz, sweep.f_stop_hz), max(sweep.f_start_hz, sweep.f_stop_hz)
        fit_lo = 2.0 * f_lo
    else:
        dev = np.abs(r - r[0])
        act = np.flatnonzero(dev > 0.05 * dev.max()) if dev.max() > 0 else np.array([], dtype=int)
        if act.size == 0:
            raise ValueError(f"rate_cmd_{ax}_dps never moves: no excitation found")
        a, b = int(act[0]), int(act[-1]) + 1
        f_lo, f_hi = 1.0, math.inf
        fit_lo = f_lo
    a, b = max(a, 0), min(b, r.size)
    if b - a < 64:
        raise ValueError(f"the sweep window has {b - a} samples in the log")
    if f_min_hz is not None:
        f_lo = fit_lo = f_min_hz
    f_hi = f_max_hz if f_max_hz is not None else min(f_hi, 0.45 / dt)
    frf = estimate_frf(r[a:b], u[a:b], y[a:b], dt, f_min_hz=f_lo, f_max_hz=f_hi, nperseg=nperseg)
    return frf, fit_plant(frf, coherence_min=coherence_min, f_min_hz=fit_lo, lag=lag)
