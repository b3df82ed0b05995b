"""The campaign's verdict and comparisons: primary metrics (drive ripple is shown, not averaged in), lags compared
by magnitude (a lead is no improvement), the miss-distance campaign's rule (high-gain ESO+KF against ESO, as the
paper's Tables 2-3), and the validation of ``primary_metrics``. Constructed results, no session runs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from hil.campaign import CampaignError, load_campaign, report
from hil.campaign.metrics import METRICS, default_primary, improvement_pct, score
from hil.campaign.model import CampaignConfig, CampaignResult, CellResult
from hil.campaign.report import profile_table, verdict
from hil.campaign.runner import judge
from hil.config import PROFILES

ROOT = Path(__file__).resolve().parents[2]
CAMPAIGNS = PROFILES / "campaigns"
P1, P3 = "1 deg / 1 Hz", "3 deg / 1 Hz"
HIL = [sys.executable, "-m", "hil"]


def config(**changes: Any) -> CampaignConfig:
    data: dict[str, Any] = {
        "name": "verdict", "title": "ESO vs high-gain ESO+KF", "session": "profiles/sessions/swing-1deg-1hz-eso.yaml",
        "profiles": [{"label": P1, "path": "profiles/swing/swing-1deg-1hz.yaml"}],
        "controllers": [{"label": "ESO", "name": "eso"}, {"label": "high-gain ESO+KF", "name": "eso_kf_high_gain"}],
        "seeds": [1, 2], "baseline": "ESO", "metrics": ["miss_std_px", "drive_ripple_el_counts"],
    }
    data.update(changes)
    return CampaignConfig.model_validate(data, context={"base_dir": ROOT})


def result(cfg: CampaignConfig, values: dict[tuple[str, str], list[float]]) -> CampaignResult:
    """Every cell completed, ``values[(controller, metric)]`` per seed (in the order of ``cfg.seeds``)."""
    cells = [CellResult(cell_id=s.cell_id, profile=s.profile.label, controller=s.controller.label,
                        controller_name=s.controller.name, seed=s.seed, status="completed", exit_code=0,
                        metrics={m: values[(s.controller.label, m)][cfg.seeds.index(s.seed)] for m in cfg.metrics})
             for s in cfg.cells()]
    return CampaignResult(config=cfg, cells=cells, acceptance=judge(cfg, cells), complete=True)


# the default rigid plant's miss std and drive ripple (docs/emulator.md, Calibration): the high-gain observer
# cuts the miss distance by ~70 % at 2.3x the ripple
MISS_AND_RIPPLE = {("ESO", "miss_std_px"): [4.72, 4.84], ("high-gain ESO+KF", "miss_std_px"): [1.45, 1.47],
                   ("ESO", "drive_ripple_el_counts"): [238.0, 240.0],
                   ("high-gain ESO+KF", "drive_ripple_el_counts"): [557.0, 561.0]}


# --- primary metrics -------------------------------------------------------------------------


def test_worse_ripple_does_not_drag_the_verdict_of_a_better_primary_metric() -> None:
    cfg = config(primary_metrics=["miss_std_px"])
    res = result(cfg, MISS_AND_RIPPLE)
    miss = 100 * (4.78 - 1.46) / 4.78  # means over the seeds: 69.5 % better
    ripple = 100 * (239.0 - 559.0) / 239.0  # -133.9 %: worse
    banner = verdict(res)
    assert banner.headline == "high-gain ESO+KF wins"
    assert banner.text.startswith(f"Best in 1 of 1 primary columns; {miss:.1f} % better than ESO on average "
                                  f"(+{miss:.1f} % to +{miss:.1f} %). Verdict on the primary metric: miss std; "
                                  "shown, not in the verdict: EL drive ripple.")
    # averaging ripple in would have said (69.5 - 133.9) / 2 = -32.2 %
    assert f"{abs((miss + ripple) / 2):.1f}" not in banner.text and "worse" not in banner.text
    # the ripple column is still in the table, with its (negative) gain
    table = profile_table(res, P1)
    rows = {row[0].text: row for row in table.rows}
    ripple_col = table.header.index("EL drive ripple [counts]")
    assert rows["high-gain ESO+KF"][ripple_col + 1].text == f"{ripple:+.1f} %"
    assert rows["ESO"][ripple_col].best and not rows["high-gain ESO+KF"][ripple_col].best


def test_the_default_primary_metrics_are_the_error_metrics() -> None:
    cfg = config()  # no primary_metrics: the table's error metrics, here miss std
    assert cfg.primary_metrics is None and cfg.verdict_metrics == ["miss_std_px"]
    banner = verdict(result(cfg, MISS_AND_RIPPLE))
    assert banner.headline == "high-gain ESO+KF wins" and "Best in 1 of 1 primary columns" in banner.text
    assert "Verdict on the primary metric (by default the error metrics): miss std; shown, not in the verdict: " \
           "EL drive ripple." in banner.text
    assert default_primary(["drive_ripple_el_counts", "latency_p99_us", "missed_cycles"]) == []
    assert default_primary(["lag_lpf_cycles", "lag_kf_cycles", "drive_ripple_el_counts"]) == ["lag_lpf_cycles",
                                                                                              "lag_kf_cycles"]
    assert default_primary(["gyro_kf_std_dps", "rate_err_el_std_dps"]) == ["rate_err_el_std_dps"]
    # a table of ripple only has no default primary metric: no winner, and the banner says how to name one
    ripple_only = config(metrics=["drive_ripple_el_counts"])
    banner = verdict(result(ripple_only, MISS_AND_RIPPLE))
    assert banner.headline.startswith("No winner: no primary metric") and "primary_metrics" in banner.headline


def test_naming_ripple_primary_turns_the_verdict() -> None:
    banner = verdict(result(config(primary_metrics=["drive_ripple_el_counts"]), MISS_AND_RIPPLE))
    assert banner.headline == "ESO wins" and "Best in 1 of 1 primary columns" in banner.text
    assert "57.2 % better than high-gain ESO+KF on average" in banner.text  # (559 - 239) / 559
    assert "shown, not in the verdict: miss std." in banner.text


def test_a_winner_worse_on_average_is_said_to_be_worse() -> None:
    # ESO+KF wins two columns by a little and loses one by a lot: best in most columns, worse on average
    cfg = config(controllers=[{"label": "ESO", "name": "eso"}, {"label": "ESO+KF", "name": "eso_kf"}],
                 metrics=["miss_std_px", "miss_range_px", "rate_err_el_std_dps"])
    values = {("ESO", "miss_std_px"): [4.0, 4.0], ("ESO+KF", "miss_std_px"): [3.9, 3.9],
              ("ESO", "miss_range_px"): [10.0, 10.0], ("ESO+KF", "miss_range_px"): [9.8, 9.8],
              ("ESO", "rate_err_el_std_dps"): [0.2, 0.2], ("ESO+KF", "rate_err_el_std_dps"): [0.4, 0.4]}
    banner = verdict(result(cfg, values))
    assert banner.headline == "ESO+KF wins" and "Best in 2 of 3 primary columns" in banner.text
    assert "31.8 % worse than ESO on average (-100.0 % to +2.5 %)" in banner.text


# --- lags: a lead is no improvement ------------------------------------------------------------


def test_lag_improvement_is_on_the_magnitude() -> None:
    assert METRICS["lag_kf_cycles"].magnitude and METRICS["lag_kf_cycles"].unit == "loop cycles of 1 ms"
    assert not METRICS["miss_std_px"].magnitude and score("miss_std_px", -1.0) == -1.0
    # the default plant's Fig 13 lags: low-pass 0.635, KF -0.424 (a lead): 33.2 % better, not 166.8 %
    assert improvement_pct("lag_kf_cycles", -0.424, 0.635) == pytest.approx(100 * (0.635 - 0.424) / 0.635)
    assert improvement_pct("lag_kf_cycles", -0.9, 0.635) == pytest.approx(-41.7, abs=0.05)  # a bigger lead: worse
    assert improvement_pct("lag_kf_cycles", 0.3, -0.6) == pytest.approx(50.0)  # from a lead to a smaller lag


def lag_config(**changes: Any) -> CampaignConfig:
    return config(**{"controllers": [{"label": "A", "name": "eso_kf"}, {"label": "B", "name": "eso_kf_high_gain"}],
                     "baseline": "A", "metrics": ["lag_kf_cycles", "lag_lpf_cycles"],
                     "primary_metrics": ["lag_kf_cycles"], **changes})


LAGS = {("A", "lag_kf_cycles"): [0.30, 0.30], ("B", "lag_kf_cycles"): [-0.50, -0.50],
        ("A", "lag_lpf_cycles"): [0.635, 0.635], ("B", "lag_lpf_cycles"): [0.635, 0.635]}


def test_a_lead_does_not_win_a_lag_column() -> None:
    res = result(lag_config(), LAGS)
    rows = {row[0].text: row for row in profile_table(res, P1).rows}
    # B's -0.50 is numerically lower, but 0.50 from the gyro's timing against A's 0.30: A is the best, B worse
    assert rows["A"][2].best and not rows["B"][2].best
    assert rows["B"][2].text == "-0.500 (-0.500–-0.500)" and rows["B"][3].text == "-66.7 %"
    banner = verdict(res)
    assert banner.headline == "A wins" and "40.0 % better than B on average" in banner.text


def test_an_acceptance_rule_on_a_lag_compares_magnitudes() -> None:
    rule = {"metric": "lag_kf_cycles", "better": "B", "than": "B", "than_metric": "lag_lpf_cycles"}
    cfg = lag_config(acceptance=[rule])
    assert cfg.acceptance[0].describe() == "B: |lag_kf_cycles| below |lag_lpf_cycles|"
    lead_ok = result(cfg, {**LAGS, ("B", "lag_kf_cycles"): [-0.424, -0.424]}).acceptance[0]
    assert lead_ok.passed and lead_ok.details[0] == (f"{P1}, seed 1: lag_lpf_cycles 0.635 -> lag_kf_cycles -0.424 "
                                                     "(+33.2 % by magnitude)")
    big_lead = result(cfg, {**LAGS, ("B", "lag_kf_cycles"): [-0.9, -0.9]}).acceptance[0]
    assert not big_lead.passed and big_lead.details[0].endswith("(-41.7 % by magnitude)  FAILS")


def test_a_lag_gap_closed_is_on_the_magnitude() -> None:
    cfg = lag_config(controllers=[{"label": "A", "name": "eso_kf"}, {"label": "B", "name": "eso_kf_high_gain"},
                                  {"label": "oracle", "name": "oracle"}])
    res = result(cfg, {**LAGS, ("oracle", "lag_kf_cycles"): [0.0, 0.0], ("oracle", "lag_lpf_cycles"): [0.6, 0.6]})
    assert report.gap_closed_fraction(res, P1, "B", "lag_kf_cycles") == pytest.approx(-2 / 3)  # (0.3 - 0.5) / 0.3


# --- the miss-distance campaign: high-gain ESO+KF against ESO -----------------------------------


def test_swing_miss_distance_compares_high_gain_eso_kf_with_eso_as_the_paper() -> None:
    cfg = load_campaign(CAMPAIGNS / "swing-miss-distance.yaml")
    assert cfg.primary_metrics == ["miss_std_px"]
    # the paper's Tables 2-3 give ESO and high-gain ESO+KF only
    for profile in (P1, P3):
        assert set(cfg.paper[profile]) == {"ESO", "high-gain ESO+KF"}
    # its "44.81 % / 39.42 %" are ratios; the improvements are 55 % and 61 %
    paper = {p: improvement_pct("miss_std_px", cfg.paper[p]["high-gain ESO+KF"]["miss_std_px"],
                                cfg.paper[p]["ESO"]["miss_std_px"]) for p in (P1, P3)}
    assert paper[P1] == pytest.approx(55.0, abs=0.05) and paper[P3] == pytest.approx(60.6, abs=0.05)
    ratio = {p: cfg.paper[p]["high-gain ESO+KF"]["miss_std_px"] / cfg.paper[p]["ESO"]["miss_std_px"] for p in (P1, P3)}
    assert ratio[P3] == pytest.approx(0.3942, abs=1e-4)  # the paper's "39.42 %"
    assert ratio[P1] == pytest.approx(0.4481, abs=0.003)  # "44.81 %" = 2.721 / 6.072 of its text; tables: 2.71 / 6.02
    # the rule with a margin: high-gain ESO+KF at least by_pct below ESO, by_pct under the paper's improvements
    main = [r for r in cfg.acceptance if r.metric == "miss_std_px" and r.than == "ESO"]
    assert [(r.better, r.reference_metric, r.profiles) for r in main] == [("high-gain ESO+KF", "miss_std_px", None)]
    assert 0 < main[0].by_pct < min(paper.values())
    # no rule asks ESO+KF at the ESO's gain for a margin (the paper gives no such number)
    assert not [r for r in cfg.acceptance if r.better == "ESO+KF" and r.by_pct > 0]


def test_swing_miss_distance_rule_passes_on_the_papers_numbers_whatever_same_gain_eso_kf_does() -> None:
    cfg = load_campaign(CAMPAIGNS / "swing-miss-distance.yaml")
    # the paper's Tables 2-3, ESO+KF at the same gain no better than ESO
    values = {("ESO", "miss_std_px"): (6.02, 15.60), ("ESO+KF", "miss_std_px"): (6.0, 15.5),
              ("high-gain ESO+KF", "miss_std_px"): (2.71, 6.15)}
    cells = [CellResult(cell_id=s.cell_id, profile=s.profile.label, controller=s.controller.label,
                        controller_name=s.controller.name, seed=s.seed, status="completed", exit_code=0,
                        metrics={m: values.get((s.controller.label, m), (1.0, 1.0))[s.profile.label == P3]
                                 for m in cfg.metrics})
             for s in cfg.cells()]
    rules = judge(cfg, cells)
    assert [r.passed for r in rules] == [True, True]
    assert rules[0].rule == "high-gain ESO+KF lowers miss_std_px vs ESO by >= 40 %"
    assert rules[0].details[0] == f"{P1}, seed 1: ESO 6.02 -> high-gain ESO+KF 2.71 (+55.0 %)"
    # the paper's 1 deg ratio with the 3 deg ESO: a cut of only 30 % fails
    worse = [c.model_copy(update={"metrics": {**c.metrics, "miss_std_px": 10.9}})
             if c.controller == "high-gain ESO+KF" and c.profile == P3 else c for c in cells]
    assert not judge(cfg, worse)[0].passed


# --- validation --------------------------------------------------------------------------------


@pytest.mark.parametrize(("primary", "message"), [
    (["miss_sd"], "primary_metrics: unknown metric 'miss_sd' (metrics: "),
    (["drive_ripple_az_counts"], "primary_metrics: 'drive_ripple_az_counts' is not one of the campaign's metrics"),
    (["miss_std_px", "miss_std_px"], "primary_metrics: 'miss_std_px' appears twice"),
    ([], "primary_metrics: List should have at least 1 item"),
])
def test_bad_primary_metrics_is_one_line_naming_the_field(tmp_path: Path, primary: list[str], message: str) -> None:
    data = yaml.safe_load((CAMPAIGNS / "swing-miss-distance.yaml").read_text())
    data.update(session=str((CAMPAIGNS / data["session"]).resolve()), primary_metrics=primary)
    for p in data["profiles"]:
        p["path"] = str((CAMPAIGNS / p["path"]).resolve())
    path = tmp_path / "campaign.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(CampaignError, match="primary_metrics") as err:
        load_campaign(path)
    assert message in str(err.value) and "\n" not in str(err.value)
    proc = subprocess.run([*HIL, "check", str(path)], capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2 and message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_every_shipped_campaign_validates_and_names_its_primary_metrics() -> None:
    files = sorted(CAMPAIGNS.glob("*.yaml"))
    assert len(files) >= 7
    for path in files:
        cfg = load_campaign(path)
        assert cfg.primary_metrics, path.name
        assert all(METRICS[m].kind not in ("effort", "health") for m in cfg.primary_metrics), path.name
    proc = subprocess.run([*HIL, "check", *map(str, files)], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr


def test_every_metric_has_its_row_in_the_documented_table() -> None:
    """docs/campaigns.md's metrics table names every metric with its kind and unit, as hil.campaign.metrics has it."""
    doc = (Path(__file__).resolve().parents[2] / "docs" / "campaigns.md").read_text()
    missing = [name for name, m in METRICS.items() if f"| `{name}` | {m.kind} | {m.unit} |" not in doc]
    assert not missing
