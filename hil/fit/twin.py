"""``hil fit``: the plant fitted to one platform's session logs (the method is in docs/fit.md).

Three estimators, each on the logs that carry its information, each returning :class:`Estimate` rows (value,
1-sigma, source) in the vocabulary of :mod:`hil.fit.ranges`:

- :func:`fit_noise` (static logs): per gyro axis, the white noise std and the band-limited component from the
  spectrum above the rate loop's bandwidth (Welch); the bias from the mean (x) or the encoder's drift (y, z);
- :func:`fit_frequency_response` (ident logs): the indirect closed-loop FRF of ``hil.analysis`` and a least-squares fit
  of ``k_m / s`` (sampled) x gyro lag x delay x two-mass mode x cable spring (seed 000 eqs 3, 33-38);
- :func:`fit_mechanics` (every log with motion): an equation-error fit of the torque balance, per axis,
  ``J dw/dt = K_t clip(i, I_max) - T_f(v) - k_c theta + T_imb`` with the gyro's own lag applied to the right-hand
  side and both sides low-passed alike; linear in T_c, T_s - T_c, D, k_c, m rho for each Stribeck rate and current
  limit on a grid. The carrier is the logged hexapod pose, the drive the logged one.

:func:`fit_logs` runs them and writes the plant: fitted values where the logs determine them, the prior's elsewhere
(said so in :attr:`TwinFit.estimates`).

One responsibility in one file (about 950 lines): fitting the plant to logs; the passes share the prior, the
fitted plant and the order in which each estimate feeds the next.
"""

from __future__ import annotations

import copy
import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np

from firmware_stub.config import load_emulator_config
from firmware_stub.plant import DEFAULT_PLANT_CONFIG, Plant, PlantConfig
from hil.analysis import (
    REVERSAL_SMOOTH_S,
    SweepShapes,
    SweptSine,
    estimate_sweep_frf,
    fit_plant,
    plant_response,
    sweep_start,
)
from hil.fit.logs import AXES, FitInputError, FitLog, load_fit_logs
from hil.fit.ranges import (
    BY_NAME,
    apply_params,
    dump_plant,
    get_param,
    k_m_of,
    load_plant_dict,
    param_range,
    validate_plant,
)
from hil.fit.rerun import match_breakaway

D2R = math.pi / 180.0
# a static log's gyro PSD bin counts for the noise only where the loop's own drive put less than this share of it
# (``|P|^2 S_uu / S``): the ident fit's P (friction left out) misses the presliding a gimbal at rest feels, and its
# term was measured 35-75 % off below 250 Hz, a bias that adds up over bins (docs/fit.md, "Gyro noise")
DRIVE_SHARE_MAX = 0.04
# ... and only where P's two small-signal limits, friction sliding (viscous) and stuck (LuGre's bristles a spring
# and damper on the motor), give noise levels within this of each other: a gimbal held at rest by a loop creeps at
# its gyro bias and reverses with the noise, so its P lies between the two; measured 35-50 deg of phase between them
# at 200-350 Hz on plants whose bristles ring at 170-225 Hz, where the sliding P alone read the white noise 5-9 % low
P_SPREAD_MAX = 0.02
NOISE_BINS_MIN = 60  # fewer bins than this below the share: the least-driven ones are kept
BREAKAWAY_UNRESOLVED = "the breakaway is not resolved (a Stribeck rate inside the stick band)"
G0 = 9.80665
Status = Literal["fitted", "weak", "prior", "bound"]  # weak: fitted, not to its target (wider sigma, or leaning on a
# prior it cannot tell itself from)


@dataclass
class Estimate:
    """One parameter: the fitted value and its 1-sigma, or the prior kept (``status``), with where it came from."""

    name: str
    value: float | None
    sigma: float | None
    unit: str
    status: Status
    source: str
    prior: float | None = None
    note: str = ""

    @property
    def relative_sigma(self) -> float | None:
        if self.value is None or self.sigma is None or self.value == 0:
            return None
        return abs(self.sigma / self.value)


def _unit(name: str, default: str = "") -> str:
    if name in BY_NAME:
        return BY_NAME[name].unit
    for suffix, unit in (("_dps", "deg/s"), ("_hz", "Hz"), ("_s", "s"), ("_n_m", "N m"), ("_a", "A"),
                         ("_ratio", "1"), ("_kg_mm", "kg mm"), ("_n_m_per_rad", "N m/rad")):
        if name.endswith(suffix):
            return unit
    return default


# --- gyro noise (static logs) ------------------------------------------------------------------------------------


