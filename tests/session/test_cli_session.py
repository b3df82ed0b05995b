"""`hil run` / `hil recover` / `hil report` as a user runs them: signals, SIGKILL, bad input."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from hil.config import PROFILES
from hil.log import read_log
from tests.factories import BASE_SESSION, run_session, session_config
from tests.session.helpers import wait_cycles

HIL = [sys.executable, "-m", "hil"]


def hil(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*HIL, *args], capture_output=True, text=True, timeout=timeout, check=False)


def wait_for_log(out: Path, timeout_s: float = 30) -> Path:
    for _ in range(int(timeout_s / 0.05)):
        logs = list(out.glob("*.h5"))
        if logs:
            return logs[0]
        time.sleep(0.05)
    raise TimeoutError("no log appeared")


def test_sigterm_disables_the_driver_first_and_closes_the_log(tmp_path: Path) -> None:
    async def terminate(emu, session) -> None:  # type: ignore[no-untyped-def]
        await wait_cycles(session, 1500)
        os.kill(os.getpid(), signal.SIGTERM)  # the session's handler takes it (pytest's is restored after)

    run = run_session(session_config(duration_s=10.0), tmp_path, during=terminate)
    assert run.result.status == "interrupted" and run.result.exit_code == 143
    after = [r for r in run.records if r["tick"] >= 0]
    kinds = [r["kind"] for r in after]
    first_disable = kinds.index("drive_disable")
    assert "STOPPING" in [r["detail"].get("state") for r in after[first_disable:]]  # the swing stops after
    assert all(r["detail"].get("state") != "STOPPING" for r in after[:first_disable])
    with h5py.File(run.result.log_path, "r") as f:  # closed cleanly
        assert f["loop/tick"].shape[0] >= 1500
    events = [str(k) for k in read_log(run.result.log_path).groups["events"]["kind"]]
    assert "signal" in events


def wait_for_rows(log: Path, rows: int, timeout_s: float = 60.0) -> None:
    """Wait until the live SWMR log holds at least `rows` loop rows."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        with contextlib.suppress(OSError, KeyError), h5py.File(log, "r", swmr=True) as f:
            if f["loop/tick"].shape[0] >= rows:
                return
        time.sleep(0.1)
    raise TimeoutError(f"{log}: fewer than {rows} loop rows after {timeout_s} s")


