"""``hil fit``: the plant fitted to one platform's session logs (the method is in docs/fit.md).

Three estimators, each on the logs that carry its information, each returning :class:`Estimate` rows (value,
1-sigma, source) in the vocabulary of :mod:`hil.fit.ranges`:

- :func:`fit_noise` (static logs): per gyro axis, the white noise std and the band-limited component from the
  spectrum above the rate loop's bandwidth (Welch); the bias from the mean (x) or the encoder's drift (y, z);
- :func:`fit_frequency_response` (ident logs): the indirect closed-loop FRF of ``hil.analysis`` and a least-squares fit
  of ``k_m / s`` (sampled) x gyro lag x delay x two-mass mode x cable spring (seed 000 eqs 3, 33-38);
- :func:`fit_mechanics` (every log with motion): an equation-error fit of the torque balance, per axis,
  ``J dw/dt = K_t clip(i, I_max) - T_f(v) - k_c theta + T_imb`` with the gyro's own lag applied to the right-hand
  side and both sides low-passed alike; linear in T_c, T_s - T_c, D, k_c, m rho for each Stribeck rate and current
  limit on a grid. The carrier is the logged hexapod pose, the drive the logged one.

:func:`fit_logs` runs them and writes the plant: fitted values where the logs determine them, the prior's elsewhere
(said so in :attr:`TwinFit.estimates`).

The code lives in private modules of :mod:`hil.fit`, re-exported here: :mod:`hil.fit._estimates` (an
:class:`Estimate` and its grade), :mod:`hil.fit._noise`, :mod:`hil.fit._frf`, :mod:`hil.fit._motor` (the drive the
plant received), :mod:`hil.fit._mechanics` (the torque balance) and :mod:`hil.fit._passes` (:func:`fit_logs`: the
passes share the prior, the fitted plant and the order in which each estimate feeds the next).
"""

from __future__ import annotations

from hil.fit._estimates import Estimate, Status, grade
from hil.fit._frf import (
    CLIP_SHARE_MAX,
    LINEAR_LOW_HZ,
    POLE_PINNED_REL,
    RHO_MAX,
    FrfFit,
    LinearFrf,
    UnusableSweep,
    correlation_inflation,
    fit_frequency_response,
    linear_frf,
    linear_plant_frf,
    nonlinear_bins,
    sweep_reading,
)
from hil.fit._mechanics import D2R, G0, MechanicsFit, fit_mechanics, specific_force_el_frame
from hil.fit._motor import armature_current_a, drive_at_current_limit, drive_with_ripple
from hil.fit._noise import DRIVE_SHARE_MAX, NOISE_BINS_MIN, P_SPREAD_MAX, fit_noise
from hil.fit._passes import (
    BREAKAWAY_UNRESOLVED,
    POLE_AGREE_SIGMAS,
    TwinFit,
    fit_logs,
    lab_wire_delay_s,
    pole_doubts,
    sweep_spring_q,
)

__all__ = [
    "BREAKAWAY_UNRESOLVED",
    "CLIP_SHARE_MAX",
    "D2R",
    "DRIVE_SHARE_MAX",
    "G0",
    "LINEAR_LOW_HZ",
    "NOISE_BINS_MIN",
    "POLE_AGREE_SIGMAS",
    "POLE_PINNED_REL",
    "P_SPREAD_MAX",
    "RHO_MAX",
    "Estimate",
    "FrfFit",
    "LinearFrf",
    "MechanicsFit",
    "Status",
    "TwinFit",
    "UnusableSweep",
    "armature_current_a",
    "correlation_inflation",
    "drive_at_current_limit",
    "drive_with_ripple",
    "fit_frequency_response",
    "fit_logs",
    "fit_mechanics",
    "fit_noise",
    "grade",
    "lab_wire_delay_s",
    "linear_frf",
    "linear_plant_frf",
    "nonlinear_bins",
    "pole_doubts",
    "specific_force_el_frame",
    "sweep_reading",
    "sweep_spring_q",
]
