"""The whole fit (:func:`fit_logs`): the passes over the logs, in the order each estimate feeds the next."""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from firmware_stub.config import load_emulator_config
from firmware_stub.plant import DEFAULT_PLANT_CONFIG
from hil.fit._estimates import Estimate, Status, _unit, grade
from hil.fit._frf import FrfFit, UnusableSweep, fit_frequency_response
from hil.fit._mechanics import G0, MechanicsFit, fit_mechanics
from hil.fit._noise import fit_noise
from hil.fit.logs import AXES, FitLog, load_fit_logs
from hil.fit.ranges import (
    BY_NAME,
    apply_params,
    dump_plant,
    get_param,
    k_m_of,
    load_plant_dict,
    validate_plant,
)
from hil.fit.rerun import match_breakaway

BREAKAWAY_UNRESOLVED = "the breakaway is not resolved (a Stribeck rate inside the stick band)"


@dataclass
class TwinFit:
    """A fitted plant: ``plant`` (dict, valid ``PlantConfig``), every parameter's :class:`Estimate`, the logs."""

    prior: dict[str, Any]
    plant: dict[str, Any]
    estimates: list[Estimate]
    logs: list[FitLog]
    frf: list[FrfFit] = field(default_factory=list)
    mechanics: dict[str, MechanicsFit] = field(default_factory=dict)
    noise: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    wire_s: float = 0.0  # the lab's wire and host delay the twin runs with (lab_wire_delay_s)

    @property
    def total_delay_s(self) -> float:
        """The loop's whole delay from a drive command to the gyro, as a low-frequency phase slope: the gyro's lag
        ``1 / (2 pi bandwidth)``, its delay, and the wire and the host's (docs/fit.md)."""
        gyro = self.plant["gyro"]
        return 1.0 / (2.0 * math.pi * float(gyro["bandwidth_hz"])) + float(gyro["delay_s"]) + self.wire_s

    def estimate(self, name: str) -> Estimate | None:
        return next((e for e in self.estimates if e.name == name), None)

    def fitted(self) -> dict[str, float]:
        return {e.name: e.value for e in self.estimates if e.status == "fitted" and e.value is not None}

    def write(self, out: str | Path, command: str = "hil fit") -> Path:
        lines = [f"Plant fitted by `{command}` (hil.fit; docs/fit.md) to {len(self.logs)} logs:"]
        lines += [f"  {lg.name} ({lg.kind}{', ' + lg.axis if lg.axis else ''})" for lg in self.logs]
        lines.append("Fitted (value +- 1 sigma; weak: wider than its target); every other value is the prior's:")
        for e in self.estimates:
            if e.status in ("fitted", "weak") and e.value is not None:
                sig = "" if e.sigma is None else f" +- {e.sigma:.3g}"
                weak = ", weak" if e.status == "weak" else ""
                lines.append(f"  {e.name} = {e.value:.5g}{sig} {e.unit}  ({e.source}{weak})")
        return dump_plant(self.plant, out, "\n".join(lines))


def lab_wire_delay_s(logs: list[FitLog]) -> float:
    """How long after its sample a logged drive command acts in the emulated lab a twin runs in (the default
    emulator at the logs' baud rates, docs/emulator.md "The wire"): the part of the measured loop delay that is the
    wire's and the host's, not the gyro's."""
    bauds: dict[str, int] = {}
    for lg in logs:
        for name, port in (lg.config.get("ports") or {}).items():
            if isinstance(port, Mapping) and "baudrate" in port:
                bauds.setdefault(name, int(port["baudrate"]))
    return load_emulator_config(baudrates=bauds).drive_delay_s()


def _mean_sigma(values: list[tuple[float, float]]) -> tuple[float, float]:
    """Inverse-variance mean of (value, sigma) pairs and its sigma."""
    w = np.array([1.0 / max(s, 1e-12) ** 2 for _, s in values])
    v = np.array([x for x, _ in values])
    return float(np.sum(w * v) / np.sum(w)), float(1.0 / math.sqrt(np.sum(w)))


