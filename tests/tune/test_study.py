"""`hil tune` end to end on a tiny campaign (2 s cells at 3 deg / 1 Hz, one seed): the study in SQLite, the
controller file, the report, resume, failed (unstable) trials, constraints, the command line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import optuna
import pytest
import yaml

from hil.campaign import runner
from hil.config import PROFILES, ConfigError, ControllerConfig, load_model
from hil.tune import _study as study_module
from hil.tune import tune

CAMPAIGNS = PROFILES / "campaigns"
SPACE = "omega_o_rad_s=200..1000:log, q_dps2=1e-5..1e-2:log"


def tiny_campaign(tmp_path: Path, **changes: Any) -> Path:
    """swing-miss-distance's 3 deg / 1 Hz profile, ESO (baseline) and ESO+KF, 2 s cells, seed 1."""
    data = yaml.safe_load((CAMPAIGNS / "swing-miss-distance.yaml").read_text())
    data.update(name="tiny-tune", session=str((CAMPAIGNS / data["session"]).resolve()), duration_s=2.0, seeds=[1],
                profiles=[{"label": "3 deg / 1 Hz", "path": str(PROFILES / "swing" / "swing-3deg-1hz.yaml")}],
                controllers=[{"label": "ESO", "name": "eso"}, {"label": "ESO+KF", "name": "eso_kf"}],
                acceptance=[], paper={}, thresholds={"missed_cycles": {"max": 0}})
    data.update(changes)
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def stored_constraints(storage: str, number: int) -> dict[str, float]:
    """The constraints as Optuna stored them on the trial (what TPE reads)."""
    return dict(optuna.load_study(study_name="tiny-tune", storage=storage).trials[number].constraints)


@pytest.mark.slow
def test_a_study_writes_its_database_controller_and_report_and_resumes(tmp_path: Path) -> None:
    campaign, out = tiny_campaign(tmp_path), tmp_path / "study"
    seen: list[int] = []
    result = tune(campaign, SPACE, trials=4, workers=2, out=out, seed=1,
                  constraints=["drive_ripple_el_counts<=100000"], on_trial=lambda t: seen.append(t.number))
    assert (out / "tune.db").is_file() and result.storage == f"sqlite:///{(out / 'tune.db').absolute()}"
    assert sorted(seen) == [0, 1, 2, 3] and result.trials_run == 4
    assert [t.state for t in result.trials] == ["COMPLETE"] * 4, [t.failure for t in result.trials]
    assert result.controller_label == "ESO+KF" and result.direction == "minimize"
    for t in result.trials:
        assert 200 <= t.params["omega_o_rad_s"] <= 1000 and 1e-5 <= t.params["q_dps2"] <= 1e-2
        # the value is the mean of the metric over the trial's cells (one here), as its campaign recorded it
        cells = json.loads((out / "trials" / f"{t.number:05d}" / "campaign.json").read_text())["cells"]
        assert len(cells) == 1 and t.value == pytest.approx(cells[0]["metrics"]["miss_std_px"], rel=1e-12)
        # constraints recorded on the trial for the sampler: the ripple's excess, then the threshold missed_cycles<=0
        ripple = cells[0]["metrics"]["drive_ripple_el_counts"]
        assert t.constraints == {"drive_ripple_el_counts<=100000": pytest.approx(ripple - 100000),
                                 "missed_cycles<=0": 0.0} and t.feasible
        assert stored_constraints(result.storage, t.number) == t.constraints
        assert not list((out / "trials" / f"{t.number:05d}").rglob("*.h5"))  # logs dropped (no --keep-logs)
        assert not list((out / "trials" / f"{t.number:05d}").rglob("*.truth.npz"))  # and their truth files
    best = min(result.trials, key=lambda t: t.value)
    assert (result.best_trial, result.best_value, result.best_params) == (best.number, best.value, best.params)
    controller = load_model(ControllerConfig, result.yaml_path)
    assert result.yaml_path == out / "eso_kf-tuned.yaml"
    assert (controller.name, controller.params) == ("eso_kf", best.params)
    assert result.report.markdown.is_file() and result.report.html.is_file()
    md = result.report.markdown.read_text()
    assert "## Best parameters" in md and "## Parameter importances" in md and "3 deg / 1 Hz" in md
    assert (out / "tune-history.png") in result.report.pngs
    assert "data:image/png;base64," in result.report.html.read_text()

    with pytest.raises(ConfigError, match=r"^study='tiny-tune': already in sqlite:///.*; pass resume=True"):
        tune(campaign, SPACE, trials=6, out=out)
    with pytest.raises(ConfigError, match=r"^resume=True: study='tiny-tune' was made with space"):
        tune(campaign, "omega_o_rad_s=200..1000:log", trials=6, out=out, resume=True)
    again = tune(campaign, SPACE, trials=6, workers=2, out=out, seed=1, resume=True,
                 constraints=["drive_ripple_el_counts<=100000"], write_report=False)
    assert again.trials_run == 2 and len(again.trials) == 6 and again.report is None
    stored = optuna.load_study(study_name="tiny-tune", storage=result.storage)
    assert len(stored.trials) == 6 and [t.number for t in again.trials] == list(range(6))
    # resumed to a target already reached: nothing runs
    assert tune(campaign, SPACE, trials=5, out=out, resume=True, write_report=False).trials_run == 0


