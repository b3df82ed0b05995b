"""`hil fit` on logs: a hidden plant drawn inside the documented ranges, the logs a lab would record on it, the fit,
then the parameters and the acceptance campaign against the hidden plant's (docs/fit.md); and bad input."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

from firmware_stub.config import load_emulator_config
from firmware_stub.plant import DEFAULT_PLANT_CONFIG, RIGID_PLANT_CONFIG
from hil.fit.logs import FitInputError, load_fit_logs
from hil.fit.ranges import (
    PLAUSIBLE,
    apply_params,
    check_authority,
    draw_plant,
    dump_plant,
    get_param,
    load_plant_dict,
)
from hil.fit.record import campaign_on_plant, record, record_platform_logs, recording_plan, session_on_plant
from hil.fit.twin import fit_frequency_response, fit_logs, lab_wire_delay_s
from tests.fit.helpers import SLOW_WIRE_BAUD

pytestmark = pytest.mark.slow

HIDDEN_SEED = 12  # a draw of hil.fit.ranges.draw_plant; benchmarks/fit_hidden_plants.py runs others
SEEDS_1_3 = (1, 2, 3)  # the acceptance campaign's seeds: a limit-cycling cell's single seed is noisy


@pytest.fixture(scope="module")
def platform(tmp_path_factory: pytest.TempPathFactory) -> dict:
    work = tmp_path_factory.mktemp("hidden")
    hidden, drawn = draw_plant(HIDDEN_SEED, load_plant_dict(DEFAULT_PLANT_CONFIG))
    path = dump_plant(hidden, work / "hidden.yaml", "a hidden plant")
    logs = record_platform_logs(path, work / "logs")  # on the default lab
    return {"work": work, "hidden": hidden, "drawn": drawn, "path": path, "logs": logs}


@pytest.fixture(scope="module")
def twin(platform: dict) -> dict:
    fit = fit_logs(platform["logs"])
    path = fit.write(platform["work"] / "twin.yaml")
    return {"fit": fit, "path": path}


def test_draws_are_reproducible_inside_the_ranges_and_drivable() -> None:
    base = load_plant_dict(DEFAULT_PLANT_CONFIG)
    a, va = draw_plant(3, base)
    b, vb = draw_plant(3, base)
    assert a == b and va == vb
    assert draw_plant(4, base)[1] != va
    for p in PLAUSIBLE:
        lo, hi = p.draw_range
        assert lo <= va[p.name] <= hi, p.name
        assert get_param(a, p.name) == pytest.approx(va[p.name], rel=1e-12), p.name
    check_authority(a)
    weak = apply_params(a, {"drive.el.current_limit_a": 0.3})
    with pytest.raises(ValueError, match="el: torque authority"):
        check_authority(weak)


def test_identifiable_parameters_recovered(platform: dict, twin: dict) -> None:
    """k_m and the gyro noise within 5 %; Coulomb friction, the structural mode, the azimuth cable and the
    imbalance's m rho_x within 10 % (docs/fit.md, "What the logs determine")."""
    hidden, fit = platform["hidden"], twin["fit"]

    def check(name: str, tol: float) -> None:
        e = fit.estimate(name)
        assert e is not None and e.status == "fitted", (name, e)
        true = get_param(hidden, name)
        assert e.value == pytest.approx(true, rel=tol), (name, e.value, true)

    for axis in ("az", "el"):
        check(f"motor_{axis}.k_m_dps2_per_count", 0.05)
        check(f"friction.{axis}.coulomb_n_m", 0.10)
        check(f"structure.{axis}.mode_hz", 0.10)
    for ax in "xyz":
        check(f"gyro.noise_std_dps.{ax}", 0.05)
    check("cable.az.stiffness_n_m_per_rad", 0.10)
    check("imbalance.m_rho_x_kg_mm", 0.10)
    # what the logs could not reach keeps a bound, never a value below what they asked for
    for axis in ("az", "el"):
        e = fit.estimate(f"drive.{axis}.current_limit_a")
        assert e is not None and e.value is not None
        if e.status == "fitted":
            assert e.value == pytest.approx(get_param(hidden, f"drive.{axis}.current_limit_a"), rel=0.10)
        else:
            assert e.status == "bound" and e.value >= fit.mechanics[axis].current_peak_a