def fit_logs(paths: list[str | Path], *, prior: str | Path | Mapping[str, Any] | None = None,
             progress: Any = None) -> TwinFit:
    """Fit the plant to the logs of one platform (docs/fit.md). ``prior``: the plant whose values are kept where the
    logs say nothing (default: the emulator's default plant). :class:`FitInputError` (one line) for bad input."""

    def say(text: str) -> None:
        if progress is not None:
            progress(text)

    base = dict(prior) if isinstance(prior, Mapping) else load_plant_dict(prior or DEFAULT_PLANT_CONFIG)
    logs = load_fit_logs(list(paths))
    plant = copy.deepcopy(base)
    notes = [f"{lg.name}: {n}" for lg in logs for n in lg.notes]

    wire_s = lab_wire_delay_s(logs)
    say("frequency response (ident logs)")
    plant, lin_est, frfs = _linear_pass(logs, base, plant, None, wire_s)
    plant, mech_est, mech = _mechanics_pass(logs, base, plant, say, wire_s)
    if frfs:  # again, with the low-frequency spring the torque balance found (k_c, gravity on the imbalance)
        say("frequency response, with the springs and the current limits of the torque balance")
        springs = {f.axis: sweep_spring_q(plant, f.axis, logs) for f in frfs}
        limits = {axis: m.current_limit_a for axis, m in mech.items()}
        plant, lin_est, frfs = _linear_pass(logs, base, plant, springs, wire_s, current_limits=limits)
        notes += [f"{f.log}: the driver held the {f.axis} current at its {limits[f.axis]:.2f} A limit (the torque "
                  f"balance's) on {f.current_limited_ticks} ticks of the sweep; the frequency response takes the "
                  "drive the plant received there, not the commanded one" for f in frfs if f.current_limited_ticks]
        plant, mech_est, mech = _mechanics_pass(logs, base, plant, say, wire_s)
    if frfs:
        bw, td = float(plant["gyro"]["bandwidth_hz"]), float(plant["gyro"]["delay_s"])
        total_ms = (1.0 / (2.0 * math.pi * bw) + td + wire_s) * 1e3
        weak = next((e.note for e in lin_est if e.name == "gyro.delay_s" and e.status == "weak"), "")
        notes.append(f"total loop delay {total_ms:.3f} ms: the gyro's lag {1e3 / (2 * math.pi * bw):.3f} ms "
                     f"(1 / 2 pi bandwidth) + its delay {td * 1e3:.3f} ms + the wire and the host "
                     f"{wire_s * 1e3:.3f} ms" + (f"; the split is weak: {weak}" if weak else ""))
    say("gyro noise (static logs)")
    plant, noise_est, noise_extra = _noise_pass(logs, plant, frfs, wire_s)
    plant, mech_est = _breakaway_pass(logs, plant, mech_est, say)
    est = grade(lin_est + noise_est + mech_est)
    validate_plant(plant)
    return TwinFit(prior=base, plant=plant, estimates=est, logs=logs, frf=frfs, mechanics=mech,
                   noise=noise_extra, notes=notes, wire_s=wire_s)


