"""The example driver package (example_pkg/: the pure-software ``replay`` table) installed for real with pip,
selected by name in a session file and run on the ``sim`` clock: the poses it produced are the log's hexapod group."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hil.boards import installed_hexapod_drivers, load_hexapod_driver
from hil.config import PROFILES
from hil.log.reader import read_log

ROLL_DEG, ROLL_HZ, X_MM, X_HZ = 1.0, 3.0, 20.0, 2.0


def replay_session(tmp_path: Path) -> Path:
    path = tmp_path / "replay.yaml"
    path.write_text(
        "name: replay-check\nduration_s: 2.0\nseed: 5\n"
        f"controller: {PROFILES / 'controllers' / 'eso.yaml'}\n"
        f"hexapod_limits: {PROFILES / 'hexapod' / 'default.yaml'}\n"
        f"emulator: {{config: {PROFILES / 'emulator' / 'default.yaml'}}}\n"
        "profile:\n  segments:\n"
        f"    - {{axis: roll, amplitude: {ROLL_DEG}, frequency_hz: {ROLL_HZ}, duration_s: 60.0}}\n"
        f"    - {{axis: x, amplitude: {X_MM}, frequency_hz: {X_HZ}, duration_s: 60.0}}\n"
        "hexapod: {driver: replay, rate_hz: 200, stop_ramp_s: 0.2, serial_number: bench-7}\n")
    return path


def hil_run(session: Path, out: Path, pythonpath: Path | None) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    return subprocess.run([sys.executable, "-m", "hil", "run", str(session), "--loopback", "--clock", "sim",
                           "--out", str(out)], capture_output=True, text=True, env=env, cwd=session.parent,
                          check=False, timeout=300)


def test_the_installed_package_registers_its_driver(replay_site: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert "replay" not in installed_hexapod_drivers()
    monkeypatch.syspath_prepend(str(replay_site))
    ep = installed_hexapod_drivers()["replay"]
    assert (ep.value, ep.dist.name, ep.dist.version) == ("hil_replay_hexapod:ReplayHexapod", "hil-replay-hexapod",
                                                         "0.1.0")
    cls = load_hexapod_driver("replay")
    assert cls.uses_link is False and cls.Options.model_fields["rate_hz"].default == 100.0


def test_a_session_runs_on_the_installed_replay_driver_and_logs_its_poses(tmp_path: Path, replay_site: Path) -> None:
    session = replay_session(tmp_path)
    res = hil_run(session, tmp_path / "runs", replay_site)
    assert res.returncode == 0, res.stdout + res.stderr
    (log_path,) = (tmp_path / "runs").glob("replay-check-*.h5")
    log = read_log(log_path)
    assert log.attrs["ident"]["hexapod"] == {"driver": "replay", "model": "replay", "serial_number": "bench-7",
                                             "rate_hz": 200.0}
    events = log.groups["events"]
    details = [(k.decode() if isinstance(k, bytes) else str(k), json.loads(d)) for k, d in
               zip(events["kind"], events["detail"], strict=True)]
    stopping = next(i for i, (k, d) in enumerate(details) if k == "state" and d["state"] == "swing stopping")
    safe = next(d for k, d in details if k == "state" and d["state"] == "safe")
    assert safe == {"state": "safe", "driver": "disabled", "hexapod": "stopped", "stream": "idle"}
    summary = next(d for k, d in details if k == "summary")
    assert summary["faults"] == [] and set(summary["link_errors"]) == {"servo", "driver", "image"}

    h = log.groups["hexapod"]
    t = np.asarray(h["t_profile_s"], dtype=float)
    t_host = np.asarray(h["t_host_ns"])
    assert np.all(np.diff(t) > 0) and np.median(np.diff(t)) >= 0.004  # its own 200 Hz timer, never faster
    swinging = t_host < np.asarray(events["t_host_ns"])[stopping]  # reported before the session stopped it
    assert swinging.sum() >= 5
    roll, x = np.asarray(h["roll_deg"], dtype=float), np.asarray(h["x_mm"], dtype=float)
    np.testing.assert_allclose(roll[swinging], ROLL_DEG * np.sin(2 * math.pi * ROLL_HZ * t[swinging]), atol=1e-6)
    np.testing.assert_allclose(x[swinging], X_MM * np.sin(2 * math.pi * X_HZ * t[swinging]), atol=2e-5)
    assert np.max(np.abs(roll[swinging])) > 0.1 and np.max(np.abs(x[swinging])) > 2.0  # it really swung
    for still in ("y_mm", "z_mm", "pitch_deg", "yaw_deg"):
        assert not np.any(np.asarray(h[still])), still
    # after the stop it ramps home over stop_ramp_s: never beyond the profile, and the last report is home
    after = ~swinging
    assert after.sum() >= 2
    assert np.all(np.abs(roll[after]) <= np.abs(ROLL_DEG * np.sin(2 * math.pi * ROLL_HZ * t[after])) + 1e-6)
    assert t[-1] - t[swinging][-1] >= 0.2 - 0.01
    assert [float(h[c][-1]) for c in ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")] == [0.0] * 6


def test_without_the_package_on_the_path_the_same_session_is_refused(tmp_path: Path) -> None:
    session = replay_session(tmp_path)
    res = hil_run(session, tmp_path / "runs", None)
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        f"error: {session}: hexapod.driver: 'replay' is not an installed hexapod driver (installed: protocol)"]
