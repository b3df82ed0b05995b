"""The targets model (profiles/targets/*.yaml), the objective, and a tiny resumable study (hil.fit.targets)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import optuna
import pytest
import yaml

from hil.fit import _targets_measure as measure_module
from hil.fit.targets import (
    PREMISES,
    TABLE_STDS,
    fit_targets,
    load_targets,
    measure,
    objective,
    paper_figures,
    partial_objective,
    premise_values,
)

ROOT = Path(__file__).resolve().parents[2]
SEED_000 = ROOT / "profiles" / "targets" / "seed-000.yaml"
STATIC = str(ROOT / "profiles" / "campaigns" / "static-gyro-noise.yaml")


def _tiny(tmp_path: Path, **changes: object) -> Path:
    data = {
        "name": "tiny",
        "plant": str(ROOT / "profiles" / "plant" / "default.yaml"),
        "trial": {"seeds": [1], "duration_s": 2.5},
        "verify": {"seeds": [1], "duration_s": 2.5},
        "search": {"plant_params": ["gyro.noise_std_dps"]},
        "targets": [{"id": "raw", "campaign": STATIC, "profile": "static", "controller": "ESO+KF",
                     "metric": "gyro_raw_peak_dps", "paper": 0.102}],
    }
    data.update(changes)
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_shipped_targets_file_is_valid() -> None:
    config = load_targets(SEED_000)
    ids = {t.id for t in config.targets}
    assert {"fig12-raw-peak", "fig13-kf-lag", "table1-hg-std", "table3-eso-std"} <= ids
    needed = {k for p in PREMISES for k in p.needs}
    assert needed <= ids | {m.id for m in config.measurements}


@pytest.mark.parametrize(("change", "field"), [
    ({"targets": [{"id": "raw", "campaign": STATIC, "profile": "static", "controller": "ESO+KF",
                   "metric": "gyro_raw_peak_dps", "paper": 0.102, "wieght": 2}]}, "targets.0.wieght"),
    ({"targets": [{"id": "raw", "kind": "spectrum", "campaign": STATIC, "profile": "static",
                   "controller": "ESO+KF", "metric": "gyro_raw_peak_dps", "paper": 0.102}]}, "targets.0.kind"),
    ({"targets": [{"id": "raw", "campaign": STATIC, "profile": "static", "controller": "ESO+KF",
                   "metric": "no_such_metric", "paper": 0.102}]}, "targets.0.metric"),
    ({"targets": [{"id": "raw", "campaign": STATIC, "profile": "windy", "controller": "ESO+KF",
                   "metric": "gyro_raw_peak_dps", "paper": 0.102}]}, "targets.0.profile"),
    ({"search": {"plant_params": ["gyro.colour"]}}, "search.plant_params"),
    ({"search": {"controller_params": [{"name": "q", "fields": ["q_dps2"], "controllers": ["eso"], "low": 1e-5,
                                        "high": 1e-3, "default": 1e-4}]}}, "search.controller_params.0"),
])
def test_bad_file_one_line_naming_the_field(tmp_path: Path, change: dict, field: str) -> None:
    path = _tiny(tmp_path, **change)
    with pytest.raises(ValueError, match=r"tiny\.yaml") as info:
        load_targets(path)
    msg = str(info.value)
    assert "\n" not in msg
    assert field in msg


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no such targets file"):
        load_targets(tmp_path / "absent.yaml")


def test_objective_is_the_weighted_sum_of_squared_log_ratios(tmp_path: Path) -> None:
    targets = [{"id": "a", "campaign": STATIC, "profile": "static", "controller": "ESO+KF",
                "metric": "gyro_raw_peak_dps", "paper": 0.1, "weight": 1.0},
               {"id": "b", "campaign": STATIC, "profile": "static", "controller": "ESO+KF",
                "metric": "gyro_kf_peak_dps", "paper": 2.0, "weight": 2.0},
               {"id": "c", "campaign": STATIC, "profile": "static", "controller": "ESO+KF",
                "metric": "gyro_lpf_peak_dps", "paper": 0.5, "weight": 0.5}]
    config = load_targets(_tiny(tmp_path, targets=targets))
    # a: x2, b: x0.5, c: a lead (negative) counts as a factor 10 short
    expected = 1.0 * math.log(2.0) ** 2 + 2.0 * math.log(0.5) ** 2 + 0.5 * math.log(0.1) ** 2
    assert objective(config, {"a": 0.2, "b": 1.0, "c": -0.3}) == pytest.approx(expected, rel=1e-12)
    # a missing value (a session that faulted) counts as a factor 10 too large
    assert objective(config, {"a": 0.1, "b": 2.0}) == pytest.approx(0.5 * math.log(10.0) ** 2, rel=1e-12)


def test_premise_values() -> None:
    v = {"eso-high-gain": 0.3, "table1-hg-std": 0.1, "table1-eso-std": 0.32, "table1-esokf-std": 0.16,
         "table2-eso-std": 6.0, "table3-eso-std": 12.0, "table2-hg-std": 2.71, "table3-hg-std": 6.15}
    config = load_targets(SEED_000)
    got = premise_values(config, v)
    assert got["a"] == pytest.approx(3.0)
    assert got["b1"] == pytest.approx(0.5)
    assert got["b2"] == pytest.approx(0.625)
    assert got["c"] == pytest.approx(2.0)
    assert got["d"] == pytest.approx(15.6 / 12.0)
    by_id = {p.id: p for p in PREMISES}
    assert by_id["a"].holds(0.9, {"eso-high-gain": "drive at its limit"})  # unstable plain ESO: the premise holds
    assert not by_id["a"].holds(0.9, {})


def test_the_paper_figures_come_from_the_targets_file(tmp_path: Path) -> None:
    """Premise d's factors and premise c's quoted figure are the targets file's paper values, not the code's."""
    data = yaml.safe_load(SEED_000.read_text())
    for t in data["targets"]:
        t["campaign"] = str((SEED_000.parent / t["campaign"]).resolve())
        if t["id"] == "table3-eso-std":
            t["paper"] = 12.04
    data["plant"] = str((SEED_000.parent / data["plant"]).resolve())
    data["measurements"] = [{**m, "campaign": str((SEED_000.parent / m["campaign"]).resolve())}
                            for m in data["measurements"]]
    path = tmp_path / "changed.yaml"
    path.write_text(yaml.safe_dump(data))
    shipped, changed = load_targets(SEED_000), load_targets(path)
    c = {p.id: p for p in PREMISES}["c"]
    assert c.describe(paper_figures(shipped)).endswith("paper 2.59)")
    assert c.describe(paper_figures(changed)).endswith("paper 2)")
    v = {k: paper_figures(shipped)[k] for k in TABLE_STDS}
    assert premise_values(shipped, v)["d"] == pytest.approx(1.0)
    assert premise_values(changed, v)["d"] == pytest.approx(15.60 / 12.04)


@pytest.mark.slow
def test_tiny_study_runs_and_resumes(tmp_path: Path) -> None:
    path = _tiny(tmp_path)
    lines: list[str] = []
    kwargs = {"out_plant": tmp_path / "plant.yaml", "out_dir": tmp_path / "fit", "study": "tiny", "seed": 3,
              "verify": False}
    first = fit_targets(path, trials=1, progress=lines.append, **kwargs)
    assert first.trials == 1 and first.complete == 1 and first.trials_run == 1
    assert first.best_trial == 0  # the base plant's own values come first
    assert lines and lines[0].startswith("trial 0: objective")
    with pytest.raises(ValueError, match="resume=True"):
        fit_targets(path, trials=2, **kwargs)
    second = fit_targets(path, trials=2, resume=True, **kwargs)
    assert second.trials == 2 and second.trials_run == 1
    assert second.best_value is not None and second.best_value <= first.best_value
    text = (tmp_path / "plant.yaml").read_text()
    assert text.startswith("# ") and "Made by: hil.fit.fit_targets(" in text and "noise_std_dps" in text
    assert "| raw |" in (tmp_path / "fit" / "residuals.md").read_text()


def test_partial_objective_is_a_lower_bound_of_the_objective(tmp_path: Path) -> None:
    targets = [{"id": "a", "campaign": STATIC, "profile": "static", "controller": "ESO+KF",
                "metric": "gyro_raw_peak_dps", "paper": 0.1, "weight": 1.0},
               {"id": "b", "campaign": STATIC, "profile": "static", "controller": "ESO+KF",
                "metric": "gyro_kf_peak_dps", "paper": 2.0, "weight": 2.0}]
    config = load_targets(_tiny(tmp_path, targets=targets))
    assert partial_objective(config, {}) == 0.0
    assert partial_objective(config, {"a": 0.2}) == pytest.approx(math.log(2.0) ** 2, rel=1e-12)
    assert partial_objective(config, {"a": 0.2}) <= objective(config, {"a": 0.2, "b": 2.0})
    assert partial_objective(config, {"a": 0.2, "b": 1.0}) == objective(config, {"a": 0.2, "b": 1.0})


def _two_cells(tmp_path: Path) -> Path:
    """A gyro-noise target on the static cell, then a filter-lag target on the lag cell, whose paper values are
    the base plant's own: the base plant scores 0, and any other noise level is off on the first cell already."""
    lag = str(ROOT / "profiles" / "campaigns" / "filter-lag-15hz.yaml")
    targets = [{"id": "raw", "campaign": STATIC, "profile": "static", "controller": "ESO+KF",
                "metric": "gyro_raw_peak_dps", "paper": 1.0},
               {"id": "lag", "campaign": lag, "profile": "static", "controller": "ESO+KF",
                "metric": "lag_lpf_cycles", "paper": 1.0}]
    path = _tiny(tmp_path, targets=targets)
    config = load_targets(path)
    seen: list[set[str]] = []
    base = measure(config, config.plant, {}, on_cell=lambda so_far: seen.append(set(so_far.per_seed)))
    assert seen == [{"raw"}, {"raw", "lag"}]  # cell by cell, in the file's order
    assert base.values["raw"] > 0 and base.values["lag"] > 0, base.values
    seen.clear()
    again = measure(config, config.plant, {}, first={"lag": 0.5, "raw": 0.1},
                    on_cell=lambda so_far: seen.append(set(so_far.per_seed)))
    assert seen == [{"lag"}, {"raw", "lag"}] and again.values == base.values  # the heavier target's cell first
    for t in targets:
        t["paper"] = base.values[t["id"]]
    return _tiny(tmp_path, targets=targets)


