"""The torque balance of the logs with motion: friction, cable, current limit, imbalance (:func:`fit_mechanics`)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil.fit._motor import armature_current_a
from hil.fit.logs import FitInputError, FitLog

D2R = math.pi / 180.0
G0 = 9.80665


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
        fx, _, fz = specific_force_el_frame(lg.pose, lg.loop["az_deg"], lg.loop["el_deg"], pivot)
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
        cols = [-b["sgn"], -np.radians(b["v"]), -b["th"]]
        if with_imb:
            cols += [-b["fx"] * 1e-3, b["fz"] * 1e-3]  # coefficients m rho_z, m rho_x in kg mm
        b["fixed"] = filt(b, cols)
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
