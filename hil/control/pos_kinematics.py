"""Gimbal kinematics for the stabilized platform: plain floats, ``math`` only (1 kHz hot path).

Two gimbal layouts:

**Roll-pitch-azimuth ISP** (Zhang et al. 2018, "A Novel Separated POS Integrated with ISP", seed 004):
frames body ``b`` (x right, y forward, z up) -> roll ``r`` (angle ``theta_r`` about ``y_b``) -> pitch ``p``
(``theta_p`` about ``x_r``) -> azimuth ``a`` (``theta_a`` about ``z_p``); the payload rides on ``a``.
Positive angles are right-handed (counter-clockwise). ``C_x^y`` is the *passive* direction-cosine matrix taking
a vector's components in frame ``x`` to frame ``y``.

Ambiguities in the seed text and the choices made here:

* Eqs 1-2 (the elementary matrices) are missing from the extracted text; they are rebuilt from the frame
  definitions of section 3.1, and the product ``C_p^a C_r^p C_b^r`` reproduces eq 4 entry by entry except
  entry (2,2) of the first matrix, printed ``cos(a) sin(p)``: the product (and orthonormality) give
  ``cos(a) cos(p)``.
* Eq 4, second matrix, entry (2,2) is printed ``-sin(p)``; the kinematics give ``-sin(a)``.
* Eqs 6 and 8 are labelled ``omega_ipx``; the right-hand side is the *y* component of ``omega_ip^p`` (the pitch
  gimbal rate ``dtheta_p`` is along ``x_p``, so it cannot be ``omega_ipx``). Eq 9 is consistent with the
  ``y`` reading, which is used here.
* Lever-arm (centripetal/tangential) terms are ignored in eq 10, as in the paper (sensors at the rotation centre).

**Azimuth-elevation (2-axis) gimbal** (the bench's platform; same approach, and the convention of Zhang & Shi,
seed 001, eqs 1 and 3): at ``az = el = 0`` the gimbal frames coincide with the carrier body frame ``b``;
x is along the line of sight (LOS), y along the elevation axis, z the azimuth axis.  Outer (azimuth) frame ``o``:
``az`` about ``z_b``; inner (elevation, LOS) frame ``e``: ``el`` about ``y_o``. Positive angles right-handed.
The carrier rates ``(p, q, r)`` are the body-frame components of the carrier's inertial angular rate.

Vectors are ``tuple[float, float, float]``; matrices are row-major ``tuple`` of three rows.
"""

from __future__ import annotations

import math

Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]

__all__ = [
    "Mat3",
    "Vec3",
    "azel_accel_body_to_el",
    "azel_carrier_rate_on_axes",
    "azel_gimbal_rates_for_los_rate",
    "azel_los_inertial_rate",
    "azel_rot_az_to_el",
    "azel_rot_body_to_az",
    "azel_rot_body_to_el",
    "mat3_mul",
    "mat3_transpose",
    "mat3_vec",
    "rot_x",
    "rot_y",
    "rot_z",
    "rpa_gimbal_gyro_rates",
    "rpa_gimbal_rate_matrix",
    "rpa_payload_accel_from_gimbal_accels",
    "rpa_payload_rate",
    "rpa_payload_rate_from_gyros",
    "rpa_rot_azimuth",
    "rpa_rot_body_to_payload",
    "rpa_rot_pitch",
    "rpa_rot_roll",
]


# --- elementary passive rotations and 3x3 helpers ---------------------------------------------------------------


def rot_x(angle_rad: float) -> Mat3:
    """Passive DCM for a frame rotated by ``angle_rad`` about its x axis (components old -> new)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return ((1.0, 0.0, 0.0), (0.0, c, s), (0.0, -s, c))


def rot_y(angle_rad: float) -> Mat3:
    """Passive DCM for a frame rotated by ``angle_rad`` about its y axis (components old -> new)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return ((c, 0.0, -s), (0.0, 1.0, 0.0), (s, 0.0, c))


