"""One axis of the rate controller: a feedback estimator, the PI rate loop, and an optional feed-forward.

Every 1 ms sample k (seed 000 Fig. 5 and 10)::

    rate_fb_k, d_k = estimator.step(gyro_k, u_{k-1})     # what the loop feeds back, disturbance in counts
    u_k = sat(PI(rate_cmd_k - rate_fb_k) - d_k + ff_k)   # RateLoop: rounded, saturated, anti-windup
    u_k is the drive sent (DRIVE_CMD k), and what the estimator gets at k+1.

The estimator is any object with ``step(rate_meas_dps, u_applied_counts) -> rate_fb_dps`` and a
``disturbance_counts`` attribute: LinearESO and NonlinearESO (their z1 is fed back, the standard
LADRC form u0 = kp (r - z1)), EsoKalman (the KF rate is fed back), or a plain filter wrapped in
:class:`FilteredFeedback` (no disturbance estimate).
"""

from __future__ import annotations

from typing import Protocol

from hil.control.loops import RateLoop
from hil.control.ukf_imbalance import ImbalanceFeedForward, ImbalanceUKF, Vec3


class RateEstimator(Protocol):
    def step(self, rate_meas_dps: float, u_applied_counts: float) -> float: ...

    @property
    def disturbance_counts(self) -> float: ...


class Filter(Protocol):
    def step(self, x: float) -> float: ...


class FilteredFeedback:
    """Adapts a plain filter (e.g. the 150 Hz low-pass) to the estimator interface: no disturbance estimate."""

    disturbance_counts = 0.0

    def __init__(self, filt: Filter | None = None) -> None:
        self.filter = filt

    def step(self, rate_meas_dps: float, u_applied_counts: float) -> float:
        return rate_meas_dps if self.filter is None else self.filter.step(rate_meas_dps)


class ImbalanceCompensation:
    """Mass-imbalance feed-forward for one axis (seed 001 Fig. 2): UKF identification plus torque feed-forward.

    ``identify`` runs the UKF (about 200 us a step, so call it decimated, every ``ukf.dt_s``, with the
    window-averaged measurements ImbalanceUKF.step documents); ``drive_counts`` evaluates the
    feed-forward every 1 ms tick from the latest eccentricity and the current carrier acceleration.
    """

    def __init__(self, *, ukf: ImbalanceUKF, feedforward: ImbalanceFeedForward) -> None:
        self.ukf = ukf
        self.feedforward = feedforward

    def identify(self, **measurements: float | Vec3) -> tuple[float, float]:
        rho = self.ukf.step(**measurements)  # type: ignore[arg-type]
        self.feedforward.set_eccentricity(*rho)
        return rho

    def drive_counts(self, accel_body_m_s2: Vec3, az_rad: float, el_rad: float) -> float:
        return self.feedforward.drive(accel_body_m_s2, az_rad, el_rad)


class RateController:
    """Estimator + rate loop for one axis; ``step`` is the whole 1 kHz computation on plain floats.

    After each step, ``rate_fb_dps`` (the fed-back rate: filtered or KF estimate), ``disturbance_counts``
    (the observer's estimate) and ``u_counts`` (the applied drive) hold the values to log.
    """

    def __init__(
        self, *, estimator: RateEstimator, loop: RateLoop, imbalance: ImbalanceCompensation | None = None
    ) -> None:
        self.estimator = estimator
        self.loop = loop
        self.imbalance = imbalance  # the session feeds it and passes drive_counts(...) as feedforward_counts
        self.u_counts = 0
        self.ff_counts = 0.0  # the feed-forward inside u_counts
        self.rate_fb_dps = 0.0
        self.disturbance_counts = 0.0

    def step(self, rate_cmd_dps: float, gyro_dps: float, feedforward_counts: float = 0.0) -> int:
        """One 1 kHz step. The estimator is told the drive applied last tick *minus* the feed-forward it held:
        an ESO estimates the whole disturbance from the drive it is told about, so with the feed-forward left in,
        the imbalance would be cancelled twice and the P term settle at -ff (a rate error of ff / kp)."""
        est = self.estimator
        self.rate_fb_dps = rate_fb = est.step(gyro_dps, self.u_counts - self.ff_counts)
        self.disturbance_counts = d = est.disturbance_counts
        self.ff_counts = feedforward_counts
        self.u_counts = u = self.loop.step(rate_cmd_dps, rate_fb, d - feedforward_counts)
        return u

    def hold(self, u_applied_counts: int) -> None:
        """Tell the controller the drive actually applied was different (a watchdog zeroed it, a driver fault)."""
        self.u_counts = u_applied_counts
