"""One fitted parameter (:class:`Estimate`) and its grade against the target accuracy (:func:`grade`)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

from hil.fit.ranges import BY_NAME, param_range

Status = Literal["fitted", "weak", "prior", "bound"]  # weak: fitted, not to its target (wider sigma, or leaning on a
# prior it cannot tell itself from)


@dataclass
class Estimate:
    """One parameter: the fitted value and its 1-sigma, or the prior kept (``status``), with where it came from."""

    name: str
    value: float | None
    sigma: float | None
    unit: str
    status: Status
    source: str
    prior: float | None = None
    note: str = ""

    @property
    def relative_sigma(self) -> float | None:
        if self.value is None or self.sigma is None or self.value == 0:
            return None
        return abs(self.sigma / self.value)


def _unit(name: str, default: str = "") -> str:
    if name in BY_NAME:
        return BY_NAME[name].unit
    for suffix, unit in (("_dps", "deg/s"), ("_hz", "Hz"), ("_s", "s"), ("_n_m", "N m"), ("_a", "A"),
                         ("_ratio", "1"), ("_kg_mm", "kg mm"), ("_n_m_per_rad", "N m/rad")):
        if name.endswith(suffix):
            return unit
    return default


def grade(estimates: list[Estimate]) -> list[Estimate]:
    """A fitted value whose 1-sigma is wider than its target accuracy (:meth:`ParamRange.tolerance`) is ``weak``, never
    ``fitted``; a weak value and a prior kept for want of a log name the recording that would resolve them."""
    return [_graded(e) for e in estimates]


def _graded(e: Estimate) -> Estimate:
    rng = param_range(e.name)
    if rng is not None and e.status == "fitted" and e.value is not None and e.sigma is not None:
        tol = rng.tolerance(e.value)
        if tol is not None and e.sigma > tol:
            return replace(e, status="weak", note=f"1 sigma {e.sigma:.3g} is wider than the target {tol:.3g} "
                           f"{e.unit}; record {rng.resolved_by or 'more of the logs above'}")
    elif rng is not None and e.status == "prior" and rng.resolved_by and "record" not in e.note:
        return replace(e, note="; ".join(x for x in (e.note, f"record {rng.resolved_by}") if x))
    return e
