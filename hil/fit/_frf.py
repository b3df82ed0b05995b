"""An ident log's frequency response and its fit, finished on the emulated plant's own response."""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np

from firmware_stub.plant import Plant, PlantConfig
from hil.analysis import (
    REVERSAL_SMOOTH_S,
    SweepShapes,
    SweptSine,
    estimate_sweep_frf,
    fit_plant,
    plant_response,
    sweep_start,
)
from hil.fit._motor import drive_at_current_limit, drive_with_ripple
from hil.fit.logs import AXES, FitInputError, FitLog
from hil.fit.ranges import apply_params


@dataclass
class FrfFit:
    """The joint fit of one ident log: ``k_m / s`` (sampled) x lag x delay x mode x cable spring."""

    axis: str
    k_m: float
    bandwidth_hz: float
    delay_s: float
    mode_hz: float | None
    damping: float | None
    spring_q: float | None  # K / J of the low-frequency spring, (rad/s)^2, signed
    sigma: dict[str, float]
    rms_db: float
    rms_deg: float
    f_range_hz: tuple[float, float]
    frf: Any = None
    log: str = ""
    bandwidth_identified: bool = True  # False: the coherent band ends below the pole; the prior's bandwidth is used
    kernel_plant: dict[str, Any] | None = None  # the plant the kernel fit finished on (None: analytic model only)
    drive_delay_s: float = 0.0  # the lab's wire and host on the drive in the kernel fit; delay_s includes it
    current_limited_ticks: int = 0  # ticks whose drive was taken at the driver's current limit (linear_frf)
    reading: Any = None  # on frf's bins, how its estimator reads the kernel (sweep_reading); None: not divided out

    def response(self, f_hz: np.ndarray) -> np.ndarray:
        """The fitted response: the kernel's own (:func:`linear_plant_frf`) where the fit finished on it."""

        s = 2j * math.pi * np.asarray(f_hz, dtype=float)
        if self.kernel_plant is not None:
            resp = np.ones(s.size, dtype=complex)
            nz = s != 0
            resp[nz] = linear_plant_frf(self.kernel_plant, self.axis, np.asarray(f_hz, dtype=float)[nz],
                                        drive_delay_s=self.drive_delay_s)
            return resp * _spring_factor(s, self.spring_q)
        p = plant_response(f_hz, self.k_m, bandwidth_hz=self.bandwidth_hz, delay_s=self.delay_s, dt_s=1e-3)
        return p * _mode_factor(s, self.mode_hz, self.damping) * _spring_factor(s, self.spring_q)


def _mode_factor(s: np.ndarray, mode_hz: float | None, zeta: float | None) -> np.ndarray:
    """Load rate over rigid-body rate of a free-free two-mass axis, drive on the motor, gyro on the load:
    ``(2 zeta w s + w^2) / (s^2 + 2 zeta w s + w^2)`` (docs/emulator.md, two-mass compliance)."""
    if mode_hz is None or zeta is None:
        return np.ones_like(s)
    w = 2.0 * math.pi * mode_hz
    return (2.0 * zeta * w * s + w * w) / (s * s + 2.0 * zeta * w * s + w * w)


def _spring_factor(s: np.ndarray, q: float | None) -> np.ndarray:
    """A spring on an integrator: ``s^2 / (s^2 + q)``, ``q = K / J`` ((rad/s)^2): the cable (K = k_c > 0) plus,
    over an elevation sweep's travel, gravity on the imbalance (either sign: a top-heavy assembly is a negative
    spring)."""
    if not q:
        return np.ones_like(s)
    return s * s / (s * s + q)


