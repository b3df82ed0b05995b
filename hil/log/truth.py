"""The sim clock's truth file: the plant's true line-of-sight rates per loop row, beside the session log.

Only the ``sim`` clock has the plant in the bench's process, so only it can record what no gyro measures: the LOS
rate before the gyro's filter, delay, noise and bias. A sim session writes it next to its log as
``<log stem>.truth.npz`` (numpy, written once at the end of the session, fault or not), so the session log itself
stays identical to a lockstep one. One row per loop row, matched by the board's sample counter:

- ``tick`` (1): GYRO_SAMPLE.tick of the loop row;
- ``los_rate_y_dps``, ``los_rate_z_dps`` (deg/s): the true LOS rates about the elevation frame's y and z (what the
  elevation and azimuth gyros measure), at the sample's tick.

The campaign metrics ``los_rate_true_*`` read it (hil.campaign.metrics); without it they are not computed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

SUFFIX = ".truth.npz"
COLUMNS = ("tick", "los_rate_y_dps", "los_rate_z_dps")


def truth_path(log_path: str | Path) -> Path:
    """Where the truth file of the session log ``log_path`` is (whether it exists or not)."""
    log_path = Path(log_path)
    return log_path.with_name(log_path.stem + SUFFIX)


def write_truth(log_path: str | Path, ticks: list[int], rates_y_dps: list[float], rates_z_dps: list[float]) -> Path:
    """Write the truth file of ``log_path``; returns its path."""
    path = truth_path(log_path)
    tmp = path.with_name(path.name + ".part")
    with tmp.open("wb") as fh:
        np.savez(fh, tick=np.asarray(ticks, dtype=np.int64), los_rate_y_dps=np.asarray(rates_y_dps, dtype=float),
                 los_rate_z_dps=np.asarray(rates_z_dps, dtype=float))
    tmp.replace(path)  # whole or absent: a reader never sees half a file
    return path


def read_truth(log_path: str | Path, ticks: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The true LOS rates y, z (deg/s) at the loop rows whose sample counters are ``ticks``, or None when the log has
    no truth file (a lockstep, realtime or hardware session). ValueError naming the file if it lacks a row."""
    path = truth_path(log_path)
    if not path.exists():
        return None
    with np.load(path) as data:
        t, y, z = (data[c] for c in COLUMNS)
    order = np.argsort(t, kind="stable")
    t, y, z = t[order], y[order], z[order]
    ticks = np.asarray(ticks, dtype=np.int64)
    if ticks.size == 0:  # a log without loop rows (a session stopped before its first sample)
        return y[:0], z[:0]
    at = np.clip(np.searchsorted(t, ticks), 0, max(t.size - 1, 0))
    if t.size == 0 or np.any(t[at] != ticks):
        missing = ticks[(t.size == 0) | (t[at] != ticks)] if t.size else ticks
        raise ValueError(f"{path}: no truth row for loop tick {int(missing[0])} ({missing.size} of {ticks.size} rows "
                         "missing)")
    return y[at], z[at]
