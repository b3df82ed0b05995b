"""Frequency-sweep identification of the rate-loop plant from a session log: one axis' columns, where the host
disturbed the loop, where the sweep starts; :func:`identify_log`: the whole chain on a session log.

Docs: docs/ident.md.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Literal

import numpy as np

from hil.analysis._frf import Frf, estimate_frf, estimate_sweep_frf
from hil.analysis._plant import PlantFit, fit_plant
from hil.config import SweptSine
from hil.log.schema import LATE_US

if TYPE_CHECKING:
    from hil.log.reader import LogData

GYRO_CHANNEL = {"el": "gyro_y_dps", "az": "gyro_z_dps"}  # the loop-group channel each axis' rate loop feeds back


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
