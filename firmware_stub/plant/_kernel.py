"""The plant's numba kernel (``@numba.njit(cache=True)``): one tick (``kernel``) or many (``_run``) over float64
arrays of parameters (``P_*``/``PA_*`` offsets) and state (``S_*``), laid out by ``pack_params``. One implementation for
every clock: the emulator, the in-process sim clock and offline runs all call it.

One job: the jitted functions of one tick, which call each other. numba's on-disk cache checks only the source of
the file a function is in, so a jitted helper moved into another module could change without recompiling the
kernels that inline it; keeping them in one file keeps the cache honest."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Literal, TypedDict, cast

import llvmlite.ir as llvm_ir  # type: ignore[import-untyped]  # llvmlite ships no type information
import numba
import numpy as np
from numba import types as nbt
from numba.extending import intrinsic

from firmware_stub.plant._config import (
    D2R,
    G0_M_S2,
    R2D,
    TICK_S,
    FrictionAxisConfig,
    MotorConfig,
    PlantConfig,
)
from firmware_stub.plant._math import axis_zoh, band_pass, foh

NOISE_WHITE = 5  # per tick: gyro x, y, z (bias + noise, output units), camera x, y (px)
NOISE_BLOCK_TICKS = 1000
_ROUND = 6755399441055744.0  # 1.5 * 2^52: (x + _ROUND) - _ROUND is x rounded to the nearest integer (|x| < 2^51)
MAX_BANDS = 8

# --- layout of the parameter array p (float64) ----------------------------------------------------------------------
# per axis (az at 0, el at PA_LEN):
PA_PHI = 0  # 25: Phi, row-major 5 x 5
PA_GAM = 25  # 20: Gamma, row-major 5 x 4 (inputs V, c, T_m, T_l)
(PA_VPC, PA_VMAX, PA_FMODEL, PA_TC, PA_IWS, PA_TS, PA_IVS, PA_S0, PA_S1, PA_ILIM, PA_R, PA_KE, PA_RIPA, PA_RIPN,
 PA_D, PA_KC, PA_CC, PA_KS, PA_CS, PA_S1H) = range(45, 65)
PA_LEN = 65
# global
(P_NSUB, P_H, P_MRX, P_MRY, P_MRZ, P_HAS_IMB, P_PVX, P_PVY, P_PVZ, P_HAS_PIV, P_EF, P_C1, P_C0, P_EA, P_D1, P_D0,
 P_DELAY, P_LSB, P_INV_LSB, P_ENC_LSB, P_NCOL, P_RW, P_STRIDE, P_TGX, P_TGY, P_TGZ, P_IFOV, P_HW, P_HH) = range(
    2 * PA_LEN, 2 * PA_LEN + 29)
P_COL = 2 * PA_LEN + 29  # MAX_BANDS x (b0 in output units per unit normal, a1, a2)
P_LEN = P_COL + 3 * MAX_BANDS

# --- layout of the state array s (float64) --------------------------------------------------------------------------
S_X = 0  # 10: per axis (i, w_m, theta_m, w_l, theta_l); az at 0, el at 5
S_Z = 10  # 2: LuGre bristle deflection z (rad)
S_V = 12  # 2: armature voltage applied over the last sub-step
S_TF = 14  # 2: friction torque held over the last sub-step (opposing motion)
S_SC = 16  # 4: sin, cos of the load's az, sin, cos of the load's el, at the tick end
S_G = 20  # 3: gyro filter state (output units)
S_XO = 23  # 3: the filter's input at the previous tick end (rad/s)
S_M = 26  # 3: gyro outputs (deg/s)
S_TICK, S_NK, S_RINGJ, S_REFILL = 29, 30, 31, 32
S_CAMN = 33  # 2: this tick's camera noise (px)
S_CARR = 35  # 18: the last tick's carrier (pose, rate, accel)
S_HASC = 53  # 1 once a tick ran
S_RW = 54  # 3: random-walk part of the gyro bias (output units)
S_IMB = 57  # 2: imbalance torque held over the last tick (az, el)
S_LOS = 59  # 3: true elevation-frame inertial rates at the tick end (rad/s)
S_ATT = 62  # 4: sin, cos of the carrier's roll and pitch at the last mid-tick
S_RIP = 66  # 4: sin, cos of N theta_m (ripple phase), az then el
S_U = 70  # 2: the drive (DAC counts, az, el) held at the end of the last tick
S_COL = 72  # MAX_BANDS x 3 axes x (e1, e2, y1, y2) of the coloured-noise filters
S_RING = S_COL + 4 * 3 * MAX_BANDS  # 3 x delay_ticks: the gyro's whole-tick delay line

OUT_LEN = 8  # step_tick's tuple: gyro x, y, z (deg/s), encoders az, el (deg), currents az, el (A), refill flag


def pack_params(cfg: PlantConfig) -> np.ndarray:
    """Every constant of the kernel, in the layout above."""
    p = np.zeros(P_LEN)
    h = cfg.internal_step_s
    for ax, axis in enumerate(("az", "el")):
        b = ax * PA_LEN
        phi, gam = axis_zoh(cfg, axis, h)  # type: ignore[arg-type]
        p[b + PA_PHI: b + PA_PHI + 25] = phi.ravel()
        p[b + PA_GAM: b + PA_GAM + 20] = gam.ravel()
        m: MotorConfig = getattr(cfg, f"motor_{axis}")
        fr: FrictionAxisConfig = getattr(cfg.friction, axis)
        p[b + PA_VPC], p[b + PA_VMAX] = m.volts_per_count, m.bus_voltage_v
        p[b + PA_TC], p[b + PA_IWS] = fr.coulomb_n_m, 1.0 / (fr.smoothing_rate_dps * D2R)
        p[b + PA_D] = fr.viscous_n_m_s_per_rad
        if fr.model == "lugre":
            assert fr.stiction_n_m is not None and fr.stribeck_rate_dps is not None
            p[b + PA_FMODEL] = 1.0
            p[b + PA_TS], p[b + PA_IVS] = fr.stiction_n_m, 1.0 / (fr.stribeck_rate_dps * D2R)
            p[b + PA_S0] = fr.bristle_stiffness_n_m_per_rad or 0.0
            p[b + PA_S1] = fr.bristle_damping_n_m_s_per_rad or 0.0
            p[b + PA_S1H] = p[b + PA_S1] / h
        p[b + PA_ILIM] = cfg.current_limit_a(axis) or 0.0  # type: ignore[arg-type]
        p[b + PA_R], p[b + PA_KE] = m.resistance_ohm, m.back_emf_v_s_per_rad
        rip = cfg.ripple_of(axis)  # type: ignore[arg-type]
        if rip is not None:
            p[b + PA_RIPA], p[b + PA_RIPN] = rip.amplitude_fraction * m.torque_constant_n_m_per_a, rip.periods_per_rev
        cab = cfg.cable_of(axis)  # type: ignore[arg-type]
        if cab is not None:
            p[b + PA_KC], p[b + PA_CC] = cab.stiffness_n_m_per_rad, cab.damping_n_m_s_per_rad
        st = cfg.structure_of(axis)  # type: ignore[arg-type]
        if st is not None:
            j = m.inertia_kg_m2
            mu = st.motor_inertia_fraction * (1.0 - st.motor_inertia_fraction) * j
            wr = 2.0 * math.pi * st.mode_hz
            p[b + PA_KS], p[b + PA_CS] = wr * wr * mu, 2.0 * st.damping_ratio * wr * mu
    p[P_NSUB], p[P_H] = round(TICK_S / h), h
    mass = cfg.imbalance.mass_kg
    mr = [mass * x * 1e-3 for x in cfg.imbalance.eccentricity_mm]
    p[P_MRX], p[P_MRY], p[P_MRZ] = mr
    p[P_HAS_IMB] = 1.0 if mass > 0.0 and any(mr) else 0.0
    piv = cfg.pivot_offset_m()
    p[P_PVX], p[P_PVY], p[P_PVZ] = piv
    p[P_HAS_PIV] = 1.0 if any(piv) else 0.0
    g = cfg.gyro
    wc = 2.0 * math.pi * g.bandwidth_hz
    ef, c1, c0 = foh(wc, TICK_S, g.scale_factor)  # filter state, tick end to tick end
    delay_ticks = int(g.delay_s / TICK_S + 1e-9)
    tau_r = g.delay_s - delay_ticks * TICK_S  # the rest of the delay, within one tick
    alpha = TICK_S - tau_r if tau_r > 1e-12 else TICK_S
    ea, c1a, c0a = foh(wc, alpha, g.scale_factor)
    fa = alpha / TICK_S  # the input at t0 + alpha, linearly interpolated
    d1, d0 = c1a * fa, c1a * (1.0 - fa) + c0a  # y(alpha) = ea y0 + d1 x1 + d0 x0
    # the filter, the delay ring and the noise work in the output's unit: gyro LSBs (deg/s if not quantised)
    lsb = g.quantisation_lsb_dps
    inv_lsb = 1.0 / lsb if lsb > 0 else 0.0
    per_rad_s = R2D * inv_lsb if lsb > 0 else R2D
    unit = lsb or 1.0
    p[P_EF], p[P_C1], p[P_C0] = ef, c1 * per_rad_s, c0 * per_rad_s
    p[P_EA], p[P_D1], p[P_D0] = ea, d1 * per_rad_s, d0 * per_rad_s
    p[P_DELAY], p[P_LSB], p[P_INV_LSB] = delay_ticks, lsb, inv_lsb
    p[P_ENC_LSB] = 360.0 / cfg.encoder.counts_per_rev
    bands = [b for b in g.noise_psd if b.std_dps > 0.0]
    p[P_NCOL] = len(bands)
    for k, band in enumerate(bands):
        b0, a1, a2, var = band_pass(band.centre_hz, band.bandwidth_hz)
        p[P_COL + 3 * k: P_COL + 3 * k + 3] = (b0 * band.std_dps / math.sqrt(var) / unit, a1, a2)
    p[P_RW] = g.random_walk * math.sqrt(TICK_S) / unit
    p[P_STRIDE] = NOISE_WHITE + 3 * len(bands) + (3 if g.random_walk > 0 else 0)
    cam = cfg.camera
    taz, tel = cam.target_az_deg * D2R, cam.target_el_deg * D2R
    p[P_TGX], p[P_TGY], p[P_TGZ] = math.cos(tel) * math.cos(taz), math.cos(tel) * math.sin(taz), -math.sin(tel)
    p[P_IFOV], p[P_HW], p[P_HH] = cam.ifov_deg_per_px, cam.half_width_px, cam.half_height_px
    return p


_HALF = 0.5 * TICK_S


class _JitOptions(TypedDict, total=False):
    """The keyword options given to ``numba.njit`` here (the subset of its options this module uses)."""

    cache: bool
    error_model: Literal["python", "numpy"]
    inline: Literal["never", "always"]


_JIT: _JitOptions = {"cache": True, "error_model": "numpy"}  # (no nogil: releasing the GIL costs ~0.2 us per call)
_INLINE: _JitOptions = {**_JIT, "inline": "always"}  # small helpers, inlined into their callers at numba's IR level


@numba.njit(**_INLINE)
def _carrier(p, pose, rate, acc):
    """Body rates (p, q, r) and derivatives at the carrier's instant, and the specific force at the gimbal's pivot in
    the body frame: ``f_c + alpha x r + omega x (omega x r)`` (seed 001 eqs 2-4; r = mount.pivot_offset_m); and the
    sin and cos of roll and pitch."""
    ph, th, ps = pose[3] * D2R, pose[4] * D2R, pose[5] * D2R
    phd, thd, psd = rate[3] * D2R, rate[4] * D2R, rate[5] * D2R
    phdd, thdd, psdd = acc[3] * D2R, acc[4] * D2R, acc[5] * D2R
    sf, cf, st, ct = math.sin(ph), math.cos(ph), math.sin(th), math.cos(th)
    pc = psd * ct
    pr = phd - psd * st
    qr = thd * cf + pc * sf
    rr = pc * cf - thd * sf
    pd = phdd - psdd * st - thd * pc
    qd = thdd * cf - thd * phd * sf + psdd * sf * ct + psd * (phd * cf * ct - thd * sf * st)
    rd = -thdd * sf - thd * phd * cf + psdd * cf * ct - psd * (phd * sf * ct + thd * cf * st)
    fz = acc[2] * 1e-3 - G0_M_S2
    if acc[0] != 0.0 or acc[1] != 0.0:
        sp, cp = math.sin(ps), math.cos(ps)
        fx, fy = acc[0] * 1e-3, acc[1] * 1e-3
        fbx = ct * cp * fx + ct * sp * fy - st * fz
        fby = (sf * st * cp - cf * sp) * fx + (sf * st * sp + cf * cp) * fy + sf * ct * fz
        fbz = (cf * st * cp + sf * sp) * fx + (cf * st * sp - sf * cp) * fy + cf * ct * fz
    else:
        fbx, fby, fbz = -st * fz, sf * ct * fz, cf * ct * fz
    if p[P_HAS_PIV] != 0.0:
        rx, ry, rz = p[P_PVX], p[P_PVY], p[P_PVZ]
        wxr_x, wxr_y, wxr_z = qr * rz - rr * ry, rr * rx - pr * rz, pr * ry - qr * rx  # omega x r
        fbx += qd * rz - rd * ry + qr * wxr_z - rr * wxr_y
        fby += rd * rx - pd * rz + rr * wxr_x - pr * wxr_z
        fbz += pd * ry - qd * rx + pr * wxr_y - qr * wxr_x
    return pr, qr, rr, pd, qd, rd, fbx, fby, fbz, sf, cf, st, ct


@numba.njit(**_INLINE)
def _imbalance(p, fbx, fby, fbz, sa, ca, se, ce):  # noqa: PLR0917
    """``-m rho x f`` with f (body) in the elevation frame (seed 001 eqs 3-4): torques about z_o and y_e."""
    mrx, mry, mrz = p[P_MRX], p[P_MRY], p[P_MRZ]
    hxy = ca * fbx + sa * fby
    fx = hxy * ce - fbz * se
    fy = ca * fby - sa * fbx
    fz = hxy * se + fbz * ce
    tix = mrz * fy - mry * fz
    tim_e = mrx * fz - mrz * fx
    tim_a = ce * (mry * fx - mrx * fy) - se * tix
    return tim_a, tim_e


@intrinsic
def _vdiv_lanes(typingctx, num, den):
    """``num[j] / den[j]`` for two tuples of n float64 as one LLVM vector division: IEEE division in each lane (the
    same quotient as ``num[j] / den[j]``, bit for bit), but the CPU divides 2 or 4 lanes in about the time of one
    (division is the slowest arithmetic and the Taylor series below need six per angle)."""
    if not (isinstance(num, nbt.UniTuple) and isinstance(den, nbt.UniTuple) and num.count == den.count
            and num.dtype == nbt.float64 and den.dtype == nbt.float64):
        return None
    n = num.count

    def codegen(context, builder, signature, args):
        vec = llvm_ir.VectorType(llvm_ir.DoubleType(), n)
        lanes = [llvm_ir.Constant(llvm_ir.IntType(32), j) for j in range(n)]
        a = b = llvm_ir.Constant(vec, llvm_ir.Undefined)
        for j in range(n):
            a = builder.insert_element(a, builder.extract_value(args[0], j), lanes[j])
            b = builder.insert_element(b, builder.extract_value(args[1], j), lanes[j])
        q = builder.fdiv(a, b)  # no fast-math flags: IEEE, correctly rounded per lane
        return context.make_tuple(builder, signature.return_type, [builder.extract_element(q, x) for x in lanes])

    return num(num, den), codegen


# how jitted code calls it: numba's stub types an intrinsic's call as its typer's (typingctx first) returning Never
_vdiv = cast("Callable[[tuple[float, ...], tuple[float, ...]], tuple[float, ...]]", _vdiv_lanes)

_TAYLOR_DEN = (6.0, 20.0, 42.0, 12.0, 30.0, 56.0)  # the divisors of the sin / cos Taylor series in _rotated


@numba.njit(**_INLINE)
def _rotated(sa, ca, d, q):
    """sin and cos of ``a + d`` from those of ``a``, with ``q = d^2 / _TAYLOR_DEN`` (see :func:`_rotate`)."""
    if abs(d) < 0.1:
        d2 = d * d
        sd = d * (1.0 - q[0] * (1.0 - q[1] * (1.0 - q[2])))  # d (1 - d^2/6 (1 - d^2/20 (1 - d^2/42)))
        cd = 1.0 - d2 / 2.0 * (1.0 - q[3] * (1.0 - q[4] * (1.0 - q[5])))  # 1 - d^2/2 (1 - d^2/12 (...))
    else:
        sd, cd = math.sin(d), math.cos(d)
    return sa * cd + ca * sd, ca * cd - sa * sd


@numba.njit(**_INLINE)
def _rotate(sa, ca, d):
    """sin and cos of ``a + d`` from those of ``a``: Taylor series of sin d and cos d to 7th / 8th order for
    |d| < 0.1 (error < 3e-15), libm above."""
    d2 = d * d
    return _rotated(sa, ca, d, _vdiv((d2, d2, d2, d2, d2, d2), _TAYLOR_DEN))


@numba.njit(**_INLINE)
def _rotate2(sa, ca, da, sb, cb, db):  # noqa: PLR0917
    """:func:`_rotate` of two angles, their 12 divisions as one vector division."""
    a2, b2 = da * da, db * db
    q = _vdiv((a2, a2, a2, a2, a2, a2, b2, b2, b2, b2, b2, b2), _TAYLOR_DEN + _TAYLOR_DEN)
    sa, ca = _rotated(sa, ca, da, q[0:6])
    sb, cb = _rotated(sb, cb, db, q[6:12])
    return sa, ca, sb, cb


@numba.njit(**_INLINE)
def _renorm(sa, ca):
    """(sin, cos) pulled back onto the unit circle: one Newton step of 1 / sqrt(s^2 + c^2) (they drift by rounding
    only, ~1e-16 per rotation)."""
    k = 0.5 * (3.0 - (sa * sa + ca * ca))
    return sa * k, ca * k


@numba.njit(**_INLINE)
def _tanh(x):
    """tanh as ``1 - 2 / (e^{2x} + 1)``: absolute error < 3e-16, 2.5x faster than libm's tanh here."""
    return 1.0 - 2.0 / (math.exp(2.0 * x) + 1.0)


