"""Frequency-sweep identification of the rate-loop plant (seed 000 Figs 8-9, eqs 33-38): the frequency response.

* :func:`estimate_frf`: Welch cross-spectra (``scipy.signal``: Hann window, 50 % overlap) and the *indirect* closed-loop
  estimate ``P = S_ry / S_ru`` of the plant ``y/u``: both spectra are cross-spectra with the external excitation
  ``r``, which the gyro noise and the disturbances are not correlated with, so neither noise nor feedback bias it
  (the direct ``S_uy / S_uu`` tends to ``-1/C`` where noise dominates, because ``u`` carries the fed-back noise).
* :func:`octave_share`: the bins of one third octave, the unit the levelling and the resonance search read an FRF in.

Docs: docs/ident.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike


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
    r: ArrayLike,
    u: ArrayLike,
    y: ArrayLike,
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


def estimate_sweep_frf(r: ArrayLike, u: ArrayLike, y: ArrayLike, dt_s: float, *, f_min_hz: float,
                       f_max_hz: float) -> Frf:
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


LEVELS_PER_OCTAVE = 3  # the level table's spacing: third octaves


def octave_share(freq_hz: np.ndarray, centre_hz: float) -> np.ndarray:
    """Where ``freq_hz`` lies in the third octave (``LEVELS_PER_OCTAVE``) centred on ``centre_hz``."""
    half = 2.0 ** (0.5 / LEVELS_PER_OCTAVE)
    return (freq_hz >= centre_hz / half) & (freq_hz < centre_hz * half)
