"""The ``sim`` clock: the same Session, boards and plant in one process, logs identical to lockstep's."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
import yaml

from hil.config import PROFILES
from hil.log.reader import read_log
from hil.session import run_sim_session
from tests.factories import run_session, session_config
from tests.session.helpers import assert_same_channels

CASES = [(3, "eso"), (11, "eso_kf"), (5, "eso_kf_ukf_ff")]


def sim_run(config, out: Path):  # type: ignore[no-untyped-def]
    return asyncio.run(run_sim_session(config, out))


@pytest.mark.parametrize(("seed", "controller"), CASES)
def test_sim_logs_equal_lockstep_logs(tmp_path: Path, seed: int, controller: str) -> None:
    config = session_config(duration_s=1.5, seed=seed,
                            controller=str(PROFILES / "controllers" / f"{controller}.yaml")
                            if (PROFILES / "controllers" / f"{controller}.yaml").exists()
                            else {"name": controller, "params": {}})
    (tmp_path / "lockstep").mkdir()
    lock = run_session(config, tmp_path / "lockstep")
    sim, emulator = sim_run(config, tmp_path / "sim")
    assert lock.result.status == sim.status == "completed", (lock.result.message, sim.message)
    assert emulator["clock"] == "sim" and emulator["sim_ticks"] >= 1500
    compared = assert_same_channels(lock.result.log_path, sim.log_path, ticks=1500)
    assert compared > 1500 * 15  # every loop channel, and the other groups
    loop = read_log(sim.log_path).groups["loop"]
    assert np.std(loop["drive_el_counts"][:1500]) > 50  # a real closed loop, not zeros on both sides
    assert read_log(sim.log_path).attrs["clock"] == "sim"


def test_sim_is_deterministic_and_seeds_differ(tmp_path: Path) -> None:
    a, _ = sim_run(session_config(duration_s=1.0, seed=2), tmp_path / "a")
    b, _ = sim_run(session_config(duration_s=1.0, seed=2), tmp_path / "b")
    c, _ = sim_run(session_config(duration_s=1.0, seed=3), tmp_path / "c")
    assert assert_same_channels(a.log_path, b.log_path, ticks=1000) > 0
    ga, gc = read_log(a.log_path).groups["loop"], read_log(c.log_path).groups["loop"]
    assert not np.array_equal(ga["gyro_y_dps"][:1000], gc["gyro_y_dps"][:1000])


def test_two_sessions_of_one_name_in_one_second_keep_both_logs(tmp_path: Path) -> None:
    """A sim session takes less than a second: the second of two of one name gets its own file, never the first's
    (a log name holds the second it started in; an ident's levelling passes run that fast)."""
    config = session_config(duration_s=0.3, seed=2)
    now = datetime.now(UTC)
    taken = [tmp_path / f"{config.name}-{now + timedelta(seconds=k):%Y%m%d-%H%M%S}.h5" for k in range(-1, 30)]
    for path in taken:  # every name the session could choose in the next 30 s already exists
        path.write_bytes(b"another log")
    first, _ = sim_run(config, tmp_path)
    second, _ = sim_run(config, tmp_path)
    assert first.status == second.status == "completed"
    assert first.log_path != second.log_path
    # the first takes "-2" of its second; the second "-3" of the same second, or "-2" of the next
    assert first.log_path.stem.endswith("-2") and second.log_path.stem[-2:] in ("-2", "-3")
    assert all(path.read_bytes() == b"another log" for path in taken)
    for result in (first, second):
        assert read_log(result.log_path).groups["loop"]["tick"].size >= 300


def _hil(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil", *args], capture_output=True, text=True, cwd=cwd, check=False)


def test_cli_sim_needs_loopback_and_refuses_link_faults(tmp_path: Path) -> None:
    session = PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml"
    res = _hil("run", str(session), "--clock", "sim", cwd=tmp_path)
    assert res.returncode == 2 and "--clock sim" in res.stderr and "--loopback" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1

    faulty = tmp_path / "emulator.yaml"
    faulty.write_text(yaml.safe_dump({"plant": str(PROFILES / "plant" / "default.yaml"),
                                      "links": {"servo": {"bit_error_rate": 1e-5}}}))
    data = yaml.safe_load(session.read_text())
    data.update(controller=str(PROFILES / "controllers" / "eso.yaml"), profile=str(PROFILES / "swing" / "static.yaml"),
                hexapod_limits=str(PROFILES / "hexapod" / "default.yaml"),
                emulator={"config": str(faulty), "clock": "sim"}, duration_s=0.5)
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump(data))
    res = _hil("run", str(path), "--loopback", "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert "links.servo" in res.stderr and "--clock lockstep" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").glob("*.h5"))


def test_cli_sim_run_completes_with_a_summary(tmp_path: Path) -> None:
    session = PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml"
    data = yaml.safe_load(session.read_text())
    for key in ("controller", "profile", "hexapod_limits"):
        data[key] = str((session.parent / data[key]).resolve())
    data["emulator"] = {"config": str((session.parent / data["emulator"]["config"]).resolve())}
    data["duration_s"] = 1.0
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump(data))
    res = _hil("run", str(path), "--loopback", "--clock", "sim", "--json", "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    import json

    summary = json.loads(res.stdout)
    assert summary["status"] == "completed" and summary["cycles"] >= 1000 and summary["missed_cycles"] == 0