def linear_plant_frf(plant: Mapping[str, Any], axis: str, f_hz: np.ndarray, *, n_ticks: int = 2048,
                     drive_delay_s: float = 0.0, at_rest: bool = False) -> np.ndarray:
    """The emulated plant's own drive -> gyro response of ``axis`` (deg/s per count) at ``f_hz``, as the 1 kHz loop
    sees it (drive k held over the tick after sample k, from ``drive_delay_s`` after that tick's start: the lab's
    wire and host, whole ticks of it as a delay line, as the emulator applies them): the plant kernel run on a
    doublet with Coulomb friction, the cable's spring, the imbalance, the current limit and noise off, then the DFT
    ratio. The linear damping stays: the viscous friction plus the cable's damping, what friction is to a small
    signal on an ident sweep's rate offset (no reversal; LuGre's bristles settle in ~0.1 ms); left out, it reads as
    ~4 deg of phase lead at 2 Hz on a plant with b / J = 1.5 /s, which the fit's heavy low-frequency weights trade
    against the gyro's pole. The cable's spring is the fit's own ``q`` (:func:`_spring_factor`). Exact for whatever
    the kernel does (zero-order hold, the two-mass mode, the gyro's lag and delay discretised as the emulator does
    them; a delay on the drive is not the same as as much more of the gyro's: the gyro's fraction of a tick is
    interpolated between tick ends). ``at_rest``: the response of a gimbal stuck in friction instead (a doublet far
    below the breakaway, every friction model as configured: LuGre's bristles a stiff spring and damper on the
    motor), what a loop holding the platform at rest sees at the top of its sliding-or-stuck range."""

    u = np.zeros(n_ticks)
    amp = 1e-3 if at_rest else 1000.0  # counts: at rest, far below any breakaway torque
    u[8], u[9] = amp, -amp  # a doublet: the rate returns to rest, so the response decays within the record
    whole_ticks = int(drive_delay_s / Plant.TICK_S + 1e-9)
    y = _linear_plant_run(plant, axis, u, drive_delay_s - whole_ticks * Plant.TICK_S, at_rest=at_rest)
    w = 2.0 * math.pi * np.asarray(f_hz, dtype=float) * Plant.TICK_S
    k = np.arange(n_ticks)
    basis = np.exp(-1j * np.outer(w, k))
    # the loop logs drive k beside sample k and the board applies it from the next tick on: one tick later than the
    # kernel's own indexing (checked against hil.analysis.plant_response, whose delay matches the plant's T_d)
    return (basis @ y) / (basis @ u) * np.exp(-1j * w * (1 + whole_ticks))


def _linear_plant_run(plant: Mapping[str, Any], axis: str, u_counts: np.ndarray, drive_delay_s: float, *,
                      at_rest: bool = False) -> np.ndarray:
    """The gyro of ``axis`` (deg/s) of :func:`linear_plant_frf`'s plant (sliding: Coulomb friction, the cable's
    spring, the imbalance, the ripple and the current limit off, the linear damping kept; ``at_rest``: every friction
    model as configured) driven by ``u_counts`` from rest, each tick's drive taking over ``drive_delay_s`` (within
    the tick) after its start; no noise."""
    c = copy.deepcopy(dict(plant))
    for ax in () if at_rest else AXES:
        damping = (float(c["friction"][ax].get("viscous_n_m_s_per_rad") or 0.0)
                   + float(((c.get("cable") or {}).get(ax) or {}).get("damping_n_m_s_per_rad") or 0.0))
        c["friction"][ax] = {"coulomb_n_m": 0.0, "viscous_n_m_s_per_rad": damping,
                             "smoothing_rate_dps": c["friction"][ax].get("smoothing_rate_dps", 0.1), "model": "tanh"}
    for key in ("cable", "ripple", "drive"):
        c.pop(key, None)
    c["imbalance"] = {**c["imbalance"], "mass_kg": 0.0}
    c["gyro"] = {**c["gyro"], "noise_std_dps": [0.0, 0.0, 0.0], "noise_psd": [], "random_walk": 0.0,
                 "quantisation_lsb_dps": 0.0, "bias_dps": [0.0, 0.0, 0.0]}
    c["camera"] = {**c["camera"], "centroid_noise_std_px": 0.0}
    u = np.asarray(u_counts, dtype=float)
    zero = np.zeros(u.size)
    gyro = "gyro_z_dps" if axis == "az" else "gyro_y_dps"
    out = Plant(PlantConfig.model_validate(c), seed=1).run(
        u if axis == "az" else zero, u if axis == "el" else zero, np.zeros((u.size, 18)), outputs=[gyro],
        drive_delay_s=max(0.0, drive_delay_s))
    return out[gyro]


