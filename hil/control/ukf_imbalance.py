"""Mass-imbalance identification (UKF) and imbalance-torque feed-forward for the elevation (inner) axis.

After Zhang & Shi, "Mass Imbalance Compensation Control for Stabilized Platform Based on UKF Identification"
(seed 001). Geometry (seed 001 eqs 1, 3, see :mod:`hil.control.pos_kinematics`): outer frame ``O`` = carrier
``B`` turned by ``psi`` (azimuth, rad) about ``z_B``; inner frame ``I`` = ``O`` turned by ``theta`` (elevation, rad)
about ``y_O``; the elevation motor acts about ``y_I``.

Model and reading of the paper (choices marked *):

* Eq 2, ``M_r = dH/dt + Omega x H + rho x m a``, about ``y_I`` with ``H = J omega`` and the gyroscopic term
  ``Omega x H`` neglected (*, second order at LOS rates): ``J eps = tau - M_imb`` with ``tau`` the known
  applied torque (motor torque minus any known friction) and ``M_imb`` of eq 4:
  ``M_imb = m (rho_z a_Ix - rho_x a_Iz)``, ``a_I = C_B^I a_B`` (eq 3).  Eq 5 is the ``tau = 0`` case
  (``eps = -M_imb / J``); the measurement here keeps ``tau`` so the filter runs in closed loop (*).
* ``a_B`` is the carrier *specific force* (what a body accelerometer reads, m/s^2) (*): the CG offset sees
  ``m (g - a)``, so gravity produces imbalance torque too; with the kinematic acceleration it would be missed.
* State (eq 6) ``X = [rho_x, rho_z, a_Bx, a_By, a_Bz, psi, theta]`` in m, m, m/s^2 x3, rad x2; measurement (eq 7)
  ``Z = [eps, a_Bx, a_By, a_Bz, psi, theta]`` in rad/s^2, m/s^2 x3, rad x2.  The paper gives no process model:
  every state is a random walk (*) (eccentricity nearly constant, acceleration and angles tracked through their
  direct measurements, which lets the filter account for their noise inside the nonlinear ``eps`` channel).
* Eccentricity ``rho`` is in metres in the API; the paper's RMSE "0.024" has no unit: the tests read it as mm (*).
* At 100 Hz, ``eps`` is the mean angular acceleration over the 10 ms window (``delta omega / delta t`` of the gyro)
  and ``tau``, ``a_B`` are window means: eq 4 is linear in ``a``, so window means keep the model exact (*).
* Feed-forward (Fig. 2, ``G_N = -M_imb / (G_cl C_m)``): the motor must *add* ``+M_imb`` to cancel the imbalance;
  ``G_cl C_m`` (drive -> torque) is the caller's ``drive_per_n_m`` (e.g. ``R / K_t`` V/N*m, or DAC counts/N*m).
"""

from __future__ import annotations

import math
import random
import time
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np

from hil.control.pos_kinematics import Vec3

__all__ = [
    "STANDARD_GRAVITY_M_S2",
    "ImbalanceFeedForward",
    "ImbalanceScenario",
    "ImbalanceUKF",
    "ScenarioResult",
    "imbalance_torque",
    "simulate_imbalance_scenario",
]

STANDARD_GRAVITY_M_S2 = 9.80665


def imbalance_torque(
    rho_m: tuple[float, float],
    mass_kg: float,
    accel_body_m_s2: Vec3,
    az_rad: float,
    el_rad: float,
) -> float:
    """Imbalance torque ``M_imb`` about the elevation axis in N*m (seed 001 eqs 3-4); ``rho_m = (rho_x, rho_z)``
    in m (inner frame), ``mass_kg`` the inner-frame mass, angles in rad.

    ``M_imb = m (rho_z a_Ix - rho_x a_Iz)`` with ``a_Ix, a_Iz`` the carrier specific force ``accel_body_m_s2``
    (body frame, m/s^2) projected on the inner frame. The imbalance acts on the axis as ``-M_imb``; ``+M_imb`` is
    the feed-forward torque that cancels it.
    """
    rho_x_m, rho_z_m = rho_m
    ax, ay, az_ = accel_body_m_s2
    ca, sa = math.cos(az_rad), math.sin(az_rad)
    ce, se = math.cos(el_rad), math.sin(el_rad)
    h = ca * ax + sa * ay
    a_ix = h * ce - az_ * se
    a_iz = h * se + az_ * ce
    return mass_kg * (rho_z_m * a_ix - rho_x_m * a_iz)