def _linear_pass(logs: list[FitLog], base: Mapping[str, Any], plant: dict[str, Any],
                 springs: Mapping[str, float] | None, wire_s: float = 0.0, *,
                 current_limits: Mapping[str, float | None] | None = None,
                 ) -> tuple[dict[str, Any], list[Estimate], list[FrfFit]]:
    """k_m, the structural modes, the gyro's bandwidth and delay from the ident logs, set in ``plant``. The FRF's
    delay is the whole transport delay from the drive command to the gyro: the gyro's is what is left after the
    lab's ``wire_s`` (:func:`lab_wire_delay_s`), never below 0. ``current_limits``: per axis, the driver's current
    limit the torque balance found (None: not reached), which the FRFs take into account (:func:`linear_frf`)."""
    frfs: list[FrfFit] = []
    unusable: dict[str, str] = {}  # axis -> why its ident log was left out
    fitted_logs: list[FitLog] = []  # the log of each of frfs

    def fit_one(lg: FitLog, prior: Mapping[str, Any]) -> FrfFit:
        return fit_frequency_response(lg, prior=prior, spring_q=(springs or {}).get(lg.axis or ""),
                                      drive_delay_s=wire_s, current_limit_a=(current_limits or {}).get(lg.axis or ""))

    for lg in logs:
        if lg.kind != "ident":
            continue
        try:
            frfs.append(fit_one(lg, plant))
            fitted_logs.append(lg)
        except UnusableSweep as exc:
            unusable[lg.axis or "el"] = str(exc)
    # bandwidth and delay trade against each other: the pair of the log that pins the pole best (smallest relative
    # sigma; weak when another log pins it elsewhere), else every log's delay with the prior's bandwidth
    resolved = sorted((f for f in frfs if f.bandwidth_identified),
                      key=lambda f: f.sigma["bandwidth_hz"] / max(f.bandwidth_hz, 1e-9))
    if resolved:
        # one gyro for every axis: a log whose band ends below its pole is fitted again with the pole the best log
        # pinned, not the prior's, which its delay and its structural mode's damping would otherwise absorb (hidden
        # plant 12: azimuth band to 198 Hz, pole 348 Hz; with a 200 Hz prior the azimuth damping read -16 %)
        pole = apply_params(plant, {"gyro.bandwidth_hz": resolved[0].bandwidth_hz})
        frfs = [f if f.bandwidth_identified else fit_one(lg, pole) for f, lg in zip(frfs, fitted_logs, strict=True)]
    est: list[Estimate] = []
    shared: dict[str, list[tuple[float, float]]] = {"gyro.bandwidth_hz": [], "gyro.delay_s": []}
    for axis in AXES:
        mine = [f for f in frfs if f.axis == axis]
        name = f"motor_{axis}.k_m_dps2_per_count"
        if not mine:
            why = unusable.get(axis)
            est.append(Estimate(name, k_m_of(base, axis), None, _unit(name), "prior",
                                "ident log left out: not linear" if why else f"no ident log on {axis}",
                                prior=k_m_of(base, axis), note=why or ""))
            continue
        km, km_s = _mean_sigma([(f.k_m, f.sigma["k_m"]) for f in mine])
        est.append(Estimate(name, km, km_s, _unit(name), "fitted", "ident: FRF " + ", ".join(f.log for f in mine),
                            prior=k_m_of(base, axis)))
        plant = apply_params(plant, {name: km})
    pole_doubt = pole_doubts(resolved)
    if resolved:
        best_pair = resolved[0]
        shared["gyro.bandwidth_hz"].append((best_pair.bandwidth_hz, max(best_pair.sigma["bandwidth_hz"], 1e-3)))
        shared["gyro.delay_s"].append((best_pair.delay_s, max(best_pair.sigma["delay_s"], 1e-7)))
    else:
        for f in frfs:
            shared["gyro.delay_s"].append((f.delay_s, max(f.sigma["delay_s"], 1e-7)))
    for axis in AXES:
        mine = [f for f in frfs if f.axis == axis]
        if not mine:
            for pname in (f"structure.{axis}.mode_hz", f"structure.{axis}.damping_ratio"):
                est.append(Estimate(pname, get_param(base, pname), None, _unit(pname), "prior",
                                    "ident log left out: not linear" if axis in unusable else
                                    f"no ident log on {axis}", prior=get_param(base, pname)))
            continue
        modes = [f for f in mine if f.mode_hz is not None]
        for key, attr in (("mode_hz", "mode_hz"), ("damping_ratio", "damping")):
            pname = f"structure.{axis}.{key}"
            if modes:
                val, sig = _mean_sigma([(getattr(f, attr), max(f.sigma["mode_hz" if attr == "mode_hz" else
                                                                        "damping"], 1e-6)) for f in modes])
                est.append(Estimate(pname, val, sig, _unit(pname), "fitted", "ident: resonance in the FRF",
                                    prior=get_param(base, pname)))
                plant = apply_params(plant, {pname: val})
            else:
                top = max(f.f_range_hz[1] for f in mine)
                est.append(Estimate(pname, get_param(base, pname), None, _unit(pname), "prior",
                                    f"ident: no resonance below {top:.0f} Hz (the sweep's top)",
                                    prior=get_param(base, pname)))
    for pname, vals in shared.items():
        if vals:
            val, sig = _mean_sigma(vals)
            source, note = "ident: FRF", ""
            status: Status = "fitted"
            if pname == "gyro.delay_s" and wire_s:
                source = f"ident: FRF, {val * 1e3:.3f} ms less the wire and the host's {wire_s * 1e3:.3f} ms"
                val = max(0.0, val - wire_s)
            if pname == "gyro.delay_s" and not resolved:  # it stands in for the unresolved pole's lag too
                status = "weak"
                note = ("fitted with the prior's bandwidth (the gyro's pole lies beyond the coherent band, so the "
                        f"delay absorbs its lag); record {BY_NAME['gyro.bandwidth_hz'].resolved_by}")
            elif pole_doubt:  # the pair trades: a doubtful pole makes a doubtful delay
                status = "weak"
                note = f"{pole_doubt}; record {BY_NAME['gyro.bandwidth_hz'].resolved_by}"
            est.append(Estimate(pname, val, sig, _unit(pname), status, source, prior=get_param(base, pname),
                                note=note))
            plant = apply_params(plant, {pname: val})
        else:
            why = ("ident: the coherent band ends below the gyro's pole (the delay absorbs its lag)" if frfs
                   else "no ident log")
            est.append(Estimate(pname, get_param(base, pname), None, _unit(pname), "prior", why,
                                prior=get_param(base, pname)))

    return plant, est, frfs


