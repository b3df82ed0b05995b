"""A study's search space and constraints, as ``hil tune`` takes them (docs/tuning.md).

``parse_params`` reads ``name=low..high[:log][:int]`` against the controller's own numeric parameters (a name the
controller does not have is refused, naming the controller's); ``parse_constraints`` reads ``metric<=value`` or
``metric>=value`` against the campaign metrics, and ``parse_objective`` the metric to minimise; either may end in
``@GLOB``, an fnmatch glob over the campaign's profile labels naming the cells it is judged on."""

from __future__ import annotations

import dataclasses
import fnmatch
import math
import re
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Literal

from hil.campaign.metrics import METRICS
from hil.config import ConfigError
from hil.control import registry
from hil.control.registry import ControllerConfigError, controller_params

if TYPE_CHECKING:
    import optuna


_PARAM = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*=\s*([^\s.][^\s]*?)\s*\.\.\s*([^\s:]+)\s*((?::\s*[a-z]+\s*)*)$")
_CONSTRAINT = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(<=|>=)\s*(\S+)\s*$")


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    """One tuned parameter: ``name=low..high`` sampled uniformly, ``:log`` log-uniformly, ``:int`` as integers."""

    name: str
    low: float
    high: float
    log: bool = False
    integer: bool = False

    def suggest(self, trial: optuna.Trial) -> float | int:
        if self.integer:
            return trial.suggest_int(self.name, int(self.low), int(self.high), log=self.log)
        return trial.suggest_float(self.name, self.low, self.high, log=self.log)

    def clip(self, value: float) -> float | int:
        """``value`` moved into the range (and rounded for ``:int``): a shipped gain enqueued as a trial."""
        x = min(max(float(value), self.low), self.high)
        return round(x) if self.integer else x

    def __str__(self) -> str:
        kind = (":int" if self.integer else "") + (":log" if self.log else "")
        return f"{self.name}={self.low:g}..{self.high:g}{kind}"


