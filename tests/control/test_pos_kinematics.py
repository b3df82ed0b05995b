"""Gimbal kinematics (seed 004 eqs 4-10; az-el per seed 001 eqs 1, 3) against independent numpy computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.control import pos_kinematics as pk

N_CASES = 300
TOL = 1e-12


# --- independent references: active elementary rotations, Rodrigues, attitude differentiation ---------------------


def r_act(axis: int, angle: float) -> np.ndarray:
    """Active rotation by ``angle`` about unit axis ``axis`` (0=x, 1=y, 2=z): rotates vectors, right-handed."""
    k = np.zeros(3)
    k[axis] = 1.0
    return expm_so3(k * angle)


def skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def expm_so3(phi: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(phi))
    if th < 1e-15:
        return np.eye(3)
    k = skew(phi / th)
    return np.eye(3) + math.sin(th) * k + (1.0 - math.cos(th)) * (k @ k)


def vee(m: np.ndarray) -> np.ndarray:
    return np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) * 0.5


def body_rate_of(attitude_fn, h: float = 1e-6) -> np.ndarray:
    """Angular rate in the moving frame of ``R(t)`` (frame -> inertial) at t = 0: vee(R^T dR/dt)."""
    r0 = attitude_fn(0.0)
    dr = (attitude_fn(h) - attitude_fn(-h)) / (2.0 * h)
    return vee(r0.T @ dr)


def rpa_attitude(ang: np.ndarray, rates: np.ndarray, w_b: np.ndarray):
    """R_ia(t) = R_ib(t) R_y(tr) R_x(tp) R_z(ta): body spinning at w_b (body frame), gimbal angles ramping."""

    def att(t: float) -> np.ndarray:
        a = ang + rates * t
        return expm_so3(w_b * t) @ r_act(1, a[0]) @ r_act(0, a[1]) @ r_act(2, a[2])

    return att


def azel_attitude(ang: tuple[float, float], rates: tuple[float, float], w_b: np.ndarray):
    """R_ie(t) = R_ib(t) R_z(az) R_y(el)."""

    def att(t: float) -> np.ndarray:
        return expm_so3(w_b * t) @ r_act(2, ang[0] + rates[0] * t) @ r_act(1, ang[1] + rates[1] * t)

    return att


def passive(active: np.ndarray) -> np.ndarray:
    """Components old -> new for a frame rotated by ``active``."""
    return active.T


def rng_cases(seed: int = 2024):
    rng = np.random.default_rng(seed)
    for _ in range(N_CASES):
        yield (
            rng.uniform(-math.pi, math.pi, 3),  # angles
            rng.uniform(-2.0, 2.0, 3),  # angle rates
            rng.uniform(-3.0, 3.0, 3),  # body rates
        )


# --- roll-pitch-azimuth (seed 004) ------------------------------------------------------------------------------


def test_elementary_and_composed_matrices_match_numpy_and_are_orthonormal() -> None:
    for ang, _, _ in rng_cases():
        tr, tp, ta = ang
        c_br = passive(r_act(1, tr))  # roll about y_b
        c_rp = passive(r_act(0, tp))  # pitch about x_r
        c_pa = passive(r_act(2, ta))  # azimuth about z_p
        np.testing.assert_allclose(pk.rpa_rot_roll(tr), c_br, atol=TOL)
        np.testing.assert_allclose(pk.rpa_rot_pitch(tp), c_rp, atol=TOL)
        np.testing.assert_allclose(pk.rpa_rot_azimuth(ta), c_pa, atol=TOL)
        c_ba = np.array(pk.rpa_rot_body_to_payload(tr, tp, ta))
        np.testing.assert_allclose(c_ba, c_pa @ c_rp @ c_br, atol=TOL)
        np.testing.assert_allclose(c_ba @ c_ba.T, np.eye(3), atol=TOL)
        assert np.linalg.det(c_ba) == pytest.approx(1.0, abs=TOL)
        prod = pk.mat3_mul(pk.mat3_mul(pk.rpa_rot_azimuth(ta), pk.rpa_rot_pitch(tp)), pk.rpa_rot_roll(tr))
        np.testing.assert_allclose(prod, c_ba, atol=TOL)
        np.testing.assert_allclose(pk.mat3_transpose(pk.rpa_rot_body_to_payload(tr, tp, ta)), c_ba.T, atol=TOL)


def test_eq4_as_printed_except_the_two_flagged_entries() -> None:
    """The printed eq 4 matrices agree with the kinematics everywhere except entry (2,2) of each."""
    for ang, _, _ in rng_cases():
        tr, tp, ta = ang
        cr, sr, cp, sp, ca, sa = (math.cos(tr), math.sin(tr), math.cos(tp), math.sin(tp), math.cos(ta), math.sin(ta))
        printed_1 = np.array(
            [
                [ca * cr + sa * sp * sr, sa * cp, sa * sp * cr - ca * sr],
                [-cr * sa + ca * sp * sr, ca * sp, ca * sp * cr + sa * sr],
                [cp * sr, -sp, cp * cr],
            ]
        )
        printed_2 = np.array([[cp * sa, ca, 0.0], [ca * cp, -sp, 0.0], [-sp, 0.0, 1.0]])
        mask = np.ones((3, 3), dtype=bool)
        mask[1, 1] = False
        np.testing.assert_allclose(np.array(pk.rpa_rot_body_to_payload(tr, tp, ta))[mask], printed_1[mask], atol=TOL)
        np.testing.assert_allclose(np.array(pk.rpa_gimbal_rate_matrix(tp, ta))[mask], printed_2[mask], atol=TOL)
        assert pk.rpa_rot_body_to_payload(tr, tp, ta)[1][1] == pytest.approx(ca * cp, abs=TOL)
        assert pk.rpa_gimbal_rate_matrix(tp, ta)[1][1] == pytest.approx(-sa, abs=TOL)


def test_payload_rate_equals_independent_composition() -> None:
    ex, ey, ez = np.eye(3)
    for ang, rates, w_b in rng_cases():
        tr, tp, ta = ang
        dr, dp, da = rates
        c_rp, c_pa = passive(r_act(0, tp)), passive(r_act(2, ta))
        r_ba = r_act(1, tr) @ r_act(0, tp) @ r_act(2, ta)  # payload attitude in the body frame (active)
        expected = r_ba.T @ w_b + c_pa @ c_rp @ (ey * dr) + c_pa @ (ex * dp) + ez * da
        got = pk.rpa_payload_rate(tuple(w_b), (tr, tp, ta), (dr, dp, da))
        np.testing.assert_allclose(got, expected, atol=1e-12)
        # the same through the two eq 4 matrices
        via_matrices = np.array(pk.rpa_rot_body_to_payload(tr, tp, ta)) @ w_b + np.array(
            pk.rpa_gimbal_rate_matrix(tp, ta)
        ) @ np.array([dr, dp, da])
        np.testing.assert_allclose(got, via_matrices, atol=1e-12)


def test_payload_rate_equals_derivative_of_payload_attitude() -> None:
    """Ground truth from the attitude itself: R_ia(t) = R_ib(t) R_y(tr) R_x(tp) R_z(ta), body spinning at w_b."""
    for ang, rates, w_b in rng_cases(7):
        expected = body_rate_of(rpa_attitude(ang, rates, w_b))
        got = pk.rpa_payload_rate(tuple(w_b), tuple(ang), tuple(rates))
        np.testing.assert_allclose(got, expected, atol=1e-7)


def test_gimbal_gyros_and_eq9_reconstruct_payload_rate() -> None:
    for ang, rates, w_b in rng_cases(11):
        tr, tp, ta = ang
        dr, dp, da = rates
        c_br, c_rp, c_pa = passive(r_act(1, tr)), passive(r_act(0, tp)), passive(r_act(2, ta))
        w_r = c_br @ w_b + np.array([0.0, dr, 0.0])
        w_p = c_rp @ w_r + np.array([dp, 0.0, 0.0])
        w_a = c_pa @ w_p + np.array([0.0, 0.0, da])
        gyros = pk.rpa_gimbal_gyro_rates(tuple(w_b), (tr, tp, ta), (dr, dp, da))
        np.testing.assert_allclose(gyros, (w_p[0], w_r[1], w_a[2]), atol=1e-12)  # eq 5 axes
        # eq 8 (read as the y component of omega_ip^p)
        eq8 = w_r[1] * math.cos(tp) + (w_b[0] * math.sin(tr) + w_b[2] * math.cos(tr)) * math.sin(tp)
        assert w_p[1] == pytest.approx(eq8)
        np.testing.assert_allclose(pk.rpa_payload_rate_from_gyros(gyros, tuple(w_b), (tr, tp, ta)), w_a, atol=1e-12)


def test_accelerometer_projection_eq10() -> None:
    rng = np.random.default_rng(5)
    for ang, _, _ in rng_cases(13):
        tr, tp, ta = ang
        f_b = rng.normal(0.0, 10.0, 3)
        f_p = passive(r_act(0, tp)) @ passive(r_act(1, tr)) @ f_b
        f_a = passive(r_act(2, ta)) @ f_p
        got = pk.rpa_payload_accel_from_gimbal_accels(f_p[0], f_p[1], f_a[2], ta)
        np.testing.assert_allclose(got, f_a, atol=1e-12)


# --- azimuth-elevation gimbal ---------------------------------------------------------------------------------


def test_azel_matrices_and_seed001_eq3() -> None:
    rng = np.random.default_rng(17)
    for ang, _, _ in rng_cases(19):
        az, el = ang[0], ang[1] / 2.0
        c_bo = passive(r_act(2, az))
        c_oe = passive(r_act(1, el))
        np.testing.assert_allclose(pk.azel_rot_body_to_az(az), c_bo, atol=TOL)
        np.testing.assert_allclose(pk.azel_rot_az_to_el(el), c_oe, atol=TOL)
        c_be = np.array(pk.azel_rot_body_to_el(az, el))
        np.testing.assert_allclose(c_be, c_oe @ c_bo, atol=TOL)
        np.testing.assert_allclose(c_be @ c_be.T, np.eye(3), atol=TOL)
        a_b = rng.normal(0.0, 10.0, 3)
        ax, ay, az_ = a_b
        ca, sa, ce, se = math.cos(az), math.sin(az), math.cos(el), math.sin(el)
        printed_eq3 = (
            ax * ca * ce + ay * sa * ce - az_ * se,
            -ax * sa + ay * ca,
            ax * ca * se + ay * sa * se + az_ * ce,
        )
        np.testing.assert_allclose(pk.azel_accel_body_to_el(tuple(a_b), az, el), printed_eq3, atol=1e-12)
        np.testing.assert_allclose(pk.mat3_vec(pk.azel_rot_body_to_el(az, el), tuple(a_b)), c_be @ a_b, atol=1e-12)


def test_azel_los_rate_against_attitude_derivative_and_seed001_eq1() -> None:
    ex, ey, ez = np.eye(3)
    for ang, rates, w_b in rng_cases(23):
        az, el = ang[0], ang[1] / 2.0
        daz, del_ = rates[0], rates[1]

        got = pk.azel_los_inertial_rate(tuple(w_b), az, el, daz, del_)
        np.testing.assert_allclose(got, body_rate_of(azel_attitude((az, el), (daz, del_), w_b)), atol=1e-7)
        # seed 001 eq 1 with omega_O = C_B^O w_b + daz z_O
        w_o = passive(r_act(2, az)) @ w_b + ez * daz
        eq1 = (
            w_o[0] * math.cos(el) - w_o[2] * math.sin(el),
            w_o[1] + del_,
            w_o[0] * math.sin(el) + w_o[2] * math.cos(el),
        )
        np.testing.assert_allclose(got, eq1, atol=1e-12)
        # carrier part on the motor axes and on the elevation-frame gyros
        on_az, on_el, cross = pk.azel_carrier_rate_on_axes(tuple(w_b), az, el)
        assert on_az == pytest.approx(float(ez @ w_b), abs=1e-12)  # azimuth axis = z_b
        assert on_el == pytest.approx(float(ey @ (passive(r_act(2, az)) @ w_b)), abs=1e-12)
        carrier_in_el = np.array(pk.azel_rot_body_to_el(az, el)) @ w_b
        assert cross == pytest.approx(float(carrier_in_el[2]), abs=1e-12)
        gyro_no_gimbal_motion = pk.azel_los_inertial_rate(tuple(w_b), az, el, 0.0, 0.0)
        np.testing.assert_allclose(gyro_no_gimbal_motion, carrier_in_el, atol=1e-12)
        assert float(ex @ carrier_in_el) == pytest.approx(gyro_no_gimbal_motion[0], abs=1e-12)


def test_azel_gimbal_rates_null_the_los_rate() -> None:
    for ang, rates, w_b in rng_cases(29):
        az, el = ang[0], ang[1] / 2.2  # keep away from el = +-90 deg
        want_y, want_z = rates[0], rates[1]
        daz, del_ = pk.azel_gimbal_rates_for_los_rate(tuple(w_b), az, el, want_y, want_z)
        _, wy, wz = pk.azel_los_inertial_rate(tuple(w_b), az, el, daz, del_)
        assert (wy, wz) == pytest.approx((want_y, want_z), abs=1e-9)
    with pytest.raises(ZeroDivisionError):
        pk.azel_gimbal_rates_for_los_rate((0.1, 0.2, 0.3), 0.0, math.pi / 2)


angles = st.floats(min_value=-2.0 * math.pi, max_value=2.0 * math.pi, allow_nan=False)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(angles, angles, angles)
def test_dcms_orthonormal_hypothesis(tr: float, tp: float, ta: float) -> None:
    for m in (pk.rpa_rot_body_to_payload(tr, tp, ta), pk.azel_rot_body_to_el(ta, tp)):
        a = np.array(m)
        np.testing.assert_allclose(a @ a.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(a) == pytest.approx(1.0, abs=1e-12)
