"""`hil tune`: an Optuna study of a controller's gains over a campaign's cells (docs/tuning.md).

``parse_params``/``parse_constraints`` read the search space and the constraints, ``tune`` runs the study (Optuna,
RDB storage, SQLite by default; on a Dask cluster with ``jobs``), ``TuneResult`` is what it found. The study plumbing
(``open_study``, ``rdb_storage``, ``storage_url``, ``start_study``, ``run_study``) and the one stability rule
(``unstable_reason``) are :mod:`hil.study`'s, shared with :func:`hil.fit.targets.fit_targets`, and re-exported here."""

from hil.study import (
    StudyRun,
    check_study_name,
    check_trials,
    failed,
    open_study,
    quiet_nan_warnings,
    rdb_storage,
    run_study,
    start_study,
    storage_url,
    unstable_reason,
)
from hil.tune._prune import PRUNE_MARGIN, PRUNE_STARTUP_TRIALS, CellPruner
from hil.tune._report import write_tune_report
from hil.tune._result import TrialInfo, TuneResult
from hil.tune._space import (
    Constraint,
    Objective,
    ParamSpec,
    check_cells,
    parse_constraints,
    parse_objective,
    parse_params,
)
from hil.tune._study import (
    choose_controller,
    compare_controllers,
    evaluate,
    log_health,
    trial_campaign,
    tune,
)

__all__ = [
    "PRUNE_MARGIN",
    "PRUNE_STARTUP_TRIALS",
    "CellPruner",
    "Constraint",
    "Objective",
    "ParamSpec",
    "StudyRun",
    "TrialInfo",
    "TuneResult",
    "check_cells",
    "check_study_name",
    "check_trials",
    "choose_controller",
    "compare_controllers",
    "evaluate",
    "failed",
    "log_health",
    "open_study",
    "parse_constraints",
    "parse_objective",
    "parse_params",
    "quiet_nan_warnings",
    "rdb_storage",
    "run_study",
    "start_study",
    "storage_url",
    "trial_campaign",
    "tune",
    "unstable_reason",
    "write_tune_report",
]
