"""A swept-sine identification as sessions: the sweep run on the closed rate loop and, by default, levelled until its
coherence holds over the band or the drive and the travel allow no more (``hil ident``, docs/ident.md "Levelling").

Each pass is a whole session (``run``) with the sweep as its excitation; its log gives the FRF, the per-third-octave
check (``hil.analysis.check_levels``) and the next sweep (``hil.analysis.next_level``). Successive passes turn the
axis in opposite directions, so a levelling ends near where it started.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from hil.analysis import (
    Frf,
    LevelCheck,
    PlantFit,
    SweptSine,
    check_levels,
    coherent_band,
    fit_plant,
    log_frf,
    next_level,
    resonance_hz,
)
from hil.config import SessionConfig
from hil.log import read_log
from hil.session import Clock, Lab, Progress, RunResult, run

COHERENCE_MIN = 0.8  # a bin counts in the fit from this coherence (hil.analysis.fit_plant's default)
K_M_BELOW_HZ = 10.0  # a coherent band that does not reach below this cannot give k_m (the integrator's band)
POLE_MIN_GAIN = 0.3  # the gyro's pole is reported only if it lowers the fit's cost by 30 % (hil.analysis.fit_plant)
RIGID_HZ = 50.0  # the rigid model is fitted up to here first; a resonance above it ends the fit at half its frequency
MAX_TRAVEL_DEG = 60.0  # a levelling raises the offset of either axis at most until a sweep turns it this far
LEVEL_PASSES = 6  # at most this many sweeps: the first, and up to five levelled ones
MIN_BAND_OCTAVES = 1.0  # a coherent band narrower than this gives no fit (a lone coherent third octave is chance)


@dataclasses.dataclass(frozen=True)
class IdentPass:
    """One sweep of an identification: the sweep, its session, and what its log showed."""

    sweep: SweptSine
    run: RunResult
    frf: Frf | None = None
    check: LevelCheck | None = None
    band_hz: tuple[float, float] | None = None  # the coherent band (hil.analysis.coherent_band)

    @property
    def reaches_k_m(self) -> bool:
        """The coherent band reaches below ``K_M_BELOW_HZ``: where the plant is an integrator, k_m's band."""
        return self.band_hz is not None and self.band_hz[0] < K_M_BELOW_HZ

    @property
    def steady(self) -> bool:
        """The axis never reversed inside the coherent band (friction stayed on one side: no relay in the data)."""
        if self.check is None or self.band_hz is None:
            return False
        inside = (self.check.freq_hz >= self.band_hz[0]) & (self.check.freq_hz <= self.band_hz[1])
        return not bool(self.check.reversed[inside].any())

    @property
    def octaves(self) -> float:
        """Width of the coherent band in octaves (0 without one)."""
        return 0.0 if self.band_hz is None else math.log2(self.band_hz[1] / self.band_hz[0])

    @property
    def spoiled(self) -> int:
        """Third octaves whose coherence failed where the host disturbed the loop (``LevelCheck.spoiled``)."""
        return 0 if self.check is None else int(np.count_nonzero(self.check.spoiled(COHERENCE_MIN)))


@dataclasses.dataclass(frozen=True)
class IdentSweeps:
    """The passes of an identification and the result taken from the best one (the widest coherent band).
    ``fit`` is None when a session did not complete or no band was coherent."""

    passes: list[IdentPass]
    best: IdentPass
    fit: PlantFit | None
    why: str  # why the levelling stopped
    resonance_hz: float | None = None  # the first resonance over the rigid model (the fit stops at half of it)

    @property
    def run(self) -> RunResult:
        return self.best.run


def fit_from_hz(sweep: SweptSine) -> float:
    """Where the fit starts: an octave above the sweep's start (the chirp's first octave starts at a Welch segment's
    edge and its bins are biased, ``hil.analysis.identify_log``)."""
    return 2.0 * min(sweep.f_start_hz, sweep.f_stop_hz)


def _examine(sweep: SweptSine, result: RunResult, max_drive_counts: float) -> IdentPass:
    if result.status != "completed" or result.log_path is None:
        return IdentPass(sweep, result)
    data = read_log(result.log_path)
    frf, _ = log_frf(data, sweep)
    check = check_levels(data, sweep, frf, max_drive_counts)
    return IdentPass(sweep, result, frf, check, coherent_band(check, sweep, COHERENCE_MIN))