def _number(text: str, what: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise ConfigError(f"{what}: {text!r} is not a number") from None
    if not math.isfinite(x):
        raise ConfigError(f"{what}: {text!r} is not a finite number")
    return x


def _controllers() -> dict[str, Any]:
    """Every controller by name: the registry's, and those that run only on the sim clock (the oracle)."""

    return {**registry.REGISTRY, **getattr(registry, "SIM_ONLY", {})}


def _numeric_fields(controller: str) -> dict[str, bool]:
    """The controller's numeric parameters: name -> whether it is an integer."""
    out = {}
    for name, field in _controllers()[controller].params.model_fields.items():
        if field.annotation is int:
            out[name] = True
        elif field.annotation is float:
            out[name] = False
    return out


def parse_params(text: str | Sequence[str], controller: str, base: dict[str, Any] | None = None) -> list[ParamSpec]:
    """``"omega_o_rad_s=100..2000:log, kp_counts_per_dps=1000..20000:log"`` -> one :class:`ParamSpec` each.

    Names must be numeric parameters of ``controller`` (hil.control.registry); ``low < high``, finite, positive
    for ``:log``, whole numbers for ``:int`` (an integer parameter is always sampled as one); each end of the range
    must validate for the controller with ``base`` (the entry's other parameters). ConfigError naming the item."""

    models = _controllers()
    if controller not in models:
        known = ", ".join(sorted(models))
        raise ConfigError(f"controller={controller!r}: unknown controller (controllers: {known})")
    items = [s for part in ([text] if isinstance(text, str) else list(text)) for s in part.split(",")]
    items = [s for s in items if s.strip()]
    if not items:
        raise ConfigError("params: nothing to tune (give name=low..high[:log|:int], comma-separated)")
    fields = _numeric_fields(controller)
    specs: list[ParamSpec] = []
    for item in items:
        m = _PARAM.match(item)
        if m is None:
            raise ConfigError(f"params={item.strip()!r}: not name=low..high[:log|:int]")
        name, lo_text, hi_text, kinds = m.groups()
        where = f"params={item.strip()!r}"
        if name not in fields:
            known = ", ".join(fields)
            numeric = name in models[controller].params.model_fields
            what = "not a numeric parameter" if numeric else "unknown parameter"
            raise ConfigError(f"{where}: {what} of controller {controller!r} (numeric parameters: {known})")
        if any(s.name == name for s in specs):
            raise ConfigError(f"{where}: given twice")
        flags = [k.strip() for k in kinds.split(":") if k.strip()]
        for flag in flags:
            if flag not in ("log", "int"):
                raise ConfigError(f"{where}: unknown suffix ':{flag}' (':log' or ':int')")
        lo, hi = _number(lo_text, where), _number(hi_text, where)
        log, integer = "log" in flags, "int" in flags or fields[name]
        if not lo < hi:
            raise ConfigError(f"{where}: the range {lo:g}..{hi:g} is empty (need low < high)")
        if log and lo <= 0:
            raise ConfigError(f"{where}: ':log' needs a positive range (got {lo:g}..{hi:g})")
        if integer and (lo != int(lo) or hi != int(hi)):
            raise ConfigError(f"{where}: an integer range needs whole numbers (got {lo:g}..{hi:g})")
        for end in (lo, hi):
            try:
                controller_params(controller, {**(base or {}), name: int(end) if integer else end})
            except ControllerConfigError as exc:
                raise ConfigError(f"{where}: {end:g} is not valid: {exc}") from None
        specs.append(ParamSpec(name, lo, hi, log=log, integer=integer))
    return specs


def split_cells(text: str, what: str) -> tuple[str, str]:
    """``"metric...@GLOB"`` -> (``"metric..."``, ``GLOB``); ``"*"`` (every cell) without ``@``. ConfigError naming
    ``what`` for an empty glob."""
    head, at, glob = text.partition("@")
    if at and not glob.strip():
        raise ConfigError(f"{what}={text.strip()!r}: nothing after '@' (a glob over the campaign's profile labels)")
    return head.strip(), glob.strip() if at else "*"


def cells_suffix(cells: str) -> str:
    return "" if cells == "*" else f"@{cells}"


@dataclasses.dataclass(frozen=True)
class Objective:
    """The study's objective: the mean of ``metric`` over the trial's cells whose profile label matches ``cells``
    (an fnmatch glob; ``*``: every cell). Written ``metric`` or ``metric@GLOB``."""

    metric: str
    cells: str = "*"

    def covers(self, profile_label: str) -> bool:
        return fnmatch.fnmatchcase(profile_label, self.cells)

    def __str__(self) -> str:
        return self.metric + cells_suffix(self.cells)


def parse_objective(text: str | Objective) -> Objective:
    """``"miss_std_px"`` or ``"los_rate_std_dps@vibration*"`` -> :class:`Objective`; ConfigError for an unknown
    metric."""
    if isinstance(text, Objective):
        return text
    metric, cells = split_cells(text, "objective")
    if metric not in METRICS:
        raise ConfigError(f"objective={text!r}: unknown metric {metric!r} (metrics: {', '.join(METRICS)})")
    return Objective(metric, cells)


@dataclasses.dataclass(frozen=True)
class Constraint:
    """``metric <= bound`` (or ``>=``) on every cell of a trial whose profile label matches ``cells`` (a glob;
    ``*``: every cell): its Optuna value is the worst such cell's excess. Written ``metric<=bound[@GLOB]``."""

    metric: str
    op: Literal["<=", ">="]
    bound: float
    cells: str = "*"

    def covers(self, profile_label: str) -> bool:
        return fnmatch.fnmatchcase(profile_label, self.cells)

    def value(self, values: Sequence[float]) -> float:
        """<= 0 when every value meets it; else how far the worst misses."""
        if self.op == "<=":
            return max(values) - self.bound
        return self.bound - min(values)

    def __str__(self) -> str:
        return f"{self.metric}{self.op}{self.bound:g}{cells_suffix(self.cells)}"


def check_cells(scoped: Sequence[Objective | Constraint], profiles: Sequence[str], what: str = "") -> None:
    """Every ``@GLOB`` matches a profile label of the campaign; ConfigError naming the item and the labels if not."""
    for item in scoped:
        if not any(item.covers(label) for label in profiles):
            name = "objective" if isinstance(item, Objective) else "constraints"
            where = what or "the campaign"
            raise ConfigError(f"{name}={str(item)!r}: @{item.cells!r} matches no profile label of {where} "
                              f"({', '.join(repr(p) for p in profiles)})")


def parse_constraints(items: str | Sequence[str | Constraint] | None) -> list[Constraint]:
    """``"drive_ripple_el_counts<=800"`` (one each, or comma-separated) -> :class:`Constraint`; ConfigError naming
    the item for an unknown metric, another operator or a bound that is not a finite number."""

    if items is None:
        return []
    raw = [items] if isinstance(items, str) else list(items)
    out: list[Constraint] = []
    for item in raw:
        if isinstance(item, Constraint):
            out.append(item)
            continue
        for part in (p for p in item.split(",") if p.strip()):
            text, cells = split_cells(part, "constraints")
            m = _CONSTRAINT.match(text)
            if m is None:
                raise ConfigError(f"constraints={part.strip()!r}: not metric<=value or metric>=value")
            metric, op, bound = m.groups()
            if metric not in METRICS:
                raise ConfigError(f"constraints={part.strip()!r}: unknown metric {metric!r} "
                                  f"(metrics: {', '.join(METRICS)})")
            out.append(Constraint(metric, op, _number(bound, f"constraints={part.strip()!r}"),  # type: ignore[arg-type]
                                  cells))
    return out