@numba.njit(**_INLINE)
def _held(p, b, v, c, tl):
    """The part of one sub-step's update that is held over the tick: ``Gamma (V, c, ., T_l)``."""
    g = b + PA_GAM
    return (p[g] * v + p[g + 1] * c + p[g + 3] * tl, p[g + 4] * v + p[g + 5] * c + p[g + 7] * tl,
            p[g + 8] * v + p[g + 9] * c + p[g + 11] * tl, p[g + 12] * v + p[g + 13] * c + p[g + 15] * tl,
            p[g + 16] * v + p[g + 17] * c + p[g + 19] * tl)


@numba.njit(**_INLINE)
def _lugre_z(p, b, vr, z, e):
    """LuGre's bristle deflection z over one sub-step, implicit (stable for any step; z -> g(v) / sigma_0 when
    sliding): ``z+ = (z + h v) / (1 + h sigma_0 |v| / g(v))``, ``g(v) = T_c + (T_s - T_c) exp(-(v / v_s)^2)``; ``e`` is
    that exponential. Returns the numerator and denominator of ``z+ = g (z + h v) / (g + h sigma_0 |v|)``."""
    tc = p[b + PA_TC]
    gv = tc + (p[b + PA_TS] - tc) * e
    return gv * (z + p[P_H] * vr), gv + p[P_H] * p[b + PA_S0] * abs(vr)