def rot_z(angle_rad: float) -> Mat3:
    """Passive DCM for a frame rotated by ``angle_rad`` about its z axis (components old -> new)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return ((c, s, 0.0), (-s, c, 0.0), (0.0, 0.0, 1.0))


def mat3_mul(a: Mat3, b: Mat3) -> Mat3:
    """Matrix product ``a @ b``."""
    bt = mat3_transpose(b)
    return (mat3_vec(bt, a[0]), mat3_vec(bt, a[1]), mat3_vec(bt, a[2]))


def mat3_vec(m: Mat3, v: Vec3) -> Vec3:
    """Matrix-vector product ``m @ v``."""
    x, y, z = v
    r0, r1, r2 = m
    return (
        r0[0] * x + r0[1] * y + r0[2] * z,
        r1[0] * x + r1[1] * y + r1[2] * z,
        r2[0] * x + r2[1] * y + r2[2] * z,
    )


def mat3_transpose(m: Mat3) -> Mat3:
    """Transpose (= inverse for a DCM)."""
    return ((m[0][0], m[1][0], m[2][0]), (m[0][1], m[1][1], m[2][1]), (m[0][2], m[1][2], m[2][2]))


# --- roll-pitch-azimuth ISP (seed 004) ----------------------------------------------------------------------------


def rpa_rot_roll(theta_r_rad: float) -> Mat3:
    """``C_b^r``: body -> roll frame, roll angle about ``y_b`` (seed 004 eq 1, rebuilt from section 3.1)."""
    return rot_y(theta_r_rad)


def rpa_rot_pitch(theta_p_rad: float) -> Mat3:
    """``C_r^p``: roll -> pitch frame, pitch angle about ``x_r`` (seed 004 eq 2, rebuilt)."""
    return rot_x(theta_p_rad)


def rpa_rot_azimuth(theta_a_rad: float) -> Mat3:
    """``C_p^a``: pitch -> azimuth (payload) frame, azimuth angle about ``z_p`` (seed 004 eqs 3, 10)."""
    return rot_z(theta_a_rad)


def rpa_rot_body_to_payload(theta_r_rad: float, theta_p_rad: float, theta_a_rad: float) -> Mat3:
    """``C_b^a = C_p^a C_r^p C_b^r`` in closed form (seed 004 eq 4, first matrix; entry (2,2) corrected)."""
    cr, sr = math.cos(theta_r_rad), math.sin(theta_r_rad)
    cp, sp = math.cos(theta_p_rad), math.sin(theta_p_rad)
    ca, sa = math.cos(theta_a_rad), math.sin(theta_a_rad)
    return (
        (ca * cr + sa * sp * sr, sa * cp, sa * sp * cr - ca * sr),
        (-cr * sa + ca * sp * sr, ca * cp, ca * sp * cr + sa * sr),
        (cp * sr, -sp, cp * cr),
    )


def rpa_gimbal_rate_matrix(theta_p_rad: float, theta_a_rad: float) -> Mat3:
    """Matrix mapping ``(dtheta_r, dtheta_p, dtheta_a)`` to the payload frame (seed 004 eq 4, second matrix;
    entry (2,2) corrected to ``-sin(theta_a)``): columns ``C_p^a C_r^p y``, ``C_p^a x``, ``z``."""
    cp, sp = math.cos(theta_p_rad), math.sin(theta_p_rad)
    ca, sa = math.cos(theta_a_rad), math.sin(theta_a_rad)
    return ((cp * sa, ca, 0.0), (ca * cp, -sa, 0.0), (-sp, 0.0, 1.0))


def rpa_payload_rate(omega_ib_rad_s: Vec3, angles_rad: Vec3, angle_rates_rad_s: Vec3) -> Vec3:
    """Payload inertial rate ``omega_ia^a`` (rad/s, payload frame) from the body rate ``omega_ib^b`` (rad/s,
    body frame), the gimbal angles ``(theta_r, theta_p, theta_a)`` (rad) and their rates (rad/s): seed 004 eq 4."""
    theta_r_rad, theta_p_rad, theta_a_rad = angles_rad
    dtheta_r_rad_s, dtheta_p_rad_s, dtheta_a_rad_s = angle_rates_rad_s
    cr, sr = math.cos(theta_r_rad), math.sin(theta_r_rad)
    cp, sp = math.cos(theta_p_rad), math.sin(theta_p_rad)
    ca, sa = math.cos(theta_a_rad), math.sin(theta_a_rad)
    wx, wy, wz = omega_ib_rad_s
    # roll frame: omega_ir^r = C_b^r omega_ib + (0, dtheta_r, 0)
    rx = cr * wx - sr * wz
    ry = wy + dtheta_r_rad_s
    rz = sr * wx + cr * wz
    # pitch frame: omega_ip^p = C_r^p omega_ir^r + (dtheta_p, 0, 0)
    px = rx + dtheta_p_rad_s
    py = cp * ry + sp * rz
    pz = -sp * ry + cp * rz
    # azimuth frame: eq 3
    return (ca * px + sa * py, -sa * px + ca * py, pz + dtheta_a_rad_s)


def rpa_gimbal_gyro_rates(omega_ib_rad_s: Vec3, angles_rad: Vec3, angle_rates_rad_s: Vec3) -> Vec3:
    """What the three gimbal gyros read, ``(omega_ipx, omega_iry, omega_iaz)`` in rad/s (seed 004 eqs 5-8):
    the pitch gyro on ``x_p``, the roll gyro on ``y_r``, the azimuth gyro on ``z_a`` (for an emulator). Arguments
    as :func:`rpa_payload_rate`; the azimuth angle does not enter."""
    theta_r_rad, theta_p_rad, _ = angles_rad
    dtheta_r_rad_s, dtheta_p_rad_s, dtheta_a_rad_s = angle_rates_rad_s
    cr, sr = math.cos(theta_r_rad), math.sin(theta_r_rad)
    cp, sp = math.cos(theta_p_rad), math.sin(theta_p_rad)
    wx, wy, wz = omega_ib_rad_s
    omega_iry = wy + dtheta_r_rad_s  # eq 5
    rx = cr * wx - sr * wz
    rz = sr * wx + cr * wz  # eq 7
    omega_ipx = rx + dtheta_p_rad_s  # eq 5
    omega_ipz = -sp * omega_iry + cp * rz
    omega_iaz = omega_ipz + dtheta_a_rad_s  # eq 5
    return (omega_ipx, omega_iry, omega_iaz)


def rpa_payload_rate_from_gyros(gyros_rad_s: Vec3, omega_ib_rad_s: Vec3, angles_rad: Vec3) -> Vec3:
    """Payload inertial rate ``omega_ia^a`` (rad/s) from the gimbal gyros ``(omega_ipx, omega_iry, omega_iaz)``
    (rad/s), the body rate (rad/s) and the gimbal angles (rad), no angle differentiation (seed 004 eq 9)."""
    omega_ipx_rad_s, omega_iry_rad_s, omega_iaz_rad_s = gyros_rad_s
    theta_r_rad, theta_p_rad, theta_a_rad = angles_rad
    sr, cr = math.sin(theta_r_rad), math.cos(theta_r_rad)
    sp, cp = math.sin(theta_p_rad), math.cos(theta_p_rad)
    sa, ca = math.sin(theta_a_rad), math.cos(theta_a_rad)
    wx, _, wz = omega_ib_rad_s
    # omega_ipy (eq 8, read as the y component)
    ipy = omega_iry_rad_s * cp + (wx * sr + wz * cr) * sp
    return (ca * omega_ipx_rad_s + sa * ipy, -sa * omega_ipx_rad_s + ca * ipy, omega_iaz_rad_s)


def rpa_payload_accel_from_gimbal_accels(
    acc_px_m_s2: float, acc_py_m_s2: float, acc_az_m_s2: float, theta_a_rad: float
) -> Vec3:
    """Payload-frame specific force (m/s^2) from the two pitch-gimbal accelerometers (``x_p``, ``y_p``) and the
    azimuth accelerometer (``z_a``): seed 004 eq 10 (the ``z`` axis is shared by ``p`` and ``a``)."""
    ca, sa = math.cos(theta_a_rad), math.sin(theta_a_rad)
    return (ca * acc_px_m_s2 + sa * acc_py_m_s2, -sa * acc_px_m_s2 + ca * acc_py_m_s2, acc_az_m_s2)


# --- azimuth-elevation gimbal (bench platform; seed 001 eqs 1, 3) ----------------------------------------------


def azel_rot_body_to_az(az_rad: float) -> Mat3:
    """``C_b^o``: carrier body -> outer (azimuth) frame, ``az`` about ``z_b``."""
    return rot_z(az_rad)


def azel_rot_az_to_el(el_rad: float) -> Mat3:
    """``C_o^e``: outer (azimuth) -> inner (elevation / LOS) frame, ``el`` about ``y_o``."""
    return rot_y(el_rad)


def azel_rot_body_to_el(az_rad: float, el_rad: float) -> Mat3:
    """``C_b^e = C_o^e C_b^o`` in closed form (the matrix of seed 001 eq 3)."""
    ca, sa = math.cos(az_rad), math.sin(az_rad)
    ce, se = math.cos(el_rad), math.sin(el_rad)
    return ((ca * ce, sa * ce, -se), (-sa, ca, 0.0), (ca * se, sa * se, ce))


def azel_accel_body_to_el(accel_b_m_s2: Vec3, az_rad: float, el_rad: float) -> Vec3:
    """Carrier acceleration / specific force (m/s^2) projected on the elevation frame: seed 001 eq 3."""
    ax, ay, az_ = accel_b_m_s2
    ca, sa = math.cos(az_rad), math.sin(az_rad)
    ce, se = math.cos(el_rad), math.sin(el_rad)
    h = ca * ax + sa * ay
    return (h * ce - az_ * se, -sa * ax + ca * ay, h * se + az_ * ce)


def azel_carrier_rate_on_axes(pqr_rad_s: Vec3, az_rad: float, el_rad: float) -> Vec3:
    """How the carrier rate ``(p, q, r)`` (rad/s, body frame) reaches the gimbal: returns ``(on_az_axis,
    on_el_axis, cross_el)`` in rad/s.

    ``on_az_axis = r`` is the carrier rate along the azimuth motor axis (``z_o = z_b``); ``on_el_axis =
    -sin(az) p + cos(az) q`` along the elevation motor axis (``y_o = y_e``); ``cross_el = sin(el)(cos(az) p +
    sin(az) q) + cos(el) r`` is the carrier part of the elevation-frame z gyro (LOS yaw). These are the
    disturbance rates each rate loop must cancel (``d az/dt = -on_az_axis`` does not null ``cross_el`` unless
    ``el = 0``; see :func:`azel_gimbal_rates_for_los_rate`).
    """
    p_rad_s, q_rad_s, r_rad_s = pqr_rad_s
    ca, sa = math.cos(az_rad), math.sin(az_rad)
    ce, se = math.cos(el_rad), math.sin(el_rad)
    return (r_rad_s, -sa * p_rad_s + ca * q_rad_s, se * (ca * p_rad_s + sa * q_rad_s) + ce * r_rad_s)


def azel_los_inertial_rate(
    pqr_rad_s: Vec3,
    az_rad: float,
    el_rad: float,
    az_rate_rad_s: float,
    el_rate_rad_s: float,
) -> Vec3:
    """Inertial rate of the elevation (LOS) frame in its own axes, ``(x: about LOS, y: elevation gyro,
    z: cross-elevation gyro)`` in rad/s: ``C_o^e (C_b^o w_b + az_rate z) + el_rate y`` (seed 001 eq 1 with
    ``omega_O = C_b^o w_b + az_rate z``; seed 004's approach). ``pqr_rad_s``: carrier rate, body frame."""
    p_rad_s, q_rad_s, r_rad_s = pqr_rad_s
    ca, sa = math.cos(az_rad), math.sin(az_rad)
    ce, se = math.cos(el_rad), math.sin(el_rad)
    ox = ca * p_rad_s + sa * q_rad_s
    oy = -sa * p_rad_s + ca * q_rad_s
    oz = r_rad_s + az_rate_rad_s
    return (ox * ce - oz * se, oy + el_rate_rad_s, ox * se + oz * ce)


def azel_gimbal_rates_for_los_rate(
    pqr_rad_s: Vec3,
    az_rad: float,
    el_rad: float,
    los_rate_y_rad_s: float = 0.0,
    los_rate_z_rad_s: float = 0.0,
) -> tuple[float, float]:
    """Gimbal angle rates ``(az_rate, el_rate)`` in rad/s giving the wanted elevation-frame y/z inertial rates
    (0, 0 = perfect stabilization): the inverse of :func:`azel_los_inertial_rate` for its y and z rows.
    ``az_rate`` carries the ``sec(el)`` gain and is singular at ``el = +-pi/2`` (raises ``ZeroDivisionError``)."""
    p_rad_s, q_rad_s, r_rad_s = pqr_rad_s
    ca, sa = math.cos(az_rad), math.sin(az_rad)
    ce, se = math.cos(el_rad), math.sin(el_rad)
    ox = ca * p_rad_s + sa * q_rad_s
    oy = -sa * p_rad_s + ca * q_rad_s
    if abs(ce) < 1e-12:
        raise ZeroDivisionError("azimuth rate is singular at el = +-90 deg")
    return ((los_rate_z_rad_s - ox * se) / ce - r_rad_s, los_rate_y_rad_s - oy)
