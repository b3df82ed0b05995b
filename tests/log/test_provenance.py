"""Provenance in the session log, the controllers' effective parameters, and the summary's board latency."""

from __future__ import annotations

import hashlib
import json
import math
import platform
import shutil
import subprocess
from pathlib import Path

import h5py
import numpy as np
import numpy.testing as npt
import pytest
import scipy

import hil
from hil.analysis import NO_BOARD_LATENCY, board_latency, json_safe, summarize_log
from hil.config import PROFILES, ControllerConfig
from hil.control.registry import REGISTRY, ControllerConfigError, controller_params, effective_params
from hil.log import SessionLog, read_attrs, read_log, read_provenance
from hil.session import collect_provenance
from hil.session._provenance import git_commit
from tests.factories import run_session, session_config
from tests.log.conftest import SIM_CONTROLLER

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_PLANT = (PROFILES / "plant" / "default.yaml").resolve()
DEFAULT_PLANT_ENTRY = {"path": str(DEFAULT_PLANT), "sha256": hashlib.sha256(DEFAULT_PLANT.read_bytes()).hexdigest()}
HAS_GIT = shutil.which("git") is not None


def _git(cwd: Path, *args: str) -> str:
    cmd = ["git", "-c", "user.name=bench", "-c", "user.email=bench@example.org", *args]
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, check=True).stdout.strip()


# --- effective_params --------------------------------------------------------------------------


def test_effective_params_resolve_each_controllers_defaults() -> None:
    eso = effective_params({"name": "eso", "params": {}})
    assert eso == {"kp_counts_per_dps": 8000.0, "ki_counts_per_deg": 0.0, "u_max_counts": 32767, "dt_s": 0.001,
                   "omega_o_rad_s": 300.0, "b0_dps2_per_count": 0.023}
    pi = effective_params("pi_lpf")
    assert pi["ki_counts_per_deg"] == 80000.0 and pi["cutoff_hz"] == 150.0 and pi["order"] == 1
    kf = effective_params({"name": "eso_kf"})
    assert kf["omega_o_rad_s"] == 300.0 and kf["q_dps2"] == 5e-4 and kf["s_dps2"] == 5e-4
    assert kf["r_dps2"] == pytest.approx(0.034**2) and kf["steady_state"] is True
    high = effective_params({"name": "eso_kf_high_gain", "params": {}})
    assert high["omega_o_rad_s"] == 1000.0  # what the name itself sets, not eso_kf's 300
    assert set(high) == set(kf) and {k: v for k, v in high.items() if k != "omega_o_rad_s"} == {
        k: v for k, v in kf.items() if k != "omega_o_rad_s"}
    ukf = effective_params({"name": "eso_kf_ukf_ff", "params": {}})
    assert ukf["mass_kg"] == 10.0 and ukf["ukf_dt_s"] == 0.01 and ukf["ff_limit_counts"] == 8000.0
    assert ukf["counts_per_n_m"] == 49830.0 and ukf["omega_o_rad_s"] == 300.0
    nonlinear = effective_params("eso_nonlinear")
    assert nonlinear["alpha"] == 0.5 and nonlinear["delta_dps"] == 0.05
    for name, kind in REGISTRY.items():  # every parameter of every controller, in the model's order
        assert list(effective_params(name)) == list(kind.params.model_fields), name


def test_effective_params_keep_overrides_and_rebuild_the_same_controller() -> None:
    given = {"kp_counts_per_dps": 5000.0, "mass_kg": 4.5, "ukf_dt_s": 0.02}
    params = effective_params(ControllerConfig(name="eso_kf_ukf_ff", params=given))
    assert params["kp_counts_per_dps"] == 5000.0 and params["mass_kg"] == 4.5 and params["ukf_dt_s"] == 0.02
    assert params["ki_counts_per_deg"] == 0.0 and params["inertia_kg_m2"] == 0.05  # the rest: defaults
    # plain JSON types, and feeding them back gives the very parameters the session built its controller from
    assert json.loads(json.dumps(params, allow_nan=False)) == params
    assert all(type(v) in (int, float, bool, str) for v in params.values())
    assert controller_params("eso_kf_ukf_ff", params) == controller_params("eso_kf_ukf_ff", given)
    pi = effective_params({"name": "pi_lpf", "params": {"order": 2, "cutoff_hz": 80}})
    assert pi["order"] == 2 and pi["cutoff_hz"] == 80.0 and type(pi["cutoff_hz"]) is float
    with pytest.raises(ControllerConfigError, match="unknown controller 'nope'"):
        effective_params({"name": "nope", "params": {}})
    with pytest.raises(ControllerConfigError, match="unknown parameter 'gain'"):
        effective_params({"name": "eso", "params": {"gain": 1}})