@numba.njit(**_INLINE)
def _lugre_torque(p, b, z, zn):
    """LuGre's friction torque over a sub-step: ``sigma_0 z+ + sigma_1 dz/dt``, ``dz/dt = (z+ - z) / h``."""
    return p[b + PA_S0] * zn + p[b + PA_S1H] * (zn - z)


@numba.njit(**_INLINE)
def _friction(p, b, vr, z):
    """Friction torque held over one sub-step (opposing the motor-side relative rate ``vr``) and LuGre's z at its
    end: LuGre, or ``T_c tanh(vr / w_s)`` (the viscous part is in the ZOH matrices)."""
    tc = p[b + PA_TC]
    if p[b + PA_FMODEL] != 0.0:
        u = vr * p[b + PA_IVS]
        num, den = _lugre_z(p, b, vr, z, math.exp(-u * u))
        zn = num / den
        return _lugre_torque(p, b, z, zn), zn
    if tc != 0.0:
        return tc * _tanh(vr * p[b + PA_IWS]), z
    return 0.0, z


@numba.njit(**_INLINE)
def _friction2(p, lugre2, vra, za, vre, ze):  # noqa: PLR0917
    """:func:`_friction` of both axes. With LuGre on both (``lugre2``) the two libm ``exp`` calls are made next to
    each other: a call clobbers every floating-point register, so the values live across it are spilled to the stack
    and reloaded, once per sub-step instead of twice. (Doing the same for tanh friction measured slower.)"""
    if lugre2:
        ua, ue = vra * p[PA_IVS], vre * p[PA_LEN + PA_IVS]
        ea = math.exp(-ua * ua)
        ee = math.exp(-ue * ue)
        na, da = _lugre_z(p, 0, vra, za, ea)
        ne, de = _lugre_z(p, PA_LEN, vre, ze, ee)
        zna, zne = na / da, ne / de
        return _lugre_torque(p, 0, za, zna), zna, _lugre_torque(p, PA_LEN, ze, zne), zne
    tfa, za = _friction(p, 0, vra, za)
    tfe, ze = _friction(p, PA_LEN, vre, ze)
    return tfa, za, tfe, ze