def sweep_reading(plant: Mapping[str, Any], axis: str, lin: LinearFrf, *, drive_delay_s: float = 0.0) -> np.ndarray:
    """How the sweep's FRF estimator reads :func:`linear_plant_frf`'s plant, relative to its exact response, on
    every bin of ``lin.frf``: the estimate (``hil.analysis.estimate_sweep_frf``: the log's own command, drive and
    band) of that plant's gyro driven by the log's drive, over the plant's exact response. Welch's segments cut the
    response to a chirp: near a lightly damped mode, whose ringing outlasts the chirp's crossing, and at the low
    band's end, the estimate of a noise-free, exactly linear plant is off by up to ~0.35 dB and ~1 deg (hidden plant
    54's elevation, a 190 Hz mode damped at 4.5 %: 0.3 dB and 0.5 deg, which its fit read as +3 us of loop
    delay)."""
    whole_ticks = int(drive_delay_s / Plant.TICK_S + 1e-9)
    shift = 1 + whole_ticks  # drive k acts from the tick after sample k (linear_plant_frf)
    u = np.concatenate([np.zeros(shift), lin.drive_counts])[: lin.drive_counts.size]
    y = _linear_plant_run(plant, axis, u, drive_delay_s - whole_ticks * Plant.TICK_S)
    est = estimate_sweep_frf(lin.rate_cmd_dps, lin.drive_counts, y, lin.dt_s, f_min_hz=lin.f_lo_hz,
                             f_max_hz=lin.f_hi_hz)
    f = lin.frf.freq_hz
    reading = np.ones(f.size, dtype=complex)
    ok = (f > 0) & np.isfinite(est.response) & (np.abs(est.response) > 0)
    reading[ok] = est.response[ok] / linear_plant_frf(plant, axis, f[ok], drive_delay_s=drive_delay_s)
    return reading


def _exact_refine(plant: Mapping[str, Any], axis: str, fs: np.ndarray, p: np.ndarray, wt: np.ndarray,  # noqa: PLR0917
                  x0: np.ndarray, with_mode: bool, bw_fixed: float | None, spring_fixed: bool = False,
                  drive_delay_s: float = 0.0) -> Any:
    """Least squares of the kernel's own response (:func:`linear_plant_frf`, the lab's ``drive_delay_s`` on the
    drive) from the analytic fit's ``x0``; ``x0``'s and the result's delay are the gyro's own."""
    from scipy.optimize import least_squares  # noqa: PLC0415  (heavy: loaded only when this computation runs)

    s = 2j * math.pi * fs

    def model(x: np.ndarray) -> np.ndarray:
        return linear_plant_frf(_kernel_plant(plant, axis, x, with_mode, bw_fixed), axis, fs,
                                drive_delay_s=drive_delay_s) * _spring_factor(s, float(x[5]))

    def resid(x: np.ndarray) -> np.ndarray:
        e = np.log(p / model(x))
        return np.concatenate([wt * e.real, wt * np.angle(np.exp(1j * e.imag))])

    q_max = float((2 * math.pi * 4 * max(float(fs.min()) / 2.0, 0.25)) ** 2)
    lo = [-12.0, math.log(20.0), 0.0, math.log(5.0), math.log(0.005), -q_max]
    hi = [2.0, math.log(5000.0), 3e-3, math.log(499.0), math.log(0.7), q_max]
    free = [0, 2] + ([] if spring_fixed else [5]) + ([] if bw_fixed else [1]) + ([3, 4] if with_mode else [])
    if spring_fixed:
        lo[5], hi[5] = float(x0[5]) - 1e-6, float(x0[5]) + 1e-6
    full = np.clip(np.asarray(x0, dtype=float), np.array(lo) + 1e-9, np.array(hi) - 1e-9)

    def sub(y: np.ndarray) -> np.ndarray:
        x = full.copy()
        x[free] = y
        return resid(x)

    res = least_squares(sub, full[free], bounds=([lo[i] for i in free], [hi[i] for i in free]), x_scale="jac",
                        diff_step=1e-4, max_nfev=40)
    full[free] = res.x
    res.x_full, res.free = full, free
    res.kernel_plant = _kernel_plant(plant, axis, full, with_mode, bw_fixed)
    return res


