"""What a tuning study found: the result records ``TrialInfo`` and ``TuneResult``."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from hil.tune._space import Constraint, ParamSpec

TRIALS = "trials"


@dataclasses.dataclass(frozen=True)
class TrialInfo:
    """One finished trial as the study stored it."""

    number: int
    state: str  # COMPLETE, FAIL, PRUNED, RUNNING
    value: float | None
    params: dict[str, Any]
    feasible: bool | None  # None: failed (no constraints evaluated)
    constraints: dict[str, float]  # name (metric<=bound) -> the worst cell's excess, <= 0 holds
    failure: str
    wall_s: float | None
    values: tuple[float, ...] | None = None  # every objective's value (``value`` is the first's)


@dataclasses.dataclass
class TuneResult:
    """A study's outcome. ``best_params``: the best feasible trial's tuned parameters (None if no trial was
    feasible); ``params``: the whole controller entry's parameters with them merged in, as the YAML holds them."""

    study: str
    storage: str
    out_dir: Path
    campaign: str
    controller_label: str
    controller: str
    objective: str
    direction: str
    space: list[ParamSpec]
    constraints: list[Constraint]
    trials: list[TrialInfo]
    trials_run: int
    wall_s: float
    engine: str
    workers: int
    best_trial: int | None = None
    best_value: float | None = None
    best_params: dict[str, Any] | None = None
    params: dict[str, Any] | None = None
    yaml_path: Path | None = None
    objectives: list[str] = dataclasses.field(default_factory=list)  # every objective (``objective``: the first)
    directions: list[str] = dataclasses.field(default_factory=list)
    pareto: list[int] = dataclasses.field(default_factory=list)  # the feasible Pareto front's trials (2+ objectives)
    best_values: list[float] | None = None
    heldout: dict[str, Any] | None = None  # hil.tune.compare_controllers on the held-out seeds
    heldout_seeds: list[int] = dataclasses.field(default_factory=list)
    heldout_duration_s: float | None = None
    profile_path: Path | None = None
    report: Any = None  # hil.reporting.ReportFiles

    @property
    def n_complete(self) -> int:
        return sum(t.state == "COMPLETE" for t in self.trials)

    @property
    def n_failed(self) -> int:
        return sum(t.state == "FAIL" for t in self.trials)

    @property
    def n_pruned(self) -> int:
        return sum(t.state == "PRUNED" for t in self.trials)

    @property
    def n_infeasible(self) -> int:
        return sum(t.state == "COMPLETE" and t.feasible is False for t in self.trials)

    def to_json(self) -> dict[str, Any]:
        return {"study": self.study, "storage": self.storage, "dir": str(self.out_dir), "campaign": self.campaign,
                "controller": {"label": self.controller_label, "name": self.controller},
                "objective": self.objective, "direction": self.direction,
                "objectives": self.objectives, "directions": self.directions, "pareto": self.pareto,
                "best_values": self.best_values, "heldout_seeds": self.heldout_seeds,
                "heldout_duration_s": self.heldout_duration_s, "heldout": self.heldout,
                "space": [str(s) for s in self.space], "constraints": [str(c) for c in self.constraints],
                "trials": len(self.trials), "trials_run": self.trials_run, "complete": self.n_complete,
                "failed": self.n_failed, "pruned": self.n_pruned, "infeasible": self.n_infeasible,
                "wall_s": self.wall_s,
                "engine": self.engine, "workers": self.workers, "best_trial": self.best_trial,
                "best_value": self.best_value, "best_params": self.best_params, "params": self.params,
                "yaml": None if self.yaml_path is None else str(self.yaml_path),
                "profile": None if self.profile_path is None else str(self.profile_path),
                "report": None if self.report is None else {"markdown": str(self.report.markdown),
                                                            "html": str(self.report.html),
                                                            "plots": [str(p) for p in self.report.pngs]}}