@numba.njit(**_INLINE)
def _zoh(p, b, x, k, tm, v, vr):  # noqa: PLR0917
    """One exact-ZOH sub-step of one axis (parameters at ``b``): ``x+ = Phi x + k + Gamma_m T_m`` with the motor-side
    torque ``T_m`` (friction, ripple) held over the sub-step and the current limit as a fast current loop. Returns
    ``(x+, applied voltage)``."""
    x0, x1, x2, x3, x4 = x
    f = b + PA_PHI
    g = b + PA_GAM
    # sums as trees (the compiler may not reassociate): the dependency chain between sub-steps is 4 adds deep, not 7
    n0 = ((p[f] * x0 + p[f + 1] * x1) + (p[f + 2] * x2 + p[f + 3] * x3)) + ((p[f + 4] * x4 + k[0]) + p[g + 2] * tm)
    n1 = ((p[f + 5] * x0 + p[f + 6] * x1) + (p[f + 7] * x2 + p[f + 8] * x3)) + ((p[f + 9] * x4 + k[1])
                                                                               + p[g + 6] * tm)
    n2 = ((p[f + 10] * x0 + p[f + 11] * x1) + (p[f + 12] * x2 + p[f + 13] * x3)) + ((p[f + 14] * x4 + k[2])
                                                                                 + p[g + 10] * tm)
    n3 = ((p[f + 15] * x0 + p[f + 16] * x1) + (p[f + 17] * x2 + p[f + 18] * x3)) + ((p[f + 19] * x4 + k[3])
                                                                                 + p[g + 14] * tm)
    n4 = ((p[f + 20] * x0 + p[f + 21] * x1) + (p[f + 22] * x2 + p[f + 23] * x3)) + ((p[f + 24] * x4 + k[4])
                                                                                 + p[g + 18] * tm)
    va = v
    ilim = p[b + PA_ILIM]
    if ilim > 0.0 and abs(n0) > ilim:
        # the driver's current loop: this sub-step again with the voltage that holds di/dt = 0 at the limit (within
        # the bus), the current clipped to the limit
        sg = 1.0 if n0 > 0.0 else -1.0
        vmax = p[b + PA_VMAX]
        va = min(max(sg * p[b + PA_R] * ilim + p[b + PA_KE] * vr, -vmax), vmax)  # V = R i + K_e v at i = +-I
        dv = va - v
        n0 += p[g] * dv
        n1 += p[g + 4] * dv
        n2 += p[g + 8] * dv
        n3 += p[g + 12] * dv
        n4 += p[g + 16] * dv
        if abs(n0) > ilim:
            n0 = sg * ilim
    return (n0, n1, n2, n3, n4), va


