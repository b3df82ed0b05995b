"""`hil ident`'s levelling (docs/ident.md, "Levelling"): the levelled sweep, the per-third-octave check of a log,
the rule that makes the next sweep, the coherent band, and the whole `hil ident` on a plant the default sweep does
not suit."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from firmware_stub.plant import DEFAULT_PLANT_CONFIG
from hil import api
from hil.analysis import (
    Frf,
    LevelCheck,
    SweptSine,
    check_levels,
    coherent_band,
    fit_plant,
    host_disturbed,
    identify_log,
    level_frequencies,
    next_level,
    plant_response,
    resonance_hz,
)
from hil.config import SessionConfig, session_yaml
from hil.fit.ranges import draw_plant, dump_plant, load_plant_dict
from hil.fit.record import session_on_plant
from hil.ident import _sweeps  # the module whose session runs the test replaces
from hil.log import LogData
from tests.ident.test_ident import LOOP_CHANNELS, as_log, run_plant

LIMIT = 30000.0


def test_a_levelled_sweep_follows_its_table_on_log_frequency() -> None:
    sweep = SweptSine(f_start_hz=1.0, f_stop_hz=100.0, duration_s=10.0, levels=((2.0, 4.0), (20.0, 1.0)))
    assert sweep.amplitude_dps == 4.0  # the table's peak
    assert sweep.amplitude_at_dps(1.0) == 4.0 and sweep.amplitude_at_dps(100.0) == 1.0  # held beyond the ends
    assert sweep.amplitude_at_dps(math.sqrt(2.0 * 20.0)) == pytest.approx(2.5)  # half-way on log frequency
    # the rate command's envelope: near 20 Hz (tau where f = 20) the peak is 1 deg/s, near 2 Hz it is 4
    tau_20 = math.log(20.0) / math.log(100.0) * 10.0
    near_20 = [abs(sweep.rate_dps(sweep.settle_s + tau_20 + k * 1e-4)) for k in range(-300, 300)]
    assert max(near_20) == pytest.approx(1.0, abs=0.02)
    tau_2 = math.log(2.0) / math.log(100.0) * 10.0
    near_2 = [abs(sweep.rate_dps(sweep.settle_s + tau_2 + k * 1e-3)) for k in range(-300, 300)]
    assert max(near_2) == pytest.approx(4.0, abs=0.05)
    with pytest.raises(ValidationError, match="must rise"):
        SweptSine(levels=((20.0, 1.0), (2.0, 4.0)))
    with pytest.raises(ValidationError, match="amplitudes"):
        SweptSine(levels=((2.0, 0.0), (20.0, 1.0)))


def check_of(coh: list[float], *, amp: float = 1.0, peak: float = 10000.0, clipped: float = 0.0, mean: float = 5000.0,
             reversed_at: tuple[int, ...] = (), swing: float = 0.5) -> LevelCheck:
    n = len(coh)
    rev = np.zeros(n, dtype=bool)
    rev[list(reversed_at)] = True
    return LevelCheck(np.geomspace(1.0, 2.0 ** ((n - 1) / 3), n), np.full(n, amp), np.array(coh), np.full(n, peak),
                      np.full(n, clipped), np.full(n, mean), rev, np.full(n, swing))


SWEEP = SweptSine(f_start_hz=1.0, f_stop_hz=4.0, duration_s=4.0, amplitude_dps=1.0, offset_dps=3.0)


def test_where_the_coherence_fails_the_amplitude_rises_as_far_as_the_drive_allows() -> None:
    check = check_of([0.5, 0.9, 0.9, 0.5, 0.9, 0.9, 0.9])
    nxt = next_level(SWEEP, check, max_drive_counts=LIMIT, offset_max_dps=10.0)
    assert nxt is not None
    amp = np.array([a for _, a in nxt.levels])
    # room: (80 % of 30000 - 5000 mean) / (10000 - 5000) = 3.8, capped at x2
    assert amp.tolist() == [2.0, 1.0, 1.0, 2.0, 1.0, 1.0, 1.0]
    tight = next_level(SWEEP, check_of([0.5] * 7, peak=20000.0), max_drive_counts=LIMIT, offset_max_dps=10.0)
    assert tight is not None and all(a == pytest.approx(19000 / 15000, abs=1e-4) for _, a in tight.levels)
    assert next_level(SWEEP, check_of([0.5] * 7, peak=24500.0), max_drive_counts=LIMIT, offset_max_dps=10.0) is None


def test_where_the_drive_clips_the_amplitude_halves_unless_its_mean_took_the_headroom() -> None:
    nxt = next_level(SWEEP, check_of([0.9] * 7, clipped=0.2), max_drive_counts=LIMIT, offset_max_dps=10.0)
    assert nxt is not None and all(a == 0.5 for _, a in nxt.levels) and nxt.offset_dps == 3.0
    # clipped with a mean drive over half the limit (friction at the offset's rate, a wound-up harness): the
    # amplitudes and the offset, and with it the travel, all fall x0.6
    biased = next_level(SWEEP, check_of([0.9] * 7, clipped=0.2, mean=20000.0), max_drive_counts=LIMIT,
                        offset_max_dps=10.0)
    assert biased is not None and biased.offset_dps == pytest.approx(1.8)
    assert all(a == pytest.approx(0.6) for _, a in biased.levels)
    # ... down to an offset of 0.3 deg/s
    low = SWEEP.model_copy(update={"offset_dps": 0.4})
    floor = next_level(low, check_of([0.9] * 7, clipped=0.2, mean=20000.0), max_drive_counts=LIMIT,
                       offset_max_dps=10.0)
    assert floor is not None and floor.offset_dps == pytest.approx(0.3)


def test_a_reversing_axis_gets_more_offset_then_less_amplitude_once_the_travel_is_used() -> None:
    reversing = check_of([0.9] * 7, reversed_at=(0, 1), swing=2.4)
    nxt = next_level(SWEEP, reversing, max_drive_counts=LIMIT, offset_max_dps=10.0)
    assert nxt is not None and nxt.offset_dps == pytest.approx(3.6)  # 1.5 x 2.4
    capped = next_level(SWEEP, reversing, max_drive_counts=LIMIT, offset_max_dps=3.0)
    assert capped is not None and capped.offset_dps == 3.0
    assert all(a == pytest.approx(3.0 / 3.6, abs=1e-4) for _, a in capped.levels)
    neg = next_level(SWEEP.model_copy(update={"offset_dps": -3.0}), reversing, max_drive_counts=LIMIT,
                     offset_max_dps=10.0)
    assert neg is not None and neg.offset_dps == pytest.approx(-3.6)  # the sign is the sweep's


def test_the_coherent_band_bridges_one_third_octave_not_two() -> None:
    centres = level_frequencies(SweptSine(f_start_hz=1.0, f_stop_hz=16.0, duration_s=4.0))
    assert centres.size == 13 and centres[0] == 1.0 and centres[-1] == pytest.approx(16.0)
    sweep = SweptSine(f_start_hz=1.0, f_stop_hz=16.0, duration_s=4.0)
    one = [0.5, 0.9, 0.9, 0.5, 0.9, 0.9, 0.9, 0.9, 0.9, 0.9, 0.9, 0.9, 0.5]
    lo, hi = coherent_band(check_of(one), sweep)  # type: ignore[misc]
    third = 2.0 ** (1 / 6)
    assert lo == pytest.approx(2.0 ** (1 / 3) / third) and hi == pytest.approx(2.0 ** (11 / 3) * third)
    two = [0.9, 0.9, 0.9, 0.9, 0.9, 0.5, 0.5, 0.9, 0.9, 0.9, 0.9, 0.9, 0.9]
    lo, hi = coherent_band(check_of(two), sweep)  # type: ignore[misc]
    assert lo == pytest.approx(2.0 ** (7 / 3) / third) and hi == 16.0  # the wider side of the gap
    assert coherent_band(check_of([0.5] * 13), sweep) is None


@pytest.mark.parametrize("offset", [0.0, 10.0])
def test_the_check_sees_the_axis_reverse_without_an_offset(offset: float) -> None:
    sweep = SweptSine(f_start_hz=1.0, f_stop_hz=300.0, duration_s=10.0, amplitude_dps=2.0, offset_dps=offset)
    data = as_log(run_plant(sweep))
    frf, _ = identify_log(data, sweep)
    check = check_levels(data, sweep, frf, LIMIT)
    low = (check.freq_hz > 1.2) & (check.freq_hz < 10.0)  # past the taper at the start
    assert check.amplitude_dps.tolist() == [2.0] * check.freq_hz.size
    if offset == 0.0:
        assert check.reversed[low].all()
    else:
        assert not check.reversed.any()
        # below the loop's bandwidth the rate follows the command: a swing of ~2 deg/s
        assert np.all((check.rate_swing_dps[low] > 1.5) & (check.rate_swing_dps[low] < 3.5))
    assert np.all(check.drive_clipped[low] == 0.0) and np.all(check.drive_peak_counts[low] < LIMIT)


@pytest.mark.slow
def test_hil_ident_levels_itself_on_a_plant_the_first_sweep_does_not_suit(tmp_path: Path) -> None:
    """A plant drawn in the plausible ranges whose first sweep is coherent only from 3.6 Hz (the low band drowns in
    the loop's own disturbances): the levelling widens the band, keeps the widest pass without a reversal, and prints
    no figure from outside the band (sim clock)."""
    hidden, values = draw_plant(1, load_plant_dict(DEFAULT_PLANT_CONFIG))
    plant = dump_plant(hidden, tmp_path / "hidden.yaml")
    session = tmp_path / "session.yaml"
    session.write_text(session_yaml(session_on_plant(plant, tmp_path, name="hidden", swing=None)), encoding="utf-8")
    out = tmp_path / "ident"
    proc = subprocess.run([sys.executable, "-m", "hil", "ident", str(session), "--loopback", "--clock", "sim",
                           "--out", str(out)], capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads((out / "ident-el.json").read_text())
    passes = report["passes"]
    assert len(passes) >= 2
    lo, hi = report["coherent_band_hz"]
    first_lo, first_hi = passes[0]["coherent_band_hz"]
    assert math.log2(hi / lo) > math.log2(first_hi / first_lo) + 0.3, passes  # a third octave wider or more
    f_lo, f_hi = report["f_range_hz"]
    assert lo <= f_lo and f_hi <= hi
    k_m = values["motor_el.k_m_dps2_per_count"]
    assert report["k_m_dps2_per_count"] == pytest.approx(k_m, rel=0.05)
    bw = report["gyro_bandwidth_hz"]
    assert bw is None or bw <= hi
    text = " ".join(proc.stdout.split())
    assert f"coherent band {lo:.3g}-{hi:.3g} Hz" in text
    if bw is None:
        assert f"gyro bandwidth above {f_hi:.3g} Hz, loop delay" in text


def test_a_resonance_over_the_rigid_model_is_found_at_its_peak() -> None:
    f = np.geomspace(2.0, 400.0, 600)
    rigid = plant_response(f, 0.023, bandwidth_hz=300.0, delay_s=1.2e-3, dt_s=1e-3)
    w, wn, zeta = 2j * np.pi * f, 2 * np.pi * 220.0, 0.05
    mode = 1.0 / (1.0 + 2 * zeta * w / wn + (w / wn) ** 2)  # the gyro on the load, past a torsion spring
    for response, expected in ((rigid * mode, 220.0), (rigid, None)):
        frf = Frf(f, response, np.full(f.size, 0.99), 1e-3, 8)
        low = fit_plant(frf, f_min_hz=2.0, f_max_hz=50.0)
        found = resonance_hz(frf, low, f_min_hz=2.0, f_max_hz=400.0)
        if expected is None:
            assert found is None
        else:
            assert found == pytest.approx(expected, rel=0.03)


@pytest.mark.slow
def test_hil_ident_says_when_the_loop_oscillates_by_itself(tmp_path: Path) -> None:
    """A plausible plant (azimuth k_m twice the controllers' b0) on which the shipped ESO limit-cycles behind the
    slow-wire lab's 0.67 ms (921 600 baud; on the default lab's 0.13 ms it keeps its margin): the drive clips where
    the sweep asks little, and `hil ident` says so instead of printing a k_m from a loop that is not linear; a
    gentler controller identifies it (sim clock)."""
    hidden, values = draw_plant(21, load_plant_dict(DEFAULT_PLANT_CONFIG))
    plant = dump_plant(hidden, tmp_path / "hidden.yaml")
    with pytest.raises(ValueError, match="the loop itself oscillates on this plant"):
        api.ident(session_on_plant(plant, tmp_path, name="eso", swing=None, baudrate=921_600), axis="az",
                  clock="sim", out=tmp_path / "eso")
    done = api.ident(session_on_plant(plant, tmp_path, name="pi", swing=None, controller="pi_lpf",
                                      baudrate=921_600), axis="az", clock="sim", out=tmp_path / "pi")
    assert done.fit.k_m_dps2_per_count == pytest.approx(values["motor_az.k_m_dps2_per_count"], rel=0.05)


# --- a host that runs the loop late ----------------------------------------------------------------------------------


def stalled_log(clock: str | None) -> LogData:
    """1000 ticks of a paced loop: one cycle 3 ms late at tick 200, and the samples of ticks 500-504 missed."""
    ticks = np.array([k for k in range(1000) if not 500 <= k < 505])
    cols = {c: np.zeros(ticks.size) for c in LOOP_CHANNELS}
    cols["tick"], cols["t_s"] = ticks.astype(float), ticks * 1e-3
    cols["latency_us"][ticks == 200] = 3000.0
    cols["tick_gap"][ticks == 505] = 5
    return LogData(path=Path("mem.h5"), attrs={} if clock is None else {"clock": clock}, groups={"loop": cols},
                   units={})


@pytest.mark.parametrize("clock", ["realtime", "hardware", None])
def test_a_late_cycle_and_missed_samples_disturb_the_loop_until_it_settles(clock: str | None) -> None:
    mask = host_disturbed(stalled_log(clock))
    assert mask.size == 1000  # the gap-free grid axis_columns uses
    expected = np.zeros(1000, dtype=bool)
    expected[200:251] = True  # the late cycle and the 50 ms after it
    expected[500:556] = True  # the missed samples from the first, and 50 ms after the one that came back
    assert np.array_equal(mask, expected)


@pytest.mark.parametrize("clock", ["lockstep", "sim"])
def test_on_a_clock_whose_world_waits_for_the_bench_nothing_is_disturbed(clock: str) -> None:
    assert not host_disturbed(stalled_log(clock)).any()


def test_a_stalls_transient_is_not_taken_for_the_levels_saturation() -> None:
    """A 100 ms stall whose transient drives the axis to the limit for 30 ms inside a third octave: on a paced clock the
    check leaves those ticks out (no saturation, the third octave marked disturbed) and the next sweep does not shrink;
    a log without the late cycle counts the clip as the level's."""
    sweep = SweptSine(f_start_hz=1.0, f_stop_hz=300.0, duration_s=10.0, amplitude_dps=2.0, offset_dps=10.0)
    cols = run_plant(sweep)
    frf, _ = identify_log(as_log(cols), sweep)
    base = check_levels(as_log(cols), sweep, frf, LIMIT)  # the loop clips by itself above ~20 Hz, not below
    at = round((0.3 + sweep.window_s[0] + 4.0) / 1e-3)  # 4 s into the chirp: near 7 Hz
    cols["drive_el_counts"][at:at + 30] = LIMIT
    plain = check_levels(as_log(cols), sweep, frf, LIMIT)
    hit = int(np.argmax(plain.drive_clipped - base.drive_clipped))
    assert base.drive_clipped[hit] == 0.0 and 4.0 < plain.freq_hz[hit] < 10.0
    assert plain.drive_clipped[hit] > 0.01 and plain.disturbed is not None and not plain.disturbed.any()
    cols["latency_us"][at - 60:at + 40] = 5000.0  # the bench 100 ms late: a stall, the clip its transient
    late = check_levels(LogData(path=Path("mem.h5"), attrs={"clock": "realtime"}, groups={"loop": cols}, units={}),
                        sweep, frf, LIMIT)
    assert late.drive_clipped[hit] == 0.0 and late.drive_peak_counts[hit] < LIMIT
    assert late.disturbed is not None and late.disturbed[hit] > 0.02
    assert late.disturbed[0] == 0.0 and late.disturbed[-1] == 0.0  # far from the stall, seconds away
    assert np.array_equal(late.saturated(), base.saturated())


def test_a_pass_spoiled_by_the_host_is_run_again_and_a_lone_coherent_third_octave_gives_no_fit(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Each pass comes back coherent in one third octave only, with the drive out of headroom everywhere (no level
    can rise) and the host late all over the sweep: the levelling repeats the sweep (turning back each time) instead
    of stopping, keeps no fit from the lone third octave, and says the host's stalls are why."""
    sweep = SweptSine(f_start_hz=1.0, f_stop_hz=16.0, duration_s=4.0, amplitude_dps=1.0, offset_dps=3.0)
    n = level_frequencies(sweep).size
    coh = [0.3] * n
    coh[6] = 0.9  # 4 Hz alone
    check = check_of(coh, peak=0.95 * LIMIT, mean=1000.0)
    spoiled = LevelCheck(*(getattr(check, f) for f in ("freq_hz", "amplitude_dps", "coherence", "drive_peak_counts",
                                                       "drive_clipped", "drive_mean_counts", "reversed",
                                                       "rate_swing_dps")), disturbed=np.full(n, 0.3))
    assert next_level(sweep, spoiled, max_drive_counts=LIMIT, offset_max_dps=10.0) is None
    ran: list[SweptSine] = []

    def fake_run(cfg: SessionConfig, **_: object) -> SweptSine:
        ran.append(cfg.excitation)
        return cfg.excitation

    def fake_examine(sw: SweptSine, result: object, limit: float) -> _sweeps.IdentPass:
        run = _sweeps.RunResult("completed", 0, "", tmp_path / "x.h5", "realtime", session=None)  # type: ignore[arg-type]
        return _sweeps.IdentPass(sw, run, None, spoiled, coherent_band(spoiled, sw))

    monkeypatch.setattr(_sweeps, "run", fake_run)
    monkeypatch.setattr(_sweeps, "_examine", fake_examine)
    config = session_on_plant(DEFAULT_PLANT_CONFIG, tmp_path, name="stalled", swing=None)
    result = _sweeps.ident_sweeps(config, sweep)
    assert len(ran) == _sweeps.LEVEL_PASSES
    assert [s.offset_dps for s in ran] == [3.0, -3.0] * (_sweeps.LEVEL_PASSES // 2)
    assert all(s.levels == ran[1].levels for s in ran[1:])  # the same sweep again, only the direction changes
    assert result.best.band_hz is not None and result.best.octaves < _sweeps.MIN_BAND_OCTAVES
    assert result.fit is None
    assert f"in {n - 1} third octaves of the kept pass the coherence failed where the bench ran late" in result.why
