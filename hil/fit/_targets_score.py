"""A measurement scored against the paper: the objective, the paper's premises, the residual table."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Literal

from hil.fit._targets_schema import TargetsConfig

RATIO_CLIP = 10.0  # a target off by more than this factor (or missing) scores as this factor


def clipped_ratio(fitted: float, paper: float) -> float:
    """fitted / paper, clipped to [1/RATIO_CLIP, RATIO_CLIP]; NaN counts as too large, <= 0 as too small."""
    if not math.isfinite(fitted):
        return RATIO_CLIP
    return min(RATIO_CLIP, max(1.0 / RATIO_CLIP, fitted / paper))


def objective(config: TargetsConfig, values: Mapping[str, float]) -> float:
    """sum over the targets of ``weight * log(ratio)^2`` (:func:`clipped_ratio`); ``values``: id -> fitted."""
    return sum(target_terms(config, {t.id: values.get(t.id, math.nan) for t in config.targets}).values())


def partial_objective(config: TargetsConfig, values: Mapping[str, float]) -> float:
    """:func:`objective` over the targets in ``values`` only (those measured so far): a lower bound of the whole
    objective, whose terms are all squares."""
    return sum(target_terms(config, values).values())


@dataclasses.dataclass(frozen=True)
class Premise:
    """One of the paper's premises as a number: ``value`` of the measured ids (and of the targets file's paper
    figures, id -> ``paper``), which holds when it is ``>= bound`` (``sense`` ">=") or ``<= bound``;
    ``unstable_holds``: an unstable ``unstable_id`` cell makes it hold. ``text`` may name ``{paper}``: the premise's
    value on the paper's own figures (:meth:`describe`)."""

    id: str
    text: str
    sense: Literal[">=", "<="]
    bound: float
    needs: tuple[str, ...]
    value: Callable[[Mapping[str, float], Mapping[str, float]], float]
    unstable_id: str | None = None

    def holds(self, value: float, unstable: Mapping[str, str] | None = None) -> bool:
        if self.unstable_id is not None and unstable and self.unstable_id in unstable:
            return True
        if not math.isfinite(value):
            return False
        return value >= self.bound if self.sense == ">=" else value <= self.bound

    def describe(self, paper: Mapping[str, float]) -> str:
        """``text`` with ``{paper}`` as the premise's value on the ``paper`` figures (id -> value; "-" without them)."""
        if "{paper}" not in self.text:
            return self.text
        try:
            x = f"{self.value(paper, paper):.3g}"
        except (KeyError, ZeroDivisionError):
            x = "-"
        return self.text.replace("{paper}", x)


def paper_figures(config: TargetsConfig) -> dict[str, float]:
    """The targets file's published figures: target id -> the paper's value."""
    return {t.id: t.paper for t in config.targets}


TABLE_STDS = ("table1-eso-std", "table1-esokf-std", "table1-hg-std", "table2-eso-std", "table2-hg-std",
              "table3-eso-std", "table3-hg-std")  # the Table 1-3 std targets of premise d


def _worst_factor(v: Mapping[str, float], paper: Mapping[str, float]) -> float:
    """The largest factor between a Table 1-3 std and the paper's (inf where one is missing or not positive)."""
    factors = [max(v[k] / paper[k], paper[k] / v[k]) if math.isfinite(v.get(k, math.nan)) and v[k] > 0 else math.inf
               for k in TABLE_STDS]
    return max(factors)


PREMISES: tuple[Premise, ...] = (
    Premise("a", "gyro noise limits the observer gain: at the high-gain omega_o plain ESO is unstable or its rate "
            "std >= 1.2 x ESO+KF's at that gain", ">=", 1.2, ("eso-high-gain", "table1-hg-std"),
            lambda v, _: v["eso-high-gain"] / v["table1-hg-std"], unstable_id="eso-high-gain"),
    Premise("b1", "ESO+KF beats ESO at the same gain (rate std ratio ESO+KF / ESO < 1)", "<=", 1.0,
            ("table1-esokf-std", "table1-eso-std"), lambda v, _: v["table1-esokf-std"] / v["table1-eso-std"]),
    Premise("b2", "high-gain ESO+KF beats ESO+KF (rate std ratio < 1)", "<=", 1.0,
            ("table1-hg-std", "table1-esokf-std"), lambda v, _: v["table1-hg-std"] / v["table1-esokf-std"]),
    Premise("c", "miss std grows with the swing amplitude (ESO, 3 deg / 1 deg >= 1.5; paper {paper})", ">=", 1.5,
            ("table3-eso-std", "table2-eso-std"), lambda v, _: v["table3-eso-std"] / v["table2-eso-std"]),
    Premise("d", "each Table 1-3 std within a factor 1.5 of the paper's (the worst factor)", "<=", 1.5,
            TABLE_STDS, _worst_factor),
)


def premise_values(config: TargetsConfig, values: Mapping[str, float]) -> dict[str, float]:
    """premise id -> its value, for every premise whose ids were measured (NaN where a value is missing, or a paper
    figure it compares with is not in ``config``'s targets)."""
    paper = paper_figures(config)
    out = {}
    for p in PREMISES:
        if all(k in values for k in p.needs):
            try:
                x = p.value(values, paper)
            except (KeyError, ZeroDivisionError):
                x = math.nan
            out[p.id] = float(x) if math.isfinite(x) or x == math.inf else math.nan
    return out


@dataclasses.dataclass(frozen=True)
class Residual:
    id: str
    figure: str
    what: str
    paper: float
    fitted: float
    ratio: float
    tolerance: float

    @property
    def within(self) -> bool:
        return math.isfinite(self.ratio) and self.ratio > 0 and max(self.ratio, 1 / self.ratio) <= self.tolerance


def residuals(config: TargetsConfig, values: Mapping[str, float]) -> list[Residual]:
    out = []
    for t in config.targets:
        f = values.get(t.id, math.nan)
        out.append(Residual(t.id, t.figure, f"{t.controller}, {t.profile}: {t.metric}", t.paper, f,
                            f / t.paper if math.isfinite(f) else math.nan, t.tolerance))
    return out


def residual_markdown(rows: Sequence[Residual]) -> str:
    lines = ["| target | figure | measured as | paper | fitted twin | ratio | within |",
             "| --- | --- | --- | ---: | ---: | ---: | --- |"]
    for r in rows:
        lines.append(f"| {r.id} | {r.figure} | {r.what} | {r.paper:g} | {r.fitted:.4g} | {r.ratio:.2f} | "
                     f"{'yes' if r.within else 'no'} (x{r.tolerance:g}) |")
    return "\n".join(lines) + "\n"


def target_terms(config: TargetsConfig, values: Mapping[str, float]) -> dict[str, float]:
    """Each measured target's term of :func:`objective` (id -> ``weight * log(ratio)^2``)."""
    return {t.id: t.weight * math.log(clipped_ratio(values[t.id], t.paper)) ** 2 for t in config.targets
            if t.id in values}