def ident_sweeps(config: SessionConfig, sweep: SweptSine, *, level: bool = True, passes: int = LEVEL_PASSES,
                 offset_max_dps: float | None = None, loopback: bool = True, clock: Clock | None = None,
                 out: str | Path | None = None, progress: Progress | None = None,
                 on_pass: Callable[[int, SweptSine], None] | None = None, lab: Lab | None = None) -> IdentSweeps:
    """Run ``sweep`` as ``config``'s excitation and, with ``level``, up to ``passes`` sweeps levelled by
    ``hil.analysis.next_level`` (the drive's limit: ``config.safety.max_drive_counts``; the offset at most
    ``offset_max_dps``, default the sweep's or what turns the axis ``MAX_TRAVEL_DEG``, the larger). ``on_pass(i,
    sweep)`` announces each pass (1-based). ``lab``: the lab every pass runs on (default: ``loopback`` and ``clock``
    choose, as for :func:`hil.session.run`). The pass kept is the one whose coherent band reaches below
    ``K_M_BELOW_HZ``, without a reversal inside it, widest, earliest (in that order); the fit is made on its band
    only, if it spans ``MIN_BAND_OCTAVES`` or more (the gyro's pole reported only inside it): the rigid model up to
    ``RIGID_HZ`` first, and if the band shows a resonance above that model (``hil.analysis.resonance_hz``), the fit
    stops at half its frequency, below which the mode bends the response by less than 2.5 dB.

    A third octave whose coherence failed where the host ran the loop late (``hil.analysis.host_disturbed``) is
    levelled as any other (the stalls' transients are noise a higher level rises above); if nothing else would
    change, the same sweep runs again (another draw of the host's stalls), and ``why`` says how many such third
    octaves the kept pass has."""
    if offset_max_dps is None:
        offset_max_dps = max(MAX_TRAVEL_DEG / sweep.total_s, abs(sweep.offset_dps))
    done: list[IdentPass] = []
    why = "levelling off: one sweep as given"
    current = sweep
    limit = config.safety.max_drive_counts
    ceiling: np.ndarray | None = None  # per third octave, the lowest amplitude that saturated the drive so far
    for i in range(1, (passes if level else 1) + 1):
        if on_pass is not None:
            on_pass(i, current)
        cfg = config.model_copy(update={"excitation": current, "duration_s": current.total_s + 0.5})
        p = _examine(current, run(cfg, loopback=loopback, clock=clock, out=out, progress=progress, lab=lab), limit)
        done.append(p)
        if p.check is None:
            why = f"pass {i}: the session ended {p.run.status}"
            break
        if not level:
            break
        fitted = p.check.freq_hz >= fit_from_hz(current)
        if bool(p.check.coherent(COHERENCE_MIN)[fitted].all()):
            why = f"pass {i}: coherent over the whole fitted band"
            break
        saturated = np.where(p.check.saturated(), p.check.amplitude_dps, np.inf)
        ceiling = saturated if ceiling is None else np.minimum(ceiling, saturated)
        nxt = next_level(current, p.check, max_drive_counts=limit, coherence_min=COHERENCE_MIN,
                         offset_max_dps=offset_max_dps, saturated_dps=ceiling)
        why = f"{passes} passes made"
        if nxt is None and bool(p.check.spoiled(COHERENCE_MIN)[fitted].any()):
            nxt = current  # the host's stalls may have failed the coherence there: the same sweep again
        elif nxt is None:
            why = f"pass {i}: the drive's headroom and the travel allow no higher level where the coherence fails"
            break
        current = SweptSine.model_validate({**nxt.model_dump(), "offset_dps": -nxt.offset_dps})  # back the way
        # the last pass came: a levelling ends near where it started
    best = max(done, key=lambda p: (p.reaches_k_m, p.steady, p.octaves, -done.index(p)))
    if best.spoiled:
        why += (f"; in {best.spoiled} third octaves of the kept pass the coherence failed where the bench ran late "
                "(late cycles or missed samples: this host's stalls)")
    fit, resonance, top = None, None, None
    if best.check is not None and best.check.oscillating(limit):
        why = (f"the drive clipped on {best.check.unasked_clipping(limit):.0%} of the ticks below 10 Hz, where the "
               "sweep asks little of it: the loop itself oscillates on this plant (a controller gain too high for "
               "it: b0_dps2_per_count far from the plant's k_m?)")
    elif best.frf is not None and best.band_hz is not None and best.reaches_k_m and best.octaves >= MIN_BAND_OCTAVES:
        lo, top = max(best.band_hz[0], fit_from_hz(best.sweep)), best.band_hz[1]
        try:  # the rigid model below RIGID_HZ, then the band up to half the first resonance above it
            low = fit_plant(best.frf, coherence_min=COHERENCE_MIN, f_min_hz=lo, f_max_hz=min(top, RIGID_HZ),
                            pole_max_ratio=1.0, pole_min_gain=POLE_MIN_GAIN)
            resonance = resonance_hz(best.frf, low, f_min_hz=lo, f_max_hz=top, coherence_min=COHERENCE_MIN)
            if resonance is not None:
                top = min(top, 0.5 * resonance)
            fit = fit_plant(best.frf, coherence_min=COHERENCE_MIN, f_min_hz=lo, f_max_hz=top,
                            pole_max_ratio=1.0, pole_min_gain=POLE_MIN_GAIN)
        except ValueError:
            fit = None
    return IdentSweeps(done, best, fit, why, resonance)