class ImbalanceUKF:
    """UKF identification of the inner-frame eccentricity ``(rho_x, rho_z)`` (seed 001 eqs 6-11), filterpy
    ``UnscentedKalmanFilter`` with ``MerweScaledSigmaPoints``; meant to run decimated (``dt_s`` = 0.01 s).

    Noise parameters are standard deviations: ``*_noise_std`` per measurement sample (of the window means passed
    to :meth:`step`), ``*_walk_std`` the random-walk increment per filter step.
    """

    DIM_X = 7
    DIM_Z = 6

    def __init__(
        self,
        *,
        mass_kg: float,
        inertia_kg_m2: float,
        dt_s: float = 0.01,
        rho0_m: tuple[float, float] = (0.0, 0.0),
        rho0_std_m: float = 0.01,
        angular_accel_noise_std_rad_s2: float = 0.05,
        accel_noise_std_m_s2: float = 0.02,
        angle_noise_std_rad: float = 1e-4,
        rho_walk_std_m: float = 1e-7,
        accel_walk_std_m_s2: float = 2.0,
        angle_walk_std_rad: float = 1e-2,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
    ) -> None:
        if mass_kg <= 0.0 or inertia_kg_m2 <= 0.0 or dt_s <= 0.0:
            raise ValueError("mass_kg, inertia_kg_m2 and dt_s must be positive")
        self.mass_kg = float(mass_kg)
        self.inertia_kg_m2 = float(inertia_kg_m2)
        self.dt_s = float(dt_s)
        # filterpy loads scipy.stats (about 60 % of the bench's import time): only a UKF controller needs it
        from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter  # noqa: PLC0415

        points = MerweScaledSigmaPoints(self.DIM_X, alpha=alpha, beta=beta, kappa=kappa)
        ukf = UnscentedKalmanFilter(
            dim_x=self.DIM_X, dim_z=self.DIM_Z, dt=self.dt_s, hx=self._hx, fx=self._fx, points=points
        )
        ukf.x = np.array([rho0_m[0], rho0_m[1], 0.0, 0.0, 0.0, 0.0, 0.0])
        ukf.P = np.diag([rho0_std_m**2] * 2 + [100.0] * 3 + [1.0] * 2)  # eq 8; angles/accels unknown before step 1
        ukf.Q = np.diag([rho_walk_std_m**2] * 2 + [accel_walk_std_m_s2**2] * 3 + [angle_walk_std_rad**2] * 2)
        ukf.R = np.diag(
            [angular_accel_noise_std_rad_s2**2] + [accel_noise_std_m_s2**2] * 3 + [angle_noise_std_rad**2] * 2
        )
        self.filter = ukf
        self._initialised = False
        self.resets = 0  # covariance resets after a failed Cholesky (see step)

    # filterpy callbacks -------------------------------------------------------------------------------------------
    @staticmethod
    def _fx(x: np.ndarray, dt: float) -> np.ndarray:
        return x  # random walk (the paper gives no process model)

    def _hx(self, x: np.ndarray, applied_torque_n_m: float = 0.0) -> np.ndarray:
        rx, rz, ax, ay, az_, psi, theta = (float(v) for v in x)
        m_imb = imbalance_torque((rx, rz), self.mass_kg, (ax, ay, az_), psi, theta)
        eps = (applied_torque_n_m - m_imb) / self.inertia_kg_m2  # eq 2 about y_I; eq 5 when tau = 0
        return np.array([eps, ax, ay, az_, psi, theta])

    # public API ---------------------------------------------------------------------------------------------------
    def step(
        self,
        *,
        angular_accel_rad_s2: float,
        accel_body_m_s2: Vec3,
        az_rad: float,
        el_rad: float,
        applied_torque_n_m: float = 0.0,
    ) -> tuple[float, float]:
        """One predict + update (eqs 9-11). Inputs are window means over the last ``dt_s``: inner-frame inertial
        angular acceleration about the elevation axis (rad/s^2), carrier specific force in the body frame (m/s^2),
        gimbal angles (rad), known applied torque about the elevation axis (N*m). Returns ``(rho_x_m, rho_z_m)``."""
        ukf = self.filter
        if not self._initialised:  # start the pseudo-states at their first measurement
            ukf.x[2:5] = accel_body_m_s2
            ukf.x[5] = az_rad
            ukf.x[6] = el_rad
            ukf.P[2:, :] = 0.0
            ukf.P[:, 2:] = 0.0
            ukf.P[2:, 2:] = ukf.R[1:, 1:]
            self._initialised = True
        z = np.array([angular_accel_rad_s2, *accel_body_m_s2, az_rad, el_rad])
        x0, p0 = ukf.x.copy(), ukf.P.copy()
        try:
            ukf.predict()
            ukf.update(z, applied_torque_n_m=applied_torque_n_m)
        except np.linalg.LinAlgError:
            # covariance lost definiteness (e.g. a gimbal slew far beyond angle_walk_std_rad): keep the eccentricity
            # block, restart the pseudo-states at this measurement, skip this update
            self.resets += 1
            ukf.x, ukf.P = x0, p0
            ukf.x[2:] = z[1:]
            ukf.P[2:, :] = 0.0
            ukf.P[:, 2:] = 0.0
            ukf.P[2:, 2:] = ukf.R[1:, 1:]
        ukf.P = 0.5 * (ukf.P + ukf.P.T)
        return float(ukf.x[0]), float(ukf.x[1])

    def reset_eccentricity(self, rho0_m: tuple[float, float] | None = None, rho0_std_m: float = 0.01) -> None:
        """Re-open the eccentricity covariance (payload change, or after a stretch where the model did not hold:
        a random-walk filter fed inconsistent data ends over-confident and recovers only slowly)."""
        ukf = self.filter
        if rho0_m is not None:
            ukf.x[0], ukf.x[1] = rho0_m
        ukf.P[:2, :] = 0.0
        ukf.P[:, :2] = 0.0
        ukf.P[0, 0] = ukf.P[1, 1] = rho0_std_m**2
        self._initialised = False  # pseudo-states restart at the next measurement

    @property
    def eccentricity_m(self) -> tuple[float, float]:
        """Current estimate ``(rho_x, rho_z)`` in m."""
        x = self.filter.x
        return float(x[0]), float(x[1])

    @property
    def eccentricity_cov_m2(self) -> np.ndarray:
        """2x2 covariance of the eccentricity estimate (m^2)."""
        return self.filter.P[:2, :2].copy()

    @property
    def state(self) -> np.ndarray:
        """Full state ``[rho_x, rho_z, a_Bx, a_By, a_Bz, psi, theta]`` (eq 6)."""
        return self.filter.x.copy()

    @property
    def covariance(self) -> np.ndarray:
        """Full 7x7 state covariance."""
        return self.filter.P.copy()