def test_the_total_loop_delay_is_recovered_within_a_tenth_of_a_millisecond(platform: dict, twin: dict) -> None:
    """The logs were recorded with the wire on (docs/emulator.md, "The wire"): the fit recovers the gyro's lag, its
    delay and the wire's together, and leaves the wire's to the twin's lab."""
    hidden, fit = platform["hidden"], twin["fit"]
    wire_s = load_emulator_config().drive_delay_s()
    assert fit.wire_s == pytest.approx(wire_s) and wire_s == pytest.approx(134e-6, abs=1e-6)  # 65 + 37 + 32 us
    true_s = 1.0 / (2.0 * math.pi * get_param(hidden, "gyro.bandwidth_hz")) + get_param(hidden, "gyro.delay_s")
    assert fit.total_delay_s == pytest.approx(true_s + wire_s, abs=1e-4), (fit.total_delay_s, true_s + wire_s)
    assert any(n.startswith("total loop delay") for n in fit.notes)


def test_the_kernel_fit_puts_the_wire_on_the_drive_where_the_lab_has_it(tmp_path: Path) -> None:
    """The emulated lab applies the wire and the host's delay to the drive, within the tick's hold; the gyro's own
    delay is interpolated between tick ends. The two are not the same filter, so the FRF fit models each where the
    lab has it. On a noise-free linear plant (a 160 Hz gyro pole, a fractional gyro delay, a 229 Hz mode) the el
    sweep then gives the gyro's bandwidth within 3 % and its own delay within 20 us; lumping the wire into the
    gyro's delay misreads the same log's bandwidth by more than 10 %."""
    plant, _ = draw_plant(32, load_plant_dict(DEFAULT_PLANT_CONFIG))
    for axis in ("az", "el"):
        plant["friction"][axis] = {"coulomb_n_m": 0.0, "viscous_n_m_s_per_rad": 0.0, "smoothing_rate_dps": 0.1,
                                   "model": "tanh"}
    for key in ("cable", "ripple", "drive"):
        plant.pop(key, None)
    plant["gyro"] |= {"noise_std_dps": [0.0, 0.0, 0.0], "noise_psd": [], "random_walk": 0.0,
                      "quantisation_lsb_dps": 0.0}
    plant = apply_params(plant, {"gyro.bandwidth_hz": 160.0, "gyro.delay_s": 0.34e-3, "structure.el.mode_hz": 229.0})
    path = dump_plant(plant, tmp_path / "linear.yaml", "a noise-free linear plant")
    base = session_on_plant(path, tmp_path, name="lin", swing=None, baudrate=SLOW_WIRE_BAUD)  # a wire of 0.67 ms
    logs = record([r for r in recording_plan(base) if r.name == "fit-ident-el"], loopback=True)
    log = load_fit_logs(logs)[0]
    wire_s = lab_wire_delay_s([log])
    assert wire_s > 6e-4
    fit = fit_frequency_response(log, prior=plant, drive_delay_s=wire_s)
    assert fit.bandwidth_hz == pytest.approx(160.0, rel=0.03)
    assert fit.delay_s - wire_s == pytest.approx(0.34e-3, abs=2e-5)
    assert fit.rms_deg < 1.5
    lumped = fit_frequency_response(log, prior=plant)
    assert abs(lumped.bandwidth_hz / 160.0 - 1.0) > 0.10


def test_a_breakaway_inside_the_stick_band_is_matched_on_the_swing_logs(platform: dict, twin: dict) -> None:
    """Plant 12's elevation breakaway (T_s / T_c 1.04, v_s 0.62 deg/s: an excess impulse of 0.023 deg/s). Through
    the slow wire's 0.67 ms it was too small for the torque balance and the swing logs re-run on the twin set it; on
    the default lab's 0.13 ms the torque balance fits it. Only the impulse is determined: one factor is fitted, the
    other keeps its value (with a note, after a re-run), and the impulse is within 0.05 deg/s of the hidden one where
    the prior's (1.28, 0.5 deg/s) was 0.14."""
    hidden, fit = platform["hidden"], twin["fit"]
    ratio, rate = fit.estimate("friction.el.stiction_ratio"), fit.estimate("friction.el.stribeck_rate_dps")
    assert ratio is not None and rate is not None
    moved, held = (ratio, rate) if ratio.status == "fitted" else (rate, ratio)
    assert moved.status == "fitted", moved
    if moved.source.startswith("swing logs re-run on the twin"):  # the torque balance could not resolve it
        assert "impulse" in held.note, held
    else:  # the default lab's 0.13 ms of wire blur the breakaway less than the slow wire's 0.67 ms did
        assert moved.source.startswith("torque balance"), moved

    def impulse(plant: dict) -> float:
        return ((get_param(plant, "friction.el.stiction_ratio") - 1.0)
                * get_param(plant, "friction.el.stribeck_rate_dps"))
    assert impulse(fit.plant) == pytest.approx(impulse(hidden), abs=0.05)
    assert abs(impulse(fit.prior) - impulse(hidden)) > 0.1


