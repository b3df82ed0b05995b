"""Multi-objective studies in `hil tune`: the feasible Pareto front, the point chosen on it (nearest the best of
every objective, each scaled over the front), the report's front, the controller file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.tune import TrialInfo, tune
from hil.tune._study import choose_on_front, pareto_front
from tests.tune.test_study import SPACE, tiny_campaign


def info(number: int, values: tuple[float, ...], feasible: bool = True, state: str = "COMPLETE") -> TrialInfo:
    return TrialInfo(number, state, values[0], {}, feasible, {}, "", 1.0, values)


def test_the_front_keeps_the_feasible_trials_nothing_beats_everywhere() -> None:
    trials = [info(0, (1.0, 9.0)), info(1, (2.0, 4.0)), info(2, (3.0, 5.0)),  # 2 is beaten by 1 on both
              info(3, (4.0, 1.0)), info(4, (0.5, 0.5), feasible=False), info(5, (2.0, 4.0)),  # 5 ties 1
              info(6, (9.0, 0.9)), TrialInfo(7, "FAIL", None, {}, None, {}, "unstable", 1.0, None)]
    front = pareto_front(trials, ["minimize", "minimize"])
    assert [t.number for t in front] == [0, 1, 3, 5, 6]
    # scaled over the front: x 1..9 -> 0..1, y 0.9..9 -> 0..1; trial 3 at (0.375, 0.012) is nearer (0, 0) than 1
    # and 5 at (0.125, 0.383)
    assert choose_on_front(front, ["minimize", "minimize"]).number == 3  # type: ignore[union-attr]
    # maximising the second objective: (1, 9) is then the best on both, the front's one point
    up = pareto_front(trials, ["minimize", "maximize"])
    assert [t.number for t in up] == [0]
    assert choose_on_front([], ["minimize"]) is None


@pytest.mark.slow
def test_a_study_of_miss_against_ripple_writes_its_front_and_its_chosen_point(tmp_path: Path) -> None:
    out = tmp_path / "s"
    result = tune(tiny_campaign(tmp_path), SPACE, objective=["miss_std_px", "drive_ripple_el_counts"], trials=5,
                  out=out, seed=3)
    assert result.objectives == ["miss_std_px", "drive_ripple_el_counts"]
    assert result.directions == ["minimize", "minimize"] and result.n_pruned == 0
    done = [t for t in result.trials if t.state == "COMPLETE" and t.feasible]
    assert len(done) >= 2 and result.pareto and result.best_trial in result.pareto
    cells = {t.number: json.loads((out / "trials" / f"{t.number:05d}" / "campaign.json").read_text())["cells"][0]
             for t in done}
    for t in done:  # each value is the cell's metric (one cell here)
        assert t.values == (pytest.approx(cells[t.number]["metrics"]["miss_std_px"], rel=1e-12),
                            pytest.approx(cells[t.number]["metrics"]["drive_ripple_el_counts"], rel=1e-12))
    for t in done:  # on the front exactly when no other feasible trial is as good on both and better on one
        beaten = any(u.values[0] <= t.values[0] and u.values[1] <= t.values[1] and u.values != t.values  # type: ignore[index]
                     for u in done)
        assert (t.number in result.pareto) == (not beaten)
    chosen = next(t for t in done if t.number == result.best_trial)
    assert result.best_values == list(chosen.values)  # type: ignore[arg-type]
    assert "nearest the best of every objective" in result.yaml_path.read_text()  # type: ignore[union-attr]
    page = result.report.markdown.read_text()
    assert "## Pareto front" in page and (out / "tune-pareto.png").is_file()
    assert json.loads((out / "best.json").read_text())["pareto"] == result.pareto