def _kernel_plant(plant: Mapping[str, Any], axis: str, x: np.ndarray, with_mode: bool,
                  bw_fixed: float | None) -> dict[str, Any]:
    """``plant`` with the FRF fit's parameters ``x`` = (ln k_m, ln bandwidth, delay, ln mode, ln damping, spring)
    set on ``axis`` (without a mode: the axis rigid)."""
    ln_k, ln_bw, td, ln_fr, ln_z, _ = x
    vals = {f"motor_{axis}.k_m_dps2_per_count": float(np.exp(ln_k)), "gyro.delay_s": float(td),
            "gyro.bandwidth_hz": float(bw_fixed or np.exp(ln_bw))}
    if with_mode:
        vals |= {f"structure.{axis}.mode_hz": float(np.exp(ln_fr)),
                 f"structure.{axis}.damping_ratio": float(np.exp(ln_z))}
    c = apply_params(plant, vals)
    if not with_mode:
        c.get("structure", {}).pop(axis, None)
        if not c.get("structure"):
            c.pop("structure", None)
    return c


class LinearFrf(NamedTuple):
    """:func:`linear_frf`'s result."""

    frf: Any  # hil.analysis.Frf
    f_lo_hz: float  # the sweep's lower frequency
    dt_s: float  # the log's tick
    current_limited_ticks: int  # ticks whose drive was taken at the driver's current limit (drive_at_current_limit)
    rate_cmd_dps: np.ndarray  # the estimate's window: the rate command
    drive_counts: np.ndarray  # ... and the drive the FRF takes as the plant's input
    f_hi_hz: float  # the estimate's upper frequency


def linear_frf(log: FitLog, *, coherence_min: float = 0.8, motor: Mapping[str, Any] | None = None,
               current_limit_a: float | None = None, ripple: Mapping[str, Any] | None = None) -> LinearFrf:
    """The ident log's FRF (``hil.analysis.estimate_sweep_frf``) with the bins the loop did not pass linearly
    (:func:`nonlinear_bins`) at coherence 0; its sweep's lower frequency and the log's tick. :class:`UnusableSweep`
    if no linear, coherent bin is left below ``LINEAR_LOW_HZ``. With the axis' ``motor`` (the plant file's
    ``motor_<axis>``) and the driver's ``current_limit_a``, the FRF's input is the drive the plant received
    (:func:`drive_at_current_limit`); ``current_limited_ticks`` counts the ticks it changed. With the motor and the
    axis' torque ``ripple`` (the plant file's ``ripple.<axis>``, which the fit takes as it is), the drive whose
    torque the motor made (:func:`drive_with_ripple`)."""
    ax = log.axis or "el"
    sweep = SweptSine(**log.excitation) if log.excitation else None
    r, u, y = log.loop[f"rate_cmd_{ax}_dps"], log.loop[f"drive_{ax}_counts"], log.gyro(ax)
    dt = log.dt_s
    if sweep is None:
        raise FitInputError(f"{log.path}: an ident log without its sweep (config 'excitation')")
    k0 = sweep_start(r, sweep, dt)
    pad = 0.5 * sweep.settle_s
    a, b = max(0, k0 + round((sweep.window_s[0] - pad) / dt)), min(r.size, k0 + round((sweep.window_s[1] + pad) / dt))
    f_lo, f_hi = sorted((sweep.f_start_hz, sweep.f_stop_hz))
    f_hi = min(f_hi, 0.45 / dt)
    u_in, limited = u[a:b], 0
    if motor is not None and current_limit_a is not None:
        u_in, limited = drive_at_current_limit(u[a:b], y[a:b], motor, current_limit_a)
    if motor is not None and ripple:
        u_in = drive_with_ripple(u_in, y[a:b], log.loop[f"{ax}_deg"][a:b], motor, ripple)
    frf = estimate_sweep_frf(r[a:b], u_in, y[a:b], dt, f_min_hz=f_lo, f_max_hz=f_hi)
    max_drive = float((log.config.get("safety") or {}).get("max_drive_counts") or 0.0)
    nonlinear = nonlinear_bins(frf.freq_hz, sweep, u, y, dt, k0, max_drive)
    if np.any(nonlinear):  # the clipped or reversed stretches are not the plant's linear response: left out
        linear_low = (frf.freq_hz >= 2 * f_lo) & (frf.freq_hz < LINEAR_LOW_HZ) & (frf.coherence >= coherence_min)
        if not np.any(linear_low & ~nonlinear):
            n_clip = float(np.mean(np.abs(u[a:b]) >= max_drive - 0.5)) if max_drive > 0 else 0.0
            raise UnusableSweep(
                f"{log.name}: the {ax} loop was not linear below {LINEAR_LOW_HZ:g} Hz, where k_m shows (the drive at "
                f"its {max_drive:g}-count limit on {n_clip:.0%} of the sweep's ticks, or the axis turning against "
                f"the offset): a loop at its limit or oscillating by itself; record `hil ident SESSION` with "
                f"axis={ax} again, with a controller whose b0 is nearer this axis (PI + LPF: docs/ident.md) or a "
                "smaller amplitude")
        frf = replace(frf, coherence=np.where(nonlinear, 0.0, frf.coherence))
    return LinearFrf(frf, f_lo, dt, limited, r[a:b], u_in, f_hi)