@pytest.mark.slow
def test_a_trial_that_cannot_beat_the_best_stops_after_its_first_cell(tmp_path: Path) -> None:
    path = _two_cells(tmp_path)
    kwargs = {"out_dir": tmp_path / "fit", "seed": 5, "verify": False, "jobs": 1}
    lines: list[str] = []
    result = fit_targets(path, trials=3, out_plant=tmp_path / "plant.yaml", study="pruned", progress=lines.append,
                         **kwargs)
    assert result.best_trial == 0 and result.best_value == pytest.approx(0.0, abs=1e-12)
    assert (result.complete, result.pruned, result.failed) == (1, 2, 0)
    study = optuna.load_study(study_name="pruned", storage=result.storage)
    for trial in study.trials[1:]:
        assert trial.state.name == "PRUNED" and "> best 0" in trial.user_attrs["pruned"]
        assert set(trial.user_attrs["measured"]) == {"raw"}  # the lag cell never ran
        assert trial.params["gyro.noise_std_dps"] != study.trials[0].params["gyro.noise_std_dps"]
    assert sum("pruned" in line for line in lines) == 2
    unpruned = fit_targets(path, trials=3, out_plant=tmp_path / "plant2.yaml", study="unpruned", prune=False,
                           **{**kwargs, "jobs": 2})
    assert (unpruned.complete, unpruned.pruned) == (3, 0)


