"""Campaign files and campaign results: one pydantic model each (docs/campaigns.md).

A campaign is a matrix: hexapod profiles x controllers (with parameters) x repetitions (seeds), each
cell one session built from a base session file. Per-cell thresholds on named metrics decide pass/fail;
acceptance rules compare controllers ("high-gain ESO+KF's miss std is >= 40 % lower than ESO's") on every
seed. The report's verdict ranks the controllers on the campaign's primary metrics only.
The results land in ``CAMPAIGN_DIR/campaign.json`` as a :class:`CampaignResult`, which `hil report`
turns into Markdown and HTML.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field, field_validator, model_validator

from hil.campaign.metrics import METRICS, default_primary
from hil.config import MAX_SESSION_S, NAME_PATTERN, Seed, Strict, resolve_relative
from hil.control.registry import controller_params

_SLUG = re.compile(r"[^A-Za-z0-9]+")
MAX_AXIS_ENTRIES = 100  # profiles, controllers, seeds: each at most this many
MAX_CELLS = 1000


def slug(text: str) -> str:
    """A file-name-safe form of a label: 'high-gain ESO+KF' -> 'high-gain-eso-kf'."""
    return _SLUG.sub("-", text).strip("-").lower()


class ProfileEntry(Strict):
    label: str = Field(min_length=1, max_length=64, description="row/section name in the tables, e.g. '1 deg / 1 Hz'")
    path: Path = Field(description="a hexapod swing profile YAML (relative to the campaign file)")

    _rel = field_validator("path", mode="before")(resolve_relative)


class ControllerEntry(Strict):
    label: str = Field(min_length=1, max_length=64, description="as the tables show it, e.g. 'ESO+KF'")
    name: str = Field(description="a hil.control registry name")
    params: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _known(self) -> ControllerEntry:

        controller_params(self.name, self.params)  # ControllerConfigError (a ValueError): one line
        return self


class Threshold(Strict):
    max: float | None = None
    min: float | None = None

    def check(self, metric: str, value: float) -> str | None:
        """None if ``value`` passes, else one line saying why."""
        if math.isnan(value):
            return f"{metric} is not available"
        if self.max is not None and value > self.max:
            return f"{metric} = {value:.4g} > max {self.max:g}"
        if self.min is not None and value < self.min:
            return f"{metric} = {value:.4g} < min {self.min:g}"
        return None


class AcceptanceRule(Strict):
    """``better``'s ``metric`` is at least ``by_pct`` % lower than ``than``'s ``than_metric`` (default: the
    same metric), per profile and seed. With better == than it compares two metrics of one run. A magnitude
    metric (a lag) compares absolute values: a lead is not "lower" than a lag of the same size."""

    metric: str
    better: str = Field(description="controller label")
    than: str = Field(description="controller label")
    than_metric: str | None = Field(None, description="the metric of `than` (default: `metric`)")
    by_pct: float = Field(0.0, ge=0, lt=100)
    profiles: list[str] | None = Field(None, description="profile labels (default: all)")

    @property
    def reference_metric(self) -> str:
        return self.than_metric or self.metric

    def describe(self) -> str:
        by = f" by >= {self.by_pct:g} %" if self.by_pct else ""

        def name(metric: str) -> str:  # a magnitude metric (a lag) is compared by |value|
            return f"|{metric}|" if metric in METRICS and METRICS[metric].magnitude else metric

        if self.reference_metric != self.metric:
            return f"{self.better}: {name(self.metric)} below {name(self.reference_metric)}{by}"
        return f"{self.better} lowers {name(self.metric)} vs {self.than}{by}"


Analysis = Literal["control", "static_noise", "filter_lag"]


class CampaignConfig(Strict):
    name: str = Field(pattern=NAME_PATTERN, description="the directory under runs/campaigns/: no '/', no leading '.'")
    title: str
    description: str = ""
    source: str = Field("", description="where the paper's numbers come from, e.g. 'seed 000, Table 1'")
    session: Path = Field(description="the base session file every cell starts from")
    duration_s: float | None = Field(None, gt=0, le=MAX_SESSION_S, description="overrides the base session's duration")
    overrides: dict[str, Any] = Field(default_factory=dict, description="merged into the base session")
    analysis: Analysis = "control"
    settle_s: float = Field(1.0, ge=0, description="left out of every metric: ramps, convergence (a UKF: seconds)")
    profiles: list[ProfileEntry] = Field(min_length=1, max_length=MAX_AXIS_ENTRIES)
    controllers: list[ControllerEntry] = Field(min_length=1, max_length=MAX_AXIS_ENTRIES)
    seeds: list[Seed] = Field(min_length=1, max_length=MAX_AXIS_ENTRIES, description="one repetition per seed")
    baseline: str | None = Field(None, description="controller label the improvements are relative to")
    metrics: list[str] = Field(min_length=1, description="the table's columns")
    primary_metrics: list[str] | None = Field(
        None, min_length=1, description="the metrics the report's verdict ranks and averages, each one of `metrics` "
        "(default: the table's error metrics, hil.campaign.metrics.default_primary); the others are shown only")
    thresholds: dict[str, Threshold] = Field(default_factory=dict)
    acceptance: list[AcceptanceRule] = Field(default_factory=list)
    paper: dict[str, dict[str, dict[str, float]]] = Field(
        default_factory=dict, description="profile label -> controller label -> metric -> the paper's value")

    _rel = field_validator("session", mode="before")(resolve_relative)

    @field_validator("metrics", "primary_metrics")
    @classmethod
    def _known_metrics(cls, names: list[str] | None) -> list[str] | None:
        for name in names or []:
            if name not in METRICS:
                raise ValueError(f"unknown metric {name!r} (metrics: {', '.join(METRICS)})")
        if names is not None and len(set(names)) != len(names):
            raise ValueError(f"{next(n for n in names if names.count(n) > 1)!r} appears twice")
        return names

    @property
    def verdict_metrics(self) -> list[str]:
        """The metrics the verdict uses: ``primary_metrics``, or by default the table's error metrics."""
        return list(self.primary_metrics) if self.primary_metrics is not None else default_primary(self.metrics)

    @model_validator(mode="after")
    def _consistent(self) -> CampaignConfig:
        labels = [c.label for c in self.controllers]
        profiles = [p.label for p in self.profiles]
        for what, names in (("controllers", labels), ("profiles", profiles)):
            dup = {n for n in names if names.count(n) > 1}
            if dup:
                raise ValueError(f"{what}: duplicate label {sorted(dup)[0]!r}")
            slugs = [slug(n) for n in names]  # the cells' directory names
            for name, s in zip(names, slugs, strict=True):
                if not s:
                    raise ValueError(f"{what}: label {name!r} has no letter or digit (cell directories are named "
                                     "after labels)")
                if slugs.count(s) > 1:
                    raise ValueError(f"{what}: labels {[n for n in names if slug(n) == s]} would share the cell "
                                     f"directory name {s!r}")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError("seeds: a seed appears twice")
        n_cells = len(self.profiles) * len(self.controllers) * len(self.seeds)
        if n_cells > MAX_CELLS:
            raise ValueError(f"seeds: {n_cells} cells (profiles x controllers x seeds), more than {MAX_CELLS}")
        if self.baseline is not None and self.baseline not in labels:
            raise ValueError(f"baseline: {self.baseline!r} is not a controller label ({', '.join(labels)})")
        for name in self.primary_metrics or []:
            if name not in self.metrics:
                raise ValueError(f"primary_metrics: {name!r} is not one of the campaign's metrics (the table's "
                                 f"columns: {', '.join(self.metrics)})")
        for name in self.thresholds:
            if name not in METRICS:
                raise ValueError(f"thresholds: unknown metric {name!r}")
        for i, rule in enumerate(self.acceptance):
            for label in (rule.better, rule.than):
                if label not in labels:
                    raise ValueError(f"acceptance.{i}: {label!r} is not a controller label ({', '.join(labels)})")
            for metric in (rule.metric, rule.reference_metric):
                if metric not in METRICS:
                    raise ValueError(f"acceptance.{i}: unknown metric {metric!r}")
            for p in rule.profiles or []:
                if p not in profiles:
                    raise ValueError(f"acceptance.{i}: {p!r} is not a profile label")
        return self

    def sim_only_metric(self) -> str | None:
        """Where the campaign first uses a metric only the sim clock computes (``los_rate_true_*``), as
        ``field: metric``; None if it uses none."""
        uses = [("metrics", m) for m in self.metrics] + [("thresholds", m) for m in self.thresholds]
        uses += [(f"acceptance.{i}", m) for i, rule in enumerate(self.acceptance)
                 for m in (rule.metric, rule.reference_metric)]
        return next((f"{where}: {m}" for where, m in uses if METRICS[m].sim_only), None)

    def cells(self) -> list[CellSpec]:
        """Every (profile, controller, seed) in run order: profile-major, so a partial run is a whole table."""
        return [CellSpec(cell_id=f"{slug(p.label)}--{slug(c.label)}--s{seed}", profile=p, controller=c, seed=seed)
                for p in self.profiles for c in self.controllers for seed in self.seeds]


