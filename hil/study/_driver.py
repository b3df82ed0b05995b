"""The one Optuna study driver, for :func:`hil.tune.tune` and :func:`hil.fit.targets.fit_targets` alike.

A study has a name (checked here), lives in an RDB storage (:mod:`hil.study._store`), is created or resumed (a study
that exists is continued only with ``resume``, and only if it was made with the same ``meta``), is sampled by a
seeded multivariate TPE (pruned by the caller's rule, if any), and owes this run the trials still missing to its
target. A trial whose objective raises is a failed trial (its ``failure`` attribute says why; a NaN objective is
Optuna's FAIL), never the study's end.
"""

from __future__ import annotations

import contextlib
import logging
import math
import re
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from hil.config import ConfigError
from hil.study._store import open_study, rdb_storage

if TYPE_CHECKING:
    import optuna

STUDY_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$")
MAX_TRIALS = 100_000
FINISHED = ("COMPLETE", "FAIL", "PRUNED")  # trial states that count towards the target


def check_study_name(name: str) -> str:
    """``name`` if it can name a study (and a directory): letters, digits, '_', '.', '-'; ConfigError if not."""
    if not STUDY_NAME.match(name):
        raise ConfigError(f"study={name!r}: not a name (letters, digits, '_', '.', '-')")
    return name


def check_trials(trials: int) -> int:
    if not 1 <= trials <= MAX_TRIALS:
        raise ConfigError(f"trials={trials}: need 1..{MAX_TRIALS}")
    return trials


@dataclass
class StudyRun:
    """An opened study and what this run owes it."""

    study: optuna.Study
    name: str
    url: str
    created: bool  # False: an existing study resumed
    todo: int  # trials this run runs: the target less the finished ones


def start_study(name: str, url: str, *, trials: int, resume: bool, direction: str | Sequence[str],
                meta: Mapping[str, Any],
                seed: int, startup_trials: int, constant_liar: bool = False,
                first_params: Mapping[str, Any] | None = None, pruner: Any = None) -> StudyRun:
    """Create the study ``name`` in ``url``, or resume it (``resume``; ConfigError if it exists without). TPE seeded
    with ``seed``, random for its first ``startup_trials``; ``constant_liar`` for trials run in parallel;
    ``direction``: one, or one per objective (a multi-objective study).
    ``first_params``: enqueued as a new study's first trial (the prior's values, the shipped gains). ``pruner``: an
    Optuna pruner (default none: every trial runs to its end)."""
    import optuna  # noqa: PLC0415  (heavy (Optuna, SQLAlchemy): loaded only when a study runs)

    check_study_name(name)
    check_trials(trials)
    rdb = rdb_storage(url)
    exists = name in optuna.study.get_all_study_names(rdb)
    if exists and not resume:
        raise ConfigError(f"study={name!r}: already in {url}; pass resume=True to continue it, or choose another name")
    with warnings.catch_warnings():  # multivariate and constant-liar TPE are marked experimental
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        sampler = optuna.samplers.TPESampler(seed=seed, n_startup_trials=startup_trials, multivariate=True,
                                             constant_liar=constant_liar)
    study = open_study(rdb, name, sampler, direction, meta=dict(meta), exists=exists,
                       pruner=pruner if pruner is not None else optuna.pruners.NopPruner())
    if not exists and first_params:
        study.enqueue_trial(dict(first_params))
    done = sum(t.state.name in FINISHED for t in study.get_trials(deepcopy=False))
    return StudyRun(study, name, url, created=not exists, todo=max(0, trials - done))


def failed(trial: Any, exc: BaseException, t0: float | None = None) -> float:
    """Mark ``trial`` failed because of ``exc`` (one line, kept on the trial) and return the NaN that fails it."""
    trial.set_user_attr("failure", " ".join(str(exc).split())[:500] or type(exc).__name__)
    if t0 is not None:
        trial.set_user_attr("wall_s", time.monotonic() - t0)
    return math.nan


def run_study(run: StudyRun, objective: Callable[[Any], float | Sequence[float]], *, n_jobs: int = 1,
              timeout_s: float | None = None, callbacks: Sequence[Callable[[Any, Any], None]] = ()) -> float:
    """Run the trials ``run`` owes (``n_jobs`` at a time; ``timeout_s`` stops earlier). Returns the wall time (s)."""
    from optuna.trial import TrialState  # noqa: PLC0415  (heavy (Optuna, SQLAlchemy): loaded only when a study runs)

    t0 = time.monotonic()
    todo = run.todo
    # An enqueued trial (the shipped gains) that two threads take at once runs twice and one of them fails to
    # record it (optuna#4002): the enqueued trials run one at a time, then the rest n_jobs at a time.
    waiting = len(run.study.get_trials(deepcopy=False, states=(TrialState.WAITING,))) if n_jobs > 1 else 0
    with quiet_nan_warnings():
        for n, jobs in ((min(waiting, todo), 1), (todo - min(waiting, todo), n_jobs)):
            left_s = None if timeout_s is None else timeout_s - (time.monotonic() - t0)
            if n and (left_s is None or left_s > 0):
                run.study.optimize(objective, n_trials=n, n_jobs=jobs, timeout=left_s, callbacks=list(callbacks))
    return time.monotonic() - t0


@contextlib.contextmanager
def quiet_nan_warnings() -> Iterator[None]:
    """Optuna logs a warning for every trial that returns NaN; the failed trials are reported by the caller instead."""
    log = logging.getLogger("optuna")
    level = log.level
    if level < logging.ERROR and not logging.getLogger("hil").isEnabledFor(logging.INFO):
        log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        log.setLevel(level)