@dataclass(slots=True)
class ImbalanceFeedForward:
    """Imbalance feed-forward (seed 001 Fig. 2) evaluated at the control rate with the latest UKF estimate.

    ``drive_per_n_m``: drive units per N*m of motor torque (1.0 -> N*m; ``R/K_t`` -> volts; counts/N*m -> DAC
    counts). ``drive_limit``: symmetric clamp in drive units (``inf`` = none).
    """

    mass_kg: float
    drive_per_n_m: float = 1.0
    drive_limit: float = math.inf
    rho_x_m: float = 0.0
    rho_z_m: float = 0.0

    def set_eccentricity(self, rho_x_m: float, rho_z_m: float) -> None:
        self.rho_x_m = rho_x_m
        self.rho_z_m = rho_z_m

    def torque_n_m(self, accel_body_m_s2: Vec3, az_rad: float, el_rad: float) -> float:
        """Feed-forward motor torque ``+M_imb`` (N*m)."""
        return imbalance_torque((self.rho_x_m, self.rho_z_m), self.mass_kg, accel_body_m_s2, az_rad, el_rad)

    def drive(self, accel_body_m_s2: Vec3, az_rad: float, el_rad: float) -> float:
        """Feed-forward in drive units, clamped to ``+-drive_limit``."""
        d = self.drive_per_n_m * self.torque_n_m(accel_body_m_s2, az_rad, el_rad)
        return max(-self.drive_limit, min(self.drive_limit, d))


