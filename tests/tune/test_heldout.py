"""A study's report compares the tuned gains with the shipped ones, the baseline and the oracle on seeds the study
never ran."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.tune import tune
from tests.tune.test_study import SPACE, tiny_campaign


@pytest.mark.slow
def test_the_tuned_gains_are_compared_on_held_out_seeds(tmp_path: Path) -> None:
    out = tmp_path / "s"
    result = tune(tiny_campaign(tmp_path), SPACE, trials=2, out=out, heldout_seeds=2, heldout_duration_s=1.5)
    assert result.best_trial is not None and result.heldout_seeds == [2, 3]  # the campaign ran seed 1
    held = result.heldout
    assert held is not None
    assert [k for k in held if not k.startswith("_")] == ["ESO", "ESO+KF", "ESO+KF tuned", "oracle"]
    for label in ("ESO", "ESO+KF", "ESO+KF tuned", "oracle"):
        assert len(held[label]["values"]) == 2 and held[label]["failed"] == []
        assert held[label]["mean"] == pytest.approx(sum(held[label]["values"]) / 2, rel=1e-12)
    assert held["oracle"]["mean"] < held["ESO"]["mean"]  # the true rate beats the gyro-fed loop
    page = result.report.markdown.read_text()
    assert "## On held-out seeds" in page and "Seeds 2, 3" in page
    assert json.loads(json.dumps(result.to_json()))["heldout_seeds"] == [2, 3]
