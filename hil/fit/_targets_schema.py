"""The targets file's model (:class:`TargetsConfig`: figures, measuring cells, search) and :func:`load_targets`."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from hil.campaign.metrics import METRICS
from hil.campaign.model import CampaignConfig
from hil.campaign.runner import load_campaign
from hil.config import ConfigError, load_model, one_line, resolve_relative
from hil.control.registry import controller_params
from hil.fit import ranges
from hil.fit.ranges import ParamRange


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Cell(_Strict):
    """A campaign cell: which campaign, which profile and controller (labels as the campaign names them)."""

    campaign: Path = Field(description="a campaign YAML (relative to the targets file)")
    profile: str = Field(min_length=1, description="the campaign's profile label")
    controller: str = Field(min_length=1, description="the campaign's controller label")

    _rel = field_validator("campaign", mode="before")(resolve_relative)


class Target(Cell):
    """One published figure and the metric of the cell that measures it."""

    id: str = Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")
    kind: Literal["metric"] = Field("metric", description="metric: one campaign metric, mean over the seeds")
    figure: str = Field("", description="where the paper shows it")
    metric: str
    paper: float = Field(gt=0, description="the paper's value (positive: the residual is a log ratio)")
    weight: float = Field(1.0, ge=0)
    tolerance: float = Field(1.5, gt=1, description="the factor the fitted twin is held to")

    @field_validator("metric")
    @classmethod
    def _known_metric(cls, v: str) -> str:

        if v not in METRICS:
            raise ValueError(f"unknown metric {v!r}")
        return v


class Measurement(Cell):
    """A cell measured beside the targets (a premise needs it); ``gain_from``: its observer bandwidth is that
    controller parameter's value (e.g. plain ESO at the high-gain omega_o)."""

    id: str = Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")
    gain_from: str | None = None


class ControllerParam(_Strict):
    """A controller parameter the fit searches: ``fields`` of every controller in ``controllers`` set to one value."""

    name: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")
    fields: list[str] = Field(min_length=1)
    controllers: list[str] = Field(min_length=1)
    low: float = Field(gt=0)
    high: float = Field(gt=0)
    log: bool = False
    default: float = Field(gt=0, description="the shipped value (the search's first trial)")

    @model_validator(mode="after")
    def _check(self) -> ControllerParam:

        if not self.low < self.high:
            raise ValueError(f"high: the range {self.low:g}..{self.high:g} is empty")
        if not self.low <= self.default <= self.high:
            raise ValueError(f"default: {self.default:g} is outside {self.low:g}..{self.high:g}")
        for c in self.controllers:
            for end in (self.low, self.high):
                controller_params(c, dict.fromkeys(self.fields, end))  # one line naming the field if not
        return self


class Search(_Strict):
    ranges: Literal["plausible", "draw"] = Field("plausible", description="PLAUSIBLE's full range or its draw range")
    plant_params: Literal["all"] | list[str] = "all"
    controller_params: list[ControllerParam] = Field(default_factory=list)

    @field_validator("plant_params")
    @classmethod
    def _known(cls, v: Literal["all"] | list[str]) -> Literal["all"] | list[str]:
        if isinstance(v, list):
            for name in v:
                if name not in ranges.BY_NAME:
                    raise ValueError(f"unknown plant parameter {name!r} (hil.fit.ranges.PLAUSIBLE)")
        return v

    def plant_ranges(self) -> list[ParamRange]:
        return list(ranges.PLAUSIBLE) if self.plant_params == "all" else [ranges.BY_NAME[n] for n in self.plant_params]

    def bounds(self, p: ParamRange) -> tuple[float, float]:
        return p.draw_range if self.ranges == "draw" else (p.lo, p.hi)


class Seeds(_Strict):
    seeds: list[int] = Field(min_length=1)
    duration_s: float | None = Field(None, gt=0, description="cap on every session's duration (None: the campaign's)")


class TargetsConfig(_Strict):
    """A targets file: the paper's figures, each with the campaign cell that measures it, and the search."""

    name: str = Field(pattern=r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$")
    source: str = ""
    plant: Path = Field(description="the base plant YAML (relative to this file)")
    trial: Seeds = Seeds(seeds=[1], duration_s=9.0)
    verify: Seeds = Seeds(seeds=[1, 2, 3])
    search: Search = Search()
    measurements: list[Measurement] = Field(default_factory=list)
    targets: list[Target] = Field(min_length=1)

    _rel = field_validator("plant", mode="before")(resolve_relative)

    @model_validator(mode="after")
    def _check(self) -> TargetsConfig:
        ids = [t.id for t in self.targets] + [m.id for m in self.measurements]
        for i, x in enumerate(ids):
            if x in ids[:i]:
                raise ValueError(f"id {x!r} is given twice")
        names = {p.name for p in self.search.controller_params}
        for i, m in enumerate(self.measurements):
            if m.gain_from is not None and m.gain_from not in names:
                raise ValueError(f"measurements.{i}.gain_from: {m.gain_from!r} is not a search.controller_params name")
        return self


def load_targets(path: str | Path) -> TargetsConfig:
    """A targets file, validated; every campaign it names is readable and has the profile and controller labels.
    ValueError with one line naming the file and the field."""

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such targets file")
    try:
        config = load_model(TargetsConfig, path)
    except ConfigError as exc:
        raise ValueError(str(exc)) from None
    except ValidationError as exc:  # pragma: no cover - load_model turns these into ConfigError
        raise ValueError(one_line(str(path), exc)) from None
    if not config.plant.is_file():
        raise ValueError(f"{path}: plant: no such file {config.plant}")
    for where, cells in (("targets", config.targets), ("measurements", config.measurements)):
        for i, cell in enumerate(cells):
            try:
                camp = _campaign(cell.campaign)
            except ValueError as exc:
                raise ValueError(f"{path}: {where}.{i}.campaign: {' '.join(str(exc).split())}") from None
            if cell.profile not in [p.label for p in camp.profiles]:
                raise ValueError(f"{path}: {where}.{i}.profile: {cell.profile!r} is not a profile of campaign "
                                 f"{camp.name!r}")
            if cell.controller not in [c.label for c in camp.controllers]:
                raise ValueError(f"{path}: {where}.{i}.controller: {cell.controller!r} is not a controller of "
                                 f"campaign {camp.name!r}")
    return config


_CAMPAIGNS: dict[Path, CampaignConfig] = {}


def _campaign(path: Path) -> CampaignConfig:

    if path not in _CAMPAIGNS:
        if not Path(path).is_file():
            raise ValueError(f"no such file {path}")
        _CAMPAIGNS[path] = load_campaign(path)
    return _CAMPAIGNS[path]
