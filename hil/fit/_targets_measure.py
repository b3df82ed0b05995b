"""The targets' campaign cells run on a plant, on the sim clock, in warm workers (:func:`measure`)."""

from __future__ import annotations

import dataclasses
import itertools
import math
import shutil
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any

from hil.campaign.model import ControllerEntry
from hil.campaign.runner import cell_session, run_cell
from hil.fit import ranges
from hil.fit._targets_schema import Cell, Measurement, Target, TargetsConfig, _campaign
from hil.session import emulator_for_plant
from hil.study import unstable_reason


@dataclasses.dataclass
class Measured:
    """What the cells gave: per target / measurement id the value on each seed (NaN where missing), and the cells
    that were unstable (id -> why)."""

    per_seed: dict[str, list[float]]
    unstable: dict[str, str]
    wall_s: float = 0.0

    def value(self, key: str) -> float:
        xs = [x for x in self.per_seed.get(key, []) if math.isfinite(x)]
        return sum(xs) / len(xs) if xs and len(xs) == len(self.per_seed[key]) else math.nan

    @property
    def values(self) -> dict[str, float]:
        return {k: self.value(k) for k in self.per_seed}


def controller_overrides(config: TargetsConfig, values: Mapping[str, float], controller: str) -> dict[str, Any]:
    """The parameters a cell's controller gets from the searched ``values`` (name -> value)."""
    out: dict[str, Any] = {}
    for p in config.search.controller_params:
        if controller in p.controllers and p.name in values:
            out.update(dict.fromkeys(p.fields, float(values[p.name])))
    return out


def proposed_controllers(config: TargetsConfig, values: Mapping[str, float]) -> dict[str, dict[str, float]]:
    """controller name -> the parameters the fit chose for it."""
    names = sorted({c for p in config.search.controller_params for c in p.controllers})
    return {c: controller_overrides(config, values, c) for c in names}


def _run_cell(cell: Cell, seed: int, *, duration: float | None, params: dict[str, Any], plant_path: Path,
              work: Path) -> tuple[dict[str, float], str]:
    """One cell on the sim clock, in a warm worker (:func:`hil.campaign.runner.run_cell`, as a campaign runs it):
    (its metrics, '' or why it is unstable). :class:`CellInterrupted` if the cell was stopped by a signal."""
    camp = _campaign(cell.campaign)
    if duration is not None and camp.duration_s is not None:
        duration = min(duration, camp.duration_s)
    camp = camp.model_copy(update={"seeds": [seed], "duration_s": duration or camp.duration_s})
    spec = next(s for s in camp.cells() if s.profile.label == cell.profile and s.controller.label == cell.controller)
    entry = spec.controller
    spec = spec.model_copy(update={"controller": ControllerEntry(label=entry.label, name=entry.name,
                                                                 params={**entry.params, **params})})
    out = work / f"{spec.cell_id}-{abs(hash((str(cell.campaign), tuple(params.items())))):x}"
    data = cell_session(camp, spec, out / "cells" / spec.cell_id)
    # without the wire's time: the paper's figures are of its whole loop, whose delay the plant's gyro lag and delay
    # stand for (docs/emulator.md, "The wire"; profiles/emulator/paper-000.yaml)
    emulator = emulator_for_plant(plant_path, work, base=data["emulator"]["config"], wire_time=False)
    data["emulator"] = {**data["emulator"], "config": str(emulator)}
    try:
        result = run_cell(camp, spec, out, session=data)
    finally:
        shutil.rmtree(out, ignore_errors=True)
    if result.status == "interrupted":
        raise CellInterrupted(f"cell {spec.cell_id}: {result.message or 'interrupted'}")
    if result.status == "error":  # a session that cannot run on this plant: no metrics, reported as unstable
        return {}, f"session error: {' '.join(result.message.split())[:200]}"
    if result.health is None:  # no log, or its metrics could not be worked out
        return {}, "; ".join(result.failures)[:200] or f"session {result.status}: no log"
    if result.status != "completed":
        return dict(result.metrics), f"session {result.status}: {result.message}".rstrip(": ")
    return dict(result.metrics), unstable_reason(*result.health)


class CellInterrupted(RuntimeError):
    """A measuring cell was stopped (SIGINT, SIGTERM): the measurement is incomplete."""