POLE_AGREE_SIGMAS = 2.0  # two ident logs' poles (one gyro) further apart than this many combined sigmas disagree


def pole_doubts(resolved: list[FrfFit]) -> str:
    """Why the gyro's pole of the best log (``resolved[0]``, the logs that pinned it, best first) is not to be called
    fitted, or "": the gyro is one for every axis, so another log that pins it further than
    :data:`POLE_AGREE_SIGMAS` combined sigmas away says the model misses something in one of them."""
    if not resolved:
        return ""
    best = resolved[0]
    for other in resolved[1:]:
        gap = abs(other.bandwidth_hz - best.bandwidth_hz)
        if gap > POLE_AGREE_SIGMAS * math.hypot(other.sigma["bandwidth_hz"], best.sigma["bandwidth_hz"]):
            return (f"the logs disagree on the gyro's pole: {best.bandwidth_hz:.0f} +- {best.sigma['bandwidth_hz']:.0f}"
                    f" Hz ({best.log}) and {other.bandwidth_hz:.0f} +- {other.sigma['bandwidth_hz']:.0f} Hz "
                    f"({other.log})")
    return ""


def _noise_pass(logs: list[FitLog], plant: dict[str, Any], frfs: list[FrfFit],
                wire_s: float = 0.0) -> tuple[dict[str, Any], list[Estimate], dict[str, Any]]:
    """The gyro's noise and bias from the static logs, set in ``plant``."""
    modes = {g: get_param(plant, f"structure.{ax}.mode_hz") for g, ax in (("y", "el"), ("z", "az"))}
    fitted_axes = {f.axis for f in frfs}
    driven = {g: plant for g, ax in (("y", "el"), ("z", "az")) if ax in fitted_axes}
    noise_est, noise_extra = fit_noise(logs, plant, modes_hz={g: m for g, m in modes.items() if m}, driven=driven,
                                       drive_delay_s=wire_s)
    est = list(noise_est)
    for e in noise_est:
        if e.status == "fitted" and e.value is not None:
            plant = apply_params(plant, {e.name: e.value})
    if "bias_dps" in noise_extra:
        plant["gyro"]["bias_dps"] = [float(b) for b in noise_extra["bias_dps"]]

    return plant, est, noise_extra


def _mechanics_pass(logs: list[FitLog], base: Mapping[str, Any], plant: dict[str, Any], say: Any,
                    wire_s: float = 0.0) -> tuple[dict[str, Any], list[Estimate], dict[str, MechanicsFit]]:
    """Friction, cable, current limit and imbalance from the torque balance, set in ``plant`` (the drive's side
    aligned with the gyro by the whole delay: the gyro's and the lab's ``wire_s``)."""
    mech: dict[str, MechanicsFit] = {}
    est: list[Estimate] = []
    bw = float(plant["gyro"]["bandwidth_hz"])
    td = float(plant["gyro"]["delay_s"]) + wire_s
    for axis in AXES:
        say(f"torque balance, {axis}")
        moving = [lg for lg in logs if lg.kind == "swing" or (lg.kind == "ident" and lg.axis == axis)]
        if not moving:
            for pname in (f"friction.{axis}.coulomb_n_m", f"friction.{axis}.stiction_ratio",
                          f"cable.{axis}.stiffness_n_m_per_rad", f"drive.{axis}.current_limit_a"):
                est.append(Estimate(pname, get_param(base, pname), None, _unit(pname), "prior",
                                    "no swing or ident log", prior=get_param(base, pname)))
            continue
        mf = fit_mechanics(moving, axis, plant, bandwidth_hz=bw, delay_s=td)
        mech[axis] = mf
        est += _mechanics_estimates(mf, base, plant, axis, has_swing=any(lg.kind == "swing" for lg in moving))
        plant = _apply_mechanics(plant, axis, est)
    return plant, est, mech


