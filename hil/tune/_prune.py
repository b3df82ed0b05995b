"""The pruning rule of `hil tune` (docs/tuning.md, "Pruning"): a trial reports, after each of its campaign's cells
(in the campaign's order), the mean of the objective over the cells run so far; it stops there when that mean is
worse than the best complete feasible trial's mean over the same cells by more than ``margin``.

Why this rule and not the median of the trials so far: a study's trials share their cells (the same profiles and
seeds), and one set of gains scores alike on two seeds of one profile, so a trial 25 % behind the best on its first
cells cannot catch up on the rest unless its cells disagree with each other by more than the margin: the rule stops
hopeless trials, not unlucky ones. The median rule would stop half of every study's trials, good ones among them.
"""

from __future__ import annotations

import math
from typing import Any

import optuna
from optuna.trial import TrialState

__all__ = ["PRUNE_MARGIN", "PRUNE_STARTUP_TRIALS", "CellPruner"]

PRUNE_MARGIN = 0.25  # a trial this much behind the best over the same cells stops
PRUNE_STARTUP_TRIALS = 5  # trials that complete before any is pruned


class CellPruner(optuna.pruners.BasePruner):
    """Stop a trial whose mean over its first cells is more than ``margin`` (relative) worse than the best complete
    feasible trial's mean over the same cells; never before ``startup_trials`` trials have completed."""

    def __init__(self, margin: float = PRUNE_MARGIN, startup_trials: int | None = None) -> None:
        if not margin > 0:
            raise ValueError("margin must be > 0")
        self.margin = float(margin)
        self.startup_trials = PRUNE_STARTUP_TRIALS if startup_trials is None else int(startup_trials)

    def prune(self, study: optuna.Study, trial: optuna.trial.FrozenTrial) -> bool:
        step = trial.last_step
        if step is None:
            return False
        value = trial.intermediate_values[step]
        best = best_feasible(study)
        if best is None or best[1] < self.startup_trials:
            return False
        reference = best[0].intermediate_values.get(step)
        if reference is None or not math.isfinite(reference) or not math.isfinite(value):
            return False
        slack = self.margin * abs(reference)
        if study.direction == optuna.study.StudyDirection.MINIMIZE:
            return value > reference + slack
        return value < reference - slack


def best_feasible(study: optuna.Study) -> tuple[Any, int] | None:
    """(the best complete trial whose constraints all hold, how many trials have completed), or None."""
    done = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    ok = [(t.value, t) for t in done
          if t.value is not None and math.isfinite(t.value) and all(c <= 0 for c in t.constraints.values())]
    if not ok:
        return None
    sign = 1.0 if study.direction == optuna.study.StudyDirection.MINIMIZE else -1.0
    return min(ok, key=lambda vt: (sign * vt[0], vt[1].number))[1], len(done)
