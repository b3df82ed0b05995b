"""The plant's math outside the kernel: the carrier's motion and attitude from the hexapod's pose, rate and
acceleration; each axis's linear part and its exact zero-order-hold discretisation (matrix exponential, at
construction); the gyro's first-order hold; the band-pass of coloured noise; the table of normal quantiles."""

from __future__ import annotations

import math
from array import array
from statistics import NormalDist
from typing import NamedTuple

import numpy as np

from firmware_stub.plant._config import (
    D2R,
    G0_M_S2,
    TICK_S,
    Axis,
    MotorConfig,
    PlantConfig,
    Vec3f,
)


class CarrierMotion(NamedTuple):
    """Hexapod pose (lab -> platform) at mid-tick and its first and second time derivatives.

    ``pose = (x_mm, y_mm, z_mm, roll_deg, pitch_deg, yaw_deg)`` (ZYX Euler angles), ``rate`` in mm/s and deg/s,
    ``accel`` in mm/s^2 and deg/s^2, same order.
    """

    pose: tuple[float, float, float, float, float, float]
    rate: tuple[float, float, float, float, float, float]
    accel: tuple[float, float, float, float, float, float]

    @classmethod
    def at_rest(cls) -> CarrierMotion:
        z = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        return cls(z, z, z)


_AT_REST = CarrierMotion.at_rest()


class _CarrierState(NamedTuple):
    """What the plant derives from one CarrierMotion (all SI, body frame)."""

    pqr: Vec3f  # body rate at mid-tick, rad/s
    pqr_dot: Vec3f  # its derivative, rad/s^2
    f_body: Vec3f  # specific force (inertial acceleration minus gravity), m/s^2
    dcm_lab_to_body: tuple[Vec3f, Vec3f, Vec3f]  # at the end of the tick (camera)


def carrier_state(carrier: CarrierMotion) -> _CarrierState:
    """Body rates (exact ZYX Euler-rate formula) and their derivative, specific force in the body frame, attitude."""
    _, _, _, roll, pitch, yaw = carrier.pose
    _, _, _, rolld, pitchd, yawd = carrier.rate
    xdd, ydd, zdd, rolldd, pitchdd, yawdd = carrier.accel
    phi, th, psi = roll * D2R, pitch * D2R, yaw * D2R
    phid, thd, psid = rolld * D2R, pitchd * D2R, yawd * D2R
    phidd, thdd, psidd = rolldd * D2R, pitchdd * D2R, yawdd * D2R
    sf, cf = math.sin(phi), math.cos(phi)
    st, ct = math.sin(th), math.cos(th)
    sp, cp = math.sin(psi), math.cos(psi)
    p = phid - psid * st
    q = thd * cf + psid * sf * ct
    r = -thd * sf + psid * cf * ct
    pd = phidd - psidd * st - psid * thd * ct
    qd = thdd * cf - thd * phid * sf + psidd * sf * ct + psid * (phid * cf * ct - thd * sf * st)
    rd = -thdd * sf - thd * phid * cf + psidd * cf * ct - psid * (phid * sf * ct + thd * cf * st)
    c = _dcm_zyx((sf, cf), (st, ct), (sp, cp))
    fx, fy, fz = xdd * 1e-3, ydd * 1e-3, zdd * 1e-3 - G0_M_S2
    f_body = (
        c[0][0] * fx + c[0][1] * fy + c[0][2] * fz,
        c[1][0] * fx + c[1][1] * fy + c[1][2] * fz,
        c[2][0] * fx + c[2][1] * fy + c[2][2] * fz,
    )
    return _CarrierState((p, q, r), (pd, qd, rd), f_body, attitude_at_tick_end(carrier))


def attitude_at_tick_end(carrier: CarrierMotion) -> tuple[Vec3f, Vec3f, Vec3f]:
    """DCM lab -> platform at the end of the tick: the pose is given at mid-tick, extrapolated by half a tick with
    its rate and acceleration (second order)."""
    dt = 0.5 * TICK_S
    k2 = 0.5 * dt * dt
    _, _, _, roll, pitch, yaw = carrier.pose
    _, _, _, rolld, pitchd, yawd = carrier.rate
    _, _, _, rolldd, pitchdd, yawdd = carrier.accel
    phi = (roll + rolld * dt + rolldd * k2) * D2R
    th = (pitch + pitchd * dt + pitchdd * k2) * D2R
    psi = (yaw + yawd * dt + yawdd * k2) * D2R
    return _dcm_zyx((math.sin(phi), math.cos(phi)), (math.sin(th), math.cos(th)), (math.sin(psi), math.cos(psi)))