def test_sigint_from_the_cli_exits_130(tmp_path: Path) -> None:
    proc = subprocess.Popen([*HIL, "run", str(BASE_SESSION), "--loopback", "--out", str(tmp_path), "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log = wait_for_log(tmp_path)
    wait_for_rows(log, 200)  # the loop is running (a loaded machine may take seconds to get there)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    summary = json.loads(out)
    assert summary["status"] == "interrupted" and summary["cycles"] > 100
    with h5py.File(log, "r"):
        pass


@pytest.mark.slow
def test_sigkill_mid_session_then_recover(tmp_path: Path) -> None:
    # the bench, its log writer and the emulator all die at once, as in a power cut
    long_run = tmp_path / "long.yaml"  # lockstep (no wall-clock watchdog), long enough to be killed mid-run
    long_run.write_text(BASE_SESSION.read_text().replace("duration_s: 10.0", "duration_s: 600.0").replace(
        "../", str(BASE_SESSION.parent.parent) + "/"))
    proc = subprocess.Popen([*HIL, "run", str(long_run), "--loopback", "--out", str(tmp_path)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    log = wait_for_log(tmp_path)
    time.sleep(2.0)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(10)
    t_kill = time.monotonic_ns()
    with h5py.File(log, "r", swmr=True) as f:
        n = f["loop/tick"].shape[0]
    data = read_log(log)
    loop = data.groups["loop"]
    n_read = loop["tick"].size
    assert n_read >= 1000, n_read  # ~2 s of a run faster than real time, less what the last flush missed
    assert np.all(np.diff(loop["tick"].astype(np.int64)) == 1)
    # what the kill took is the rows still in the bench's buffers: one flush interval (100 ms) on a quiet machine,
    # more when a loaded host ran the flusher late (docs/log-format.md has the figures, tests/log/test_log.py
    # checks that every flushed row survives); seconds would mean the flusher had stopped
    lost_ms = (t_kill - int(loop["t_host_ns"][-1])) / 1e6
    assert lost_ms < 2000, lost_ms
    rec = hil("recover", str(log))
    assert rec.returncode == 0, rec.stderr
    with h5py.File(log, "r") as f:  # opens normally now
        assert f["loop/tick"].shape[0] == n_read <= n
    report = hil("report", str(log), "--json")
    assert report.returncode == 0, report.stderr
    summary = json.loads(report.stdout)
    assert summary["cycles"] == n_read and summary["complete"] is False
    text = hil("report", str(log))
    assert text.returncode == 0 and "incomplete: the bench stopped without a summary" in " ".join(text.stdout.split())


@pytest.mark.parametrize(("edit", "needle"), [
    ({"controller": {"name": "eso_turbo"}}, "controller"),
    ({"profile": {"segments": [{"axis": "pitch", "amplitude": 25.0, "frequency_hz": 1.0, "duration_s": 5.0}]}},
     "pitch position reaches 25"),
    ({"duration_s": -1}, "duration_s"),
    ({"tracking": {"kp_per_s": "fast"}}, "tracking.kp_per_s"),
])
def test_bad_session_files_are_one_line_and_exit_2(tmp_path: Path, edit: dict, needle: str) -> None:  # type: ignore[type-arg]
    import yaml

    data = yaml.safe_load(BASE_SESSION.read_text())
    for key in ("controller", "profile", "hexapod_limits"):
        data[key] = str((PROFILES / "sessions" / data[key]).resolve())
    data.update(edit)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    res = hil("run", str(bad), "--loopback", "--out", str(tmp_path))
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in res.stderr, res.stderr
    assert not list(tmp_path.glob("*.h5"))  # nothing started


def test_missing_ports_and_missing_file_are_exit_2(tmp_path: Path) -> None:
    res = hil("run", str(BASE_SESSION), "--out", str(tmp_path))
    assert res.returncode == 2 and "ports" in res.stderr and "--loopback" in res.stderr
    res = hil("run", str(tmp_path / "nope.yaml"))
    assert res.returncode == 2 and "nope.yaml: no such file" in res.stderr
    res = hil("report", str(tmp_path / "nope.h5"))
    assert res.returncode == 2 and "no such file" in res.stderr


@pytest.mark.slow
def test_a_lockstep_session_needs_no_wall_clock_margin(tmp_path: Path) -> None:
    """Bounds that hold on a loaded machine (the speed itself is in benchmarks/): every tick of a lockstep
    run is answered and none is late in simulated time."""
    run = run_session(session_config(duration_s=4.0), tmp_path)
    assert run.result.status == "completed"
    assert run.emulator["lockstep_timeouts"] <= 1  # at most the sample after the last one the bench took
    assert run.emulator["servo"]["missing_commands"] <= 1
    assert run.result.stats.cycles >= 3990


def test_the_emulator_stall_grace_is_refused_with_real_ports(tmp_path: Path) -> None:
    import yaml

    data = yaml.safe_load(BASE_SESSION.read_text())
    for key in ("controller", "profile", "hexapod_limits"):
        data[key] = str((PROFILES / "sessions" / data[key]).resolve())
    data["safety"] = {**data["safety"], "emulator_stall_grace_ms": 500}
    data["ports"] = {name: {"port": str(tmp_path / f"tty-{name}")} for name in ("servo", "driver", "image", "hexapod")}
    lab = tmp_path / "lab.yaml"
    lab.write_text(yaml.safe_dump(data))
    res = hil("run", str(lab), "--out", str(tmp_path))
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "safety.emulator_stall_grace_ms" in lines[0] and "--loopback" in lines[0], res.stderr
    assert not list(tmp_path.glob("*.h5"))