class CellSpec(Strict):
    cell_id: str
    profile: ProfileEntry
    controller: ControllerEntry
    seed: int


class CellResult(BaseModel):
    """One finished cell (``cells/<cell_id>/result.json``)."""

    cell_id: str
    profile: str
    controller: str = Field(description="the controller's label")
    controller_name: str
    seed: int
    status: str = Field(description="the session's: completed, fault, interrupted, error")
    exit_code: int
    message: str = ""
    log: str | None = Field(None, description="the session log, relative to the campaign directory")
    metrics: dict[str, float] = Field(default_factory=dict)
    failures: list[str] = Field(default_factory=list, description="thresholds not met, or why the run failed")
    wall_s: float = 0.0
    health: tuple[float, float | None] | None = Field(
        None, description="hil.campaign.metrics.log_health of the log (drive at its limit, valid tracking frames), "
        "when the cell's worker worked it out")

    @property
    def passed(self) -> bool:
        return self.status == "completed" and not self.failures


class RuleResult(BaseModel):
    rule: str
    passed: bool
    details: list[str] = Field(default_factory=list, description="per profile and seed: the two values and the %")


class CampaignResult(BaseModel):
    """``CAMPAIGN_DIR/campaign.json``: everything the report needs."""

    config: CampaignConfig
    cells: list[CellResult]
    acceptance: list[RuleResult] = Field(default_factory=list)
    jobs: int = 1
    wall_s: float = 0.0
    complete: bool = Field(False, description="every cell of the matrix has a result")

    def cell(self, profile: str, controller: str, seed: int) -> CellResult | None:
        return next((c for c in self.cells
                     if c.profile == profile and c.controller == controller and c.seed == seed), None)

    def values(self, profile: str, controller: str, metric: str) -> list[float]:
        """The metric over the repetitions that completed."""
        return [c.metrics[metric] for c in self.cells if c.profile == profile and c.controller == controller
                and c.status == "completed" and metric in c.metrics]

    def mean(self, profile: str, controller: str, metric: str) -> float:
        v = self.values(profile, controller, metric)
        return sum(v) / len(v) if v else float("nan")

    @property
    def passed(self) -> bool:
        return self.complete and all(c.passed for c in self.cells) and all(r.passed for r in self.acceptance)