def sweep_spring_q(plant: Mapping[str, Any], axis: str, logs: list[FitLog]) -> float:
    """K / J of the spring an ident sweep on ``axis`` feels: the cable, plus for elevation gravity on the imbalance
    at the sweep's mean elevation (``T = -m rho_z g sin(el) - m rho_x g cos(el)``, linearised)."""
    k = float(((plant.get("cable") or {}).get(axis) or {}).get("stiffness_n_m_per_rad") or 0.0)
    if axis == "el" and plant.get("imbalance"):
        el = [float(np.mean(lg.loop["el_deg"])) for lg in logs if lg.kind == "ident" and lg.axis == "el"]
        e = math.radians(el[0]) if el else 0.0
        m_rho_x = (get_param(plant, "imbalance.m_rho_x_kg_mm") or 0.0) * 1e-3  # kg m
        m_rho_z = (get_param(plant, "imbalance.m_rho_z_kg_mm") or 0.0) * 1e-3
        k += G0 * (m_rho_z * math.cos(e) - m_rho_x * math.sin(e))
    return k / float(plant[f"motor_{axis}"]["inertia_kg_m2"])


def _mechanics_estimates(mf: MechanicsFit, base: Mapping[str, Any], plant: Mapping[str, Any], axis: str,
                         has_swing: bool) -> list[Estimate]:
    out: list[Estimate] = []
    src = "torque balance: " + ", ".join(mf.rms_n_m)
    reversals = "swing logs (rate reversals)" if has_swing else "no swing log: no rate reversal"

    def add(name: str, value: float | None, sigma: float | None, ok: bool, why: str) -> None:
        out.append(Estimate(name, value if ok else get_param(base, name), sigma if ok else None, _unit(name),
                            "fitted" if ok else "prior", src if ok else why, prior=get_param(base, name)))

    add(f"friction.{axis}.coulomb_n_m", mf.coulomb_n_m, mf.sigma["coulomb_n_m"], mf.coulomb_n_m > 0, reversals)
    ratio = mf.stiction_n_m / mf.coulomb_n_m if mf.coulomb_n_m > 0 else None
    ratio_sigma = mf.sigma["stiction_n_m"] / max(mf.coulomb_n_m, 1e-9)
    plausible = BY_NAME[f"friction.{axis}.stiction_ratio"]
    add(f"friction.{axis}.stiction_ratio", ratio, ratio_sigma,
        has_swing and ratio is not None and 1.0 <= ratio <= 1.2 * plausible.hi and ratio_sigma < 0.1,
        reversals if not has_swing else BREAKAWAY_UNRESOLVED)
    add(f"friction.{axis}.stribeck_rate_dps", mf.stribeck_rate_dps, None,
        has_swing and ratio is not None and ratio > 1.02, "stiction not above Coulomb: no Stribeck rate")
    # the balance sees bearing and harness damping together (both act on v): the harness keeps the prior's
    cable_damping = float(((plant.get("cable") or {}).get(axis) or {}).get("damping_n_m_s_per_rad") or 0.0)
    bearing = mf.viscous_n_m_s_per_rad - cable_damping
    add(f"friction.{axis}.viscous_n_m_s_per_rad", bearing, mf.sigma["viscous_n_m_s_per_rad"], bearing > 0,
        "not above the cable's damping in the fit")
    add(f"cable.{axis}.stiffness_n_m_per_rad", mf.cable_n_m_per_rad, mf.sigma["cable_n_m_per_rad"],
        mf.cable_n_m_per_rad > 0 and mf.sigma["cable_n_m_per_rad"] < 0.5 * abs(mf.cable_n_m_per_rad) + 0.05,
        "not determined by the travel in these logs")
    name = f"drive.{axis}.current_limit_a"
    prior_limit = get_param(base, name)
    if mf.current_limit_a is not None:
        out.append(Estimate(name, mf.current_limit_a, 0.03 * mf.current_limit_a, "A", "fitted",
                            "saturation episodes in the torque balance", prior=prior_limit))
    else:
        keep = prior_limit if prior_limit is None or prior_limit >= mf.current_peak_a else mf.current_peak_a
        out.append(Estimate(name, keep, None, "A", "bound",
                            f"not reached: the logs asked for at most {mf.current_peak_a:.2f} A", prior=prior_limit,
                            note=f"limit >= {mf.current_peak_a:.2f} A"))
    if mf.m_rho_x_kg_mm is not None and mf.m_rho_z_kg_mm is not None:
        for key, val in (("x", mf.m_rho_x_kg_mm), ("z", mf.m_rho_z_kg_mm)):
            pname = f"imbalance.m_rho_{key}_kg_mm"
            out.append(Estimate(pname, val, mf.sigma[f"m_rho_{key}_kg_mm"], "kg mm", "fitted", src,
                                prior=get_param(base, pname)))
    return out


