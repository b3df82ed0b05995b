"""`hil tune`'s inputs: the search space, the constraints, the controller entry, a trial's campaign and its score
(no sessions run here)."""

from __future__ import annotations

import math

import pytest

from hil.campaign.model import CampaignConfig, CampaignResult, CellResult
from hil.config import PROFILES, ConfigError
from hil.tune import (
    Constraint,
    Objective,
    ParamSpec,
    check_cells,
    choose_controller,
    evaluate,
    parse_constraints,
    parse_objective,
    parse_params,
    trial_campaign,
)

CAMPAIGN = PROFILES / "campaigns" / "swing-miss-distance.yaml"


def test_the_issue_s_space_parses_to_exact_ranges() -> None:
    space = parse_params("omega_o_rad_s=100..2000:log, kp_counts_per_dps=1000..20000:log, q_dps2=1e-6..1e-2:log",
                         "eso_kf")
    assert space == [ParamSpec("omega_o_rad_s", 100.0, 2000.0, log=True),
                     ParamSpec("kp_counts_per_dps", 1000.0, 20000.0, log=True),
                     ParamSpec("q_dps2", 1e-6, 1e-2, log=True)]
    assert [str(s) for s in space] == ["omega_o_rad_s=100..2000:log", "kp_counts_per_dps=1000..20000:log",
                                       "q_dps2=1e-06..0.01:log"]


def test_linear_int_and_list_forms() -> None:
    assert parse_params(["s_dps2=0..1e-3", " ki_counts_per_deg = 0 .. 5000 :int "], "eso_kf") == [
        ParamSpec("s_dps2", 0.0, 1e-3), ParamSpec("ki_counts_per_deg", 0.0, 5000.0, integer=True)]
    # an integer parameter is always sampled as an integer
    assert parse_params("u_max_counts=1000..30000", "eso_kf") == [ParamSpec("u_max_counts", 1000, 30000,
                                                                            integer=True)]
    assert parse_params("cutoff_hz=50..400:log", "pi_lpf") == [ParamSpec("cutoff_hz", 50.0, 400.0, log=True)]


@pytest.mark.parametrize(("spec", "message"), [
    ("", "params: nothing to tune"),
    ("foo=1..2", "params='foo=1..2': unknown parameter of controller 'eso_kf' (numeric parameters: kp_counts_per_dps,"),
    ("steady_state=0..1", "params='steady_state=0..1': not a numeric parameter of controller 'eso_kf'"),
    ("omega_o_rad_s=2000..100", "params='omega_o_rad_s=2000..100': the range 2000..100 is empty (need low < high)"),
    ("omega_o_rad_s=5..5", "params='omega_o_rad_s=5..5': the range 5..5 is empty"),
    ("q_dps2=0..1e-2:log", "params='q_dps2=0..1e-2:log': ':log' needs a positive range (got 0..0.01)"),
    ("omega_o_rad_s=100..5000", "params='omega_o_rad_s=100..5000': 5000 is not valid: controller 'eso_kf': parameter "
                                "omega_o_rad_s: omega_o * dt_s = 5 is above pi"),
    ("kp_counts_per_dps=1000..50000", "params='kp_counts_per_dps=1000..50000': 50000 is not valid"),
    ("omega_o_rad_s=100..200:cubic",
     "params='omega_o_rad_s=100..200:cubic': unknown suffix ':cubic' (':log' or ':int')"),
    ("omega_o_rad_s=100-200", "params='omega_o_rad_s=100-200': not name=low..high[:log|:int]"),
    ("omega_o_rad_s=a..200", "params='omega_o_rad_s=a..200': 'a' is not a number"),
    ("omega_o_rad_s=nan..200", "params='omega_o_rad_s=nan..200': 'nan' is not a finite number"),
    ("ki_counts_per_deg=0.5..10:int", "params='ki_counts_per_deg=0.5..10:int': an integer range needs whole numbers"),
    ("q_dps2=1e-6..1e-2, q_dps2=1e-5..1e-3", "params='q_dps2=1e-5..1e-3': given twice"),
])
def test_a_bad_space_is_one_line_naming_params(spec: str, message: str) -> None:
    with pytest.raises(ConfigError) as exc:
        parse_params(spec, "eso_kf")
    assert str(exc.value).startswith(message) and "\n" not in str(exc.value)


def test_constraints_parse_and_measure_the_worst_cell() -> None:
    assert parse_constraints("drive_ripple_el_counts<=800, miss_std_px >= 0.5") == [
        Constraint("drive_ripple_el_counts", "<=", 800.0), Constraint("miss_std_px", ">=", 0.5)]
    assert Constraint("drive_ripple_el_counts", "<=", 800.0).value([700.0, 850.0]) == 50.0
    assert Constraint("drive_ripple_el_counts", "<=", 800.0).value([700.0, 750.0]) == -50.0
    assert Constraint("miss_std_px", ">=", 0.5).value([0.75, 0.25]) == 0.25
    for bad, message in (("ripple<=3", "^constraints='ripple<=3': unknown metric 'ripple'"),
                         ("miss_std_px<3", "^constraints='miss_std_px<3': not metric<=value"),
                         ("miss_std_px<=inf", "^constraints='miss_std_px<=inf': 'inf' is not a finite number")):
        with pytest.raises(ConfigError, match=message):
            parse_constraints([bad])


