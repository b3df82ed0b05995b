"""The sim clock's truth file: the plant's true LOS rate per loop row, the ``los_rate_true_*`` metrics it gives,
and the refusal of those metrics on any other clock."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import numpy as np

from hil.campaign.metrics import compute_metrics
from hil.config import PROFILES
from hil.log.reader import read_log
from hil.log.truth import read_truth, truth_path
from hil.session import run_sim_session
from tests.factories import run_session, session_config

TRUE = ("los_rate_true_rms_dps", "los_rate_true_lf_std_dps")


def sim_run(config, out: Path):  # type: ignore[no-untyped-def]
    return asyncio.run(run_sim_session(config, out))[0]


def test_a_sim_session_records_the_true_los_rate_of_each_loop_row(tmp_path: Path) -> None:
    config = session_config(duration_s=2.0, seed=4)
    sim = sim_run(config, tmp_path / "sim")
    assert sim.status == "completed", sim.message
    loop = read_log(sim.log_path).groups["loop"]
    truth = read_truth(sim.log_path, loop["tick"])
    assert truth is not None and truth_path(sim.log_path).is_file()
    true_y, true_z = truth
    assert true_y.size == loop["tick"].size >= 2000
    # the gyro is the true rate filtered, delayed and noisy: it follows the truth a tick or two behind, never ahead
    gyro = loop["gyro_y_dps"].astype(float)
    misfit = {k: float(np.std(gyro[k:] - true_y[:true_y.size - k])) for k in range(4)}
    assert min(misfit, key=misfit.__getitem__) in (1, 2), misfit
    assert np.corrcoef(gyro, true_y)[0, 1] > 0.95 and np.std(true_y) > 0.05  # the swing's residual (0.2 deg/s)
    assert np.std(true_z) > 0
    m = compute_metrics(sim.log_path)
    assert set(TRUE) <= m.keys()
    # on the swing the gyro's noise is small beside the error: the true and the gyro-read LOS rate agree closely
    assert abs(m["los_rate_true_rms_dps"] / m["los_rate_rms_dps"] - 1) < 0.1, m

    # lockstep: the same log, no truth file, no true-rate metrics
    (tmp_path / "lockstep").mkdir()
    lock = run_session(config, tmp_path / "lockstep").result
    assert lock.status == "completed" and not truth_path(lock.log_path).exists()
    assert not set(TRUE) & compute_metrics(lock.log_path).keys()


def test_under_imbalance_vibration_the_oracle_bounds_the_true_los_rate_not_the_gyro_reading(tmp_path: Path) -> None:
    """imbalance-ukf-ff's scenario (0.5 g / 2.5 Hz, 10 s, the first 5 s left out): on the true LOS rate the oracle
    is far below the feed-forward, which is below feedback alone; on the gyro's reading the oracle sits at the
    gyro's own noise floor, which the feed-forward also reaches."""
    profile = str(PROFILES / "swing" / "vibration-0.5g-2.5hz.yaml")
    got = {}
    for name in ("eso_kf", "eso_kf_ukf_ff", "oracle"):
        config = session_config(duration_s=10.0, seed=1, profile=profile, tracking={"enabled": False},
                                controller={"name": name, "params": {}})
        res = sim_run(config, tmp_path / name)
        assert res.status == "completed", res.message
        got[name] = compute_metrics(res.log_path, settle_s=5.0)
    true = {k: v["los_rate_true_lf_std_dps"] for k, v in got.items()}
    gyro = {k: v["los_rate_lf_std_dps"] for k, v in got.items()}
    # measured (seed 1): 0.0224, 0.0100, 0.0025 deg/s true; 0.0231, 0.0105, 0.0115 read by the gyro
    assert true["oracle"] < 0.4 * true["eso_kf_ukf_ff"] < 0.4 * 0.6 * true["eso_kf"], true
    assert gyro["oracle"] > 3 * true["oracle"] and gyro["oracle"] > 0.8 * gyro["eso_kf_ukf_ff"], gyro


def test_a_campaign_with_a_true_rate_metric_is_refused_on_the_lockstep_clock(tmp_path: Path) -> None:
    campaign = PROFILES / "campaigns" / "tune-eso-kf-ukf-ff-imbalance.yaml"
    out = subprocess.run([sys.executable, "-m", "hil", "campaign", str(campaign), "--clock", "lockstep", "--out",
                          str(tmp_path / "c")], capture_output=True, text=True, check=False)
    assert out.returncode == 2, out.stderr
    assert out.stderr.strip().splitlines() == [
        f"error: {campaign}: metrics: los_rate_true_lf_std_dps is read from the plant's truth, which only the sim "
        "clock records (not lockstep); run with --clock sim"]
    assert not (tmp_path / "c").exists()
