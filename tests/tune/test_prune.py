"""Pruning and warm starts in `hil tune`: the rule (a trial stops once its running mean over its first cells trails the
best complete feasible trial's over the same cells by more than 25 %), a pruned trial's cells not run, and the shipped
gains as a new study's first trial."""

from __future__ import annotations

import json
from pathlib import Path

import optuna
import pytest

from hil.tune import CellPruner, _prune, tune
from tests.tune.test_study import tiny_campaign

KP = "kp_counts_per_dps=1000..20000:log"


def study(direction: str = "minimize", startup: int = 2) -> optuna.Study:
    return optuna.create_study(direction=direction, pruner=CellPruner(startup_trials=startup))


def complete(st: optuna.Study, steps: list[float], value: float, constraint: float | None = None) -> None:
    t = st.ask()
    for i, v in enumerate(steps):
        t.report(v, i)
    if constraint is not None:
        t.set_constraint("ripple<=800", constraint)
    st.tell(t, value)


def first_cell(st: optuna.Study, value: float) -> bool:
    t = st.ask()
    t.report(value, 0)
    return t.should_prune()


def test_a_trial_25_percent_behind_the_best_over_the_same_cells_is_pruned() -> None:
    st = study()
    complete(st, [4.0, 4.1], 4.05)
    complete(st, [6.0, 6.2], 6.1)
    assert first_cell(st, 5.01)  # 4.0 x 1.25 = 5.0
    assert not first_cell(st, 4.99)
    t = st.ask()
    t.report(4.5, 0)
    t.report(5.2, 1)  # the best's running mean after two cells is 4.1: 5.125 is the bound
    assert t.should_prune()


def test_no_trial_is_pruned_before_the_startup_trials_have_completed() -> None:
    st = study(startup=2)
    complete(st, [4.0, 4.1], 4.05)
    assert not first_cell(st, 40.0)
    complete(st, [5.0, 5.0], 5.0)
    assert first_cell(st, 40.0)


def test_an_infeasible_trial_is_not_the_reference_and_maximising_turns_the_rule_around() -> None:
    st = study()
    complete(st, [1.0, 1.0], 1.0, constraint=+5.0)  # best value, but its ripple bound is broken
    complete(st, [4.0, 4.0], 4.0, constraint=-1.0)
    assert not first_cell(st, 4.9) and first_cell(st, 5.1)  # against 4.0, not 1.0
    up = study("maximize")
    complete(up, [4.0, 4.0], 4.0)
    complete(up, [3.0, 3.0], 3.0)
    assert first_cell(up, 2.9) and not first_cell(up, 3.1)  # 4.0 x 0.75 = 3.0


@pytest.mark.slow
def test_a_hopeless_trial_stops_after_its_first_cell_and_the_shipped_gains_come_first(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_prune, "PRUNE_STARTUP_TRIALS", 1)
    campaign, out = tiny_campaign(tmp_path, seeds=[1, 2]), tmp_path / "s"
    first = tune(campaign, KP, trials=1, out=out, write_report=False)
    assert first.trials[0].params == {"kp_counts_per_dps": 8000.0}  # the registry's default: the shipped gains
    assert first.trials[0].state == "COMPLETE"
    shipped = first.trials[0].value
    # a gain far below the shipped one: its first cell's miss is well over 1.25 x the shipped gains' first cell
    optuna.load_study(study_name="tiny-tune", storage=first.storage).enqueue_trial({"kp_counts_per_dps": 1000.0})
    again = tune(campaign, KP, trials=2, out=out, resume=True, write_report=True)
    pruned = again.trials[1]
    assert pruned.params == {"kp_counts_per_dps": 1000.0} and pruned.state == "PRUNED", pruned
    assert pruned.failure.startswith("pruned after 1 of 2 cells: mean miss_std_px")
    ran = json.loads((out / "trials" / "00001" / "campaign.json").read_text())["cells"]
    assert sum(c["status"] == "completed" for c in ran) == 1  # the second cell was stopped, or never started
    stored = optuna.load_study(study_name="tiny-tune", storage=first.storage).trials
    assert list(stored[1].intermediate_values) == [0]
    assert stored[1].intermediate_values[0] > 1.25 * stored[0].intermediate_values[0]
    assert stored[1].intermediate_values[0] == pytest.approx(ran[0]["metrics"]["miss_std_px"], rel=1e-12)
    assert shipped == pytest.approx(stored[0].intermediate_values[1], rel=1e-12)  # the running mean of both cells
    assert again.best_trial == 0 and "PRUNED" in again.report.markdown.read_text()