def test_a_sweep_that_ends_below_the_gyro_pole_takes_the_pole_another_log_pinned(platform: dict,
                                                                                tmp_path: Path) -> None:
    """One gyro for both axes. On this plant (a 348 Hz pole, a 181 Hz azimuth mode) the azimuth sweep is recorded to
    220 Hz only: its coherent band ends at ~200 Hz, under the pole and just above the mode, and pins no pole. It is
    fitted with the pole the elevation sweep pinned: fitted with the prior's 200 Hz instead, its delay and its
    mode's damping absorbed the missing lag (the damping read 16 % low, the twin's high-gain ESO+KF miss 17 % high)."""
    hidden = platform["hidden"]
    base = session_on_plant(platform["path"], tmp_path, name="p12", swing=None)
    el = record([r for r in recording_plan(base) if r.name == "fit-ident-el"], loopback=True)
    az = record([r for r in recording_plan(base, f_stop_hz=220.0) if r.name == "fit-ident-az"], loopback=True)
    fit = fit_logs(el + az)
    by_axis = {f.axis: f for f in fit.frf}
    assert by_axis["el"].bandwidth_identified and not by_axis["az"].bandwidth_identified
    assert get_param(hidden, "gyro.bandwidth_hz") > 1.5 * by_axis["az"].f_range_hz[1]
    assert by_axis["az"].f_range_hz[1] > 1.05 * get_param(hidden, "structure.az.mode_hz")
    assert by_axis["az"].bandwidth_hz == pytest.approx(by_axis["el"].bandwidth_hz)
    e = fit.estimate("structure.az.damping_ratio")
    assert e is not None and e.status == "fitted"
    assert e.value == pytest.approx(get_param(hidden, "structure.az.damping_ratio"), rel=0.08)


def test_both_sweeps_give_the_mode_dampings(platform: dict, twin: dict) -> None:
    """The default recordings: each axis' structural mode and its damping within 8 % (measured: -1.9 % and +1.3 %)."""
    hidden, fit = platform["hidden"], twin["fit"]
    for axis in ("az", "el"):
        for name, rel in (("mode_hz", 0.02), ("damping_ratio", 0.08)):
            e = fit.estimate(f"structure.{axis}.{name}")
            assert e is not None and e.status == "fitted"
            assert e.value == pytest.approx(get_param(hidden, f"structure.{axis}.{name}"), rel=rel), (axis, name)


def test_twin_gives_the_hidden_plants_campaign_within_15_percent(platform: dict, twin: dict) -> None:
    """ESO, ESO+KF and high-gain ESO+KF at 1 and 3 deg / 1 Hz (miss range and std, rate error std): every metric
    on the twin within 15 % of the hidden plant's, each the mean over seeds 1-3, as a campaign reports it. The
    high-gain ESO+KF limit-cycles at 3 deg: its miss std on seed 1 alone read +7.7 %, +9.5 % and +16.8 % on three
    twins of this plant whose parameters differ by 1e-7 (the fit's float rounding from run to run), and +6.5 % to
    +9.4 % as the mean over the three seeds (docs/fit.md)."""
    hid = campaign_on_plant(platform["path"], platform["work"] / "on-hidden", seeds=SEEDS_1_3, duration_s=8.0)
    twn = campaign_on_plant(twin["path"], platform["work"] / "on-twin", seeds=SEEDS_1_3, duration_s=8.0)
    assert len(hid) == 2 * 3 * 5
    off = {k: twn[k] / v - 1.0 for k, v in hid.items()}
    assert all(math.isfinite(x) for x in off.values())
    worst = max(off, key=lambda k: abs(off[k]))
    assert abs(off[worst]) <= 0.15, (worst, hid[worst], twn[worst])