def fit_frequency_response(log: FitLog, *, prior: Mapping[str, Any] | None = None, coherence_min: float = 0.8,
                           spring_q: float | None = None, drive_delay_s: float = 0.0,
                           current_limit_a: float | None = None) -> FrfFit:
    """The ident log's FRF (``hil.analysis.estimate_sweep_frf``, indirect, at two resolutions) and the joint least-
    squares fit on its coherent bins: log-magnitude (nepers) and phase (rad) alike, weights ``g/(1-g)/f`` as
    ``hil.analysis.fit_plant``. The rigid fit of ``hil.analysis`` starts it; the mode's frequency starts from a grid
    over the band. ``drive_delay_s``: the lab's wire and host (:func:`lab_wire_delay_s`); the kernel's fit puts it
    on the drive, where the lab has it, and fits the gyro's own delay. The result's ``delay_s`` is the whole
    transport delay, both together. ``current_limit_a``: the driver's current limit on this axis (the torque
    balance's), with ``prior``'s motor: the FRF takes the drive the plant received (:func:`linear_frf`), and with the
    prior's torque ripple on the axis, the drive whose torque the motor made."""
    from scipy.optimize import least_squares  # noqa: PLC0415  (heavy: loaded only when this computation runs)

    ax = log.axis or "el"
    motor = prior.get(f"motor_{ax}") if prior is not None else None
    ripple = (prior.get("ripple") or {}).get(ax) if prior is not None else None
    lin = linear_frf(log, coherence_min=coherence_min, motor=motor, current_limit_a=current_limit_a, ripple=ripple)
    frf, f_lo, dt, limited = lin.frf, lin.f_lo_hz, lin.dt_s, lin.current_limited_ticks
    try:
        rigid = fit_plant(frf, coherence_min=coherence_min, f_min_hz=2.0 * f_lo, lag=True)
    except ValueError as exc:
        raise FitInputError(f"{log.path}: the {ax} sweep has no usable response ({exc}); check that the axis "
                            "followed the sweep (drive saturation, a restrained axis) and record it again") from None
    f = frf.freq_hz
    sel = np.isfinite(frf.response) & (np.abs(frf.response) > 0) & (frf.coherence >= coherence_min) & (f >= 2 * f_lo)
    if np.count_nonzero(sel) < 8:
        raise FitInputError(f"{log.path}: only {np.count_nonzero(sel)} coherent bins in the sweep")
    fs, p = f[sel], frf.response[sel]
    w = 2.0 * math.pi * fs
    s = 1j * w
    g = np.minimum(frf.coherence[sel], 0.99)
    wt = np.sqrt(g / (1.0 - g) / fs)
    shapes = SweepShapes(w, dt)
    f_top = float(fs.max())

    def model(x: np.ndarray, with_mode: bool) -> np.ndarray:
        ln_k, ln_bw, td, ln_fr, ln_z, q = x
        m = np.exp(ln_k) * shapes.shape(float(np.exp(ln_bw)), float(td))
        if with_mode:
            m = m * _mode_factor(s, float(np.exp(ln_fr)), float(np.exp(ln_z)))
        return m * _spring_factor(s, float(q))

    def resid(x: np.ndarray, with_mode: bool) -> np.ndarray:
        e = np.log(p / model(x, with_mode))
        return np.concatenate([wt * e.real, wt * np.angle(np.exp(1j * e.imag))])

    def search(bw_fixed: float | None) -> tuple[float, bool, Any, float | None]:
        bw0 = bw_fixed or rigid.gyro_bandwidth_hz or 2.0 * f_top
        base = [math.log(rigid.k_m_dps2_per_count), math.log(min(bw0, 3000.0)), rigid.model_delay_s]
        q_max = float((2 * math.pi * 4 * f_lo) ** 2)
        lo = [-12.0, math.log(20.0), 0.0, math.log(max(5.0, 2 * f_lo)), math.log(0.005), -q_max]
        hi = [2.0, math.log(5000.0), 3e-3, math.log(0.499 / dt), math.log(0.7), q_max]
        if spring_q is not None:  # known from the torque balance: k_c (+ gravity on the imbalance) over J
            lo[5], hi[5] = spring_q - 1e-6, spring_q + 1e-6
        if bw_fixed:
            lo[1], hi[1] = math.log(bw_fixed) - 1e-9, math.log(bw_fixed) + 1e-9
        fits = []
        for with_mode in (False, True):
            grid = np.geomspace(max(20.0, 4 * f_lo), 0.49 / dt, 14) if with_mode else [100.0]
            for fr0 in grid:
                q_starts = (0.0, (2 * math.pi * f_lo) ** 2, -((2 * math.pi * f_lo) ** 2) / 2)
                for q0 in (spring_q,) if spring_q is not None else q_starts:
                    x0 = np.array([*base, math.log(fr0), math.log(0.05), q0])
                    x0 = np.clip(x0, np.array(lo) + 1e-10, np.array(hi) - 1e-10)
                    try:
                        res = least_squares(resid, x0, args=(with_mode,), bounds=(lo, hi), x_scale="jac")
                    except ValueError:
                        continue
                    fits.append((res.cost, with_mode, res))
        rigid_cost = min(c for c, m, _ in fits if not m)
        cost, with_mode, res = min(fits, key=lambda t: t[0])
        mode_hz = float(np.exp(res.x[3])) if with_mode else None
        # the mode counts only if it explains the data (halves the residual) and sits inside the measured band
        if with_mode and (cost > 0.5 * rigid_cost or mode_hz is None or mode_hz > 1.05 * f_top):
            cost, with_mode, res = min(((c, m, r_) for c, m, r_ in fits if not m), key=lambda t: t[0])
            mode_hz = None
        return cost, with_mode, res, mode_hz

    prior_bandwidth_hz = float(prior["gyro"]["bandwidth_hz"]) if prior is not None else 200.0
    _, with_mode, res, mode_hz = search(None)
    # the gyro's pole is told from a delay only where the coherent band reaches it and pins it (POLE_PINNED_REL;
    # a value pinned more loosely than its 10 % target is graded weak); else the prior's bandwidth, and the delay
    # absorbs what lag there is
    bandwidth_identified = (float(np.exp(res.x[1])) <= 1.25 * f_top
                            and _sigmas(res, with_mode, fs.size)[1] < POLE_PINNED_REL)
    if not bandwidth_identified:
        _, with_mode, res, mode_hz = search(prior_bandwidth_hz)
    kernel_plant = None
    reading = None
    if prior is not None:  # the analytic model approximates the kernel's sampling; finish on the kernel itself

        def refine(x: np.ndarray, bw_fixed: float | None) -> tuple[Any, np.ndarray]:
            nonlocal p, reading
            x0 = x.copy()
            x0[2] = max(0.0, float(x0[2]) - drive_delay_s)  # the kernel's delay is the gyro's own
            # the data as the kernel would read exactly: the estimator's reading of the analytic start taken out
            reading = sweep_reading(_kernel_plant(prior, ax, x0, with_mode, bw_fixed), ax, lin,
                                    drive_delay_s=drive_delay_s)
            p = frf.response[sel] / reading[sel]
            ex = _exact_refine(prior, ax, fs, p, wt, x0, with_mode, bw_fixed, spring_fixed=spring_q is not None,
                               drive_delay_s=drive_delay_s)
            cov = (np.linalg.pinv(ex.jac.T @ ex.jac) * (2.0 * ex.cost / max(1, 2 * fs.size - len(ex.free)))
                   * correlation_inflation(ex.fun))
            sd = np.zeros(6)
            sd[ex.free] = np.sqrt(np.clip(np.diag(cov), 0.0, None))
            return ex, sd

        ex, sd = refine(res.x, None if bandwidth_identified else prior_bandwidth_hz)
        if bandwidth_identified and sd[1] >= POLE_PINNED_REL:
            bandwidth_identified = False
            _, with_mode, res, mode_hz = search(prior_bandwidth_hz)
            ex, sd = refine(res.x, prior_bandwidth_hz)
        res.x = ex.x_full
        res.x[2] += drive_delay_s
        kernel_plant = ex.kernel_plant
        if mode_hz is not None:
            mode_hz = float(np.exp(res.x[3]))
    else:
        sd = _sigmas(res, with_mode, fs.size)
    q = float(res.x[5])
    fitted = (linear_plant_frf(kernel_plant, ax, fs, drive_delay_s=drive_delay_s) * _spring_factor(s, q)
              if kernel_plant is not None else model(res.x, with_mode))
    e = np.log(p / fitted)
    return FrfFit(
        axis=ax, k_m=float(np.exp(res.x[0])), bandwidth_hz=float(np.exp(res.x[1])), delay_s=float(res.x[2]),
        mode_hz=mode_hz, damping=float(np.exp(res.x[4])) if with_mode else None,
        spring_q=q,
        sigma={"k_m": float(sd[0]) * float(np.exp(res.x[0])), "bandwidth_hz": float(sd[1]) * float(np.exp(res.x[1])),
               "delay_s": float(sd[2]), "mode_hz": float(sd[3]) * (mode_hz or 0.0),
               "damping": float(sd[4]) * float(np.exp(res.x[4])) if with_mode else 0.0,
               "spring_q": float(sd[5])},
        rms_db=float(np.sqrt(np.mean((e.real * 20 / math.log(10)) ** 2))),
        rms_deg=float(np.degrees(np.sqrt(np.mean(np.angle(np.exp(1j * e.imag)) ** 2)))),
        f_range_hz=(float(fs.min()), f_top), frf=frf, log=log.name, bandwidth_identified=bandwidth_identified,
        kernel_plant=kernel_plant, drive_delay_s=drive_delay_s if kernel_plant is not None else 0.0,
        current_limited_ticks=limited, reading=reading,
    )


