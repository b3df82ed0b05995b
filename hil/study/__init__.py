"""The one Optuna study driver that tuning (``hil tune``) and the fit to published targets share (docs/tuning.md),
below both.

A study is named (``check_study_name``), sized (``check_trials``), created or resumed (``start_study``) in an RDB
storage (``storage_url``, ``rdb_storage``, ``open_study``: SQLite by default, any SQLAlchemy URL) and run
(``run_study``); a trial whose objective raises is failed (``failed``). ``unstable_reason`` is the one rule saying when
a session counts as unstable, for tuning and for the paper-targets fit alike."""

from hil.study._driver import (
    FINISHED,
    MAX_TRIALS,
    STUDY_NAME,
    StudyRun,
    check_study_name,
    check_trials,
    failed,
    quiet_nan_warnings,
    run_study,
    start_study,
)
from hil.study._stability import SATURATION_MAX_FRAC, TRACK_VALID_MIN_FRAC, unstable_reason
from hil.study._store import GRACE_S, HEARTBEAT_S, open_study, rdb_storage, storage_url

__all__ = [
    "FINISHED",
    "GRACE_S",
    "HEARTBEAT_S",
    "MAX_TRIALS",
    "SATURATION_MAX_FRAC",
    "STUDY_NAME",
    "TRACK_VALID_MIN_FRAC",
    "StudyRun",
    "check_study_name",
    "check_trials",
    "failed",
    "open_study",
    "quiet_nan_warnings",
    "rdb_storage",
    "run_study",
    "start_study",
    "storage_url",
    "unstable_reason",
]