@numba.njit(**_JIT)
def _axes(p, s, v_a0, v_a, v_e0, v_e, n_old, c_a, tl_a, c_e, tl_e):  # noqa: PLR0917
    """Both axes over one tick: ``n_sub`` sub-steps with the carrier rate ``c`` and the load torque ``tl`` held over
    the tick, and the drive ``v0`` (the last tick's) for the first ``n_old`` sub-steps, ``v`` after. ``n_old`` may be
    a fraction: the sub-step it ends in holds the time-weighted mean of the two (exact for the voltage's integral).
    Each sub-step: the friction torques (:func:`_friction2`), the motor-side torques ``T_m = -T_f + a K_t i sin(N
    theta_m)`` (ripple; ``sin(N theta_m)`` at the sub-step's start), the exact-ZOH update (:func:`_zoh`), the ripple
    phase rotated. The axes are stepped in the same loop (their dependency chains overlap); the mechanism switches
    are read once per tick."""
    xa = (s[S_X], s[S_X + 1], s[S_X + 2], s[S_X + 3], s[S_X + 4])
    xe = (s[S_X + 5], s[S_X + 6], s[S_X + 7], s[S_X + 8], s[S_X + 9])
    ka1 = _held(p, 0, v_a, c_a, tl_a)
    ke1 = _held(p, PA_LEN, v_e, c_e, tl_e)
    ka, ke, v_a_j, v_e_j = ka1, ke1, v_a, v_e
    ka0, ke0 = ka1, ke1
    if n_old > 0.0:
        ka0 = _held(p, 0, v_a0, c_a, tl_a)
        ke0 = _held(p, PA_LEN, v_e0, c_e, tl_e)
    za, ze = s[S_Z], s[S_Z + 1]
    tfa = tfe = 0.0
    vaa, vae = v_a, v_e
    lugre_a, lugre_e = p[PA_FMODEL] != 0.0, p[PA_LEN + PA_FMODEL] != 0.0
    lugre2 = lugre_a and lugre_e
    ripa_a, ripa_e = p[PA_RIPA], p[PA_LEN + PA_RIPA]
    # ripple phase sin / cos(N theta_m), carried in the state: rotated by N (change of theta_m) each sub-step
    na, ne = p[PA_RIPN], p[PA_LEN + PA_RIPN]
    sra, cra, sre, cre = s[S_RIP], s[S_RIP + 1], s[S_RIP + 2], s[S_RIP + 3]
    for j in range(int(p[P_NSUB])):
        if n_old > j:  # the last tick's drive still (partly) holds in this sub-step
            w = n_old - j
            if w >= 1.0:
                ka, ke, v_a_j, v_e_j = ka0, ke0, v_a0, v_e0
            else:
                v_a_j, v_e_j = w * v_a0 + (1.0 - w) * v_a, w * v_e0 + (1.0 - w) * v_e
                ka, ke = _held(p, 0, v_a_j, c_a, tl_a), _held(p, PA_LEN, v_e_j, c_e, tl_e)
        else:
            ka, ke, v_a_j, v_e_j = ka1, ke1, v_a, v_e
        vra, vre = xa[1] - c_a, xe[1] - c_e
        tfa, za, tfe, ze = _friction2(p, lugre2, vra, za, vre, ze)
        tma, tme = -tfa, -tfe
        if ripa_a != 0.0:
            tma += ripa_a * xa[0] * sra
        if ripa_e != 0.0:
            tme += ripa_e * xe[0] * sre
        xa1, vaa = _zoh(p, 0, xa, ka, tma, v_a_j, vra)
        xe1, vae = _zoh(p, PA_LEN, xe, ke, tme, v_e_j, vre)
        if na != 0.0 and ne != 0.0:
            sra, cra, sre, cre = _rotate2(sra, cra, na * (xa1[2] - xa[2]), sre, cre, ne * (xe1[2] - xe[2]))
        elif na != 0.0:
            sra, cra = _rotate(sra, cra, na * (xa1[2] - xa[2]))
        elif ne != 0.0:
            sre, cre = _rotate(sre, cre, ne * (xe1[2] - xe[2]))
        xa, xe = xa1, xe1
    s[S_X], s[S_X + 1], s[S_X + 2], s[S_X + 3], s[S_X + 4] = xa
    s[S_X + 5], s[S_X + 6], s[S_X + 7], s[S_X + 8], s[S_X + 9] = xe
    if na != 0.0:
        s[S_RIP], s[S_RIP + 1] = _renorm(sra, cra)
    if ne != 0.0:
        s[S_RIP + 2], s[S_RIP + 3] = _renorm(sre, cre)
    s[S_Z], s[S_Z + 1] = za, ze
    s[S_TF], s[S_TF + 1] = tfa, tfe
    s[S_V], s[S_V + 1] = vaa, vae


@numba.njit(**_INLINE)
def _encoders(p, s):
    """Encoder readings (deg; az wrapped to [-180, 180), motor side), quantised to the encoder's LSB."""
    lsb = p[P_ENC_LSB]
    az = s[S_X + 2] * R2D
    if az < -180.0 or az >= 180.0:
        az = (az + 180.0) % 360.0 - 180.0
    el = s[S_X + 7] * R2D
    qa, qe = _vdiv((az, el), (lsb, lsb))
    return ((qa + _ROUND) - _ROUND) * lsb, ((qe + _ROUND) - _ROUND) * lsb


@numba.njit(**_INLINE)
def _outputs(p, s, flag):
    """step_tick's tuple: gyro (deg/s), encoders (deg), currents, flag."""
    az, el = _encoders(p, s)
    return s[S_M], s[S_M + 1], s[S_M + 2], az, el, s[S_X], s[S_X + 5], flag


@numba.njit(**_INLINE)
def _tick(p, s, nz, u_az, u_el, at, pose, rate, acc):  # noqa: PLR0917
    """One 1 ms tick (:func:`_advance`); returns :func:`_outputs` (step_tick's entry point)."""
    return _outputs(p, s, _advance(p, s, nz, u_az, u_el, at, pose, rate, acc))