def _bandpass_shape(f_hz: np.ndarray, centre_hz: float, bandwidth_hz: float, fs_hz: float) -> np.ndarray:
    """|H|^2 of the plant's coloured-noise band-pass (``scipy.signal.iirpeak``), normalised to unit variance gain:
    the one-sided PSD of a component of std 1 is ``2 / fs * shape``."""
    from scipy.signal import freqz, iirpeak  # noqa: PLC0415  (heavy: loaded only when this computation runs)

    b, a = iirpeak(centre_hz, centre_hz / bandwidth_hz, fs=fs_hz)
    grid = np.linspace(0.0, fs_hz / 2.0, 4097)
    _, h_grid = freqz(b, a, worN=grid, fs=fs_hz)
    gain = float(np.mean(np.abs(h_grid) ** 2))  # variance gain for white input (Parseval on the uniform grid)
    _, h = freqz(b, a, worN=f_hz, fs=fs_hz)
    return np.abs(h) ** 2 / gain


def _residual_inflation(resid: np.ndarray, bins_hz: np.ndarray, *, dof: float, lags: int = 3) -> float:
    """The factor a weighted least squares' 1-sigma grows by when its residuals ``resid`` (at frequencies
    ``bins_hz``, ``dof`` degrees of freedom left) are not the independent, unit-variance ones the weights assume:
    ``sqrt(max(1, chi2 / dof) * max(1, 1 + 2 sum_k rho_k))``, ``rho_k`` their correlation between bins ``k`` apart
    (``k <= lags``; only pairs with no bin left out between them). Welch's Hann segments correlate neighbouring
    bins (rho_1 = 4/9, rho_2 = 1/36 in theory), so a spectral fit that counts every bin as independent understates
    its 1-sigma by about sqrt(1 + 2 (4/9 + 1/36)) = 1.39."""
    ss = float(resid @ resid)
    if ss <= 0.0 or dof <= 0.0 or resid.size < 2:
        return 1.0
    df = float(np.min(np.diff(bins_hz)))
    rho_sum = 0.0
    for k in range(1, min(lags, resid.size - 1) + 1):
        adjacent = np.isclose(bins_hz[k:] - bins_hz[:-k], k * df)
        rho_sum += float(resid[k:][adjacent] @ resid[:-k][adjacent]) / ss
    return math.sqrt(max(1.0, ss / dof) * max(1.0, 1.0 + 2.0 * rho_sum))