def _breakaway_pass(logs: list[FitLog], plant: dict[str, Any], est: list[Estimate],
                    say: Any) -> tuple[dict[str, Any], list[Estimate]]:
    """Where the torque balance left an axis' breakaway unresolved (its Stribeck rate inside the stick band), the
    swing logs re-run on the twin choose it (``hil.fit.rerun.match_breakaway``: the rate error std at the reversals).
    Only the breakaway's impulse ``(T_s / T_c - 1) v_s`` is determined: the parameter the match moved is fitted, the
    other keeps its value with a note saying so."""
    by_name = {e.name: e for e in est}
    axes = [ax for ax in AXES if (e := by_name.get(f"friction.{ax}.stiction_ratio")) is not None
            and e.status == "prior" and e.source == BREAKAWAY_UNRESOLVED]
    if not axes:
        return plant, est
    matched = match_breakaway(logs, plant, axes, progress=say)
    for ax, b in matched.items():
        names = {"stiction_ratio": f"friction.{ax}.stiction_ratio",
                 "stribeck_rate_dps": f"friction.{ax}.stribeck_rate_dps"}
        logs_text = ", ".join(b.logs)
        if not b.resolved:
            for name in names.values():
                by_name[name] = replace(by_name[name], note=(
                    f"the swing logs' {ax} rate error does not move with the breakaway ({logs_text}): record a swing "
                    "with more reversals (the 1 deg / 1 Hz swing) to resolve it"))
            continue
        held = names["stiction_ratio" if b.moved == "stribeck_rate_dps" else "stribeck_rate_dps"]
        moved = names[b.moved]
        value = b.stribeck_rate_dps if b.moved == "stribeck_rate_dps" else b.stiction_ratio
        by_name[moved] = replace(by_name[moved], value=value, sigma=None, status="fitted", source=(
            f"swing logs re-run on the twin: {ax} rate error std within {b.rms_log_ratio * 100:.1f} % rms "
            f"({logs_text})"), note="")
        held_value = b.stiction_ratio if held == names["stiction_ratio"] else b.stribeck_rate_dps
        at_bound = not math.isclose(held_value, by_name[held].value or 0.0, rel_tol=1e-9)
        by_name[held] = replace(by_name[held], value=held_value, status="bound" if at_bound else "prior", note=(
            ("at its plausible bound" if at_bound else "held")
            + ": the swing logs determine the breakaway's impulse (T_s / T_c - 1) v_s, not each factor"))
        plant = apply_params(plant, {names["stiction_ratio"]: max(1.0, b.stiction_ratio),
                                     names["stribeck_rate_dps"]: b.stribeck_rate_dps})
    return plant, [by_name[e.name] for e in est]


def _apply_mechanics(plant: dict[str, Any], axis: str, est: list[Estimate]) -> dict[str, Any]:
    """The torque balance's fitted and bound values of ``axis`` set in ``plant``: Coulomb before the stiction ratio
    (setting Coulomb keeps the ratio, so the prior's ratio stays when the fit has none)."""
    mine = {e.name: e.value for e in est if e.value is not None and e.status in ("fitted", "bound")
            and (e.name.startswith((f"friction.{axis}.", f"cable.{axis}.", f"drive.{axis}."))
                 or (axis == "el" and e.name.startswith("imbalance.")))}
    ratio = f"friction.{axis}.stiction_ratio"
    if ratio in mine:
        mine[ratio] = max(1.0, mine.pop(ratio))  # last, over the fitted Coulomb
    return apply_params(plant, mine)