@numba.njit(**_INLINE)
def _advance(p, s, nz, u_az, u_el, at, pose, rate, acc):  # noqa: PLR0917
    """One 1 ms tick; ``pose``, ``rate``, ``acc`` at mid-tick (tuples or array rows). The drive ``u`` (DAC counts)
    takes over from the last tick's at the fraction ``at`` of the tick (0: from its start; the wire's and the host's
    delay, docs/emulator.md "The wire"). Returns 1.0 if the tick used up the noise block (the caller refills it), else
    0.0."""
    for j in range(6):
        s[S_CARR + j] = pose[j]
        s[S_CARR + 6 + j] = rate[j]
        s[S_CARR + 12 + j] = acc[j]
    s[S_HASC] = 1.0
    pr, qr, rr, pd, qd, _, fbx, fby, fbz, sf, cf, st, ct = _carrier(p, pose, rate, acc)
    s[S_ATT], s[S_ATT + 1], s[S_ATT + 2], s[S_ATT + 3] = sf, cf, st, ct  # for the camera (_los)
    # p and q at the tick end, for the gyro (the azimuth rate carries r)
    pe = pr + pd * _HALF
    qe = qr + qd * _HALF
    # load angles predicted at mid-tick (held over the tick: midpoint rule); sin and cos by rotating the tick end's
    # through the half-tick angle d (first order: error d^2/2 < 2e-6)
    sa, ca, se, ce = s[S_SC], s[S_SC + 1], s[S_SC + 2], s[S_SC + 3]
    d = (s[S_X + 3] - rr) * _HALF
    sa, ca = sa + ca * d, ca - sa * d
    c_a = rr  # carrier rate on the azimuth axis (z_o = z_b)
    c_e = ca * qr - sa * pr  # carrier rate on the elevation axis (y_o, carried by the azimuth load)
    d = (s[S_X + 8] - c_e) * _HALF
    se, ce = se + ce * d, ce - se * d
    tim_a = tim_e = 0.0
    if p[P_HAS_IMB] != 0.0:
        tim_a, tim_e = _imbalance(p, fbx, fby, fbz, sa, ca, se, ce)
    s[S_IMB], s[S_IMB + 1] = tim_a, tim_e
    vmax = p[PA_VMAX]
    v_a = min(max(u_az * p[PA_VPC], -vmax), vmax)
    v_a0 = min(max(s[S_U] * p[PA_VPC], -vmax), vmax)
    vmax = p[PA_LEN + PA_VMAX]
    v_e = min(max(u_el * p[PA_LEN + PA_VPC], -vmax), vmax)
    v_e0 = min(max(s[S_U + 1] * p[PA_LEN + PA_VPC], -vmax), vmax)
    s[S_U], s[S_U + 1] = u_az, u_el
    n_old = 0.0 if at <= 0.0 else min(at, 1.0) * p[P_NSUB]
    th_a, th_e = s[S_X + 4], s[S_X + 9]
    _axes(p, s, v_a0, v_a, v_e0, v_e, n_old, c_a, tim_a, c_e, tim_e)
    # sin, cos of the load angles at the tick end: the tick start's rotated by the tick's change (exact up to
    # rounding, which _renorm keeps off the norm; reset() starts them exact)
    sa, ca, se, ce = _rotate2(s[S_SC], s[S_SC + 1], s[S_X + 4] - th_a, s[S_SC + 2], s[S_SC + 3], s[S_X + 9] - th_e)
    sa, ca = _renorm(sa, ca)
    se, ce = _renorm(se, ce)
    s[S_SC], s[S_SC + 1], s[S_SC + 2], s[S_SC + 3] = sa, ca, se, ce
    # gyro: true elevation-frame inertial rates of the load at the tick end (seed 001 eq 1)
    w_a, w_e = s[S_X + 3], s[S_X + 8]
    ox = ca * pe + sa * qe
    xn = ox * ce - w_a * se
    zn = ox * se + w_a * ce
    s[S_LOS], s[S_LOS + 1], s[S_LOS + 2] = xn, w_e, zn
    # filter k_a w_c / (s + w_c), input linear between tick ends; the delay's fraction of a tick evaluated exactly
    # inside this tick, whole ticks from the ring
    ef, c1, c0, ea, d1, d0 = p[P_EF], p[P_C1], p[P_C0], p[P_EA], p[P_D1], p[P_D0]
    gx, gy, gz = s[S_G], s[S_G + 1], s[S_G + 2]
    xo, yo, zo = s[S_XO], s[S_XO + 1], s[S_XO + 2]
    mx = ea * gx + d1 * xn + d0 * xo
    my = ea * gy + d1 * w_e + d0 * yo
    mz = ea * gz + d1 * zn + d0 * zo
    s[S_G] = ef * gx + c1 * xn + c0 * xo
    s[S_G + 1] = ef * gy + c1 * w_e + c0 * yo
    s[S_G + 2] = ef * gz + c1 * zn + c0 * zo
    s[S_XO], s[S_XO + 1], s[S_XO + 2] = xn, w_e, zn
    delay = int(p[P_DELAY])
    if delay:
        j = int(s[S_RINGJ])
        r = S_RING + 3 * j
        ox_, oy_, oz_ = s[r], s[r + 1], s[r + 2]
        s[r], s[r + 1], s[r + 2] = mx, my, mz
        mx, my, mz = ox_, oy_, oz_
        j += 1
        s[S_RINGJ] = 0.0 if j == delay else float(j)
    # noise: bias + white (precomputed per block, output units), camera; then coloured bands and random walk
    k = int(s[S_NK])
    mx += nz[k]
    my += nz[k + 1]
    mz += nz[k + 2]
    s[S_CAMN], s[S_CAMN + 1] = nz[k + 3], nz[k + 4]
    e = k + NOISE_WHITE
    for c in range(int(p[P_NCOL])):
        b0, a1, a2 = p[P_COL + 3 * c], p[P_COL + 3 * c + 1], p[P_COL + 3 * c + 2]
        for j in range(3):
            o = S_COL + 4 * (3 * c + j)
            en = nz[e]
            e += 1
            y = b0 * (en - s[o + 1]) - a1 * s[o + 2] - a2 * s[o + 3]
            s[o + 1], s[o] = s[o], en
            s[o + 3], s[o + 2] = s[o + 2], y
            if j == 0:
                mx += y
            elif j == 1:
                my += y
            else:
                mz += y
    rw = p[P_RW]
    if rw != 0.0:
        s[S_RW] += rw * nz[e]
        s[S_RW + 1] += rw * nz[e + 1]
        s[S_RW + 2] += rw * nz[e + 2]
        mx += s[S_RW]
        my += s[S_RW + 1]
        mz += s[S_RW + 2]
    k += int(p[P_STRIDE])
    flag = 0.0
    if k >= nz.shape[0]:
        k = 0
        flag = 1.0
    s[S_NK] = k
    s[S_REFILL] = flag
    lsb = p[P_LSB]
    if p[P_INV_LSB] != 0.0:  # LSBs to deg/s, rounded: adding and removing 1.5 * 2^52 rounds a float to an integer
        mx = ((mx + _ROUND) - _ROUND) * lsb
        my = ((my + _ROUND) - _ROUND) * lsb
        mz = ((mz + _ROUND) - _ROUND) * lsb
    s[S_M], s[S_M + 1], s[S_M + 2] = mx, my, mz
    s[S_TICK] += 1.0
    return flag


@numba.njit(**_INLINE)
def _los(p, s):
    """Exact LOS error (deg about z_e, deg about -y_e, x_e component of the target) at the tick end."""
    t0, t1, t2 = p[P_TGX], p[P_TGY], p[P_TGZ]
    if s[S_HASC] != 0.0:  # attitude at the tick end: the mid-tick pose extrapolated by half a tick (2nd order)
        k2 = 0.5 * _HALF * _HALF
        c = S_CARR
        sf, cf, st, ct = _rotate2(s[S_ATT], s[S_ATT + 1], (s[c + 9] * _HALF + s[c + 15] * k2) * D2R,
                                  s[S_ATT + 2], s[S_ATT + 3], (s[c + 10] * _HALF + s[c + 16] * k2) * D2R)
        ps = (s[c + 5] + s[c + 11] * _HALF + s[c + 17] * k2) * D2R
        sp, cp = math.sin(ps), math.cos(ps)
        tb0 = ct * cp * t0 + ct * sp * t1 - st * t2
        tb1 = (sf * st * cp - cf * sp) * t0 + (sf * st * sp + cf * cp) * t1 + sf * ct * t2
        tb2 = (cf * st * cp + sf * sp) * t0 + (cf * st * sp - sf * cp) * t1 + cf * ct * t2
    else:
        tb0, tb1, tb2 = t0, t1, t2
    sa, ca, se, ce = s[S_SC], s[S_SC + 1], s[S_SC + 2], s[S_SC + 3]  # of the load's angles at the tick end
    hxy = ca * tb0 + sa * tb1
    tex = hxy * ce - tb2 * se
    tey = ca * tb1 - sa * tb0
    tez = hxy * se + tb2 * ce
    return math.atan2(tey, tex) * R2D, math.atan2(-tez, math.hypot(tex, tey)) * R2D, tex


