"""Campaigns end to end: cells as lockstep loopback sessions in parallel, resume, thresholds, acceptance,
bad input; and the shipped campaigns' acceptance on short lockstep versions."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from hil.campaign import CampaignError, load_campaign, load_results, run_campaign
from hil.campaign.runner import cell_session
from hil.config import PROFILES

CAMPAIGNS = PROFILES / "campaigns"
HIL = [sys.executable, "-m", "hil"]


def write_campaign(tmp_path: Path, **changes: Any) -> Path:
    """A small lag campaign (2 seeds x 1 controller, 2 s) built from the shipped one, with ``changes``."""
    data = yaml.safe_load((CAMPAIGNS / "filter-lag-15hz.yaml").read_text())
    data.update(session=str(CAMPAIGNS / data["session"]), duration_s=2.0, seeds=[1, 2])
    for p in data["profiles"]:
        p["path"] = str((CAMPAIGNS / p["path"]).resolve())
    data.update(changes)
    path = tmp_path / "campaign.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_cells_run_in_parallel_keep_their_logs_and_resume(tmp_path: Path) -> None:
    config = load_campaign(write_campaign(tmp_path, thresholds={"lag_lpf_cycles": {"max": 0.1}}))
    out = tmp_path / "out"
    seen: list[str] = []
    result = run_campaign(config, out, jobs=2, on_cell=lambda c: seen.append(c.cell_id))
    assert result.complete and sorted(seen) == sorted(s.cell_id for s in config.cells())
    assert len(result.cells) == 2
    for cell in result.cells:
        assert cell.status == "completed", cell.message
        assert (out / cell.log).is_file() and (out / "cells" / cell.cell_id / "session.yaml").is_file()
        # the first-order 150 Hz low-pass at 1 kHz lags (1 - a)/a = 0.64 samples at low frequency
        assert 0.55 < cell.metrics["lag_lpf_cycles"] < 0.75
        assert cell.failures == [f"lag_lpf_cycles = {cell.metrics['lag_lpf_cycles']:.4g} > max 0.1"]
    assert not result.passed  # the threshold fails every cell
    assert [r.passed for r in result.acceptance] == [True]  # the KF leads the delayed gyro: less lag
    assert load_results(out).model_dump() == result.model_dump()

    with pytest.raises(CampaignError, match="resume=True"):
        run_campaign(config, out)
    # resume: nothing to run; then lose one cell's result and only that one runs again
    assert run_campaign(config, out, resume=True, on_cell=lambda c: None).complete
    first = config.cells()[0].cell_id
    (out / "cells" / first / "result.json").unlink()
    rerun: list[str] = []
    again = run_campaign(
        config.model_copy(update={"thresholds": {}}), out, resume=True, on_cell=lambda c: rerun.append(c.cell_id)
    )
    assert again.complete and again.passed
    # lockstep: the re-run cell reproduces its control metrics exactly (the latency is the host's own)
    old = next(c for c in result.cells if c.cell_id == first).metrics
    new = next(c for c in again.cells if c.cell_id == first).metrics
    assert {k: v for k, v in new.items() if k != "latency_p99_us"} == {
        k: v for k, v in old.items() if k != "latency_p99_us"
    }
    assert rerun.count(first) == 1 and len(rerun) == 2  # the done one is reported, not run


def test_lockstep_cells_drop_cpu_placement_so_parallel_jobs_do_not_share_one_cpu(tmp_path: Path) -> None:
    config = load_campaign(write_campaign(tmp_path, session=str(PROFILES / "sessions" / "demo.yaml")))
    spec = config.cells()[0]
    emulated = cell_session(config, spec, tmp_path)
    assert emulated["host"]["loop_cpu"] is None and emulated["emulator"]["cpu"] is None
    lab = cell_session(config, spec, tmp_path, hardware=True)  # one cell at a time: the session's own placement
    assert lab["host"]["loop_cpu"] == -1


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"controllers": [{"label": "X", "name": "pid"}]}, "unknown controller 'pid'"),
        ({"metrics": ["miss_sd"]}, "unknown metric 'miss_sd'"),
        ({"acceptance": [{"metric": "lag_kf_cycles", "better": "KF", "than": "ESO+KF"}]}, "'KF' is not a controller"),
        ({"seeds": [1, 1]}, "seeds: a seed appears twice"),
        ({"session": "/nope/session.yaml"}, "no such file"),
    ],
)
def test_bad_campaign_is_one_line_and_exit_2(tmp_path: Path, changes: dict[str, Any], message: str) -> None:
    path = write_campaign(tmp_path, **changes)
    proc = subprocess.run(
        [*HIL, "campaign", str(path), "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr
    assert message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr


def shortened(name: str, tmp_path: Path, duration_s: float, seeds: list[int], **changes: Any) -> Path:
    data = yaml.safe_load((CAMPAIGNS / name).read_text())
    data.update(session=str((CAMPAIGNS / data["session"]).resolve()), duration_s=duration_s, seeds=seeds, **changes)
    for p in data["profiles"]:
        p["path"] = str((CAMPAIGNS / p["path"]).resolve())
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def on_the_slow_wire(name: str) -> dict[str, Any]:
    """Overrides that run campaign ``name`` on the slow-wire lab (profiles/emulator/slow-wire.yaml: every link at
    921 600 baud, docs/emulator.md "The default lab's line rate")."""
    data = yaml.safe_load((CAMPAIGNS / name).read_text())
    overrides = data.get("overrides") or {}
    return {"overrides": {**overrides, "emulator": {**overrides.get("emulator", {}),
                                                    "config": str(PROFILES / "emulator" / "slow-wire.yaml")}}}


@pytest.mark.parametrize(
    ("name", "duration_s", "changes"),
    [
        ("static-gyro-noise.yaml", 3.0, {}),
        ("filter-lag-15hz.yaml", 2.0, {}),
        # Table 1's ordering (high-gain ESO+KF below ESO+KF below ESO) on the default lab, the wire on at 6 Mbaud;
        # on the slow wire the high-gain loop loses its lead (test_on_the_slow_wire_the_high_gain_loop_loses_its_lead)
        ("swing-rate-error.yaml", 4.0, {}),
        # its rules as shipped: high-gain ESO+KF >= 40 % below ESO (the paper's Tables 2-3: 55 % / 61 %; the
        # default lab ~70 %), and below ESO+KF
        ("swing-miss-distance.yaml", 4.0, {}),
        (
            "imbalance-ukf-ff.yaml",
            9.0,
            {
                "controllers": [
                    {"label": "ESO+KF (feedback alone)", "name": "eso_kf"},
                    {"label": "ESO+KF + UKF feed-forward", "name": "eso_kf_ukf_ff"},
                ],
                "acceptance": [
                    {
                        "metric": "los_rate_lf_std_dps",
                        "better": "ESO+KF + UKF feed-forward",
                        "than": "ESO+KF (feedback alone)",
                        "by_pct": 25,
                    }
                ],
            },
        ),
    ],
)
@pytest.mark.slow
def test_shipped_campaign_acceptance_on_a_short_lockstep_run(
    tmp_path: Path, name: str, duration_s: float, changes: dict[str, Any]
) -> None:
    path = shortened(name, tmp_path, duration_s, seeds=[7], **changes)
    proc = subprocess.run(
        [*HIL, "campaign", str(path), "--out", str(tmp_path / "out"), "--jobs", "2", "--no-report"],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    result = json.loads((tmp_path / "out" / "campaign.json").read_text())
    failed = [r for r in result["acceptance"] if not r["passed"]]
    assert proc.returncode == 0 and not failed, (proc.stdout[-3000:], proc.stderr[-2000:], failed)
    assert "PASS" in proc.stdout


@pytest.mark.slow
def test_on_the_slow_wire_the_high_gain_loop_loses_its_lead(tmp_path: Path) -> None:
    """On the slow-wire lab (921 600 baud), Table 1's campaign keeps ESO+KF below ESO but the high-gain ESO+KF's rate
    error rises above ESO+KF's: its loop has no margin for the wire's 0.63 ms (docs/emulator.md, "What the wire costs
    the controllers"). The campaign says so: FAIL, exit 1, the rule named."""
    path = shortened("swing-rate-error.yaml", tmp_path, 4.0, seeds=[7], **on_the_slow_wire("swing-rate-error.yaml"))
    proc = subprocess.run([*HIL, "campaign", str(path), "--out", str(tmp_path / "out"), "--jobs", "2",
                           "--no-report"], capture_output=True, text=True, timeout=600, check=False)
    result = json.loads((tmp_path / "out" / "campaign.json").read_text())
    rules = {r["rule"]: r["passed"] for r in result["acceptance"]}
    assert proc.returncode == 1 and "FAIL" in proc.stdout, proc.stdout[-2000:]
    assert rules == {"ESO+KF lowers rate_err_el_std_dps vs ESO": True,
                     "high-gain ESO+KF lowers rate_err_el_std_dps vs ESO+KF": False}
    cells = {c["controller"]: c["metrics"]["rate_err_el_std_dps"] for c in result["cells"]}
    assert cells["high-gain ESO+KF"] > 2 * cells["ESO+KF"], cells
