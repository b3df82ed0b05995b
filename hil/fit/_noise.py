"""The gyro's white noise, band-limited component and bias from the static logs (:func:`fit_noise`)."""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from hil.fit._estimates import Estimate, _unit
from hil.fit._frf import linear_plant_frf
from hil.fit.logs import FitLog
from hil.fit.ranges import get_param

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