@numba.njit(**_INLINE)
def _views(buf):
    """The parameter, state and noise arrays ``p``, ``s``, ``nz``: consecutive parts of the plant's one buffer (see
    :class:`Plant`), so that a per-tick call unboxes one array, not three (~50 ns each)."""
    ns = S_RING + 3 * int(buf[P_DELAY])
    return buf[:P_LEN], buf[P_LEN:P_LEN + ns], buf[P_LEN + ns:]


@numba.njit(**_JIT)
def _tick_entry(buf, u_az, u_el, at, pose, rate, acc):  # noqa: PLR0917
    """:func:`_tick` on the plant's buffer (step_tick's one compiled call per tick)."""
    p, s, nz = _views(buf)
    return _tick(p, s, nz, u_az, u_el, at, pose, rate, acc)


@numba.njit(**_JIT)
def _los_entry(buf):
    """:func:`_los` on the plant's buffer."""
    p, s, _ = _views(buf)
    return _los(p, s)


@numba.njit(**_JIT)
def _friction_now(p, s, ax, vr):
    """Friction torque acting on the axis (N m) at the current state, motor-side relative rate ``vr``."""
    b = ax * PA_LEN
    tc = p[b + PA_TC]
    if p[b + PA_FMODEL] != 0.0:
        z, s0, ts = s[S_Z + ax], p[b + PA_S0], p[b + PA_TS]
        u = vr * p[b + PA_IVS]
        gv = tc + (ts - tc) * math.exp(-u * u)
        zdot = vr - s0 * abs(vr) * z / gv
        return -(s0 * z + p[b + PA_S1] * zdot + p[b + PA_D] * vr)
    return -(tc * math.tanh(vr * p[b + PA_IWS]) + p[b + PA_D] * vr)


@numba.njit(**_JIT)
def _truth(p, s):
    """Noise-free values at the tick end, in the order of ``TRUTH_KEYS`` (SI, rates in rad/s)."""
    pr = qr = rr = 0.0
    fbx, fby, fbz = 0.0, 0.0, -G0_M_S2
    if s[S_HASC] != 0.0:
        c = s[S_CARR: S_CARR + 18]
        pr, qr, rr, pd, qd, rd, fbx, fby, fbz, _, _, _, _ = _carrier(p, c[0:6], c[6:12], c[12:18])
        pr += pd * _HALF
        qr += qd * _HALF
        rr += rd * _HALF
    i_a, wm_a, thm_a, w_a, th_a = s[S_X], s[S_X + 1], s[S_X + 2], s[S_X + 3], s[S_X + 4]
    i_e, wm_e, thm_e, w_e, th_e = s[S_X + 5], s[S_X + 6], s[S_X + 7], s[S_X + 8], s[S_X + 9]
    ca, sa, ce, se = math.cos(th_a), math.sin(th_a), math.cos(th_e), math.sin(th_e)
    ox = ca * pr + sa * qr
    c_e = ca * qr - sa * pr
    tim_a = tim_e = 0.0
    if p[P_HAS_IMB] != 0.0:
        tim_a, tim_e = _imbalance(p, fbx, fby, fbz, sa, ca, se, ce)
    vr_a, vr_e = wm_a - rr, wm_e - c_e
    ex, ey, _ = _los(p, s)
    b = PA_LEN
    return (
        ox * ce - w_a * se, w_e, ox * se + w_a * ce,  # los rates x, y, z
        w_a, w_e, w_a - rr, w_e - c_e, th_a, th_e,  # load rates, relative rates, angles
        i_a, i_e, s[S_V], s[S_V + 1],
        _friction_now(p, s, 0, vr_a), _friction_now(p, s, 1, vr_e), tim_a, tim_e,
        pr, qr, rr, ex, ey,
        wm_a, wm_e, thm_a, thm_e,  # motor side
        -(p[PA_KC] * thm_a + p[PA_CC] * vr_a), -(p[b + PA_KC] * thm_e + p[b + PA_CC] * vr_e),  # cable
        p[PA_KS] * (thm_a - th_a) + p[PA_CS] * (wm_a - w_a),  # shaft torque on the load
        p[b + PA_KS] * (thm_e - th_e) + p[b + PA_CS] * (wm_e - w_e),
        s[S_Z], s[S_Z + 1],
    )


# what truth() returns, and the unit conversion of each kernel value
TRUTH_KEYS: tuple[tuple[str, float], ...] = (
    ("los_rate_x_dps", R2D), ("los_rate_y_dps", R2D), ("los_rate_z_dps", R2D),
    ("az_rate_dps", R2D), ("el_rate_dps", R2D), ("az_rel_rate_dps", R2D), ("el_rel_rate_dps", R2D),
    ("az_deg", R2D), ("el_deg", R2D),
    ("current_az_a", 1.0), ("current_el_a", 1.0), ("voltage_az_v", 1.0), ("voltage_el_v", 1.0),
    ("friction_az_n_m", 1.0), ("friction_el_n_m", 1.0), ("imbalance_az_n_m", 1.0), ("imbalance_el_n_m", 1.0),
    ("carrier_p_dps", R2D), ("carrier_q_dps", R2D), ("carrier_r_dps", R2D),
    ("los_error_x_deg", 1.0), ("los_error_y_deg", 1.0),
    ("az_motor_rate_dps", R2D), ("el_motor_rate_dps", R2D), ("az_motor_deg", R2D), ("el_motor_deg", R2D),
    ("cable_az_n_m", 1.0), ("cable_el_n_m", 1.0), ("shaft_az_n_m", 1.0), ("shaft_el_n_m", 1.0),
    ("bristle_az_rad", 1.0), ("bristle_el_rad", 1.0),
)