def test_the_cli_writes_a_valid_plant_and_the_report(platform: dict, tmp_path: Path) -> None:
    logs = [str(p) for p in platform["logs"]]
    out = tmp_path / "my-gimbal.yaml"
    proc = subprocess.run([sys.executable, "-m", "hil", "fit", *logs, "--out", str(out), "--report-dir",
                           str(tmp_path / "report"), "--json"], check=False, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    assert Path(data["plant"]) == out and out.is_file()
    load_plant_dict(out)
    status = {e["name"]: e["status"] for e in data["estimates"]}
    assert status["motor_el.k_m_dps2_per_count"] == "fitted"
    assert status["friction.el.coulomb_n_m"] == "fitted"
    assert status["friction.el.viscous_n_m_s_per_rad"] in ("fitted", "prior")
    text = (tmp_path / "report" / "fit.md").read_text()
    assert "The logged sessions on the twin" in text and "fit-torque.png" in text
    assert {c["metric"] for c in data["checks"]} >= {"rate_err_el_std_dps", "miss_std_px"}
    for c in data["checks"]:  # the same sessions on the twin: within 15 % of the logs
        assert abs(c["ratio"] - 1.0) < 0.15, c
    check = subprocess.run([sys.executable, "-m", "hil", "check", str(out)], check=False, capture_output=True,
                           text=True)
    assert check.returncode == 0, check.stderr


def test_without_ident_logs_k_m_keeps_its_prior_and_says_why(platform: dict) -> None:
    fit = fit_logs([p for p in platform["logs"] if "ident" not in p.name])
    e = fit.estimate("motor_az.k_m_dps2_per_count")
    assert e is not None and e.status == "prior" and "no ident log" in e.source
    assert "record `hil ident SESSION` with axis=az" in e.note  # what would resolve it
    assert e.value == pytest.approx(0.023, rel=0.01)
    assert fit.estimate("friction.el.coulomb_n_m").status == "fitted"  # type: ignore[union-attr]


def _cli_error(args: list[str]) -> str:
    proc = subprocess.run([sys.executable, "-m", "hil", "fit", *args], check=False, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    return lines[0]


def test_logs_of_two_platforms_are_refused(platform: dict, tmp_path: Path) -> None:
    from hil import api

    other = api.run(session_on_plant(RIGID_PLANT_CONFIG, tmp_path, name="other", swing=None, seconds=3.0),
                    clock="sim").log_path
    with pytest.raises(FitInputError, match="two different platforms"):
        load_fit_logs([platform["logs"][0], other])
    line = _cli_error([str(platform["logs"][0]), str(other), "--out", str(tmp_path / "x.yaml")])
    assert "two different platforms" in line and "plant sha256" in line


def test_a_log_without_a_needed_channel_names_it(platform: dict, tmp_path: Path) -> None:
    bad = tmp_path / "no-gyro.h5"
    shutil.copy(platform["logs"][0], bad)
    with h5py.File(bad, "a") as f:
        del f["loop"]["gyro_y_dps"]
    line = _cli_error([str(bad), "--out", str(tmp_path / "x.yaml")])
    assert "no-gyro.h5" in line and "gyro_y_dps" in line


def test_a_truncated_log_is_one_line(platform: dict, tmp_path: Path) -> None:
    bad = tmp_path / "cut.h5"
    data = Path(platform["logs"][-1]).read_bytes()
    bad.write_bytes(data[: len(data) // 3])
    line = _cli_error([str(bad), "--out", str(tmp_path / "x.yaml")])
    assert "cut.h5" in line
    short = tmp_path / "short"
    from hil import api

    log = api.run(session_on_plant(platform["path"], short, name="short", swing=None, seconds=1.5),
                  clock="sim").log_path
    line = _cli_error([str(log), "--out", str(tmp_path / "x.yaml")])
    assert "too short" in line or "armed for" in line


def test_a_campaign_runs_on_a_given_plant(tmp_path: Path) -> None:
    """`hil campaign FILE --plant TWIN.yaml`: every cell's emulator names the twin; a bad plant is one line."""
    from firmware_stub.config import read_yaml_mapping
    from hil import api
    from hil.config import PROFILES, ConfigError

    campaign = PROFILES / "campaigns" / "swing-miss-distance.yaml"
    config, _, sessions = api.prepare_campaign(campaign, out=tmp_path / "c", plant=RIGID_PLANT_CONFIG)
    assert len(sessions) == len(config.cells())
    for session in sessions.values():
        emulator = read_yaml_mapping(session["emulator"]["config"])
        assert Path(emulator["plant"]) == RIGID_PLANT_CONFIG.resolve()
    bad = tmp_path / "bad.yaml"
    bad.write_text("motor_az: {resistance_ohm: -1}\n")
    with pytest.raises(ConfigError, match=r"^plant='"):
        api.prepare_campaign(campaign, out=tmp_path / "d", plant=bad)
