"""`hil ident` as a user runs it: a swept sine on the emulator's closed rate loop, over ptys, in lockstep."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from hil.config import PROFILES
from hil.control.registry import K_M_DEFAULT

SESSION = PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml"


def test_ident_recovers_the_emulators_k_m_within_5_percent(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "hil", "ident", str(SESSION), "--loopback", "--out", str(tmp_path),
                           "--sweep-s", "6", "--f-stop-hz", "250"], capture_output=True, text=True, timeout=300,
                          check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads((tmp_path / "ident-el.json").read_text())
    # the emulated plant's k_m is K_t V/count / (J R) = 0.0230 deg/s^2 per count (profiles/plant/default.yaml)
    assert abs(report["k_m_dps2_per_count"] - K_M_DEFAULT) / K_M_DEFAULT < 0.05, report
    assert 150 < report["gyro_bandwidth_hz"] < 250 and 0.3 < report["delay_ms"] < 0.8, report
    assert (tmp_path / "bode-el.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "k_m" in proc.stdout


def test_ident_refuses_an_elevation_sweep_that_would_reach_the_gimbals_singularity(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "hil", "ident", str(SESSION), "--loopback", "--out", str(tmp_path),
                           "--offset-dps", "10"], capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "--offset-dps: the elevation axis would turn 210 deg" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
