"""The oracle: the best any rate controller could do with the bench's own loop, a reference for campaigns.

A real rate controller sees the plant only through the gyro (noisy, filtered, delayed) and its own drive, and must
estimate the disturbance (ESO, KF, UKF feed-forward). The oracle is given what no lab can measure: per axis, the
plant's true line-of-sight rate and the true disturbance on the axis in drive counts, at the instant of each gyro
sample. It runs the same rate loop as every other controller (:class:`~hil.control.loops.RateLoop`: P(I) on the rate
error, the disturbance subtracted, rounded and saturated to ``u_max_counts``), with the true rate fed back instead of
an estimate and the true disturbance cancelled instead of an estimated one; the session then applies the same
safety clip and slew limit and sends the drive as the same DRIVE_CMD, so it has the same loop delay.

Only the ``sim`` clock has the truth (the plant runs in the bench's process: :class:`hil.session.PlantTruth`); on any
other clock a session refuses the oracle before it starts (docs/control.md, "The oracle").

A truth source is a callable returning, for the current tick, ``{"az": AxisTruth, "el": AxisTruth}``:
``rate_dps`` is the LOS rate the axis' gyro measures (azimuth: the gyro's z, elevation: its y) without noise,
filter or delay; ``disturbance_counts`` is ``d`` of the rate-loop model ``d(rate)/dt = k_m (u + d)``: every torque on
the axis but the motor's nominal drive torque, converted to the drive counts that would produce it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, NamedTuple

if TYPE_CHECKING:
    from hil.control.controller import RateController

AXES = ("az", "el")


class AxisTruth(NamedTuple):
    """One axis' truth at one tick, in the rate loop's units."""

    rate_dps: float  # the true LOS rate the axis' gyro measures (deg/s)
    disturbance_counts: float  # d of d(rate)/dt = k_m (u + d), in drive counts


TruthSource = Callable[[], Mapping[str, AxisTruth]]


class TruthRequired(ValueError):
    """The oracle was asked to run without the plant's truth (any clock but ``sim``, a replay, an offline loop)."""


def truth_refusal(name: str = "oracle", clock: str | None = None) -> str:
    """The one-line refusal of controller ``name`` on ``clock`` (None: no truth source at all)."""
    where = f" (not {clock})" if clock else ""
    return (f"controller.name: {name} needs the true plant state, which only the sim clock has{where}; "
            "run with clock='sim'")


class TruthFeedback:
    """The oracle's estimator (the :class:`~hil.control.controller.RateEstimator` interface): no estimation, the
    truth of one axis read from a bound :data:`TruthSource` each step. ``step`` returns the true LOS rate and sets
    ``disturbance_counts`` to the true disturbance, which the rate loop then subtracts (u = kp e + I - d).
    Unbound, ``step`` raises :class:`TruthRequired`."""

    def __init__(self) -> None:
        self.source: TruthSource | None = None
        self.axis = ""
        self.rate_dps = 0.0
        self.disturbance_counts = 0.0

    def bind(self, source: TruthSource, axis: str) -> None:
        if axis not in AXES:
            raise ValueError(f"axis: {axis!r} is not az or el")
        self.source, self.axis = source, axis

    def step(self, rate_meas_dps: float, u_applied_counts: float) -> float:
        if self.source is None:
            raise TruthRequired(truth_refusal())
        truth = self.source()[self.axis]
        self.rate_dps = truth.rate_dps
        self.disturbance_counts = truth.disturbance_counts
        return truth.rate_dps


def bind_truth(controller: RateController, source: TruthSource | None, axis: str) -> None:
    """Give ``controller`` the truth of ``axis`` if it is an oracle (others are left alone). TruthRequired if it is
    one and ``source`` is None."""
    est = controller.estimator
    if isinstance(est, TruthFeedback):
        if source is None:
            raise TruthRequired(truth_refusal())
        est.bind(source, axis)