# --- scenario simulator (seed 001 section 4) ----------------------------------------------------------------------


class UkfOptions(TypedDict, total=False):
    """The :class:`ImbalanceUKF` keyword arguments a scenario passes on (the rest it sets from its own fields)."""

    rho0_m: tuple[float, float]
    rho0_std_m: float
    rho_walk_std_m: float
    accel_walk_std_m_s2: float
    angle_walk_std_rad: float
    alpha: float
    beta: float
    kappa: float


@dataclass(slots=True)
class ImbalanceScenario:
    """Seed 001 section 4 scenario on a 2-axis platform (eqs 1-5).

    Motor (paper): L = 2.8 mH, R = 5.1 ohm, K_t = 0.21 N*m/A (back-EMF K_e = K_t V*s/rad); rate-loop PI on the
    gyro with ``kp_v_per_rad_s`` = 34.5 (the paper's "feed-back control gain", read as V per rad/s *) plus an
    integral term. Carrier: specific force ``g`` along ``+z_B`` plus a 0.5 g, 2.5 Hz sinusoid on each body axis
    with phases ``vib_phase_rad`` (non-collinear in time so ``rho_x`` and ``rho_z`` are separable *). No carrier
    angular motion. Outer (azimuth) axis: same loop, own eccentricity (``rho_outer_m``, default balanced), no
    feed-forward; the inner frame's reaction on the outer axis is not modelled (*). Plant integrated at
    ``plant_substeps`` x the 1 kHz control rate; UKF every ``ukf_decimation`` control ticks.
    """

    duration_s: float = 3.0
    use_feedforward: bool = True
    seed: int = 1
    rho_true_m: tuple[float, float] = (5.0e-3, -3.0e-3)
    rho_outer_m: tuple[float, float] = (0.0, 0.0)
    mass_inner_kg: float = 10.0
    inertia_inner_kg_m2: float = 0.05
    mass_outer_kg: float = 15.0
    inertia_outer_kg_m2: float = 0.1
    az0_rad: float = 0.3
    el0_rad: float = -0.4
    vib_amp_g: float = 0.5
    vib_freq_hz: float = 2.5
    vib_phase_rad: tuple[float, float, float] = (0.0, 0.7, math.pi / 2)
    include_gravity: bool = True
    motor_r_ohm: float = 5.1
    motor_l_h: float = 2.8e-3
    motor_kt_n_m_per_a: float = 0.21
    kp_v_per_rad_s: float = 34.5
    ki_v_per_rad: float = 200.0
    v_limit_v: float = 28.0
    ctrl_dt_s: float = 1e-3
    plant_substeps: int = 10
    ukf_decimation: int = 10
    gyro_noise_rad_s: float = 2e-4
    accel_noise_m_s2: float = 0.02
    angle_noise_rad: float = 1e-5
    current_noise_a: float = 0.005
    ukf_kwargs: UkfOptions = field(default_factory=UkfOptions)


