"""The levelling of a sweep (``hil ident``, docs/ident.md "Levelling"): what one sweep's log says about its level
per third octave (:func:`check_levels`), the next sweep (:func:`next_level`) and the coherent band
(:func:`coherent_band`).

Docs: docs/ident.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hil.analysis._frf import HI_NPERSEG, LEVELS_PER_OCTAVE, Frf, default_nperseg, octave_share
from hil.analysis._logs import axis_columns, host_disturbed, sweep_start
from hil.config import SweptSine

if TYPE_CHECKING:
    from hil.log.reader import LogData


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
        bins = octave_share(frf.freq_hz, fc)
        coh[i] = float(np.median(frf.coherence[bins])) if np.any(bins) else 0.0
        there = octave_share(f_t, fc)
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
