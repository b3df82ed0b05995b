"""Campaign files: every cell is validated before anything is written, and a campaign's name cannot leave
runs/campaigns/."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from hil.campaign import runner
from hil.config import MAX_YAML_NODES, PROFILES
from tests.factories import session_data, write_yaml
from tests.reliability.helpers import bad_input, listing

CAMPAIGN = PROFILES / "campaigns" / "filter-lag-15hz.yaml"


def campaign_file(tmp_path: Path, **changes: Any) -> Path:
    data = yaml.safe_load(CAMPAIGN.read_text())
    data["session"] = str((CAMPAIGN.parent / data["session"]).resolve())
    for p in data["profiles"]:
        p["path"] = str((CAMPAIGN.parent / p["path"]).resolve())
    data.update(changes)
    return write_yaml(tmp_path / "campaign.yaml", data)


@pytest.fixture
def no_cell_runs(monkeypatch: pytest.MonkeyPatch, no_board_contact: None) -> None:
    def touched(*_args: Any, **_kwargs: Any) -> None:
        raise AssertionError("a cell of a bad campaign ran")

    monkeypatch.setattr(runner, "run_cell", touched)


def campaign_bad(capsys: pytest.CaptureFixture[str], tmp_path: Path, path: Path, *needles: str,
                 out: Path | None = None) -> None:
    out = out or tmp_path / "out"
    before = listing(tmp_path)
    bad_input(capsys, ["campaign", path, "--out", out], *needles)
    assert listing(tmp_path) == before


@pytest.mark.parametrize(("changes", "needles"), [
    ({"overrides": {"tracking": {"kp_per_s": float("nan")}}},
     ("cell static--eso-kf--s1: tracking.kp_per_s: Input should be a finite number",)),
    ({"controllers": [{"label": "ESO+KF", "name": "eso_kf"}, {"label": "fast", "name": "eso",
                                                                "params": {"kp_counts_per_dps": 9e4}}]},
     ("controllers.1", "kp * b0 * dt_s = 2.07, need < 1")),
    ({"overrides": {"excitation": {"axis": "el", "amplitude_dps": 5.0, "freq_hz": 900.0}}},
     ("cell static--eso-kf--s1: excitation.sine.freq_hz: Input should be less than or equal to 450",)),
    ({"duration_s": 1e9}, ("duration_s: Input should be less than or equal to 86400",)),
    ({"seeds": [1, -1]}, ("seeds.1: Input should be greater than or equal to 0",)),
    ({"name": ".."}, ("name: String should match pattern",)),
    ({"name": "../../etc"}, ("name: String should match pattern",)),
    ({"name": ".hidden"}, ("name: String should match pattern",)),
    ({"controllers": [{"label": "ESO+KF", "name": "eso_kf"}, {"label": "eso kf", "name": "eso"}]},
     ("labels ['ESO+KF', 'eso kf'] would share the cell directory name 'eso-kf'",)),
    ({"controllers": [{"label": "+++", "name": "eso_kf"}]}, ("label '+++' has no letter or digit",)),
    ({"thresholds": {"lag_kf_cycles": {"max": float("inf")}}}, ("thresholds.lag_kf_cycles.max: Input should be a "
                                                               "finite number",)),
])
def test_a_bad_campaign_writes_nothing(
    *, capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_cell_runs: None,
    changes: dict[str, Any], needles: tuple[str, ...],
) -> None:
    path = campaign_file(tmp_path, **changes)
    campaign_bad(capsys, tmp_path, path, str(path), *needles)


def test_a_campaign_named_dot_dot_cannot_write_outside_runs_campaigns(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_cell_runs: None,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Without --out the directory is runs/campaigns/NAME under the working directory."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    path = campaign_file(tmp_path, name="..")
    before = listing(tmp_path)
    bad_input(capsys, ["campaign", path], str(path), "name: String should match pattern", "(got '..')")
    assert listing(tmp_path) == before and not (work / "runs").exists()


def test_an_alias_bomb_in_overrides_is_refused_unexpanded(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_cell_runs: None,
) -> None:
    path = campaign_file(tmp_path)
    levels = "".join(f"  l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]\n" for i in range(1, 7))
    path.write_text(path.read_text().replace("overrides:\n", "overrides:\n  l0: &l0 [1, 2, 3, 4, 5, 6, 7, 8, 9]\n"
                                             + levels, 1))
    campaign_bad(capsys, tmp_path, path, str(path), f"more than {MAX_YAML_NODES} values once its aliases are expanded")


def test_a_cell_that_would_write_the_mqtt_password_in_clear_text_is_refused(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_cell_runs: None,
) -> None:
    session = write_yaml(tmp_path / "s.yaml", session_data(mqtt={"host": "h", "password": "hunter2-campaign"}))
    path = campaign_file(tmp_path, session=str(session))
    line = bad_input(capsys, ["campaign", path, "--out", tmp_path / "out"], str(path), "mqtt.password",
                     "mqtt.password_env or mqtt.password_file")
    assert "hunter2" not in line and not (tmp_path / "out").exists()


def test_an_existing_campaign_is_not_touched_without_resume(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_cell_runs: None,
) -> None:
    out = tmp_path / "out"
    (out / "cells").mkdir(parents=True)
    (out / "campaign.json").write_text("{}")
    path = campaign_file(tmp_path)
    campaign_bad(capsys, tmp_path, path, f"{out}: already holds a campaign; pass --resume", out=out)