@dataclass(slots=True)
class ScenarioResult:
    """Time series of a scenario run (lists of floats). ``t_ukf_s``/``rho_est_m`` at the UKF rate, the rest at
    the control rate. ``los_rate_rad_s``: inner-frame inertial rate ``(y: elevation, z: cross-elevation)``
    (seed 001 eq 1)."""

    t_s: list[float]
    los_rate_y_rad_s: list[float]
    los_rate_z_rad_s: list[float]
    m_imb_true_n_m: list[float]
    m_imb_est_n_m: list[float]
    t_ukf_s: list[float]
    rho_est_m: list[tuple[float, float]]
    rho_true_m: tuple[float, float]
    ukf_step_s: list[float]


def simulate_imbalance_scenario(sc: ImbalanceScenario) -> ScenarioResult:
    """Run the scenario; the UKF always runs (so its estimate can be inspected), the feed-forward is applied only
    when ``sc.use_feedforward``."""
    rng = random.Random(sc.seed)
    g = STANDARD_GRAVITY_M_S2
    amp = sc.vib_amp_g * g
    w_vib = 2.0 * math.pi * sc.vib_freq_hz
    dt = sc.ctrl_dt_s
    h = dt / sc.plant_substeps
    r_, l_, kt = sc.motor_r_ohm, sc.motor_l_h, sc.motor_kt_n_m_per_a
    decay = math.exp(-r_ * h / l_)
    ph = sc.vib_phase_rad
    grav = g if sc.include_gravity else 0.0

    def accel(t: float) -> Vec3:
        return (
            amp * math.sin(w_vib * t + ph[0]),
            amp * math.sin(w_vib * t + ph[1]),
            grav + amp * math.sin(w_vib * t + ph[2]),
        )

    def m_imb_outer(a_b: Vec3, psi: float) -> float:
        # (rho_O x m_O a_O)_z with a_O = C_B^O a_B, the outer-axis analogue of eq 4
        c, s = math.cos(psi), math.sin(psi)
        a_ox, a_oy = c * a_b[0] + s * a_b[1], -s * a_b[0] + c * a_b[1]
        return sc.mass_outer_kg * (sc.rho_outer_m[0] * a_oy - sc.rho_outer_m[1] * a_ox)

    ukf = ImbalanceUKF(
        mass_kg=sc.mass_inner_kg,
        inertia_kg_m2=sc.inertia_inner_kg_m2,
        dt_s=dt * sc.ukf_decimation,
        angular_accel_noise_std_rad_s2=math.sqrt(2.0) * sc.gyro_noise_rad_s / (dt * sc.ukf_decimation) + 0.01,
        accel_noise_std_m_s2=sc.accel_noise_m_s2 / math.sqrt(sc.ukf_decimation) + 1e-3,
        angle_noise_std_rad=sc.angle_noise_rad + 1e-5,
        **sc.ukf_kwargs,
    )
    ff = ImbalanceFeedForward(mass_kg=sc.mass_inner_kg, drive_per_n_m=r_ / kt, drive_limit=sc.v_limit_v)

    # plant state: inner (theta, omega_Iy, current), outer (psi, omega_Oz, current)
    th, w_i, i_i = sc.el0_rad, 0.0, 0.0
    ps, w_o, i_o = sc.az0_rad, 0.0, 0.0
    integ_i = integ_o = 0.0
    t = 0.0
    n_ctrl = round(sc.duration_s / dt)
    out = ScenarioResult([], [], [], [], [], [], [], sc.rho_true_m, [])
    # window sums for the decimated UKF (trapezoid over the control samples)
    win_acc = [0.0, 0.0, 0.0]
    win_tau = 0.0
    win_w0 = 0.0
    prev: tuple[Vec3, float] | None = None

    for k in range(n_ctrl + 1):
        # --- sample sensors at t
        a_true = accel(t)
        a_meas: Vec3 = (
            a_true[0] + rng.gauss(0.0, sc.accel_noise_m_s2),
            a_true[1] + rng.gauss(0.0, sc.accel_noise_m_s2),
            a_true[2] + rng.gauss(0.0, sc.accel_noise_m_s2),
        )
        gyro_i = w_i + rng.gauss(0.0, sc.gyro_noise_rad_s)
        gyro_o = w_o + rng.gauss(0.0, sc.gyro_noise_rad_s)
        th_m = th + rng.gauss(0.0, sc.angle_noise_rad)
        ps_m = ps + rng.gauss(0.0, sc.angle_noise_rad)
        tau_meas = kt * (i_i + rng.gauss(0.0, sc.current_noise_a))

        # --- decimated UKF on the window ending at this sample
        if prev is not None:
            pa, ptau = prev
            for j in range(3):
                win_acc[j] += 0.5 * (pa[j] + a_meas[j])
            win_tau += 0.5 * (ptau + tau_meas)
        if k % sc.ukf_decimation == 0:
            if k > 0:
                n = sc.ukf_decimation
                t0 = time.perf_counter()
                rho = ukf.step(
                    angular_accel_rad_s2=(gyro_i - win_w0) / (n * dt),
                    accel_body_m_s2=(win_acc[0] / n, win_acc[1] / n, win_acc[2] / n),
                    az_rad=ps_m,
                    el_rad=th_m,
                    applied_torque_n_m=win_tau / n,
                )
                out.ukf_step_s.append(time.perf_counter() - t0)
                ff.set_eccentricity(*rho)
                out.t_ukf_s.append(t)
                out.rho_est_m.append(rho)
            win_acc = [0.0, 0.0, 0.0]
            win_tau = 0.0
            win_w0 = gyro_i
        prev = (a_meas, tau_meas)

        # --- record
        m_true = imbalance_torque(sc.rho_true_m, sc.mass_inner_kg, a_true, ps, th)
        out.t_s.append(t)
        out.los_rate_y_rad_s.append(w_i)  # eq 1 y row with omega_Oy = 0 (no carrier rotation)
        out.los_rate_z_rad_s.append(w_o * math.cos(th))  # eq 1 z row with omega_Ox = 0
        out.m_imb_true_n_m.append(m_true)
        out.m_imb_est_n_m.append(ff.torque_n_m(a_meas, ps_m, th_m))
        if k == n_ctrl:
            break

        # --- 1 kHz rate loops (command: zero inertial rate)
        integ_i += gyro_i * dt
        integ_o += gyro_o * dt
        v_i = -sc.kp_v_per_rad_s * gyro_i - sc.ki_v_per_rad * integ_i
        if sc.use_feedforward:
            v_i += ff.drive(a_meas, ps_m, th_m)
        v_o = -sc.kp_v_per_rad_s * gyro_o - sc.ki_v_per_rad * integ_o
        v_i = max(-sc.v_limit_v, min(sc.v_limit_v, v_i))
        v_o = max(-sc.v_limit_v, min(sc.v_limit_v, v_o))

        # --- plant, ZOH voltage, exact L-R current step, semi-implicit Euler mechanics
        for _ in range(sc.plant_substeps):
            a_b = accel(t)
            i_i = i_i * decay + (1.0 - decay) * (v_i - kt * w_i) / r_
            i_o = i_o * decay + (1.0 - decay) * (v_o - kt * w_o) / r_
            m_i = imbalance_torque(sc.rho_true_m, sc.mass_inner_kg, a_b, ps, th)
            w_i += h * (kt * i_i - m_i) / sc.inertia_inner_kg_m2  # eq 2 about y_I, J eps = tau - M_imb
            w_o += h * (kt * i_o - m_imb_outer(a_b, ps)) / sc.inertia_outer_kg_m2
            th += h * w_i
            ps += h * w_o
            t += h
        t = (k + 1) * dt
    return out
