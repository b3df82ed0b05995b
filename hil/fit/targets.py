"""The paper's platform as a fitted preset: the plant (and the KF / high-gain observer defaults) fitted to a paper's
published figures (:func:`fit_targets`, docs/emulator.md, paper-000).

A targets file (:class:`TargetsConfig`, e.g. ``profiles/targets/seed-000.yaml``) lists each published figure with
the campaign cell that measures it (campaign file, profile label, controller label, metric). A trial of the search
draws the plant parameters of :data:`hil.fit.ranges.PLAUSIBLE` (and the controller parameters the file names), runs
every measuring cell on the ``sim`` clock as its campaign would (the campaign's own session, overrides and metrics:
:func:`hil.campaign.runner.cell_session` and :func:`hil.campaign.runner.run_cell`, in a warm worker process), and
scores the weighted sum of squared log ratios ``sum w_i log(fitted_i / paper_i)^2``. A ratio is clipped to
``[1/10, 10]``: a missing metric (a session that faulted) or a non-positive one (a lead where the paper has a lag)
counts as a factor 10 off, so the sampler still learns from it. Each trial also stores the paper's premises
(:data:`PREMISES`) as user attributes, so the study itself shows how close to each premise the search came.
Trials run ``jobs`` at a time. A trial stops early (pruned) once the targets measured so far already sum to more than
the best complete trial's objective: every term is a square, so the rest can only add to it, and a pruned trial could
never have been the best (docs/emulator.md, "The paper's platform as a fitted preset", Method).

The study is Optuna's (TPE, seeded, multivariate) in an RDB storage (SQLite by default), resumable; the
storage, heartbeat and quiet-failure helpers are :mod:`hil.study`'s. The best trial's plant is written with
:func:`hil.fit.ranges.dump_plant`, then measured again on the verification seeds at each campaign's full duration:
those numbers make the residual table.

The code lives in private modules of :mod:`hil.fit`, re-exported here: :mod:`hil.fit._targets_schema` (the file's
model), :mod:`hil.fit._targets_measure` (the cells run), :mod:`hil.fit._targets_score` (the objective, the premises,
the residuals) and :mod:`hil.fit._targets_study` (the study).
"""

from __future__ import annotations

from hil.fit._targets_measure import (
    CellInterrupted,
    Measured,
    controller_overrides,
    measure,
    proposed_controllers,
)
from hil.fit._targets_schema import (
    Cell,
    ControllerParam,
    Measurement,
    Search,
    Seeds,
    Target,
    TargetsConfig,
    load_targets,
)
from hil.fit._targets_score import (
    PREMISES,
    RATIO_CLIP,
    TABLE_STDS,
    Premise,
    Residual,
    clipped_ratio,
    objective,
    paper_figures,
    partial_objective,
    premise_values,
    residual_markdown,
    residuals,
    target_terms,
)
from hil.fit._targets_study import (
    FIT_DIR,
    MAX_JOBS,
    PremiseResult,
    TargetsResult,
    best_complete_value,
    default_jobs,
    fit_targets,
    mean_terms,
    summary_markdown,
)

__all__ = [
    "FIT_DIR",
    "MAX_JOBS",
    "PREMISES",
    "RATIO_CLIP",
    "TABLE_STDS",
    "Cell",
    "CellInterrupted",
    "ControllerParam",
    "Measured",
    "Measurement",
    "Premise",
    "PremiseResult",
    "Residual",
    "Search",
    "Seeds",
    "Target",
    "TargetsConfig",
    "TargetsResult",
    "best_complete_value",
    "clipped_ratio",
    "controller_overrides",
    "default_jobs",
    "fit_targets",
    "load_targets",
    "mean_terms",
    "measure",
    "objective",
    "paper_figures",
    "partial_objective",
    "premise_values",
    "proposed_controllers",
    "residual_markdown",
    "residuals",
    "summary_markdown",
    "target_terms",
]