class UnusableSweep(FitInputError):
    """An ident log whose loop did not pass linearly through the band that gives k_m: the fit keeps the axis' prior
    and says why, rather than read the clipper's response as the plant's."""


LINEAR_LOW_HZ = 50.0  # an ident log needs linear, coherent bins below this (the rigid band: k_m, the spring)
CLIP_SHARE_MAX = 0.01  # a third octave whose drive sat at its limit on more ticks than this is left out of the fit


def nonlinear_bins(freq_hz: np.ndarray, sweep: SweptSine, u: np.ndarray, y: np.ndarray,  # noqa: PLR0917
                   dt: float, k0: int, max_drive_counts: float) -> np.ndarray:
    """The FRF bins (``freq_hz``) of an ident log whose third octave the loop did not pass through linearly: while
    the chirp was there (its time-to-frequency map, ``SweptSine.frequency_hz``), the drive sat at
    ``max_drive_counts`` on more than ``CLIP_SHARE_MAX`` of the ticks, or the axis' rate (5 ms mean) went against
    the sweep's offset (friction switched sides). A loop at its limit, or one oscillating by itself, gives such
    stretches; their bins are the clipper's and the friction's, not the plant's linear response."""
    t0, t1 = sweep.window_s
    a, b = max(k0 + round(t0 / dt), 0), min(k0 + round(t1 / dt), u.size)
    out = np.zeros(np.asarray(freq_hz).size, dtype=bool)
    if b - a < 2:
        return out
    f_t = np.array([sweep.frequency_hz((k - k0) * dt) for k in range(a, b)])
    clipped = (np.abs(u[a:b]) >= max_drive_counts - 0.5) if max_drive_counts > 0 else np.zeros(b - a, dtype=bool)
    width = max(1, round(REVERSAL_SMOOTH_S / dt))  # the levelling's own reading of a reversal
    y_s = np.convolve(y, np.ones(width) / width, mode="same")[a:b]
    against = (np.sign(sweep.offset_dps) * y_s < 0.0) if sweep.offset_dps else np.zeros(b - a, dtype=bool)
    half = 2.0 ** (1.0 / 6.0)  # a third octave around each bin
    order = np.argsort(f_t)
    f_sorted = f_t[order]
    clip_cum = np.concatenate([[0], np.cumsum(clipped[order])])
    rev_cum = np.concatenate([[0], np.cumsum(against[order])])
    for i, f in enumerate(np.asarray(freq_hz, dtype=float)):
        lo, hi = np.searchsorted(f_sorted, f / half), np.searchsorted(f_sorted, f * half)
        n = hi - lo
        if n == 0:
            continue
        out[i] = (clip_cum[hi] - clip_cum[lo]) / n > CLIP_SHARE_MAX or rev_cum[hi] - rev_cum[lo] > 0
    return out