# --- collect_provenance --------------------------------------------------------------------------


def test_collect_provenance_plant_follows_the_emulator_file(tmp_path: Path) -> None:
    config = session_config(controller={"name": "eso", "params": {"omega_o_rad_s": 250.0}})
    prov = collect_provenance(config, emulated=True)
    assert prov["plant"] == DEFAULT_PLANT_ENTRY
    assert prov["controller"] == {"name": "eso", "params": {**effective_params("eso"), "omega_o_rad_s": 250.0}}
    assert collect_provenance(config, emulated=False)["plant"] is None  # the lab's boards: no plant file
    assert config.ports is None and collect_provenance(config)["plant"] == prov["plant"]  # no ports: the emulator

    # an emulator file naming its own plant, relative to itself
    (tmp_path / "plants").mkdir()
    plant = tmp_path / "plants" / "stiff.yaml"
    plant.write_bytes(DEFAULT_PLANT.read_bytes() + b"\n# a copy with one more line\n")
    emulator = tmp_path / "emulator.yaml"
    emulator.write_text("plant: plants/stiff.yaml\nseed: 3\n")
    other = collect_provenance(session_config(emulator={"config": str(emulator)}), emulated=True)
    assert other["plant"] == {"path": str(plant.resolve()), "sha256": hashlib.sha256(plant.read_bytes()).hexdigest()}
    assert other["plant"]["sha256"] != prov["plant"]["sha256"]
    emulator.write_text("plant: plants/absent.yaml\n")  # unreadable: recorded as unknown, never an error
    assert collect_provenance(session_config(emulator={"config": str(emulator)}), emulated=True)["plant"] is None


def test_collect_provenance_versions() -> None:
    prov = collect_provenance(session_config(), emulated=True)
    assert prov["hil_version"] == hil.__version__ and prov["python"] == platform.python_version()
    assert prov["numpy"] == np.__version__ and prov["h5py"] == h5py.__version__
    assert prov["scipy"] == scipy.__version__ and prov["hdf5"] == h5py.version.hdf5_version
    assert isinstance(prov["numba"], str) and prov["numba"][0].isdigit()
    assert json.loads(json.dumps(prov, allow_nan=False)) == prov


@pytest.mark.skipif(not HAS_GIT, reason="git is not installed")
def test_git_commit_clean_dirty_and_outside_a_checkout(tmp_path: Path) -> None:
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    assert git_commit(repo) is None  # no commit yet
    (repo / "a.txt").write_text("one\n")
    _git(repo, "add", "a.txt")
    _git(repo, "commit", "-q", "-m", "first")
    head = _git(repo, "rev-parse", "HEAD")
    assert len(head) == 40 and git_commit(repo) == head
    (repo / "new.txt").write_text("untracked\n")
    assert git_commit(repo) == head  # untracked files do not count
    (repo / "a.txt").write_text("two\n")
    assert git_commit(repo) == head + "-dirty"
    assert not (repo / ".git" / "index.lock").exists()
    assert git_commit(tmp_path) is None  # not a checkout
    assert git_commit(repo, timeout_s=1e-9) is None  # too slow: unknown, not an error


# --- in a real session log ---------------------------------------------------------------------