def _dcm_zyx(
    roll_sc: tuple[float, float], pitch_sc: tuple[float, float], yaw_sc: tuple[float, float]
) -> tuple[Vec3f, Vec3f, Vec3f]:
    """Passive DCM lab -> body for ZYX Euler angles, given (sin, cos) of each: ``R_x(roll) R_y(pitch) R_z(yaw)``."""
    (sf, cf), (st, ct), (sp, cp) = roll_sc, pitch_sc, yaw_sc
    return (
        (ct * cp, ct * sp, -st),
        (sf * st * cp - cf * sp, sf * st * sp + cf * cp, sf * ct),
        (cf * st * cp + sf * sp, cf * st * sp - sf * cp, cf * ct),
    )


def _expm(a: np.ndarray) -> np.ndarray:
    """Matrix exponential (construction only): ``scipy.linalg.expm`` of the balanced matrix. The augmented
    ``[[A, B], [0, 0]] h`` of an axis with a structural mode has entries ten decades apart; balancing (a diagonal
    scaling by powers of two, exact) keeps every entry of the result to ~1e-13 relative, where plain ``expm`` leaves
    ~1e-9 on the smallest ones (current and voltage into the load rate and the angles). The tests check every
    entry against a 50-digit series, and the plant against analytic solutions."""
    from scipy.linalg import expm, matrix_balance  # noqa: PLC0415  (heavy: loaded only when this computation runs)

    balanced, (scale, _) = matrix_balance(a, permute=False, separate=True)
    return expm(balanced) * scale[:, None] / scale[None, :]


def axis_matrices(cfg: PlantConfig, axis: Axis) -> tuple[np.ndarray, np.ndarray]:
    """Continuous ``(A, B)`` of one axis: state ``(i, w_m, theta_m, w_l, theta_l)`` [A, rad/s, rad, rad/s, rad],
    inputs ``(V, c, T_m, T_l)`` [V, rad/s, N m, N m]: ``T_m`` the nonlinear torque on the motor side (friction,
    ripple), ``T_l`` on the load (imbalance). Without ``structure`` the load rows repeat the motor rows (one rigid
    body, ``T_l`` on the same inertia)."""
    m: MotorConfig = getattr(cfg, f"motor_{axis}")
    r, ll, kt, ke, j = (m.resistance_ohm, m.inductance_h, m.torque_constant_n_m_per_a, m.back_emf_v_s_per_rad,
                        m.inertia_kg_m2)
    d = getattr(cfg.friction, axis).viscous_n_m_s_per_rad
    cab = cfg.cable_of(axis)
    kc, cc = (0.0, 0.0) if cab is None else (cab.stiffness_n_m_per_rad, cab.damping_n_m_s_per_rad)
    st = cfg.structure_of(axis)
    a = np.zeros((5, 5))
    b = np.zeros((5, 4))
    a[0, 0], a[0, 1] = -r / ll, -ke / ll
    b[0, 0], b[0, 1] = 1.0 / ll, ke / ll
    a[2, 1], b[2, 1] = 1.0, -1.0
    if st is None:
        a[1, 0], a[1, 1], a[1, 2] = kt / j, -(d + cc) / j, -kc / j
        b[1, 1], b[1, 2], b[1, 3] = (d + cc) / j, 1.0 / j, 1.0 / j
        a[3:5], b[3:5] = a[1:3], b[1:3]  # the load is the motor
        a[:, 3:5] = 0.0
        return a, b
    f = st.motor_inertia_fraction
    jm, jl = f * j, (1.0 - f) * j
    mu = jm * jl / j
    wr = 2.0 * math.pi * st.mode_hz
    ks, cs = wr * wr * mu, 2.0 * st.damping_ratio * wr * mu
    a[1, 0], a[1, 1], a[1, 2], a[1, 3], a[1, 4] = kt / jm, -(d + cc + cs) / jm, -(ks + kc) / jm, cs / jm, ks / jm
    b[1, 1], b[1, 2] = (d + cc) / jm, 1.0 / jm
    a[3, 1], a[3, 2], a[3, 3], a[3, 4] = cs / jl, ks / jl, -cs / jl, -ks / jl
    b[3, 3] = 1.0 / jl
    a[4, 3], b[4, 1] = 1.0, -1.0
    return a, b


