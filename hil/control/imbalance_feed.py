"""What the bench has per 1 ms tick -> the imbalance UKF's measurements and the elevation feed-forward (seed 001).

:class:`ImbalanceFeed` sits between the session's 1 kHz loop and a controller's
:class:`~hil.control.controller.ImbalanceCompensation` (``RateController.imbalance``)::

    ff = feed.tick(t_profile_s, gyro_el_dps=g.rate_y_dps, az_deg=g.az_deg, el_deg=g.el_deg,
                   drive_el_counts=u_el_applied_last_tick)
    u_el = ctrl_el.step(cmd_el, g.rate_y_dps, ff)

**The estimator must not see the feed-forward** as part of its known input: an ESO estimates the *whole*
disturbance (imbalance included) from the drive it is told was applied, so with ``u = PI - d + ff`` and ``u`` fed
back as is, the imbalance is cancelled twice and the P term settles at ``-ff`` (a rate error of ``ff / kp``: ~0.6
deg/s on the default plant). The estimator must get ``u - ff`` (then it estimates the residual ``D + ff``), which
is what ``RateController.step`` does.

Measurements (window means over each UKF step, ``ukf.dt_s`` = 10 ticks by default; seed 001 eq 7):

* **carrier specific force** ``f_B`` (body frame, m/s^2): there is no accelerometer on the bench, so *the hexapod
  controller's commanded motion is the accelerometer*: the loaded profile's analytic acceleration
  (:func:`hil.protocol.swing.evaluate`: mm/s^2, deg) at the profile time, minus gravity, rotated into the carrier
  body by the commanded attitude. Conventions of the emulated plant (firmware_stub/plant.py ``carrier_state``):
  lab and body z **down**, so ``f_lab = (x'', y'', z'' - g)``; ``f_B = R_x(roll) R_y(pitch) R_z(yaw) f_lab`` (ZYX
  Euler angles, passive DCM lab -> body). Lever arms and the hexapod's tracking error are ignored.
* **angular acceleration** about the elevation axis (rad/s^2): the elevation gyro (``rate_y``, the inertial rate
  of the elevation frame about ``y_e``) differenced over the window, ``(w_k - w_{k-n}) / (n dt)``. The gyro's lag
  (~1.3 ms on the default plant) is left uncorrected: in closed loop this term is small beside the torque.
* **applied torque** (N*m): the drive applied over each tick divided by ``counts_per_n_m`` (back-EMF and bearing
  friction unmodelled).
* **gimbal angles** (rad): the encoders, az about ``z_b``, el about ``y_o``, positive el raises the LOS.

With these, ``imbalance_torque`` (seed 001 eq 4, acting as ``-M_imb``) equals the plant's ``imbalance_torques``
elevation torque (``-m rho x f``) exactly (tests/control/test_imbalance_feed.py).

Timing: the drive ``u_k`` computed at tick ``k`` is applied over ``[t_k, t_k + dt]``, and the plant holds the
imbalance torque at mid-tick, so the feed-forward uses ``f_B(t_k + dt/2)``; the same value, kept, is the specific
force of the window tick ``[t_k, t_k+1]`` in which ``u_k`` (passed back as ``drive_el_counts`` at ``k + 1``) acts:
one profile evaluation per tick. A constant error in the profile time rotates the estimate (x and z vibration are
in quadrature): 1 ms is ~0.9 deg at 2.5 Hz (see :class:`ProfileClock`).

Friction, and the choices it forces (the UKF model, eq 2, has none):

* mean removal (``ac_only``, default on): the gimbal creeps at the gyro's bias against a Coulomb friction ~5x the
  default imbalance moment, and that mean friction torque is, at a fixed elevation, indistinguishable from the
  static gravity moment ``m g rho_x`` (it moved rho_x from 0.5 to 1.16 mm). So the window means of torque, angular
  acceleration and specific force given to the UKF are high-passed by the same first-order filter (time constant
  ``dc_time_constant_s``): ``rho`` is identified from the vibration (eq 4 is linear in ``f`` at fixed angles).
  The feed-forward itself uses the full specific force, gravity included.
* in the bearing's stiff pre-sliding zone friction carries part of the imbalance, so the motor torque (what the
  UKF sees) is only a share of it: with feedback alone the estimate is biased (rho_z 0.1 mm for 1.0 mm). Once the
  feed-forward is on, the torque still unexplained shrinks as the estimate improves, so the estimate iterates to
  the truth; that needs the eccentricity to keep a random walk (``rho_walk_std_m``, set on the UKF's Q: 1e-6 m
  per step; the UKF's 1e-7 freezes it, 1e-5 made the loop diverge). When friction takes nearly all of the
  residual (5/-3 mm payload) the iteration stalls short of the truth (rho ~ 3/-2.3 mm).

The feed-forward is 0 while ``t_profile_s`` is None (no profile running: the windows restart) and until the
eccentricity is identified: at least ``warmup_s`` of UKF updates (after ``3 dc_time_constant_s`` for the means)
and both eccentricity standard deviations below ``converged_std_m``.

Per-tick cost: plain floats (one profile evaluation, one rotation, the feed-forward torque); numpy only inside the
decimated UKF step (~0.25 ms every 10 ms; ``ukf_last_s``, ``ukf_max_s``, ``ukf_total_s / ukf_steps``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

from hil.control.controller import ImbalanceCompensation
from hil.control.ukf_imbalance import STANDARD_GRAVITY_M_S2
from hil.protocol.swing import Profile, Segment

__all__ = ["RHO_WALK_STD_M", "ImbalanceFeed", "ProfileClock", "specific_force_body"]

D2R = math.pi / 180.0
RHO_WALK_STD_M = 1e-6  # eccentricity random walk per UKF step set by the feed (the UKF's own default: 1e-7)


def specific_force_body(
    accel_mm_s2: tuple[float, float, float], attitude_deg: tuple[float, float, float]
) -> tuple[float, float, float]:
    """Carrier specific force in the body frame (m/s^2) from the hexapod's translational acceleration (mm/s^2,
    lab frame, z down) and attitude ``(roll, pitch, yaw)`` in deg (ZYX): ``C_lab^body (a - (0, 0, g))``."""
    roll, pitch, yaw = attitude_deg
    sf, cf = math.sin(roll * D2R), math.cos(roll * D2R)
    st, ct = math.sin(pitch * D2R), math.cos(pitch * D2R)
    sp, cp = math.sin(yaw * D2R), math.cos(yaw * D2R)
    fx, fy, fz = accel_mm_s2[0] * 1e-3, accel_mm_s2[1] * 1e-3, accel_mm_s2[2] * 1e-3 - STANDARD_GRAVITY_M_S2
    return (
        ct * cp * fx + ct * sp * fy - st * fz,
        (sf * st * cp - cf * sp) * fx + (sf * st * sp + cf * cp) * fy + sf * ct * fz,
        (cf * st * cp + sf * sp) * fx + (cf * st * sp - sf * cp) * fy + cf * ct * fz,
    )


class ImbalanceFeed:
    """Feeds one :class:`ImbalanceCompensation` (elevation axis) from the bench's 1 kHz samples.

    ``segments``: the loaded hexapod profile (``config.profile.protocol_segments()``), evaluated at the profile
    time given to :meth:`tick`. ``counts_per_n_m`` defaults to the feed-forward's ``drive_per_n_m``.
    ``apply=False`` identifies but returns 0 (to watch the UKF with feedback alone). ``rho_walk_std_m`` is written
    into the controller's UKF (its Q, eccentricity block; None leaves the registry's value).
    """

    def __init__(
        self,
        imbalance: ImbalanceCompensation,
        segments: Sequence[Segment],
        *,
        dt_s: float = 1e-3,
        counts_per_n_m: float | None = None,
        ac_only: bool = True,
        dc_time_constant_s: float = 0.5,
        warmup_s: float = 1.0,
        converged_std_m: float = 2e-4,
        apply: bool = True,
        rho_walk_std_m: float | None = RHO_WALK_STD_M,
    ) -> None:
        if dt_s <= 0.0 or dc_time_constant_s <= 0.0:
            raise ValueError("dt_s and dc_time_constant_s must be positive")
        self.imbalance = imbalance
        ukf_dt = imbalance.ukf.dt_s
        self.decimation = n = max(1, round(ukf_dt / dt_s))
        if abs(n * dt_s - ukf_dt) > 1e-6 * ukf_dt:
            raise ValueError(f"the UKF step {ukf_dt!r} s is not a whole number of {dt_s!r} s ticks")
        self.dt_s = float(dt_s)
        self.counts_per_n_m = float(counts_per_n_m or imbalance.feedforward.drive_per_n_m)
        self.ac_only = ac_only
        self.dc_alpha = min(1.0, ukf_dt / dc_time_constant_s)
        self.dc_settle_steps = round(3.0 * dc_time_constant_s / ukf_dt) if ac_only else 0
        self.warmup_steps = round(warmup_s / ukf_dt)
        self.converged_std_m = converged_std_m
        self.apply = apply
        if rho_walk_std_m is not None:
            q = imbalance.ukf.filter.Q
            q[0, 0] = q[1, 1] = rho_walk_std_m**2
        self.segments = tuple(segments)
        self._profile = Profile(self.segments)
        # outputs
        self.ff_counts = 0.0
        self.identified = False
        self.ukf_steps = 0  # UKF updates so far
        self.ukf_last_s = 0.0  # wall time of the last UKF step
        self.ukf_max_s = 0.0
        self.ukf_total_s = 0.0  # sum over the UKF steps (mean = ukf_total_s / ukf_steps)
        self.f_body: tuple[float, float, float] = (0.0, 0.0, -STANDARD_GRAVITY_M_S2)  # at t_k + dt/2
        self._restart()
        self._dc: list[float] | None = None  # running means: eps, tau, f_x, f_y, f_z
        self._dc_steps = 0

    # -- state -----------------------------------------------------------------------------------------------------

    def _restart(self) -> None:
        """Open a new window at the next tick (no previous sample to difference against)."""
        self._running = False
        self._count = 0
        self._w0 = 0.0
        self._s_tau = self._s_fx = self._s_fy = self._s_fz = self._s_az = self._s_el = 0.0

    def reset(self) -> None:
        """Forget the windows and the running means (the UKF's estimate is kept)."""
        self._restart()
        self._dc = None
        self._dc_steps = 0
        self.ff_counts = 0.0

    @property
    def rho_m(self) -> tuple[float, float]:
        """Current eccentricity estimate ``(rho_x, rho_z)`` in m (elevation frame: x LOS, z down)."""
        return self.imbalance.ukf.eccentricity_m

    @property
    def rho_std_m(self) -> tuple[float, float]:
        p = self.imbalance.ukf.filter.P
        return math.sqrt(max(0.0, float(p[0, 0]))), math.sqrt(max(0.0, float(p[1, 1])))

    # -- profile ---------------------------------------------------------------------------------------------------

    def carrier_specific_force(self, t_s: float) -> tuple[float, float, float]:
        """The profile's specific force in the body frame (m/s^2) at profile time ``t_s``."""
        pose, _, acc = self._profile(t_s)
        return specific_force_body((acc[0], acc[1], acc[2]), (pose[3], pose[4], pose[5]))

    # -- the 1 kHz path --------------------------------------------------------------------------------------------

    def tick(
        self, t_profile_s: float | None, gyro_el_dps: float, az_deg: float, el_deg: float, drive_el_counts: float
    ) -> float:
        """One 1 ms sample: ``t_profile_s`` the profile time at this gyro sample (None: no profile running),
        ``gyro_el_dps`` the elevation gyro (rate_y), ``az_deg``/``el_deg`` the encoders, ``drive_el_counts`` the
        elevation drive applied over the previous tick (what was sent last tick, after clamps). Returns the
        feed-forward (drive counts) to pass to ``RateController.step`` for the drive of this tick."""
        if t_profile_s is None:
            if self._running:
                self._restart()
            self.ff_counts = 0.0
            return 0.0
        if self._running:
            f = self.f_body  # specific force of the tick the drive acted in
            self._s_tau += drive_el_counts
            self._s_fx += f[0]
            self._s_fy += f[1]
            self._s_fz += f[2]
            self._s_az += az_deg
            self._s_el += el_deg
            self._count += 1
            if self._count == self.decimation:
                self._identify(gyro_el_dps)
        else:
            self._running = True
            self._w0 = gyro_el_dps
        self.f_body = f = self.carrier_specific_force(t_profile_s + 0.5 * self.dt_s)
        if not self.identified:
            self.ff_counts = 0.0
            return 0.0
        ff = self.imbalance.drive_counts(f, az_deg * D2R, el_deg * D2R) if self.apply else 0.0
        self.ff_counts = ff
        return ff

    def _identify(self, gyro_el_dps: float) -> None:
        n = self._count
        inv = 1.0 / n
        eps = (gyro_el_dps - self._w0) * D2R / (n * self.dt_s)
        tau = self._s_tau * inv / self.counts_per_n_m
        fx, fy, fz = self._s_fx * inv, self._s_fy * inv, self._s_fz * inv
        az = self._s_az * inv * D2R
        el = self._s_el * inv * D2R
        self._w0 = gyro_el_dps
        self._count = 0
        self._s_tau = self._s_fx = self._s_fy = self._s_fz = self._s_az = self._s_el = 0.0
        if self.ac_only:
            dc = self._dc
            if dc is None:
                self._dc = dc = [eps, tau, fx, fy, fz]
            else:
                a = self.dc_alpha
                dc[0] += a * (eps - dc[0])
                dc[1] += a * (tau - dc[1])
                dc[2] += a * (fx - dc[2])
                dc[3] += a * (fy - dc[3])
                dc[4] += a * (fz - dc[4])
            self._dc_steps += 1
            if self._dc_steps <= self.dc_settle_steps:
                return  # the running means are still settling
            eps, tau = eps - dc[0], tau - dc[1]
            fx, fy, fz = fx - dc[2], fy - dc[3], fz - dc[4]
        t0 = time.perf_counter()
        self.imbalance.identify(
            angular_accel_rad_s2=eps, accel_body_m_s2=(fx, fy, fz), az_rad=az, el_rad=el, applied_torque_n_m=tau
        )
        self.ukf_last_s = dt = time.perf_counter() - t0
        self.ukf_total_s += dt
        self.ukf_max_s = max(self.ukf_max_s, dt)
        self.ukf_steps += 1
        if not self.identified and self.ukf_steps >= self.warmup_steps:
            sx, sz = self.rho_std_m
            self.identified = max(sx, sz) < self.converged_std_m


class ProfileClock:
    """The profile time at a gyro sample, from the hexapod's POSE messages (``t_ms``: profile clock, 0 at START).

    ``on_pose(t_profile_s, t_s)`` with ``t_s`` the session time of the latest gyro sample when the POSE arrived;
    ``at(t_s)`` the profile time at gyro sample ``t_s``, or None before the first POSE and once POSEs stop for
    ``stale_s``. A POSE is generated before it arrives (and ``t_ms`` is truncated), so ``t_profile - t_s`` at
    arrival is at most the true offset: the offset kept is the largest seen (the least-delayed POSE), lowered
    by ``slew`` s per s so a drift between the boards' clocks is followed.
    """

    def __init__(self, *, stale_s: float = 0.1, slew: float = 1e-4) -> None:
        self.stale_s = stale_s
        self.slew = slew
        self.offset_s: float | None = None
        self._last_s = -math.inf

    def on_pose(self, t_profile_s: float, t_s: float) -> None:
        off = t_profile_s - t_s
        if self.offset_s is None or t_s - self._last_s > self.stale_s:
            self.offset_s = off  # first POSE, or a new run of the profile
        else:
            decayed = self.offset_s - self.slew * (t_s - self._last_s)
            self.offset_s = off if off > decayed else decayed
        self._last_s = t_s

    def at(self, t_s: float) -> float | None:
        if self.offset_s is None or t_s - self._last_s > self.stale_s:
            return None
        return t_s + self.offset_s
