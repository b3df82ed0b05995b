"""`hil ident` as a user runs it: a swept sine on the emulator's closed rate loop, over ptys, in lockstep."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from firmware_stub.config import load_emulator_config
from hil.config import PROFILES
from hil.control.registry import K_M_DEFAULT

SESSION = PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml"


@pytest.mark.slow
def test_ident_recovers_the_emulators_k_m_within_5_percent(tmp_path: Path) -> None:
    """`hil ident SESSION --loopback` with its defaults (a levelled sweep, lockstep)."""
    proc = subprocess.run([sys.executable, "-m", "hil", "ident", str(SESSION), "--loopback", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads((tmp_path / "ident-el.json").read_text())
    # the emulated plant's k_m is K_t V/count / (J R) = 0.0230 deg/s^2 per count (profiles/plant/default.yaml)
    assert abs(report["k_m_dps2_per_count"] - K_M_DEFAULT) / K_M_DEFAULT < 0.05, report
    # the delay is the loop's: the gyro's (200 Hz: 0.80 ms of lag, and 0.5 ms of delay) and the wire's
    wire_ms = load_emulator_config().drive_delay_s() * 1e3  # 0.67 ms at 921 600 baud (docs/emulator.md, "The wire")
    lag_ms = 1e3 / (2 * math.pi * 200.0)
    band_lo, band_hi = report["coherent_band_hz"]
    assert band_lo < 3.0 and band_hi > 150.0, report  # the levelled sweep is coherent over most of the band
    if report["gyro_bandwidth_hz"] is None:  # the pole above the band: one loop delay, lag included
        assert abs(report["loop_delay_ms"] - (lag_ms + 0.5 + wire_ms)) < 0.2, report
    else:
        assert 150 < report["gyro_bandwidth_hz"] < 250 and 0.3 < report["delay_ms"] - wire_ms < 0.8, report
    assert (tmp_path / "bode-el.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "k_m" in proc.stdout and "coherent band" in proc.stdout


def test_ident_refuses_an_elevation_sweep_that_would_reach_the_gimbals_singularity(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "hil", "ident", str(SESSION), "--loopback", "--out", str(tmp_path),
                           "--offset-dps", "10"], capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "error: --offset-dps 10: the elevation axis would turn 90 deg" in proc.stderr  # 10 x (8 + 1) s
    assert proc.stderr.strip().endswith("lower --offset-dps or --sweep-s, or identify --axis az")
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr


@pytest.mark.slow
def test_ident_shows_a_structural_mode_as_a_resonance_at_its_frequency(tmp_path: Path) -> None:
    """A two-mass mode on the elevation axis (gyro on the load) appears in `hil ident`'s frequency response as a
    peak over the rigid fit near ``mode_hz``; the same sweep on the rigid plant has none (sim clock)."""
    import numpy as np
    import yaml

    from hil.analysis import SweptSine, identify_log
    from hil.log import read_log

    mode_hz = 150.0

    def ident(name: str, structure: dict | None) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[type-arg]
        plant = yaml.safe_load((PROFILES / "plant" / "rigid.yaml").read_text())
        if structure is not None:
            plant["structure"] = {"el": structure}
        (tmp_path / f"{name}-plant.yaml").write_text(yaml.safe_dump(plant))
        emulator = yaml.safe_load((PROFILES / "emulator" / "default.yaml").read_text())
        emulator["plant"] = str(tmp_path / f"{name}-plant.yaml")
        (tmp_path / f"{name}-emulator.yaml").write_text(yaml.safe_dump(emulator))
        session = yaml.safe_load(SESSION.read_text())
        for key in ("controller", "profile", "hexapod_limits"):
            session[key] = str((SESSION.parent / session[key]).resolve())
        session["emulator"] = {"config": str(tmp_path / f"{name}-emulator.yaml"), "clock": "sim"}
        (tmp_path / f"{name}.yaml").write_text(yaml.safe_dump(session))
        out = tmp_path / name
        proc = subprocess.run([sys.executable, "-m", "hil", "ident", str(tmp_path / f"{name}.yaml"), "--loopback",
                               "--out", str(out), "--sweep-s", "8", "--f-start-hz", "0.5", "--f-stop-hz", "300",
                               "--amplitude-dps", "2", "--offset-dps", "2.5", "--no-level"], capture_output=True,
                              text=True, timeout=300, check=False)
        assert proc.returncode == 0, proc.stderr[-2000:]
        report = json.loads((out / "ident-el.json").read_text())
        frf, fit = identify_log(read_log(Path(report["log"])), SweptSine(**report["sweep"]), coherence_min=0.5)
        excess_db = 20 * np.log10(np.abs(frf.response) / np.abs(fit.response(frf.freq_hz)))
        good = frf.coherence >= 0.9  # above ~200 Hz the gyro's noise and filter leave little coherence
        return frf.freq_hz[good], excess_db[good]

    f, excess = ident("mode", {"mode_hz": mode_hz, "damping_ratio": 0.1, "motor_inertia_fraction": 0.6})
    smooth = np.array([np.median(excess[max(0, i - 3):i + 4]) for i in range(len(excess))])  # single bins are noisy
    peak = f[np.argmax(smooth)]
    assert abs(peak - mode_hz) <= 0.1 * mode_hz, (peak, smooth.max())
    near = (f > 0.9 * mode_hz) & (f < 1.1 * mode_hz)
    assert np.median(excess[near]) > 6.0  # 1 / (2 zeta) = 14 dB at the peak, less the fit's share
    f0, excess0 = ident("rigid", None)
    near0 = (f0 > 0.9 * mode_hz) & (f0 < 1.1 * mode_hz)
    assert abs(np.median(excess0[near0])) < 1.0