def _welch_variance(segments: int, nperseg: int = 1024) -> float:
    """The variance of a Welch PSD bin over its mean squared, for ``segments`` half-overlapping Hann segments of
    Gaussian noise: ``(1 + 2 c^2) / K``, ``c`` the window's correlation with itself half a segment on (1/6 for Hann;
    Welch 1967)."""
    w = np.hanning(nperseg + 1)[:-1]  # scipy.signal.welch's periodic Hann
    c = float(w[: nperseg // 2] @ w[nperseg // 2:]) / float(w @ w)
    return (1.0 + 2.0 * c * c) / segments


def _over(x: np.ndarray, limit: float) -> np.ndarray:
    """``x / limit``, zero for an infinite ``limit`` (no limit)."""
    return x / limit if math.isfinite(limit) else np.zeros_like(x)


class _AxisSpectrum(NamedTuple):
    """One gyro axis of :func:`fit_noise`: the bins kept, their PSD, its model (white std, band std, band centre)
    and that axis' own fit as the joint fit's start; ``k_avg`` Welch averages per bin."""

    axis: str
    lsb: float
    f_hz: np.ndarray
    psd: np.ndarray
    model: Any
    start: np.ndarray
    k_avg: int


def fit_noise(logs: list[FitLog], prior: Mapping[str, Any], *, f_min_hz: float = 150.0, settle_s: float = 1.0,
              modes_hz: Mapping[str, float] | None = None,
              driven: Mapping[str, Mapping[str, Any]] | None = None,
              drive_delay_s: float = 0.0,
              drive_share_max: float = DRIVE_SHARE_MAX,
              p_spread_max: float = P_SPREAD_MAX) -> tuple[list[Estimate], dict[str, Any]]:
    """Gyro white noise std per axis and one band-limited component (``gyro.noise_psd``) from static logs.

    Welch PSD (1024-sample Hann segments) of each gyro axis above ``f_min_hz`` (above the rate loop's bandwidth, so
    the closed loop does not shape it), modelled as ``2/fs (sigma_w^2 + sigma_c^2 shape_c(f))`` + the quantisation
    floor ``LSB^2/12`` (LSB from the data's value grid). One joint least squares on ``PSD / model - 1``: a white std
    per axis, one band component (std and centre) for the three, as the plant has it; its width is the prior's (not
    separable from its std at this resolution). On y and z the loop's own drive moves the gimbal (the noise fed
    back, ringing the structure): with ``driven`` (gyro axis -> a plant whose drive -> gyro response the ident fit
    has set), the spectrum is that of ``gyro - P drive``, ``S_yy - 2 Re(P* S_uy) + |P|^2 S_uu``
    (:func:`linear_plant_frf`, the lab's wire and host ``drive_delay_s`` on the drive), and only the bins where the
    drive's part ``|P|^2 S_uu`` is under ``drive_share_max`` of the PSD and where P sliding and P stuck
    (``at_rest``) give PSDs within ``p_spread_max`` of each other count (P's error there is a bias, not noise; at
    least :data:`NOISE_BINS_MIN`, the least driven); bins within 20 % of ``modes_hz`` (gyro axis -> structural
    mode) are left out. The undriven x axis pins the band where a driven axis keeps few bins. Each 1-sigma is the
    least squares' own, grown by :func:`_residual_inflation` (neighbouring Welch bins are not independent).
    Bias: x from its mean (no loop on it), y and z from the encoders' drift (the loop holds the measured rate at
    zero, so the gimbal turns at minus the bias)."""
    from scipy.optimize import least_squares  # noqa: PLC0415  (heavy: loaded only when this computation runs)
    from scipy.signal import welch  # noqa: PLC0415  (heavy: loaded only when this computation runs)

    static = [lg for lg in logs if lg.kind == "static"]
    extras: dict[str, Any] = {"psd": {}}
    if not static:
        return [Estimate(n, get_param(prior, n), None, _unit(n, "deg/s"), "prior", "no static log")
                for n in ("gyro.noise_std_dps", "gyro.noise_psd.std_dps", "gyro.noise_psd.centre_hz")], extras
    psd_prior = (prior["gyro"].get("noise_psd") or [{"centre_hz": 450.0, "bandwidth_hz": 100.0, "std_dps": 0.0}])[0]
    bw = float(psd_prior["bandwidth_hz"])
    rows: dict[str, list[np.ndarray]] = {ax: [] for ax in "xyz"}
    for lg in static:
        k0 = int(settle_s / lg.dt_s)
        for ax in "xyz":
            rows[ax].append(lg.loop[f"gyro_{ax}_dps"][k0:])
    fs = 1.0 / static[0].dt_s
    out: list[Estimate] = []
    axes_fit: list[_AxisSpectrum] = []  # per axis, for the joint fit
    fc_lo, fc_hi = 0.55 * f_min_hz + 0.45 * fs / 2.0 - 60.0, 0.49 * fs
    for ax in "xyz":
        x = np.concatenate([r - r.mean() for r in rows[ax]])
        levels = np.unique(np.round(np.concatenate(rows[ax]), 7))
        steps = np.diff(levels)
        lsb = float(np.median(steps[steps > 0])) if steps.size else 0.0
        f, pxx = welch(x, fs=fs, nperseg=1024)
        # how far each bin is from being trusted, 1 at the limit: the part the loop's drive put there over
        # drive_share_max, the spread between P sliding and P stuck over p_spread_max, whichever is larger
        doubt = np.zeros(f.size)
        sel = (f >= f_min_hz) & (f < 0.5 * fs * 0.98)
        motor = {"y": "el", "z": "az"}.get(ax)
        if driven is not None and motor is not None and ax in driven:
            from scipy.signal import csd  # noqa: PLC0415  (heavy: loaded only when this computation runs)

            u = np.concatenate([lg.loop[f"drive_{motor}_counts"][int(settle_s / lg.dt_s):] for lg in static])
            u = u - u.mean()
            _, s_uu = welch(u, fs=fs, nperseg=1024)
            _, s_uy = csd(u, x, fs=fs, nperseg=1024)
            raw, est = pxx, {}
            for at_rest in (False, True):
                resp = np.zeros(f.size, dtype=complex)
                resp[1:] = linear_plant_frf(driven[ax], motor, f[1:], drive_delay_s=drive_delay_s, at_rest=at_rest)
                moved = np.abs(resp) ** 2 * s_uu
                est[at_rest] = np.maximum(raw - 2.0 * np.real(np.conj(resp) * s_uy) + moved, 1e-3 * raw), moved
            (pxx, moved), (stuck, _) = est[False], est[True]
            doubt = np.maximum(_over(moved / pxx, drive_share_max), _over(np.abs(stuck / pxx - 1.0), p_spread_max))
        if (mode := (modes_hz or {}).get(ax)):  # the mode's damping is the least certain part of P
            sel &= np.abs(f - mode) > 0.2 * mode
        if driven is not None and motor is not None and ax in driven:
            quiet = sel & (doubt < 1.0)
            if quiet.sum() < NOISE_BINS_MIN:
                quiet = sel & (doubt <= np.sort(doubt[sel])[min(NOISE_BINS_MIN, int(sel.sum())) - 1])
            sel = quiet
        k_avg = max(1, x.size // 512 - 1)  # Welch segments per bin (1024 samples, half overlapping)
        # least squares on PSD / model - 1 settles on E[PSD^2] / E[PSD] = (1 + v) E[PSD], v the variance of a bin
        # over its mean squared: divided out, so the fit is unbiased (+0.9 % on the white std of a 30 s log if not)
        f, pxx = f[sel], pxx[sel] / (1.0 + _welch_variance(k_avg))
        q_floor = lsb * lsb / 12.0
        shape = functools.partial(_bandpass_shape, f, bandwidth_hz=bw, fs_hz=fs)

        def model(p: np.ndarray, q_floor: float = q_floor, shape: Any = shape) -> np.ndarray:
            sw, sc, fc = p
            return 2.0 / fs * (sw * sw + q_floor + sc * sc * shape(centre_hz=fc))

        best = None
        for fc0 in (320.0, 380.0, 440.0, float(psd_prior["centre_hz"])):
            p0 = np.array([math.sqrt(max(np.median(pxx) * fs / 2.0 - q_floor, 1e-8)), 0.01, fc0])
            res = least_squares(lambda p, pxx=pxx, model=model: pxx / model(p) - 1.0, p0,
                                bounds=([1e-5, 0.0, fc_lo], [1.0, 1.0, fc_hi]))
            if best is None or res.cost < best.cost:
                best = res
        assert best is not None
        axes_fit.append(_AxisSpectrum(ax, lsb, f, pxx, model, best.x, k_avg))
    # one joint fit: each axis its white noise, the three one band (the plant's model: one component for all axes),
    # which the undriven x axis pins where a driven axis keeps only the bins its drive leaves alone
    starts = np.array([a.start for a in axes_fit])
    sc0 = float(np.median(starts[:, 1]))
    fc0 = float(np.average(starts[:, 2], weights=starts[:, 1] + 1e-9))

    def joint(p: np.ndarray) -> np.ndarray:
        return np.concatenate([math.sqrt(a.k_avg) * (a.psd / a.model(np.array([p[i], p[-2], p[-1]])) - 1.0)
                               for i, a in enumerate(axes_fit)])

    n_ax = len(axes_fit)
    res = least_squares(joint, np.array([*starts[:, 0], sc0, fc0]),
                        bounds=([1e-5] * n_ax + [0.0, fc_lo], [1.0] * n_ax + [1.0, fc_hi]))
    sig = np.sqrt(np.clip(np.diag(np.linalg.pinv(res.jac.T @ res.jac)), 0.0, None))
    # each axis' white noise by its own residuals; the shared band by all of them (its 2 parameters shared out)
    bounds = np.cumsum([0] + [a.f_hz.size for a in axes_fit])
    n_bins = int(bounds[-1])
    grow = [_residual_inflation(res.fun[bounds[i]:bounds[i + 1]], a.f_hz,
                                dof=a.f_hz.size - 1.0 - 2.0 * a.f_hz.size / n_bins) for i, a in enumerate(axes_fit)]
    sig[:n_ax] *= grow
    sig[-2:] *= max(grow)
    std_c, centre = float(res.x[-2]), float(res.x[-1])
    for i, (ax, lsb, f, pxx, model, _, _) in enumerate(axes_fit):
        name = f"gyro.noise_std_dps.{ax}"
        out.append(Estimate(name, float(res.x[i]), float(sig[i]), "deg/s", "fitted",
                            f"static: PSD above {f_min_hz:g} Hz", prior=get_param(prior, name),
                            note=f"quantisation LSB {lsb:.3g} deg/s; {f.size} bins"))
        extras["psd"][ax] = {"f_hz": f, "psd": pxx, "model": model(np.array([res.x[i], std_c, centre])), "lsb": lsb}
    strong = std_c > 0.2 * min(e.value or 0.0 for e in out)
    out.append(Estimate("gyro.noise_psd.std_dps", std_c, float(sig[-2]), "deg/s", "fitted",
                        "static: PSD band component", prior=get_param(prior, "gyro.noise_psd.std_dps")))
    if strong:
        out.append(Estimate("gyro.noise_psd.centre_hz", centre, float(sig[-1]), "Hz", "fitted",
                            "static: PSD band component", prior=get_param(prior, "gyro.noise_psd.centre_hz")))
    else:
        out.append(Estimate("gyro.noise_psd.centre_hz", get_param(prior, "gyro.noise_psd.centre_hz"), None, "Hz",
                            "prior", "static: the band component is too weak to place",
                            prior=get_param(prior, "gyro.noise_psd.centre_hz")))
    # bias
    k0s = [int(settle_s / lg.dt_s) for lg in static]
    bx = float(np.mean(np.concatenate([lg.loop["gyro_x_dps"][k:] for lg, k in zip(static, k0s, strict=True)])))
    slopes = {}
    for ax, enc in (("y", "el_deg"), ("z", "az_deg")):
        vals = []
        for lg, k in zip(static, k0s, strict=True):
            t = lg.loop["t_s"][k:]
            vals.append(-float(np.polyfit(t - t[0], np.unwrap(lg.loop[enc][k:], period=360.0), 1)[0]))
        slopes[ax] = float(np.mean(vals))
    extras["bias_dps"] = [bx, slopes["y"], slopes["z"]]
    return out, extras


# --- frequency response (ident logs) ------------------------------------------------------------------------------


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


def armature_current_a(drive_counts: np.ndarray, rate_dps: np.ndarray, motor: Mapping[str, Any]) -> np.ndarray:
    """The armature current (A) a drive makes at the motor's rate, ``i = (clip(u V_count, bus) - K_e w) / R``, from
    the plant file's motor (``motor_<axis>``); the inductance's lag (L / R ~0.1 ms) left out."""
    volts = np.clip(drive_counts * motor["volts_per_count"], -motor["bus_voltage_v"], motor["bus_voltage_v"])
    return (volts - motor["back_emf_v_s_per_rad"] * np.radians(rate_dps)) / motor["resistance_ohm"]


def drive_at_current_limit(drive_counts: np.ndarray, rate_dps: np.ndarray, motor: Mapping[str, Any],
                           current_limit_a: float) -> tuple[np.ndarray, int]:
    """The drive the plant received where the driver held the current at ``current_limit_a``: on those ticks the drive
    (counts, as a float) whose current is the limit (:func:`armature_current_a` inverted), elsewhere the commanded
    one; and how many ticks were limited. The driver's limit acts inside the power stage, so the log's commanded
    drive is not the plant's input there: a few limited ticks bias an FRF of the command (hidden plant 14: 20 ticks
    at 64 Hz moved k_m by +1 % and read a 355 Hz gyro pole as a pinned 303 +- 15 Hz)."""
    i = armature_current_a(drive_counts, rate_dps, motor)
    limited = np.abs(i) > current_limit_a
    if not limited.any():
        return np.asarray(drive_counts, dtype=float), 0
    held = (np.clip(i, -current_limit_a, current_limit_a) * motor["resistance_ohm"]
            + motor["back_emf_v_s_per_rad"] * np.radians(rate_dps)) / motor["volts_per_count"]
    return np.where(limited, held, drive_counts), int(np.count_nonzero(limited))


def drive_with_ripple(drive_counts: np.ndarray, rate_dps: np.ndarray, angle_deg: np.ndarray,
                      motor: Mapping[str, Any], ripple: Mapping[str, Any]) -> np.ndarray:
    """The drive (counts, as a float) whose current makes the torque the motor made: the plant file's torque ripple
    ``K_t i (1 + a sin(N th_m))`` (docs/emulator.md, "Torque ripple"; ``th_m`` the motor-side angle the encoder
    reads) taken into the drive, ``u + a sin(N th_m) (u - K_e w / V_count)``. Over an ident sweep the axis turns a few
    ripple periods, so the loop's gain wanders by ``+-a`` with the sweep's frequency; read as the plant's, the
    wander moves the gyro's pole and the delay with it (hidden plant 54: the elevation's total delay +4.4 us over
    nine recordings)."""
    a = float(ripple.get("amplitude_fraction") or 0.0)
    u = np.asarray(drive_counts, dtype=float)
    if a == 0.0:
        return u
    n = float(ripple["periods_per_rev"])
    emf_counts = motor["back_emf_v_s_per_rad"] * np.radians(rate_dps) / motor["volts_per_count"]
    return u + a * np.sin(n * np.radians(angle_deg)) * (u - emf_counts)


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


# --- torque balance (logs with motion) ----------------------------------------------------------------------------


def specific_force_el_frame(pose: Mapping[str, np.ndarray], az_deg: np.ndarray, el_deg: np.ndarray,
                            pivot_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The specific force (m/s^2) at the gimbal's pivot in the elevation frame (seed 001 eqs 2-4): the hexapod's
    linear acceleration minus gravity through its attitude (``C_lab^body = R_x(roll) R_y(pitch) R_z(yaw)``), plus
    ``alpha x r + omega x (omega x r)`` for a pivot ``r`` off the rotation centre, then the gimbal's az, el."""
    phi, th, psi = (np.radians(pose[k]) for k in ("roll_deg", "pitch_deg", "yaw_deg"))
    phid, thd, psid = (np.radians(pose[f"{k}_rate"]) for k in ("roll_deg", "pitch_deg", "yaw_deg"))
    phidd, thdd, psidd = (np.radians(pose[f"{k}_accel"]) for k in ("roll_deg", "pitch_deg", "yaw_deg"))
    sf, cf, st, ct, sp, cp = np.sin(phi), np.cos(phi), np.sin(th), np.cos(th), np.sin(psi), np.cos(psi)
    c = np.array([[ct * cp, ct * sp, -st],
                  [sf * st * cp - cf * sp, sf * st * sp + cf * cp, sf * ct],
                  [cf * st * cp + sf * sp, cf * st * sp - sf * cp, cf * ct]])
    a_lab = np.stack([pose["x_mm_accel"] * 1e-3, pose["y_mm_accel"] * 1e-3, pose["z_mm_accel"] * 1e-3 - G0])
    f_b = np.einsum("ijn,jn->in", c, a_lab)
    if any(pivot_m):
        w = np.stack([phid - psid * st, thd * cf + psid * sf * ct, -thd * sf + psid * cf * ct])
        wd = np.stack([phidd - psidd * st - psid * thd * ct,
                       thdd * cf - thd * phid * sf + psidd * sf * ct + psid * (phid * cf * ct - thd * sf * st),
                       -thdd * sf - thd * phid * cf + psidd * cf * ct - psid * (phid * sf * ct + thd * cf * st)])
        r = np.asarray(pivot_m, dtype=float)[:, None] * np.ones_like(w)
        f_b = f_b + np.cross(wd, r, axis=0) + np.cross(w, np.cross(w, r, axis=0), axis=0)
    fbx, fby, fbz = f_b
    az, el = np.radians(az_deg), np.radians(el_deg)
    ca, sa, ce, se = np.cos(az), np.sin(az), np.cos(el), np.sin(el)
    hxy = ca * fbx + sa * fby
    return hxy * ce - fbz * se, ca * fby - sa * fbx, hxy * se + fbz * ce


@dataclass
class MechanicsFit:
    """The torque-balance fit of one axis."""

    axis: str
    coulomb_n_m: float
    stiction_n_m: float
    stribeck_rate_dps: float
    viscous_n_m_s_per_rad: float
    cable_n_m_per_rad: float
    m_rho_x_kg_mm: float | None
    m_rho_z_kg_mm: float | None
    current_limit_a: float | None  # None: not reached in these logs
    current_peak_a: float  # the largest current the logs asked for
    sigma: dict[str, float]
    rms_n_m: dict[str, float]  # per log
    n_rows: int
    traces: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # per log: t, measured, model


def _smooth(x: np.ndarray, half_width: int) -> np.ndarray:
    """Zero-phase Hann-window average over ``2 half_width + 1`` rows (compact support: a row depends only on rows
    within ``half_width``; first null at ``2 / ((2 half_width + 1) dt)``, sidelobes -31 dB)."""
    from scipy.ndimage import convolve1d  # noqa: PLC0415  (heavy: loaded only when this computation runs)

    w = np.hanning(2 * half_width + 3)[1:-1]
    return convolve1d(x, w / w.sum(), axis=0, mode="nearest")


def _gyro_lag(x: np.ndarray, bandwidth_hz: float, delay_s: float, dt: float) -> np.ndarray:
    """The gyro's first-order lag and delay (seed 000 eq 3) applied to a regressor sampled every tick."""
    from scipy.signal import lfilter  # noqa: PLC0415  (heavy: loaded only when this computation runs)

    a = math.exp(-2.0 * math.pi * bandwidth_hz * dt)
    y = lfilter([1.0 - a], [1.0, -a], x, axis=0)
    shift = delay_s / dt
    n = np.arange(x.shape[0], dtype=float)
    if y.ndim == 1:
        return np.interp(n - shift, n, y)
    return np.stack([np.interp(n - shift, n, y[:, j]) for j in range(y.shape[1])], axis=1)


def fit_mechanics(logs: list[FitLog], axis: str, plant: Mapping[str, Any], *, bandwidth_hz: float,
                  delay_s: float, smooth_ms: int = 10, settle_s: float = 1.0, stick_dps: float = 0.1,
                  fixed: Mapping[str, float] | None = None) -> MechanicsFit:
    """Equation-error fit of the torque balance of one axis over every log with motion (docs/fit.md).

    Left: ``J dw/dt`` from the gyro (J from the plant's k_m, which the ident fit has set). Right, per tick k (the
    drive of row k acts over the tick that ends at row k + 1): ``K_t clip(i, I_max)`` with
    ``i = (clip(u V_count, bus) - K_e v) / R``; friction ``T_c sgn v + (T_s - T_c) sgn v exp(-(v/v_s)^2) + D v``
    (LuGre's steady state); cable ``k_c theta``; for elevation the imbalance ``-m (rho_z f_x - rho_x f_z)``.
    v and theta are the encoder's (motor side). The right side goes through the gyro's lag and delay, both sides
    through the same zero-phase Hann average (+-``smooth_ms``: nulls the structural modes); rows whose average
    reaches a stick (|v| < ``stick_dps``, where friction is the unknown holding torque) are left out. ``fixed``
    holds coefficients (``cable_n_m_per_rad``, ``m_rho_z_kg_mm``) at given values instead of fitting them."""
    m = plant[f"motor_{axis}"]
    kt = m["torque_constant_n_m_per_a"]
    j_kg_m2 = m["inertia_kg_m2"]
    use = [lg for lg in logs if lg.kind in ("swing", "ident")]
    if not use:
        raise FitInputError("no swing or ident log: friction, cable and imbalance need motion")
    blocks = []
    for lg in use:
        dt = lg.dt_s
        k0, k1 = int(settle_s / dt), lg.loop["t_s"].size - 1
        theta_deg = np.unwrap(lg.loop[f"{axis}_deg"], period=360.0)
        from scipy.signal import savgol_filter  # noqa: PLC0415  (heavy: loaded only when this computation runs)

        v_dps = savgol_filter(theta_deg, 9, 2, deriv=1, delta=dt)
        v_mid = 0.5 * (v_dps[:-1] + v_dps[1:])  # over the tick k -> k + 1
        th_mid = np.radians(0.5 * (theta_deg[:-1] + theta_deg[1:]))
        i_cmd = armature_current_a(lg.loop[f"drive_{axis}_counts"][:-1], v_mid, m)
        g = lg.gyro(axis)
        half = max(1, round(smooth_ms * 1e-3 / dt))
        acc = np.radians(np.diff(_smooth(g, half))) / dt  # rad/s^2 over the tick k -> k + 1
        pivot = tuple((plant.get("mount") or {}).get("pivot_offset_m") or (0.0, 0.0, 0.0))
        fx, _, fz = specific_force_el_frame(lg.pose, lg.loop["az_deg"], lg.loop["el_deg"], pivot)  # type: ignore[arg-type]
        fx, fz = 0.5 * (fx[:-1] + fx[1:]), 0.5 * (fz[:-1] + fz[1:])
        stick = np.abs(v_mid) < stick_dps
        pad = half + 2
        bad = np.convolve(stick.astype(float), np.ones(2 * pad + 1), mode="same") > 0
        bad[: k0] = True
        bad[k1 - pad:] = True
        tick = lg.loop["tick"]
        gaps = np.flatnonzero(np.diff(tick) != 1)
        for gi in gaps:
            bad[max(0, gi - pad): gi + pad + 1] = True
        blocks.append(dict(log=lg.name, dt=dt, half=half, v=v_mid, th=th_mid, i=i_cmd, lhs=j_kg_m2 * acc, fx=fx, fz=fz,
                           keep=~bad, t=lg.loop["t_s"][:-1]))
    i_peak = float(max(np.max(np.abs(b["i"][b["keep"]])) if b["keep"].any() else 0.0 for b in blocks))
    limits: list[float | None] = [None]
    limits += [float(x) for x in np.geomspace(0.35 * i_peak, 0.98 * i_peak, 12)] if i_peak > 0 else []
    vs_grid = np.geomspace(2.0 * stick_dps, 2.0, 9)  # a Stribeck rate inside the stick band cannot be seen
    with_imb = axis == "el"
    order = ["coulomb_n_m", "stribeck_n_m", "viscous_n_m_s_per_rad", "cable_n_m_per_rad"]
    order += ["m_rho_z_kg_mm", "m_rho_x_kg_mm"] if with_imb else []
    held = {order.index(k): float(v) for k, v in (fixed or {}).items() if k in order}

    def filt(b: dict[str, Any], cols: list[np.ndarray]) -> np.ndarray:
        return _smooth(_gyro_lag(np.stack(cols, axis=1), bandwidth_hz, delay_s, b["dt"]), b["half"])

    for b in blocks:  # the columns that do not depend on the grid, filtered once
        b["sgn"] = np.tanh(b["v"] / 0.02)
        fixed = [-b["sgn"], -np.radians(b["v"]), -b["th"]]
        if with_imb:
            fixed += [-b["fx"] * 1e-3, b["fz"] * 1e-3]  # coefficients m rho_z, m rho_x in kg mm
        b["fixed"] = filt(b, fixed)
        b["motor"] = {}

    def design(b: dict[str, Any], vs: float, limit: float | None) -> tuple[np.ndarray, np.ndarray]:
        if limit not in b["motor"]:
            i = b["i"] if limit is None else np.clip(b["i"], -limit, limit)
            b["motor"][limit] = filt(b, [kt * i])[:, 0]
        stribeck = filt(b, [-b["sgn"] * np.exp(-(b["v"] / vs) ** 2)])[:, 0]
        f = b["fixed"]
        x = np.column_stack([b["motor"][limit], f[:, 0], stribeck, f[:, 1:]])
        return x, b["lhs"]

    best: tuple[float, float, float | None, np.ndarray, np.ndarray, np.ndarray] | None = None
    cache: dict[tuple[float, float | None], tuple[np.ndarray, np.ndarray]] = {}

    def evaluate(vs: float, limit: float | None) -> tuple[float, float, float | None, np.ndarray, np.ndarray,
                                                          np.ndarray]:
        xs, ys = [], []
        for b in blocks:
            x, y = design(b, vs, limit)
            xs.append(x[b["keep"]])
            ys.append(y[b["keep"]])
        x_all, y_all = np.concatenate(xs), np.concatenate(ys)
        y_adj = y_all - x_all[:, 0]  # the motor torque is known: coefficient 1
        coef = _lstsq_fixed(x_all[:, 1:], y_adj, held)
        cache[(vs, limit)] = (x_all, y_adj)
        return float(np.sum((y_adj - x_all[:, 1:] @ coef) ** 2)), vs, limit, coef, x_all, y_adj

    for limit in limits:
        for vs in vs_grid:
            trial = evaluate(float(vs), limit)
            if best is None or trial[0] < best[0]:
                best = trial
    assert best is not None
    if best[2] is not None:  # the grid's limits are ~10 % apart: refine between the best one's neighbours
        from scipy.optimize import minimize_scalar  # noqa: PLC0415  (heavy: loaded only when this computation runs)

        grid = [lim for lim in limits if lim is not None]
        at = grid.index(best[2])
        lo, hi = grid[max(0, at - 1)], grid[at + 1] if at + 1 < len(grid) else 0.999 * i_peak
        vs_best = best[1]
        found = minimize_scalar(lambda lim: evaluate(vs_best, float(lim))[0], bounds=(lo, hi), method="bounded",
                                options={"xatol": 1e-3 * best[2]})
        refined = evaluate(vs_best, float(found.x))
        if refined[0] < best[0]:
            best = refined
    sse, vs, limit, coef, x_all, y_adj = best
    # a limit counts only if it explains the data better than none by more than noise would (F-test-like, 1 %)
    sse_none = min(float(np.sum((yn - xn[:, 1:] @ _lstsq_fixed(xn[:, 1:], yn, held)) ** 2))
                   for xn, yn in (cache[(float(v), None)] for v in vs_grid))
    clipped = (float(np.mean(np.concatenate([np.abs(b["i"][b["keep"]]) > limit for b in blocks])))
               if limit is not None else 0.0)
    if limit is not None and (sse > 0.98 * sse_none or clipped < 0.005):
        limit = None  # a limit counts where saturation episodes (>= 0.5 % of rows) explain the data (2 % less residual)
        sse, vs, coef = min(((float(np.sum((yn - xn[:, 1:] @ c) ** 2)), float(v), c)
                             for v in vs_grid for xn, yn in [cache[(float(v), None)]]
                             for c in [_lstsq_fixed(xn[:, 1:], yn, held)]), key=lambda t: t[0])
        x_all, y_adj = cache[(vs, None)]
    n = y_adj.size
    n_eff = max(10.0, n / blocks[0]["half"])  # the average leaves ~1 independent row per half width
    s2 = sse / max(1.0, n - coef.size)
    free = [j for j in range(coef.size) if j not in held]
    sd = np.zeros(coef.size)
    cov = np.linalg.pinv(x_all[:, 1:][:, free].T @ x_all[:, 1:][:, free]) * s2 * (n / n_eff)
    sd[free] = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    tc, dts, visc, kc = (float(c) for c in coef[:4])
    rms: dict[str, float] = {}
    traces: dict[str, dict[str, np.ndarray]] = {}
    for b in blocks:
        x, y = design(b, vs, limit)
        pred = x[:, 0] + x[:, 1:] @ coef
        k = b["keep"]
        rms[b["log"]] = float(np.sqrt(np.mean((y[k] - pred[k]) ** 2))) if k.any() else float("nan")
        traces[b["log"]] = {"t_s": b["t"], "measured_n_m": y, "model_n_m": pred, "kept": k}
    return MechanicsFit(
        axis=axis, coulomb_n_m=tc, stiction_n_m=tc + dts, stribeck_rate_dps=vs, viscous_n_m_s_per_rad=visc,
        cable_n_m_per_rad=kc,
        m_rho_z_kg_mm=float(coef[4]) if with_imb else None, m_rho_x_kg_mm=float(coef[5]) if with_imb else None,
        current_limit_a=limit, current_peak_a=i_peak,
        sigma={"coulomb_n_m": float(sd[0]), "stiction_n_m": float(math.hypot(sd[0], sd[1])),
               "viscous_n_m_s_per_rad": float(sd[2]), "cable_n_m_per_rad": float(sd[3]),
               **({"m_rho_z_kg_mm": float(sd[4]), "m_rho_x_kg_mm": float(sd[5])} if with_imb else {})},
        rms_n_m=rms, n_rows=n, traces=traces,
    )


def _lstsq_fixed(x: np.ndarray, y: np.ndarray, held: Mapping[int, float]) -> np.ndarray:
    """Least squares with the columns in ``held`` at given coefficients."""
    coef = np.zeros(x.shape[1])
    free = [j for j in range(x.shape[1]) if j not in held]
    y2 = y - sum((x[:, j] * v for j, v in held.items()), np.zeros_like(y))
    coef[free] = np.linalg.lstsq(x[:, free], y2, rcond=None)[0]
    for j, v in held.items():
        coef[j] = v
    return coef


# --- the whole fit ------------------------------------------------------------------------------------------------


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


def grade(estimates: list[Estimate]) -> list[Estimate]:
    """A fitted value whose 1-sigma is wider than its target accuracy (:meth:`ParamRange.tolerance`) is ``weak``, never
    ``fitted``; a weak value and a prior kept for want of a log name the recording that would resolve them."""
    return [_graded(e) for e in estimates]


def _graded(e: Estimate) -> Estimate:
    rng = param_range(e.name)
    if rng is not None and e.status == "fitted" and e.value is not None and e.sigma is not None:
        tol = rng.tolerance(e.value)
        if tol is not None and e.sigma > tol:
            return replace(e, status="weak", note=f"1 sigma {e.sigma:.3g} is wider than the target {tol:.3g} "
                           f"{e.unit}; record {rng.resolved_by or 'more of the logs above'}")
    elif rng is not None and e.status == "prior" and rng.resolved_by and "record" not in e.note:
        return replace(e, note="; ".join(x for x in (e.note, f"record {rng.resolved_by}") if x))
    return e


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


__all__ = ["Estimate", "FrfFit", "MechanicsFit", "TwinFit", "fit_frequency_response", "fit_logs", "fit_mechanics",
           "fit_noise"]