# columns of Plant.run's output
RUN_COLUMNS = (
    "gyro_x_dps", "gyro_y_dps", "gyro_z_dps", "encoder_az_deg", "encoder_el_deg", "current_az_a", "current_el_a",
    "los_error_x_deg", "los_error_y_deg", "miss_x_px", "miss_y_px", "track_valid",
    "los_rate_x_dps", "los_rate_y_dps", "los_rate_z_dps", "az_deg", "el_deg", "voltage_az_v", "voltage_el_v",
)
RUN_INDEX = {name: j for j, name in enumerate(RUN_COLUMNS)}


@numba.njit(**_JIT)
def _run(p, s, nz, u_az, u_el, at, carrier, out, rows, k0):  # noqa: PLR0917
    """Ticks ``k0 ..`` of a batch (one row of ``carrier`` = pose, rate, accel per tick); stops after the tick that
    used up the noise block (the caller refills it) or at the end. Column ``j`` of :data:`RUN_COLUMNS` goes to
    ``out[rows[j], tick]``, not computed if ``rows[j] < 0`` (the LOS error and camera columns cost 2 atan2, a
    hypot and a sin / cos per tick). Each tick's drive takes over from the last one's at the fraction ``at`` of the
    tick (:func:`_advance`). Returns the next tick."""
    n = u_az.shape[0]
    ifov, hw, hh = p[P_IFOV], p[P_HW], p[P_HH]
    r_gx, r_gy, r_gz, r_ea, r_ee, r_ia, r_ie = rows[0], rows[1], rows[2], rows[3], rows[4], rows[5], rows[6]
    r_lx, r_ly, r_mx, r_my, r_tv = rows[7], rows[8], rows[9], rows[10], rows[11]
    r_wx, r_wy, r_wz, r_az, r_el, r_va, r_ve = rows[12], rows[13], rows[14], rows[15], rows[16], rows[17], rows[18]
    enc = r_ea >= 0 or r_ee >= 0
    cam = r_lx >= 0 or r_ly >= 0 or r_mx >= 0 or r_my >= 0 or r_tv >= 0
    k = k0
    while k < n:
        c = carrier
        flag = _advance(p, s, nz, u_az[k], u_el[k], at,
                        (c[k, 0], c[k, 1], c[k, 2], c[k, 3], c[k, 4], c[k, 5]),
                        (c[k, 6], c[k, 7], c[k, 8], c[k, 9], c[k, 10], c[k, 11]),
                        (c[k, 12], c[k, 13], c[k, 14], c[k, 15], c[k, 16], c[k, 17]))
        if r_gx >= 0:
            out[r_gx, k] = s[S_M]
        if r_gy >= 0:
            out[r_gy, k] = s[S_M + 1]
        if r_gz >= 0:
            out[r_gz, k] = s[S_M + 2]
        if enc:
            ea, ee = _encoders(p, s)
            if r_ea >= 0:
                out[r_ea, k] = ea
            if r_ee >= 0:
                out[r_ee, k] = ee
        if r_ia >= 0:
            out[r_ia, k] = s[S_X]
        if r_ie >= 0:
            out[r_ie, k] = s[S_X + 5]
        if cam:
            ex, ey, front = _los(p, s)
            qx, qy = _vdiv((ex, ey), (ifov, ifov))
            mx = qx + s[S_CAMN]
            my = qy + s[S_CAMN + 1]
            if r_lx >= 0:
                out[r_lx, k] = ex
            if r_ly >= 0:
                out[r_ly, k] = ey
            if r_mx >= 0:
                out[r_mx, k] = mx
            if r_my >= 0:
                out[r_my, k] = my
            if r_tv >= 0:
                out[r_tv, k] = 1.0 if front > 0.0 and abs(mx) <= hw and abs(my) <= hh else 0.0
        if r_wx >= 0:
            out[r_wx, k] = s[S_LOS] * R2D
        if r_wy >= 0:
            out[r_wy, k] = s[S_LOS + 1] * R2D
        if r_wz >= 0:
            out[r_wz, k] = s[S_LOS + 2] * R2D
        if r_az >= 0:
            out[r_az, k] = s[S_X + 4] * R2D
        if r_el >= 0:
            out[r_el, k] = s[S_X + 9] * R2D
        if r_va >= 0:
            out[r_va, k] = s[S_V]
        if r_ve >= 0:
            out[r_ve, k] = s[S_V + 1]
        k += 1
        if flag != 0.0:
            break
    return k


@numba.njit(**_JIT)
def _fill_noise(nz, stride, col0, ncols, raw, table, scales, offsets):  # noqa: PLR0917
    """Columns ``col0 .. col0 + ncols`` of the noise block: ``offsets[j] + scales[j] * table[raw]`` per tick."""
    ticks = nz.shape[0] // stride
    for t in range(ticks):
        for j in range(ncols):
            nz[t * stride + col0 + j] = offsets[j] + scales[j] * table[raw[t * ncols + j]]


_A1 = nbt.Array(nbt.float64, 1, "C")
_A2 = nbt.Array(nbt.float64, 2, "C")
_T6 = nbt.UniTuple(nbt.float64, 6)
_SIGNATURES: dict[str, tuple[Any, tuple[Any, ...]]] = {
    "tick": (_tick_entry, (_A1, nbt.float64, nbt.float64, nbt.float64, _T6, _T6, _T6)),
    "run": (_run, (_A1, _A1, _A1, _A1, _A1, nbt.float64, _A2, _A2, nbt.Array(nbt.int64, 1, "C"), nbt.int64)),
    "los": (_los_entry, (_A1,)),
    "truth": (_truth, (_A1, _A1)),
    "outputs": (_outputs, (_A1, _A1, nbt.float64)),
    "fill": (_fill_noise, (_A1, nbt.int64, nbt.int64, nbt.int64, nbt.Array(nbt.uint16, 1, "C"), _A1, _A1, _A1)),
}
_ENTRY: dict[str, Any] = {}


def kernel(name: str) -> Any:
    """The compiled entry point of one kernel function (compiled, or loaded from numba's cache, on first use in a
    process). Calling the entry point of the one compiled signature skips the dispatcher's type resolution (~0.4 us
    per call); its argument checks still refuse wrong types and tuple sizes (TypeError / ValueError)."""
    ep = _ENTRY.get(name)
    if ep is None:
        disp, sig = _SIGNATURES[name]
        ep = disp.compile(sig)  # returns the compiled entry point
        if not callable(ep):  # pragma: no cover (numba API change): the dispatcher is always correct
            ep = disp
        _ENTRY[name] = ep
    return ep