def test_a_stop_from_on_cell_starts_no_further_cell(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = _tiny(tmp_path, targets=[{"id": f"raw{i}", "campaign": STATIC, "profile": "static",
                                     "controller": "ESO+KF", "metric": "gyro_raw_peak_dps", "paper": 0.1,
                                     "weight": 1.0} for i in range(2)],
                 search={"plant_params": ["gyro.noise_std_dps"], "controller_params": [
                     {"name": "kf_q", "fields": ["q_dps2"], "controllers": ["eso_kf"], "low": 1e-6, "high": 1e-2,
                      "log": True, "default": 5e-4}]})
    config = load_targets(path)
    calls: list[int] = []
    started: list[str] = []
    run_cell = measure_module.run_cell

    def counted(*args: Any, **kwargs: Any) -> Any:
        started.append(args[1].cell_id)
        return run_cell(*args, **kwargs)

    def stop(so_far: object) -> None:
        calls.append(1)
        raise RuntimeError("enough")

    monkeypatch.setattr(measure_module, "run_cell", counted)
    with pytest.raises(RuntimeError, match="enough"):
        measure(config, config.plant, {}, seeds=[1, 2, 3], on_cell=stop)
    assert calls == [1] and len(started) == 1  # one cell ran; the other two seeds' never started