def measure(config: TargetsConfig, plant: Mapping[str, Any] | str | Path, controller_values: Mapping[str, float],
            *, seeds: Sequence[int] | None = None, full: bool = False, work_dir: str | Path | None = None,
            ids: Sequence[str] | None = None, jobs: int = 1, first: Mapping[str, float] | None = None,
            on_cell: Callable[[Measured], None] | None = None) -> Measured:
    """Run every cell the targets and measurements need (each once per seed, ``sim`` clock, each in a warm worker
    process, ``jobs`` at a time) on ``plant`` (a plant dict or YAML file) with ``controller_values``
    (search.controller_params name -> value; missing ones keep their ``default``). ``full``: each campaign's own
    duration and ``verify.seeds``; else ``trial.duration_s`` and ``trial.seeds``. ``ids``: only these targets /
    measurements. The cells run in the file's order, the targets' cells before the measurements' (``first``: id ->
    weight; the cells whose ids weigh most run first, the rest in the file's order). ``on_cell``: called
    after each cell (in this thread) with what is measured so far (an id whose cells are all done has its values);
    an exception it raises stops the measurement (cells running finish, none starts) and propagates."""

    t0 = time.monotonic()
    values = {p.name: p.default for p in config.search.controller_params}
    values.update({k: float(v) for k, v in controller_values.items()})
    plan = config.verify if full else config.trial
    seeds = list(seeds) if seeds is not None else list(plan.seeds)
    duration = None if full else plan.duration_s
    own = work_dir is None
    work = Path(tempfile.mkdtemp(prefix="hil-targets-")) if work_dir is None else Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    try:
        plant_path = Path(plant) if isinstance(plant, str | Path) else ranges.dump_plant(plant, work / "plant.yaml")
        wanted: list[Target | Measurement] = [*config.targets, *config.measurements]
        if ids is not None:
            wanted = [c for c in wanted if c.id in set(ids)]
        cells: dict[tuple[Any, ...], tuple[Cell, dict[str, Any]]] = {}
        owners: dict[tuple[Any, ...], list[Target | Measurement]] = {}
        for c in wanted:
            params = controller_overrides(config, values, _campaign_entry(c).name)
            if isinstance(c, Measurement) and c.gain_from is not None:
                params["omega_o_rad_s"] = float(values[c.gain_from])
            key = (str(c.campaign), c.profile, c.controller, tuple(sorted(params.items())))
            cells.setdefault(key, (c, params))
            owners.setdefault(key, []).append(c)
        order = list(cells)
        if first is not None:  # the cells whose targets weigh most first; stable: the file's order otherwise
            order.sort(key=lambda key: -sum(first.get(owner.id, 0.0) for owner in owners[key]))
        runs = [(key, seed) for key in order for seed in seeds]
        got: dict[tuple[Any, ...], dict[int, tuple[dict[str, float], str]]] = {key: {} for key in cells}

        def one(item: tuple[tuple[Any, ...], int]) -> tuple[tuple[Any, ...], int, tuple[dict[str, float], str]]:
            key, seed = item
            cell, params = cells[key]
            return key, seed, _run_cell(cell, seed, duration=duration, params=params, plant_path=plant_path,
                                        work=work)

        def so_far() -> Measured:
            per_seed: dict[str, list[float]] = {}
            unstable: dict[str, str] = {}
            for key, done in got.items():
                if len(done) < len(seeds):
                    continue
                for seed in seeds:
                    metrics, why = done[seed]
                    for owner in owners[key]:
                        metric = owner.metric if isinstance(owner, Target) else "rate_err_el_std_dps"
                        per_seed.setdefault(owner.id, []).append(metrics.get(metric, math.nan))
                        if why:
                            unstable[owner.id] = f"seed {seed}: {why}"
            return Measured(per_seed, unstable, time.monotonic() - t0)

        todo = iter(runs)
        with ThreadPoolExecutor(max_workers=max(1, jobs), thread_name_prefix="hil-measure") as pool:
            # a cell starts only once ``on_cell`` has seen the one before it ended: a stop starts nothing more
            running = {pool.submit(one, item) for item in itertools.islice(todo, max(1, jobs))}
            while running:
                done, running = wait(running, return_when=FIRST_COMPLETED)
                for future in done:
                    key, seed, outcome = future.result()
                    got[key][seed] = outcome
                    if on_cell is not None:
                        on_cell(so_far())
                    running |= {pool.submit(one, item) for item in itertools.islice(todo, 1)}
        measured = so_far()
        measured.per_seed = {c.id: measured.per_seed[c.id] for c in wanted}  # the file's order
        return measured
    finally:
        if own:
            shutil.rmtree(work, ignore_errors=True)


def _campaign_entry(cell: Cell) -> ControllerEntry:
    camp = _campaign(cell.campaign)
    return next(c for c in camp.controllers if c.label == cell.controller)