@pytest.mark.slow
def test_a_failing_trial_is_failed_and_the_study_goes_on(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real = runner.run_campaign

    def faulty(config, out_dir, **kwargs):  # type: ignore[no-untyped-def]
        result = real(config, out_dir, **kwargs)
        if Path(out_dir).name == "00001":  # trial 1: its cell ended in a fault
            cells = [c.model_copy(update={"status": "fault", "message": "watchdog: no GYRO_SAMPLE for 5 ms"})
                     for c in result.cells]
            return result.model_copy(update={"cells": cells})
        return result

    monkeypatch.setattr(study_module, "run_campaign", faulty)  # the runner as the study calls it
    result = tune(tiny_campaign(tmp_path), SPACE, trials=3, out=tmp_path / "s", seed=2, write_report=True)
    assert [t.state for t in result.trials] == ["COMPLETE", "FAIL", "COMPLETE"]
    failed = result.trials[1]
    assert failed.value is None and failed.feasible is None
    assert failed.failure == "cell 3-deg-1-hz--eso-kf--s1: session fault: watchdog: no GYRO_SAMPLE for 5 ms"
    assert result.n_failed == 1 and result.best_trial in (0, 2)
    assert "failed" in result.report.markdown.read_text()


def test_an_unstable_loop_is_a_failed_trial(tmp_path: Path) -> None:
    # b0 a hundred times below the plant's k_m: the ESO's compensation u0 - z2/b0 drives the loop to its limits
    result = tune(tiny_campaign(tmp_path), "b0_dps2_per_count=1e-4..2e-4:log", trials=2, out=tmp_path / "s",
                  write_report=True)
    assert [t.state for t in result.trials] == ["FAIL", "FAIL"]
    # the drive at its limit, or the line of sight swinging off the target
    assert all("unstable" in t.failure or "lost the target" in t.failure for t in result.trials), result.trials
    assert result.best_trial is None and result.yaml_path is None
    assert "no feasible trial" in result.report.markdown.read_text()


HIL = [sys.executable, "-m", "hil"]


def hil(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*HIL, *map(str, args)], check=False, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "COLUMNS": "200"})


def test_the_command_line_refuses_a_bad_space_in_one_line(tmp_path: Path) -> None:
    out = hil("tune", tiny_campaign(tmp_path), "--params", "omega_o_rad_s=2000..100", "--out", tmp_path / "o")
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.strip() == ("error: --params omega_o_rad_s=2000..100: the range 2000..100 is empty "
                                  "(need low < high)")
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_the_command_line_with_an_infeasible_constraint(tmp_path: Path) -> None:
    out = hil("-q", "tune", tiny_campaign(tmp_path), "--params", SPACE, "--trials", "2", "--out", tmp_path / "o",
              "--constraint", "miss_std_px<=0.0001", "--json", "--no-report")
    assert out.returncode == 1, out.stderr
    data = json.loads(out.stdout)
    assert (data["trials"], data["complete"], data["infeasible"], data["best_trial"]) == (2, 2, 2, None)
    assert data["constraints"] == ["miss_std_px<=0.0001"] and data["yaml"] is None


@pytest.mark.slow
def test_a_study_on_the_dask_engine_scores_each_trial_as_the_local_engine_does(tmp_path: Path) -> None:
    """`hil tune --engine dask` with no scheduler: a LocalCluster of two worker processes runs the trials' cells;
    each trial's value is the one the local engine gives for the same parameters (same seeds, sim clock)."""
    from hil.campaign.model import ControllerEntry

    campaign = tiny_campaign(tmp_path)
    result = tune(campaign, SPACE, trials=3, workers=2, engine="dask", out=tmp_path / "dask", seed=3,
                  write_report=False)
    assert result.engine == "dask" and result.workers == 2 and result.trials_run == 3
    assert [t.state for t in result.trials] == ["COMPLETE"] * 3, [t.failure for t in result.trials]
    config = runner.load_campaign(campaign)
    local = config.model_copy(update={"controllers": [
        ControllerEntry(label=f"t{t.number}", name="eso_kf", params=t.params) for t in result.trials],
        "baseline": None, "acceptance": []})
    cells = {c.controller: c for c in runner.run_campaign(local, tmp_path / "local", jobs=2).cells}
    for t in result.trials:
        assert t.value == cells[f"t{t.number}"].metrics["miss_std_px"], t.params
    assert len({t.value for t in result.trials}) == 3  # three different gains, three different scores