def _sigmas(res: Any, with_mode: bool, n_bins: int) -> np.ndarray:
    """1-sigma of a least-squares fit's parameters from its Jacobian and residual (log-scale ones are relative),
    widened for residuals correlated from bin to bin (:func:`correlation_inflation`)."""
    dof = max(1, 2 * n_bins - (6 if with_mode else 4))
    cov = np.linalg.pinv(res.jac.T @ res.jac) * (2.0 * res.cost / dof) * correlation_inflation(res.fun)
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))


POLE_PINNED_REL = 0.25  # the gyro's bandwidth counts as measured (fitted, or weak beyond 10 %) within this 1-sigma
RHO_MAX = 0.98  # the widest correlation counted: at most (1 + 0.98) / (1 - 0.98) = 99 bins to one


def correlation_inflation(resid: np.ndarray) -> float:
    """How much wider an FRF fit's parameter variance is than independent bins would make it: ``(1 + rho) / (1 -
    rho)``, ``rho`` the residuals' correlation from one bin to the next (the mean over the log-magnitude and the
    phase halves, each in frequency order; clipped to [0, RHO_MAX]). A Welch FRF's neighbouring bins share their
    segments and a chirp crosses each high bin in milliseconds, so the residuals run in long correlated stretches;
    with AR(1) residuals the least-squares variance grows by this factor (the effective number of bins shrinks
    by it)."""
    r = np.asarray(resid, dtype=float)
    n = r.size // 2
    rhos = []
    for half in (r[:n], r[n:]):
        if half.size >= 3 and np.std(half[:-1]) > 0 and np.std(half[1:]) > 0:
            rhos.append(float(np.corrcoef(half[:-1], half[1:])[0, 1]))
    rho = min(max(float(np.mean(rhos)) if rhos else 0.0, 0.0), RHO_MAX)
    return (1.0 + rho) / (1.0 - rho)