def axis_zoh(cfg: PlantConfig, axis: Axis, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact ZOH of :func:`axis_matrices` over ``h``: ``(Phi, Gamma)`` from ``expm([[A, B], [0, 0]] h)``. Without
    ``structure`` the rigid 3-state system is discretised and its rate and angle rows copied to the load rows (so
    the load equals the motor bit for bit)."""
    a, b = axis_matrices(cfg, axis)
    n = 3 if cfg.structure_of(axis) is None else 5
    aug = np.zeros((n + 4, n + 4))
    aug[:n, :n], aug[:n, n:] = a[:n, :n] * h, b[:n] * h
    e = _expm(aug)
    phi, gam = np.zeros((5, 5)), np.zeros((5, 4))
    phi[:n, :n], gam[:n] = e[:n, :n], e[:n, n:]
    if n == 3:
        phi[3:5], gam[3:5] = phi[1:3], gam[1:3]
    return phi, gam


def foh(wc: float, tau: float, gain: float) -> tuple[float, float, float]:
    """Exact discretisation of ``gain * wc / (s + wc)`` over ``tau`` for an input linear in time (first-order hold):
    ``y(tau) = e y(0) + c1 x(tau) + c0 x(0)``; returns ``(e, c1, c0)``."""
    e = math.exp(-wc * tau)
    one_minus_e = -math.expm1(-wc * tau)
    k = one_minus_e / (wc * tau)
    return e, gain * (1.0 - k), gain * (k - e)


def band_pass(centre_hz: float, bandwidth_hz: float, fs_hz: float = 1.0 / TICK_S) -> tuple[float, float, float, float]:
    """Second-order digital band-pass ``H(z) = b0 (1 - z^-2) / (1 + a1 z^-1 + a2 z^-2)``, unit gain at the centre,
    -3 dB width ``bandwidth_hz`` (the bilinear peak filter of ``scipy.signal.iirpeak(centre, centre / bandwidth,
    fs)``). Returns ``(b0, a1, a2, var_gain)``, ``var_gain`` the output variance for unit white input
    (``2 b0^2 (gamma_0 - gamma_2)`` from the AR(2) autocovariances)."""
    w0 = 2.0 * math.pi * centre_hz / fs_hz
    bw = 2.0 * math.pi * bandwidth_hz / fs_hz
    gain = 1.0 / (1.0 + math.tan(bw / 2.0))
    b0 = 1.0 - gain
    a1, a2 = -2.0 * gain * math.cos(w0), 2.0 * gain - 1.0
    f1, f2 = -a1, -a2  # x_t = f1 x_{t-1} + f2 x_{t-2} + e_t
    g0 = (1.0 - f2) / ((1.0 + f2) * ((1.0 - f2) ** 2 - f1 * f1))
    g1 = f1 * g0 / (1.0 - f2)
    g2 = f1 * g1 + f2 * g0
    return b0, a1, a2, 2.0 * b0 * b0 * (g0 - g2)


_NORMAL_BITS = 16
_NORMAL_TABLE = array("d")


def normal_table() -> array[float]:
    """2^16 standard-normal quantiles at ``(k + 1/2) / 2^16``: indexed by 16 random bits, a Gaussian draw that costs
    one table lookup (tails cut at +-4.17 sigma; std 0.9999). Built once per process (~50 ms)."""
    if not _NORMAL_TABLE:
        inv = NormalDist().inv_cdf
        n = 1 << _NORMAL_BITS
        _NORMAL_TABLE.extend(inv((k + 0.5) / n) for k in range(n))
    return _NORMAL_TABLE
