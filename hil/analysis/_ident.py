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

import contextlib
import itertools
import math
from bisect import bisect_right
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, model_validator

from hil.log.schema import LATE_US

if TYPE_CHECKING:
    from hil.log.reader import LogData

__all__ = [
    "GYRO_CHANNEL",
    "IDENT_SWEEP",
    "Frf",
    "LevelCheck",
    "PlantFit",
    "SweptSine",
    "axis_columns",
    "bode_plot",
    "check_levels",
    "coherent_band",
    "estimate_frf",
    "estimate_sweep_frf",
    "fit_caption",
    "fit_plant",
    "host_disturbed",
    "identify_log",
    "level_frequencies",
    "log_frf",
    "next_level",
    "plant_response",
    "resonance_hz",
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
    levels: tuple[tuple[float, float], ...] = Field(
        (), description="[frequency_hz, amplitude_dps] pairs, frequencies rising: the amplitude at the chirp's "
        "frequency, interpolated on log frequency and held beyond the ends (a levelled sweep); empty: amplitude_dps "
        "throughout")

    _c: tuple[float, ...] = PrivateAttr(default=())
    _lv: tuple[tuple[float, ...], tuple[float, ...]] = PrivateAttr(default=((), ()))

    @model_validator(mode="before")
    @classmethod
    def _peak_of_levels(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("levels"):
            with contextlib.suppress(TypeError, ValueError):  # the field's own validation names what is wrong
                data = {**data, "amplitude_dps": max(float(a) for _, a in data["levels"])}
        return data

    @model_validator(mode="after")
    def _check(self) -> SweptSine:
        if self.f_stop_hz == self.f_start_hz:
            raise ValueError("f_stop_hz must differ from f_start_hz")
        if 2.0 * self.taper_s > self.duration_s:
            raise ValueError("taper_s: the two tapers are longer than duration_s")
        freqs = [f for f, _ in self.levels]
        if any(not 0 < f <= 500 for f in freqs) or any(b <= a for a, b in itertools.pairwise(freqs)):
            raise ValueError("levels: frequencies must rise and lie in (0, 500] Hz")
        if any(not 0 < a <= 200 for _, a in self.levels):
            raise ValueError("levels: amplitudes must lie in (0, 200] deg/s")
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
        if self.levels:
            self._lv = (tuple(math.log(f) for f, _ in self.levels), tuple(a for _, a in self.levels))

    def amplitude_at_dps(self, f_hz: float) -> float:
        """The sweep's amplitude at frequency ``f_hz``: ``levels`` interpolated on log frequency, else
        ``amplitude_dps``."""
        lf, amp = self._lv
        if not lf:
            return self.amplitude_dps
        x = math.log(f_hz)
        if x <= lf[0]:
            return amp[0]
        i = bisect_right(lf, x)
        if i >= len(lf):
            return amp[-1]
        w = (x - lf[i - 1]) / (lf[i] - lf[i - 1])
        return amp[i - 1] + w * (amp[i] - amp[i - 1])

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
            a = self.amplitude_dps if not self.levels else self.amplitude_at_dps(self.frequency_hz(t_s))
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


IDENT_SWEEP = SweptSine(f_start_hz=1.0, f_stop_hz=450.0, duration_s=8.0, amplitude_dps=1.5, offset_dps=3.0)
"""Where ``hil ident``'s sweep starts (its levelling goes on from here): 1-450 Hz in 8 s, 1.5 deg/s around 3 deg/s
(the axis turns 27 deg)."""


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


# --- plot ----------------------------------------------------------------------------------------------------------


def fit_caption(fit: PlantFit) -> str:
    """The fitted figures, each once, on two lines: the model's parameters, then the fit's band and residuals (the
    Bode plot's heading; :meth:`PlantFit.describe` is the one-line form)."""
    lo, hi = fit.f_range_hz
    return (f"k_m = {fit.k_m_dps2_per_count:.5g} deg/s\u00b2 per count, {fit.lag_and_delay()}\n"
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


def axis_columns(data: LogData, axis: Literal["el", "az"]) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """One axis' rate command ``r`` (deg/s), drive ``u`` (counts) and gyro ``y`` (deg/s) from a log's loop group on
    a gap-free tick grid, and the tick's period ``dt_s``."""
    loop = data.groups.get("loop")
    if not loop:
        raise ValueError("the log has no 'loop' group")
    names = (f"rate_cmd_{axis}_dps", f"drive_{axis}_counts", GYRO_CHANNEL[axis])
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
    return r, u, y, dt


HOST_SETTLE_S = 0.05  # after a late cycle or a missed sample the loop is taken as disturbed this long (its settling)
UNPACED_CLOCKS = ("lockstep", "sim")  # the emulated world waits for the bench: a late cycle disturbs nothing


def host_disturbed(data: LogData) -> np.ndarray:
    """Per tick of the log's gap-free grid (:func:`axis_columns`'), True where the host disturbed the loop: a late
    cycle (``latency_us`` over ``LATE_US``: its command reached the board after the next sample was due, so the
    board held the old one) or a missed sample, and the ``HOST_SETTLE_S`` after it while the loop settles. There the
    logged drive is not the one the board applied, and the loop's transient is noise the excitation did not make.
    All False on a log of the ``lockstep`` or ``sim`` clock, whose world waits for the bench."""
    loop = data.groups["loop"]
    rows = np.asarray(loop["t_s"]).size
    tick = np.asarray(loop["tick"], dtype=np.int64) if "tick" in loop else np.arange(rows, dtype=np.int64)
    n = int(tick[-1] - tick[0]) + 1 if rows else 0
    out = np.zeros(n, dtype=bool)
    if rows < 2 or data.attrs.get("clock") in UNPACED_CLOCKS:
        return out
    late = np.asarray(loop["latency_us"], dtype=float) > LATE_US if "latency_us" in loop else np.zeros(rows, bool)
    gap = np.asarray(loop["tick_gap"], dtype=np.int64) if "tick_gap" in loop else np.zeros(rows, np.int64)
    bad = late | (gap > 0)
    if not bad.any():
        return out
    settle = max(1, round(HOST_SETTLE_S / float(np.median(np.diff(np.asarray(loop["t_s"], dtype=float))))))
    at = tick[bad] - tick[0]
    start = np.maximum(at - gap[bad], 0)  # a missed sample's span starts at the first tick missed
    edges = np.zeros(n + 1, dtype=np.int64)
    np.add.at(edges, start, 1)
    np.add.at(edges, np.minimum(at + settle + 1, n), -1)
    out[:] = np.cumsum(edges[:n]) > 0
    return out


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
    frf, fit_lo = log_frf(data, sweep, axis=axis, f_min_hz=f_min_hz, f_max_hz=f_max_hz, nperseg=nperseg)
    return frf, fit_plant(frf, coherence_min=coherence_min, f_min_hz=fit_lo, lag=lag)


def log_frf(data: LogData, sweep: SweptSine | None = None, *, axis: Literal["el", "az"] | None = None,
            f_min_hz: float | None = None, f_max_hz: float | None = None,
            nperseg: int | None = None) -> tuple[Frf, float]:
    """The FRF of :func:`identify_log` without the fit, and the frequency its fit would start from."""
    ax = axis or (sweep.axis if sweep is not None else "el")
    r, u, y, dt = axis_columns(data, ax)
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
    if sweep is not None and nperseg is None:
        frf = estimate_sweep_frf(r[a:b], u[a:b], y[a:b], dt, f_min_hz=f_lo, f_max_hz=f_hi)
    else:
        frf = estimate_frf(r[a:b], u[a:b], y[a:b], dt, f_min_hz=f_lo, f_max_hz=f_hi, nperseg=nperseg)
    return frf, fit_lo




# --- levelling -----------------------------------------------------------------------------------------------------

LEVELS_PER_OCTAVE = 3  # the level table's spacing: third octaves
CLIPPED_SHARE = 0.01  # a third octave whose drive sat at its limit on more than this share of its ticks saturated
DISTURBED_SHARE = 0.02  # a third octave whose ticks the host disturbed (host_disturbed) more than this: its
# failed coherence may be the host's
DRIVE_TARGET = 0.8  # a raise stops where the drive's peak would reach this fraction of the limit
OFFSET_MIN_DPS = 0.3  # a levelling lowers the offset no further
REVERSAL_SMOOTH_S = 0.005  # the axis' rate is averaged over this before its sign is read (gyro noise is not motion)


@dataclass(frozen=True)
class LevelCheck:
    """What one sweep's log says about its level, per third octave of the sweep (:func:`check_levels`)."""

    freq_hz: np.ndarray  # centre of each third octave
    amplitude_dps: np.ndarray  # the sweep's amplitude there
    coherence: np.ndarray  # median coherence of the FRF bins in the third octave (0 where there is none)
    drive_peak_counts: np.ndarray  # 99th percentile of |drive| while the chirp was in the third octave
    drive_clipped: np.ndarray  # share of those ticks with the drive at the limit (the loop clipped it)
    drive_mean_counts: np.ndarray  # mean drive there (friction, imbalance, harness at the offset's rate)
    reversed: np.ndarray  # the axis' rate (5 ms mean) went against the offset there: friction switched sides
    rate_swing_dps: np.ndarray  # largest departure of the axis' rate (5 ms mean) from its mean there
    disturbed: np.ndarray | None = None  # share of the ticks the host disturbed (host_disturbed) in the FRF's segments
    # that carry the third octave; None: unknown

    def coherent(self, coherence_min: float) -> np.ndarray:
        return self.coherence >= coherence_min

    def spoiled(self, coherence_min: float) -> np.ndarray:
        """Where the coherence failed with the host disturbing more than ``DISTURBED_SHARE`` of the ticks: the
        host's stalls may be the cause, and the same sweep run again may pass there."""
        if self.disturbed is None:
            return np.zeros(self.freq_hz.size, dtype=bool)
        return ~self.coherent(coherence_min) & (self.disturbed > DISTURBED_SHARE)

    def unasked_clipping(self, max_drive_counts: float) -> float:
        """Median share of ticks at the drive's limit over the third octaves below 10 Hz whose mean drive is under
        half the limit: there a sweep of a few deg/s asks a few thousand counts, so clipping is the loop's own."""
        low = (self.freq_hz < 10.0) & (np.abs(self.drive_mean_counts) < 0.5 * max_drive_counts)
        return float(np.median(self.drive_clipped[low])) if np.any(low) else 0.0

    def oscillating(self, max_drive_counts: float) -> bool:
        """The loop oscillates by itself: its drive clips on more than 5 % of the ticks the sweep asks little of."""
        return self.unasked_clipping(max_drive_counts) > 0.05

    def saturated(self) -> np.ndarray:
        """Where the drive sat at its limit on more than 1 % of the ticks."""
        return self.drive_clipped > CLIPPED_SHARE


def level_frequencies(sweep: SweptSine) -> np.ndarray:
    """Third-octave centres from the sweep's lower to its upper frequency (both ends included)."""
    lo, hi = sorted((sweep.f_start_hz, sweep.f_stop_hz))
    n = max(2, round(math.log2(hi / lo) * LEVELS_PER_OCTAVE) + 1)
    return np.geomspace(lo, hi, n)


def _octave_share(freq_hz: np.ndarray, centre_hz: float) -> np.ndarray:
    half = 2.0 ** (0.5 / LEVELS_PER_OCTAVE)
    return (freq_hz >= centre_hz / half) & (freq_hz < centre_hz * half)


def check_levels(data: LogData, sweep: SweptSine, frf: Frf, max_drive_counts: float) -> LevelCheck:
    """Per third octave of ``sweep`` on the log ``data`` (the sweep located as :func:`identify_log` does), the
    coherence of ``frf`` (the log's FRF), the drive's peak, mean and share of ticks at ``max_drive_counts`` while
    the chirp was there, whether the axis reversed against the offset (the time-to-frequency map of the chirp,
    ``SweptSine.frequency_hz``) and the share of the ticks the host disturbed (:func:`host_disturbed`) over the span
    of the Welch segments that carry the third octave's bins (:func:`estimate_sweep_frf`'s). The drive's and the
    rate's figures leave the disturbed ticks out where any others remain: a stall's transient is not the level's."""
    r, u, y, dt = axis_columns(data, sweep.axis)
    host = host_disturbed(data)
    k0 = sweep_start(r, sweep, dt)
    t0, t1 = sweep.window_s
    a, b = max(k0 + round(t0 / dt), 0), min(k0 + round(t1 / dt), r.size)
    if b - a < 64:
        raise ValueError(f"the sweep window has {b - a} samples in the log")
    f_t = np.array([sweep.frequency_hz((k - k0) * dt) for k in range(a, b)])
    u_w = u[a:b]
    width = max(1, round(REVERSAL_SMOOTH_S / dt))
    y_s = np.convolve(y, np.ones(width) / width, mode="same")[a:b]
    sign = 1.0 if sweep.offset_dps >= 0 else -1.0
    centres = level_frequencies(sweep)
    host_w = host[a:b] if host.size == r.size else np.zeros(b - a, dtype=bool)
    lo_hz = min(sweep.f_start_hz, sweep.f_stop_hz)
    n_frf = round((t1 - t0 + sweep.settle_s) / dt)  # log_frf's window: the sweep and half its settling each side
    low_seg, split_hz = default_nperseg(n_frf, dt, lo_hz), max(20.0, 8.0 / (HI_NPERSEG * dt))
    coh, peak, clip, mean, rev, swing, dist = (np.zeros(centres.size) for _ in range(7))
    for i, fc in enumerate(centres):
        bins = _octave_share(frf.freq_hz, fc)
        coh[i] = float(np.median(frf.coherence[bins])) if np.any(bins) else 0.0
        there = _octave_share(f_t, fc)
        if np.any(there):
            at = np.flatnonzero(there)
            half = (HI_NPERSEG if fc >= split_hz else low_seg) // 2
            dist[i] = float(np.mean(host_w[max(at[0] - half, 0): at[-1] + half + 1]))
            calm = there & ~host_w
            use = calm if np.any(calm) else there
            peak[i] = float(np.percentile(np.abs(u_w[use]), 99.0))
            clip[i] = float(np.mean(np.abs(u_w[use]) >= max_drive_counts - 0.5))
            mean[i] = float(np.mean(u_w[use]))
            rev[i] = float(np.min(sign * y_s[use]) < 0.0)
            swing[i] = float(np.max(np.abs(y_s[use] - np.mean(y_s[use]))))
    amp = np.array([sweep.amplitude_at_dps(float(fc)) for fc in centres])
    return LevelCheck(centres, amp, coh, peak, clip, mean, rev.astype(bool), swing, dist)


def next_level(sweep: SweptSine, check: LevelCheck, *, max_drive_counts: float, coherence_min: float = 0.8,
               offset_max_dps: float, amplitude_max_dps: float = 20.0, amplitude_min_dps: float = 0.05,
               saturated_dps: np.ndarray | None = None) -> SweptSine | None:
    """The next sweep of a levelling (``hil ident``, docs/ident.md "Levelling"), or None when there is nothing left
    to change.

    If the drive saturated (at ``max_drive_counts`` on more than 1 % of a third octave's ticks) with its mean over
    half the limit, the mean took the headroom (friction at the offset's rate, a harness wound up by the travel,
    the imbalance): amplitudes and offset all fall x0.6, the travel with them. Otherwise, per third octave: where
    the drive saturated the amplitude halves; where the coherence is under ``coherence_min`` it rises, at most x2
    and only as far as the drive's headroom allows (its 99th percentile to 80 % of the limit, the mean counted;
    where the host disturbed the loop too: its stalls' transients are noise the level rises above); elsewhere it
    stays. Then the offset rises (x1.5 at most, up to ``offset_max_dps``, the travel's limit) until it
    is 1.5 times the axis' largest rate swing at the new amplitudes (the swing measured, so the loop's resonance
    counts, and never expected to fall with the amplitude: the loop's noise swings the rate too), and amplitudes
    whose swing the offset cannot carry fall until it can: the axis never reverses, so friction stays on one side.
    Amplitudes stay in [``amplitude_min_dps``, ``amplitude_max_dps``] and under 0.7 times ``saturated_dps`` (per
    third octave, the lowest amplitude that saturated the drive in an earlier pass), so a levelling does not swing
    between a level that saturates and one that does not; the offset stays at 0.3 deg/s or more."""
    old = check.amplitude_dps
    limit = float(max_drive_counts)
    offset = abs(sweep.offset_dps)
    saturated = check.saturated()
    if np.any(saturated & (np.abs(check.drive_mean_counts) > 0.5 * limit)):
        amp = 0.6 * old
        offset *= 0.6
    else:
        amp = old.copy()
        for i in range(amp.size):
            peak, bias = check.drive_peak_counts[i], abs(check.drive_mean_counts[i])
            if saturated[i]:
                amp[i] *= 0.5
            elif check.coherence[i] < coherence_min:
                room = (DRIVE_TARGET * limit - bias) / max(peak - bias, 1.0)
                if room > 1.05:
                    amp[i] *= min(2.0, room)
        if saturated_dps is not None:
            amp = np.minimum(amp, 0.7 * saturated_dps)
        amp = np.clip(amp, amplitude_min_dps, amplitude_max_dps)
        swing = check.rate_swing_dps * np.maximum(amp / old, 1.0)  # the swing each third octave would have
        need = 1.5 * float(np.max(swing)) if swing.size else 0.0
        if need > offset:
            offset = min(need, max(1.5 * offset, 0.5), offset_max_dps)
        over = 1.5 * swing > offset
        amp[over] *= offset / (1.5 * swing[over])
    amp = np.clip(amp, amplitude_min_dps, amplitude_max_dps)
    offset = max(offset, OFFSET_MIN_DPS)
    if np.allclose(amp, old, rtol=0.02) and math.isclose(offset, abs(sweep.offset_dps), rel_tol=0.02):
        return None
    data = sweep.model_dump()
    data.update(levels=tuple((float(f), round(float(a), 4)) for f, a in zip(check.freq_hz, amp, strict=True)),
                offset_dps=math.copysign(round(offset, 4), sweep.offset_dps or 1.0))
    return SweptSine.model_validate(data)


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
        there = _octave_share(f, fc) & ok
        if np.count_nonzero(there) >= 3 and float(np.median(excess[there])) >= excess_db:
            return float(f[there][np.argmax(excess[there])])
    return None


def coherent_band(check: LevelCheck, sweep: SweptSine, coherence_min: float = 0.8) -> tuple[float, float] | None:
    """The widest run of third octaves whose median coherence holds ``coherence_min``, a single third octave under it
    bridged (a notch at an anti-resonance or a clip does not end a band; the fit leaves out its incoherent bins), as
    (low, high) Hz within the sweep; None if no third octave holds it. (A drive the loop clipped does not bias the
    band: the log holds the drive as written, after the clip, and the estimate is of the plant from it.)"""
    ok = check.coherent(coherence_min)
    ok[1:-1] |= ok[:-2] & ok[2:]
    best: tuple[int, int] | None = None
    i = 0
    while i < ok.size:
        if ok[i]:
            j = i
            while j + 1 < ok.size and ok[j + 1]:
                j += 1
            if best is None or j - i > best[1] - best[0]:
                best = (i, j)
            i = j + 1
        else:
            i += 1
    if best is None:
        return None
    half = 2.0 ** (0.5 / LEVELS_PER_OCTAVE)
    lo, hi = sorted((sweep.f_start_hz, sweep.f_stop_hz))
    return max(lo, float(check.freq_hz[best[0]]) / half), min(hi, float(check.freq_hz[best[1]]) * half)