def test_provenance_is_recorded_in_a_session_log(sim_log: Path) -> None:
    prov = read_provenance(sim_log)
    assert prov == read_log(sim_log).attrs["provenance"] == summarize_log(sim_log)["provenance"]
    assert prov["hil_version"] == hil.__version__ and prov["numpy"] == np.__version__
    assert prov["plant"] == DEFAULT_PLANT_ENTRY
    assert prov["controller"]["name"] == "eso_kf_high_gain"
    params = prov["controller"]["params"]
    assert params == effective_params(SIM_CONTROLLER)
    assert params["kp_counts_per_dps"] == 6000.0 and params["omega_o_rad_s"] == 1000.0 and params["q_dps2"] == 5e-4
    if HAS_GIT and (ROOT / ".git").exists():
        assert prov["git_commit"].removesuffix("-dirty") == _git(ROOT, "rev-parse", "HEAD")
    attrs = read_attrs(sim_log)
    assert attrs["clock"] == "sim" and attrs["loopback"] is True and attrs["controller"] == "eso_kf_high_gain"
    assert "provenance" in attrs["json_attrs"]
    with h5py.File(sim_log, "r") as f:  # JSON text in the file, as MATLAB's jsondecode wants it
        assert json.loads(f.attrs["provenance"]) == prov


def test_read_provenance_of_a_log_written_before_it_existed(tmp_path: Path) -> None:
    p = tmp_path / "old.h5"
    with SessionLog(p, attrs={"config": {"name": "old"}, "ident": {}, "seed": 1}) as log:
        log.append("loop", (0,) * 22)
    assert read_provenance(p) == {}
    assert summarize_log(p)["provenance"] == {}


# --- board latency in the summary ----------------------------------------------------------------


def test_board_latency_is_not_applicable_in_sim_and_gives_null_in_json(sim_log: Path) -> None:
    timing = read_log(sim_log).groups["timing"]["board_latency_us"]
    # what the emulated board sends when it waits for the bench: the modelled delay (docs/emulator.md, "The wire")
    assert timing.size > 500 and set(np.unique(timing[~np.isnan(timing)])) == {134}  # at 6 Mbaud
    s = summarize_log(sim_log)
    assert s["board_latency_us"] == {"p50": None, "p99": None, "na_reason": NO_BOARD_LATENCY["sim"]}
    assert s["latency_us"]["p50"] > 0  # the bench's own latency is measured on every clock
    text = json.dumps(json_safe(s), allow_nan=False)
    assert '"board_latency_us": {"p50": null, "p99": null, "na_reason": "sim: ' in text


def test_board_latency_is_not_applicable_in_lockstep(tmp_path: Path) -> None:
    run = run_session(session_config(duration_s=0.4, seed=2), tmp_path)
    assert run.result.status == "completed", run.result.message
    assert read_attrs(run.result.log_path)["clock"] == "lockstep"  # the session names its clock itself
    board = summarize_log(run.result.log_path)["board_latency_us"]
    assert board == {"p50": None, "p99": None, "na_reason": NO_BOARD_LATENCY["lockstep"]}
    assert "waits for each command" in board["na_reason"]


def test_board_latency_figures_on_the_realtime_and_hardware_clocks() -> None:
    measured = np.array([300.0, 310.0, 320.0, np.nan, 900.0], dtype=np.float32)
    for clock in ("realtime", "hardware", None):
        b = board_latency(measured, clock)
        assert b["p50"] == pytest.approx(315.0) and b["p99"] == pytest.approx(882.6, rel=1e-6)
        assert b["missing"] == 1 and "na_reason" not in b
    assert board_latency(measured, "lockstep")["p50"] is None
    none = board_latency(np.zeros(0, dtype=np.float32), "hardware")
    assert none["p50"] is None and "no loop timing" in none["na_reason"]
    lost = board_latency(np.full(30, np.nan, dtype=np.float32), "realtime")
    assert lost["p99"] is None and "no command" in lost["na_reason"]
    zeros = board_latency(np.zeros(40, dtype=np.float32))  # an older lockstep log, without the clock attribute
    assert zeros["p50"] is None and "0 us on every tick" in zeros["na_reason"]


def test_json_safe_turns_nan_into_null() -> None:
    summary = {"a": math.nan, "b": [np.float32(1.5), math.inf], "c": {"d": np.int64(3), "e": "x", "f": None}}
    text = json.dumps(json_safe(summary), allow_nan=False)
    assert text == '{"a": null, "b": [1.5, null], "c": {"d": 3, "e": "x", "f": null}}'
    npt.assert_equal(summary["a"], math.nan)  # the summary itself is left as it was
