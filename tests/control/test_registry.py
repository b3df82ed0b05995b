"""Controllers by name: validation errors, and every registered controller closing the rate loop."""

from __future__ import annotations

import itertools
import math
import random
import statistics

import pytest

from hil.control.controller import RateController
from hil.control.registry import REGISTRY, ControllerConfigError, EsoKfParams, build_controller, controller_params

K_M = 0.023
H = 1e-3


def run_axis(controller: RateController, *, d_counts, seconds: float = 3.0, noise_dps: float = 0.034, seed: int = 1):
    """Rate loop at rate command 0 on d(rate)/dt = k_m (u + d(t)) with gyro noise; stats after 1 s."""
    rng = random.Random(seed)
    rate = 0.0
    errors, drives = [], []
    for k in range(int(seconds / H)):
        u = controller.step(0.0, rate + rng.gauss(0.0, noise_dps))
        rate += K_M * (u + d_counts(k * H)) * H
        if k * H >= 1.0:
            errors.append(rate)
            drives.append(u)
    ripple = statistics.pstdev([b - a for a, b in itertools.pairwise(drives)])
    return statistics.pstdev(errors), ripple


def swing(amplitude_counts: float):
    """A 1 Hz sine plus a Coulomb-friction-like square wave, in counts."""
    def d_counts(t: float) -> float:
        s = math.sin(2 * math.pi * t)
        return amplitude_counts * s + 300.0 * math.copysign(1.0, s)

    return d_counts


def test_the_names_the_issue_asks_for_are_registered():
    assert {"eso", "eso_nonlinear", "eso_kf", "eso_kf_high_gain", "pi_lpf", "eso_kf_ukf_ff"} <= set(REGISTRY)


def test_unknown_controller_lists_the_ones_that_exist():
    with pytest.raises(ControllerConfigError, match=r"^unknown controller 'lqr' \(controllers: eso, .*pi_lpf"):
        build_controller("lqr")


def test_unknown_parameter_is_named_with_the_valid_ones():
    expected = r"^controller 'eso': unknown parameter 'omega_o' \(parameters: .*omega_o_rad_s"
    with pytest.raises(ControllerConfigError, match=expected):
        controller_params("eso", {"omega_o": 100})


def test_bad_value_names_the_field_and_the_reason():
    expected = r"^controller 'eso_kf': parameter 'r_dps2': Input should be greater than 0 \(got -1\)$"
    with pytest.raises(ControllerConfigError, match=expected):
        controller_params("eso_kf", {"r_dps2": -1})


def test_high_gain_is_the_same_method_with_a_faster_observer():
    normal, high = controller_params("eso_kf"), controller_params("eso_kf_high_gain")
    assert type(build_controller("eso_kf").estimator) is type(build_controller("eso_kf_high_gain").estimator)
    assert high.omega_o_rad_s > normal.omega_o_rad_s
    assert high.model_dump(exclude={"omega_o_rad_s"}) == normal.model_dump(exclude={"omega_o_rad_s"})


def test_a_params_object_builds_the_same_controller_as_its_dict():
    p = EsoKfParams(omega_o_rad_s=500.0)
    from_dict = build_controller("eso_kf", {"omega_o_rad_s": 500})
    assert build_controller("eso_kf", p).estimator.eso.l1 == from_dict.estimator.eso.l1


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_every_controller_holds_the_rate_near_zero_under_a_swing_disturbance(name):
    std, _ = run_axis(build_controller(name), d_counts=swing(300.0))
    assert std < 0.05  # deg/s; the open loop would drift by tens of deg/s


def test_disturbance_rejection_beats_the_low_pass_baseline_on_a_strong_swing():
    baseline, _ = run_axis(build_controller("pi_lpf"), d_counts=swing(3000.0))
    for name in ("eso", "eso_kf", "eso_kf_high_gain"):
        std, _ = run_axis(build_controller(name), d_counts=swing(3000.0))
        assert std < 0.5 * baseline, name


def test_the_kalman_filter_cuts_the_drive_ripple_that_gyro_noise_causes():
    """Seed 000's point: with the same ESO gain, ESO + KF feeds less gyro noise into the drive. It needs a slow KF
    (q = s = 5e-5, gain 0.25); the registry's default (q = s = 5e-4, gain 0.59, the process noise measured on the
    emulated plant's swing: docs/control.md) tracks friction transients instead and passes the ESO's ripple."""
    _, ripple_eso = run_axis(build_controller("eso"), d_counts=swing(300.0))
    _, ripple_kf = run_axis(build_controller("eso_kf", {"q_dps2": 5e-5, "s_dps2": 5e-5}), d_counts=swing(300.0))
    assert ripple_kf < 0.6 * ripple_eso
    _, ripple_default = run_axis(build_controller("eso_kf"), d_counts=swing(300.0))
    assert ripple_default < 1.05 * ripple_eso


def test_controller_feeds_the_applied_drive_back_and_reports_its_estimates():
    c = build_controller("eso", {"u_max_counts": 100})
    u = c.step(0.0, -10.0)  # huge rate error: saturates
    assert u == 100 and c.u_counts == 100
    c.hold(0)  # a watchdog zeroed the drive: the observer must be told
    assert c.u_counts == 0
    c.step(0.0, -10.0)
    assert c.rate_fb_dps == c.estimator.rate_dps  # eso feeds back its z1, the standard LADRC form
    assert c.disturbance_counts == c.estimator.disturbance_counts != 0.0


def test_imbalance_feedforward_controller_identifies_and_feeds_forward_in_counts():
    """Noise-free measurements from a known eccentricity: the identified feed-forward matches the true torque."""
    from hil.control.ukf_imbalance import imbalance_torque

    c = build_controller("eso_kf_ukf_ff", {"ff_limit_counts": 32767})
    assert c.imbalance is not None and build_controller("eso_kf").imbalance is None
    rho_true = (0.004, -0.002)  # m
    mass, inertia = 10.0, 0.05
    for k in range(200):  # 2 s of 100 Hz identification, 0.5 g at 2.5 Hz on two body axes
        t = k * 0.01
        accel = (4.9 * math.sin(2 * math.pi * 2.5 * t), 0.0, 4.9 * math.sin(2 * math.pi * 2.5 * t + 1.0))
        torque_imb = imbalance_torque(rho_true, mass, accel, 0.0, 0.0)
        c.imbalance.identify(angular_accel_rad_s2=-torque_imb / inertia, accel_body_m_s2=accel, az_rad=0.0, el_rad=0.0)
    rho = c.imbalance.ukf.eccentricity_m
    assert rho[0] == pytest.approx(rho_true[0], abs=2e-4) and rho[1] == pytest.approx(rho_true[1], abs=2e-4)
    accel = (3.0, 0.0, -2.0)
    expected = 49830.0 * imbalance_torque(rho_true, mass, accel, 0.0, 0.0)
    assert c.imbalance.drive_counts(accel, 0.0, 0.0) == pytest.approx(expected, rel=0.05)
