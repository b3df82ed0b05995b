"""The one stability rule of tuning and of the paper-targets fit: when a session counts as unstable."""

from __future__ import annotations

SATURATION_MAX_FRAC = 0.05  # a cell whose drive sits at its limit longer than this (after settling) is unstable
TRACK_VALID_MIN_FRAC = 0.5  # a tracking cell with fewer valid frames than this (after settling) lost the target


def unstable_reason(saturated_frac: float, valid_frac: float | None) -> str:
    """Why a session with this :func:`hil.campaign.metrics.log_health` counts as unstable, "" if it does not: the
    one rule of tuning and of the paper-targets fit. A drive at its limit more than SATURATION_MAX_FRAC of the time,
    or (a tracking session) fewer than TRACK_VALID_MIN_FRAC of the frames valid."""
    if saturated_frac > SATURATION_MAX_FRAC:
        return f"unstable: the drive sat at its limit {100 * saturated_frac:.0f} % of the time"
    if valid_frac is not None and valid_frac < TRACK_VALID_MIN_FRAC:
        return f"lost the target: {100 * valid_frac:.0f} % valid frames"
    return ""
