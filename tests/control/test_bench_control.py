"""The control benchmark runs and times every case (no timing assertions: targets live in docs/performance.md)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

from hil.control.registry import REGISTRY

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_control.py"


def test_control_benchmark_times_every_estimator_and_controller(tmp_path):
    spec = importlib.util.spec_from_file_location("bench_control", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = tmp_path / "control.json"
    results = module.main(["--steps", "1000", "--json", str(out)])
    cases = results["cases"]
    for name in REGISTRY:
        assert cases[f"RateController {name!r} (whole 1 kHz step)"]["median_us"] > 0
    assert cases["filterpy KalmanFilter predict+update (1 state)"]["median_us"] > 0
    assert cases["ImbalanceUKF.step (filterpy UKF, 7 states)"]["p99_us"] >= cases[
        "ImbalanceUKF.step (filterpy UKF, 7 states)"]["median_us"]
    assert set(results["seed002_run_us"]) == {
        "LesoFilter (tau 0.5, omega_o 0.1)", "plain-float KF (R 0.1, Q 0.001)", "filterpy KalmanFilter"}
    assert json.loads(out.read_text())["steps"] == 1000
    assert set(results["drive_step"]) == set(REGISTRY)
    for r in results["drive_step"].values():
        assert r["controllers_us"] > 0 and r["drive_step_us"] > 0
        assert r["own_us"] == r["drive_step_us"] - r["controllers_us"]
