"""The identification ``hil ident`` runs (``hil.api.ident``): the sweep's options checked, the session made from
the lab's (tracking off, no swing, the sweep as its excitation), the levelled passes (:func:`ident_sweeps`), the fit's
refusals, the Bode plot and the JSON beside the log (docs/ident.md)."""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from pydantic import ValidationError

from hil.analysis import IDENT_SWEEP, Frf, PlantFit, SweptSine, bode_plot
from hil.config import ConfigError, SessionConfig, one_line, require_writable_dir
from hil.control.registry import K_M_DEFAULT
from hil.ident._sweeps import MIN_BAND_OCTAVES, IdentPass, ident_sweeps
from hil.session import Clock, Lab, Progress, RunResult, as_session_config

MAX_EL_TRAVEL_DEG = 60.0  # ident: keep the elevation axis away from the az-el gimbal's 90 deg singularity


@dataclasses.dataclass
class IdentRun:
    """A swept-sine identification: the session that ran it (``run``: the pass the fit was made on), the measured
    frequency response (``frf``), the plant fit (``fit``: k_m, gyro bandwidth, delay, on the coherent band only),
    the Bode plot and the JSON written beside the log, every pass of the levelling (``passes``) and the coherent
    band (``band_hz``). ``fit`` is None when the session did not complete."""

    run: RunResult
    frf: Frf | None = None
    fit: PlantFit | None = None
    bode_png: Path | None = None
    json_path: Path | None = None
    report: dict[str, Any] = dataclasses.field(default_factory=dict)
    passes: list[IdentPass] = dataclasses.field(default_factory=list)
    band_hz: tuple[float, float] | None = None