def test_the_tuned_entry_is_the_first_non_baseline_or_the_label() -> None:
    from hil.campaign import load_campaign

    config = load_campaign(CAMPAIGN)
    assert choose_controller(config, None).label == "ESO+KF"  # ESO is the baseline
    assert choose_controller(config, "high-gain ESO+KF").name == "eso_kf_high_gain"
    with pytest.raises(ConfigError, match=r"^controller='PID': not a controller label of campaign "):
        choose_controller(config, "PID")
    trial = trial_campaign(config, choose_controller(config, "high-gain ESO+KF"), {"q_dps2": 1e-4})
    assert [(c.label, c.name, c.params) for c in trial.controllers] == [
        ("high-gain ESO+KF", "eso_kf_high_gain", {"q_dps2": 1e-4})]
    assert trial.baseline is None and trial.acceptance == [] and trial.seeds == config.seeds
    assert len(trial.cells()) == len(config.profiles) * len(config.seeds)


def _result(config: CampaignConfig, metrics: list[dict[str, float]], status: str = "completed") -> CampaignResult:
    cells = [CellResult(cell_id=s.cell_id, profile=s.profile.label, controller=s.controller.label,
                        controller_name=s.controller.name, seed=s.seed, status=status, exit_code=0, metrics=m)
             for s, m in zip(config.cells(), metrics, strict=True)]
    return CampaignResult(config=config, cells=cells, complete=True)


def test_the_score_is_the_mean_over_cells_and_constraints_take_the_worst_cell(tmp_path) -> None:
    from hil.campaign import load_campaign

    config = load_campaign(CAMPAIGN)
    trial = trial_campaign(config, choose_controller(config, None), {})
    n = len(trial.cells())
    assert n == 6  # 2 profiles x 3 seeds
    ms = [{"miss_std_px": 1.0 + i, "drive_ripple_el_counts": 100.0 * (i + 1), "missed_cycles": 0.0}
          for i in range(n)]
    value, cons, attrs = evaluate(_result(trial, ms), tmp_path, "miss_std_px",
                                  [Constraint("drive_ripple_el_counts", "<=", 500.0)], check_logs=False)
    assert value == 3.5  # mean of 1..6
    # the campaign's thresholds are constraints too: miss_std_px max 40, missed_cycles max 0
    assert cons == [100.0, 6.0 - 40.0, 0.0]
    assert attrs["constraint_names"] == ["drive_ripple_el_counts<=500", "miss_std_px<=40", "missed_cycles<=0"]
    with pytest.raises(ValueError, match="session fault"):
        evaluate(_result(trial, ms, status="fault"), tmp_path, "miss_std_px", [], check_logs=False)
    ms[2]["miss_std_px"] = math.nan
    with pytest.raises(ValueError, match="miss_std_px is not available"):
        evaluate(_result(trial, ms), tmp_path, "miss_std_px", [], check_logs=False)
    partial = _result(trial, ms)
    with pytest.raises(ValueError, match="1 cell"):
        evaluate(partial.model_copy(update={"cells": partial.cells[:-1]}), tmp_path, "miss_std_px", [],
                 check_logs=False)


def test_an_objective_or_a_constraint_on_some_cells_is_judged_on_those_only(tmp_path) -> None:
    from hil.campaign import load_campaign

    config = load_campaign(CAMPAIGN)
    labels = [p.label for p in config.profiles]
    assert labels == ["1 deg / 1 Hz", "3 deg / 1 Hz"]
    goal = parse_objective("miss_std_px@3 deg*")
    assert goal == Objective("miss_std_px", "3 deg*") and str(goal) == "miss_std_px@3 deg*"
    assert parse_objective("miss_std_px") == Objective("miss_std_px", "*")
    bound = parse_constraints("rate_err_el_std_dps<=0.3 @ 1 deg*")
    assert bound == [Constraint("rate_err_el_std_dps", "<=", 0.3, "1 deg*")]
    assert str(bound[0]) == "rate_err_el_std_dps<=0.3@1 deg*"
    trial = trial_campaign(config, choose_controller(config, None), {})
    cells = trial.cells()
    ms = [{"miss_std_px": 1.0 + i, "rate_err_el_std_dps": 0.1 * (i + 1), "missed_cycles": 0.0}
          for i in range(len(cells))]
    value, cons, attrs = evaluate(_result(trial, ms), tmp_path, goal, bound, check_logs=False)
    on_3deg = [m["miss_std_px"] for s, m in zip(cells, ms, strict=True) if s.profile.label.startswith("3 deg")]
    on_1deg = [m["rate_err_el_std_dps"] for s, m in zip(cells, ms, strict=True) if s.profile.label.startswith("1 deg")]
    assert len(on_3deg) == len(on_1deg) == 3
    assert value == pytest.approx(sum(on_3deg) / 3)
    assert cons[0] == pytest.approx(max(on_1deg) - 0.3)  # the worst 1 deg cell, not the worst cell
    assert sorted(attrs["cells"]) == sorted(s.cell_id for s in cells if s.profile.label.startswith("3 deg"))
    check_cells([goal, *bound], labels)
    with pytest.raises(ConfigError, match=r"^objective='miss_std_px@vib\*': @'vib\*' matches no profile label of "
                                          r"the campaign \('1 deg / 1 Hz', '3 deg / 1 Hz'\)"):
        check_cells([parse_objective("miss_std_px@vib*")], labels)
    for bad, message in (("miss_std_px@", "nothing after '@'"), ("ripple@3*", "unknown metric 'ripple'")):
        with pytest.raises(ConfigError, match=message):
            parse_objective(bad)