def run_ident(session: SessionConfig | str | Path, *, axis: Literal["el", "az"] = "el", loopback: bool = True,
              clock: Clock | None = None, out: str | Path = "runs/ident", f_start_hz: float = IDENT_SWEEP.f_start_hz,
              f_stop_hz: float = IDENT_SWEEP.f_stop_hz, sweep_s: float = IDENT_SWEEP.duration_s,
              amplitude_dps: float = IDENT_SWEEP.amplitude_dps, offset_dps: float = IDENT_SWEEP.offset_dps,
              level: bool = True, progress: Progress | None = None,
              on_pass: Callable[[int, SweptSine], None] | None = None, lab: Lab | None = None) -> IdentRun:
    """Frequency-sweep identification (seed 000 Figs. 8-9, docs/ident.md): a swept sine on one axis's rate command
    of the closed rate loop (``session``'s controller, tracking off, no swing), the plant's frequency response from
    the log, a Bode plot and the fit of k_m, the gyro's bandwidth and the delay.

    With ``level`` (the default) the sweep levels itself (docs/ident.md "Levelling"): ``amplitude_dps`` and
    ``offset_dps`` are where it starts; up to five more sweeps raise the amplitude where the coherence fails and
    the drive has headroom, lower it where the drive saturates, raise the offset while the axis reverses (at most
    60 deg of travel), each pass turning the axis back. The fit is made on the widest coherent band only, and
    ``band_hz`` reports it. ``on_pass(i, sweep)`` announces each pass. ``lab``: the lab to run on
    (:class:`hil.session.Lab`), whatever ``loopback`` and ``clock`` say. ValueError (ConfigError) for bad input; a
    fit that cannot be made raises ValueError naming the log."""
    if axis not in ("el", "az"):
        raise ConfigError(f"axis={axis!r}: not el or az")
    for option, value in (("f_start_hz", f_start_hz), ("f_stop_hz", f_stop_hz), ("sweep_s", sweep_s),
                          ("amplitude_dps", amplitude_dps), ("offset_dps", offset_dps)):
        if not math.isfinite(value):
            raise ConfigError(f"{option}={value!r}: not a finite number")
    out_dir = require_writable_dir(Path(out), "out")
    base = as_session_config(session)
    try:
        sweep = SweptSine(f_start_hz=f_start_hz, f_stop_hz=f_stop_hz, duration_s=sweep_s,
                          amplitude_dps=amplitude_dps, axis=axis, offset_dps=offset_dps)
        data = base.model_dump(mode="json", exclude_none=True)
        data.update(name=f"{base.name}-ident-{axis}", duration_s=sweep.total_s + 0.5, excitation=sweep.model_dump(),
                    tracking={**data.get("tracking", {}), "enabled": False}, profile={"segments": []},
                    mqtt=base.mqtt, hexapod=base.hexapod)  # the objects themselves: their dumps hide secrets
        config = SessionConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(one_line("ident", exc)) from None
    travel_deg = abs(offset_dps) * sweep.total_s
    if axis == "el" and travel_deg > MAX_EL_TRAVEL_DEG:
        raise ConfigError(f"offset_dps={offset_dps:g}: the elevation axis would turn {travel_deg:.0f} deg during the "
                          f"sweep (at most {MAX_EL_TRAVEL_DEG:g}: near 90 deg the cross-elevation gyro loses the "
                          "azimuth axis); lower offset_dps= or sweep_s=, or identify axis='az'")
    sweeps = ident_sweeps(config, sweep, level=level, loopback=loopback, clock=clock, out=out_dir, progress=progress,
                          on_pass=on_pass, lab=lab)
    best, fit = sweeps.best, sweeps.fit
    passes = [{"pass": i, "log": None if p.run.log_path is None else str(p.run.log_path), "status": p.run.status,
               "amplitude_dps": p.sweep.amplitude_dps, "offset_dps": p.sweep.offset_dps,
               "levels": [list(lv) for lv in p.sweep.levels], "coherent_band_hz": p.band_hz}
              for i, p in enumerate(sweeps.passes, 1)]
    if best.frf is None or best.run.log_path is None:
        return IdentRun(run=best.run, passes=sweeps.passes)
    if fit is None:
        check = best.check
        clipped = 0.0 if check is None else float(check.drive_clipped.mean())
        if check is not None and check.oscillating(config.safety.max_drive_counts):
            raise ValueError(f"{best.run.log_path}: cannot identify: {sweeps.why}; identify it with a gentler "
                             "controller (controller: profiles/controllers/pi_lpf.yaml in the session) or one whose "
                             "b0_dps2_per_count is nearer the plant's")
        band = "" if best.band_hz is None else f"{best.band_hz[0]:.3g}-{best.band_hz[1]:.3g} Hz"
        seen = ("no third octave reached coherence 0.8" if best.band_hz is None else
                f"coherent only {band}, not below 10 Hz where k_m shows" if not best.reaches_k_m else
                f"coherent only {band}, less than an octave" if best.octaves < MIN_BAND_OCTAVES else
                f"the fit found no model on the coherent band {band}")
        what = (f"{best.run.log_path}: cannot identify: {seen} in {len(sweeps.passes)} passes ({sweeps.why}; the "
                f"drive sat at its limit on {clipped:.0%} of the sweep)")
        if best.spoiled:
            raise ValueError(f"{what}; the bench's host ran the loop late: identify on an idle host (host.rt_priority "
                             "and host.loop_cpu in the session), or on the emulator with clock='lockstep', the same "
                             "lab without this host's timing")
        raise ValueError(f"{what}; check that the axis turns freely (friction, a harness, the current limit) and the "
                         "drive is enabled, or start from a lower offset_dps= and amplitude_dps=")
    png = bode_plot(best.frf, fit, out_dir / f"bode-{axis}.png", title=config.name)
    error_pct = 100.0 * (fit.k_m_dps2_per_count - K_M_DEFAULT) / K_M_DEFAULT
    js = out_dir / f"ident-{axis}.json"
    data = {"log": str(best.run.log_path), "axis": axis, "sweep": best.sweep.model_dump(mode="json"),
            "k_m_dps2_per_count": fit.k_m_dps2_per_count, "k_m_vs_default_pct": error_pct,
            "gyro_bandwidth_hz": fit.gyro_bandwidth_hz, "delay_ms": fit.delay_ms,
            "loop_delay_ms": fit.model_delay_s * 1e3 if fit.gyro_bandwidth_hz is None else None,
            "rms_error_db": fit.rms_error_db, "coherent_band_hz": list(best.band_hz or ()),
            "f_range_hz": list(fit.f_range_hz), "bins": fit.n_bins, "bode_png": str(png),
            "resonance_hz": sweeps.resonance_hz, "levelling": sweeps.why, "passes": passes}
    js.write_text(json.dumps(data, indent=2))
    return IdentRun(run=best.run, frf=best.frf, fit=fit, bode_png=png, json_path=js, report=data,
                    passes=sweeps.passes, band_hz=best.band_hz)

