"""Named metrics of one session log: what campaign tables, thresholds and acceptance rules refer to.

Three analyses (a campaign picks one; ``control`` metrics are always computed):

- ``control``: seed 000 Tables 1-3 and seed 001: rate error and miss distance range (+-, half the
  peak-to-peak) and std, drive ripple, LOS rate, loop health (hil.analysis.summarize_log); on the sim clock also
  the true LOS rate (``los_rate_true_*``, from the session's truth file, hil.log.truth);
- ``static_noise``: seed 000 Fig. 12: the elevation gyro at rest, raw vs the 150 Hz first-order
  low-pass (applied here to the logged raw gyro) vs the KF estimate the loop fed back;
- ``filter_lag``: seed 000 Fig. 13: with a sine on the rate command, the lag of the 150 Hz low-pass
  and of the KF behind the raw gyro at the sine's frequency, in loop cycles of 1 ms (samples: 0.63 is
  0.63 ms), never in periods of the excitation; negative is a lead.

"Cycles" in a metric's name or unit are always the bench's 1 ms loop cycles (``lag_*_cycles``: a time in
loop cycles; ``missed_cycles``: a count of loop cycles). Each metric has a ``kind`` (error, noise, lag,
effort, health): a campaign's verdict ranks and averages its ``primary_metrics``, by default its error
metrics (:func:`default_primary`), never effort or health. A lag is compared by its magnitude
(:func:`score`): a lead is as far off in time as a lag of the same size, and never an improvement over it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from hil.analysis import summarize_log
from hil.control.filters import LowPass1
from hil.log import LogData, read_log
from hil.log.truth import read_truth

PAPER_LPF_HZ = 150.0  # seed 000 section 4.3: "a traditional low-pass filter bandwidth of 150 Hz"
LOS_BAND_HZ = 20.0  # seed 001's LOS rate: the 2.5 Hz vibration's band, above it the gyro's white noise dominates
RECORD_S = 1.0  # peak-to-peak noise is read per 1 s record, as the paper's Fig. 12 shows one


MetricKind = Literal["error", "noise", "lag", "effort", "health"]
LOOP_CYCLES = "loop cycles of 1 ms"  # the unit of every lag metric: samples of the 1 kHz loop, i.e. ms


@dataclass(frozen=True)
class Metric:
    """``kind``: ``error`` what the stabilisation leaves (rate error, miss distance, LOS rate); ``noise`` a
    signal's noise at rest; ``lag`` a filter's lag; ``effort`` what the controller spends (drive ripple);
    ``health`` the loop's timing. ``magnitude``: the sign is a direction, not better or worse (a lag's: + lag,
    - lead), so improvements compare ``abs(value)``. ``sim_only``: computed from the plant's truth, so only on the
    sim clock."""

    label: str
    unit: str
    description: str
    lower_is_better: bool = True
    kind: MetricKind = "error"
    magnitude: bool = False
    sim_only: bool = False  # read from the plant's truth, which only the sim clock records (hil.log.truth)


METRICS: dict[str, Metric] = {
    "rate_err_el_std_dps": Metric("EL rate error std", "deg/s", "std of command minus raw gyro, elevation"),
    "rate_err_el_range_dps": Metric("EL rate error +-", "deg/s", "half peak-to-peak of the elevation rate error"),
    "rate_err_az_std_dps": Metric("AZ rate error std", "deg/s", "std of command minus raw gyro, azimuth"),
    "rate_err_az_range_dps": Metric("AZ rate error +-", "deg/s", "half peak-to-peak of the azimuth rate error"),
    "drive_ripple_el_counts": Metric("EL drive ripple", "counts", "std of the drive minus its 20 ms moving mean",
                                     kind="effort"),
    "drive_ripple_az_counts": Metric("AZ drive ripple", "counts", "std of the drive minus its 20 ms moving mean",
                                     kind="effort"),
    "miss_x_std_px": Metric("miss x std", "px", "std of the valid frames' x miss distance"),
    "miss_x_range_px": Metric("miss x +-", "px", "half peak-to-peak of the x miss distance"),
    "miss_y_std_px": Metric("miss y std", "px", "std of the valid frames' y miss distance"),
    "miss_y_range_px": Metric("miss y +-", "px", "half peak-to-peak of the y miss distance"),
    "miss_std_px": Metric("miss std", "px", "the larger of the x and y miss-distance std (the paper's off-target std)"),
    "miss_range_px": Metric("miss +-", "px", "the larger of the x and y miss-distance +- range"),
    "los_rate_rms_dps": Metric("LOS rate rms", "deg/s", "rms of the gyro's y-z (line-of-sight) rate minus command"),
    "los_rate_lf_std_dps": Metric("LOS rate std < 20 Hz", "deg/s", "std of the y-z rate error after a 20 Hz "
                                  "first-order low-pass: the carrier-disturbance band without the gyro's white noise"),
    "los_rate_true_rms_dps": Metric("true LOS rate rms", "deg/s", "rms of the plant's true y-z (line-of-sight) "
                                    "rate minus command: no gyro noise, filter or delay (sim clock only: its truth "
                                    "file, hil.log.truth)", sim_only=True),
    "los_rate_true_lf_std_dps": Metric("true LOS rate std < 20 Hz", "deg/s", "std of the true y-z rate error after "
                                       "the same 20 Hz low-pass: what the LOS really does, which a controller that "
                                       "follows its gyro's noise cannot read below (sim clock only)", sim_only=True),
    "gyro_raw_peak_dps": Metric("raw gyro +-", "deg/s", "median over 1 s records of max |x - mean|, elevation",
                                kind="noise"),
    "gyro_raw_std_dps": Metric("raw gyro std", "deg/s", "std of the raw elevation gyro", kind="noise"),
    "gyro_lpf_peak_dps": Metric("LPF 150 Hz +-", "deg/s", "the same after a 150 Hz first-order low-pass",
                                kind="noise"),
    "gyro_lpf_std_dps": Metric("LPF 150 Hz std", "deg/s", "std after the 150 Hz low-pass", kind="noise"),
    "gyro_kf_peak_dps": Metric("KF +-", "deg/s", "the same for the KF estimate the loop fed back", kind="noise"),
    "gyro_kf_std_dps": Metric("KF std", "deg/s", "std of the KF estimate", kind="noise"),
    "lag_lpf_cycles": Metric("LPF lag", LOOP_CYCLES, "lag of the 150 Hz low-pass behind the raw gyro at the "
                             "excitation frequency, in 1 ms loop cycles (not periods of the excitation); "
                             "negative = a lead, compared by magnitude", kind="lag", magnitude=True),
    "lag_kf_cycles": Metric("KF lag", LOOP_CYCLES, "lag of the KF estimate behind the raw gyro at the excitation "
                            "frequency, in 1 ms loop cycles (not periods of the excitation); negative = a lead, "
                            "compared by magnitude", kind="lag", magnitude=True),
    "latency_p99_us": Metric("latency p99", "us", "bench side: sample decoded -> DRIVE_CMD written", kind="health"),
    "missed_cycles": Metric("missed loop cycles", "count", "1 ms loop cycles whose sample the bench never saw "
                            "(a count, not a time)", kind="health"),
}


def default_primary(metrics: list[str]) -> list[str]:
    """The metrics a campaign's verdict uses when it names no ``primary_metrics``: those of ``metrics`` (the
    table's columns) of kind ``error``; if it has none, those of kind ``noise`` and ``lag``; never ``effort``
    (drive ripple) or ``health`` (latency, missed cycles). May be empty (then the verdict names no winner)."""
    errors = [m for m in metrics if METRICS[m].kind == "error"]
    return errors or [m for m in metrics if METRICS[m].kind in ("noise", "lag")]


def score(metric: str, value: float) -> float:
    """``value`` as better-or-worse compares it: ``abs(value)`` for a magnitude metric (a lag: a lead of 0.4 loop
    cycles is as far off as a lag of 0.4, and worse than a lag of 0.3), else the value itself."""
    return abs(value) if METRICS[metric].magnitude else value


def gain_pct(value: float, ref: float, lower_is_better: bool = True) -> float:
    """How much better ``value`` is than ``ref``, % of ``ref`` (positive = better); NaN if undefined."""
    if not (math.isfinite(value) and math.isfinite(ref)) or ref == 0:
        return math.nan
    return 100.0 * ((ref - value) if lower_is_better else (value - ref)) / abs(ref)


def improvement_pct(metric: str, value: float, ref: float) -> float:
    """How much better ``value`` is than ``ref`` on ``metric``, % of ``ref`` (positive = better), on the
    :func:`score`: for a lag, ``100 * (|ref| - |value|) / |ref|``, so a lead never counts as more than a lag
    removed (lag 0.63 -> lead -0.36 is +42.9 %, not +157 %; -> lead -0.9 is -42.9 %). NaN if undefined."""
    return gain_pct(score(metric, value), score(metric, ref), METRICS[metric].lower_is_better)


def gap_closed(value: float, baseline: float, oracle: float) -> float:
    """The fraction of the gap from ``baseline`` to ``oracle`` (the best any rate controller could do: the
    ``oracle`` controller, sim clock only) that ``value`` closes: ``(baseline - value) / (baseline - oracle)``.
    0 at the baseline, 1 at the oracle, negative when worse than the baseline, above 1 past the oracle; the same
    formula whichever way the metric improves. NaN when a value is not finite or the gap is zero."""
    gap = baseline - oracle
    if not (math.isfinite(value) and math.isfinite(baseline) and math.isfinite(oracle)) or gap == 0:
        return math.nan
    return (baseline - value) / gap


def _nan_if_empty(x: np.ndarray, f: Any) -> float:
    return float(f(x)) if x.size else math.nan


def peak_per_record(x: np.ndarray, record: int = round(RECORD_S * 1000)) -> float:
    """Median over whole records of ``max |x - mean(record)|`` (the paper's "+-" for noise at rest)."""
    n = x.size // record
    if n == 0:
        return _nan_if_empty(x, lambda v: np.max(np.abs(v - v.mean())))
    rec = x[: n * record].reshape(n, record)
    return float(np.median(np.max(np.abs(rec - rec.mean(axis=1, keepdims=True)), axis=1)))


def low_pass(x: np.ndarray, cutoff_hz: float = PAPER_LPF_HZ, dt_s: float = 1e-3) -> np.ndarray:
    """The bench's own first-order low-pass (hil.control.filters.LowPass1) over a logged channel."""

    f = LowPass1(cutoff_hz=cutoff_hz, dt_s=dt_s)
    f.reset(float(x[0]) if x.size else 0.0)
    return np.fromiter((f.step(float(v)) for v in x), dtype=float, count=x.size)


def lag_cycles(reference: np.ndarray, filtered: np.ndarray, freq_hz: float, dt_s: float = 1e-3) -> float:
    """How many loop cycles (samples of ``dt_s``: 1 ms, so the lag in ms) ``filtered`` lags ``reference`` at
    ``freq_hz``: the phase difference of their single-frequency DFT components over whole periods, divided by
    2 pi f dt (a lag in periods of the excitation is this times ``freq_hz * dt_s``). Negative: a lead."""
    period = 1.0 / (freq_hz * dt_s)
    n = int(math.floor(reference.size / period) * period)
    if n < period:
        return math.nan
    t = np.arange(n) * dt_s
    w = np.exp(-2j * math.pi * freq_hz * t)
    phase = np.angle(np.dot(filtered[:n], w) / np.dot(reference[:n], w))
    return float(-phase / (2 * math.pi * freq_hz * dt_s))


def compute_metrics(path: str | Path, analysis: str = "control", settle_s: float = 1.0, *,
                    data: LogData | None = None) -> dict[str, float]:
    """Every metric of ``analysis`` (plus the control ones) for the session log at ``path`` (``data``: that log
    already read with :func:`hil.log.read_log`)."""
    data = read_log(path) if data is None else data
    s = summarize_log(path, settle_s=settle_s, data=data)
    m: dict[str, float] = {}
    for axis in ("el", "az"):
        m[f"rate_err_{axis}_std_dps"] = s[f"rate_error_{axis}_dps"]["std"]
        m[f"rate_err_{axis}_range_dps"] = s[f"rate_error_{axis}_dps"]["range_pm"]
        m[f"drive_ripple_{axis}_counts"] = s[f"drive_ripple_{axis}_counts"]
    if "miss_x_px" in s:
        for axis in ("x", "y"):
            m[f"miss_{axis}_std_px"] = s[f"miss_{axis}_px"]["std"]
            m[f"miss_{axis}_range_px"] = s[f"miss_{axis}_px"]["range_pm"]
        m["miss_std_px"] = max(m["miss_x_std_px"], m["miss_y_std_px"])
        m["miss_range_px"] = max(m["miss_x_range_px"], m["miss_y_range_px"])
    m["latency_p99_us"] = s["latency_us"]["p99"]
    m["missed_cycles"] = float(s["missed_cycles"])

    loop = data.groups["loop"]
    t = loop["t_s"] - (loop["t_s"][0] if loop["t_s"].size else 0.0)
    config = data.attrs.get("config") or {}
    run_s = float(config.get("duration_s", np.inf))
    keep = (t >= settle_s) & (t < run_s)
    err_y = (loop["rate_cmd_el_dps"] - loop["gyro_y_dps"])[keep].astype(float)
    err_z = (loop["rate_cmd_az_dps"] - loop["gyro_z_dps"])[keep].astype(float)
    m["los_rate_rms_dps"] = _nan_if_empty(err_y, lambda _: np.sqrt(np.mean(err_y**2 + err_z**2)))
    lf_y, lf_z = (low_pass(e, LOS_BAND_HZ) for e in (err_y, err_z))
    m["los_rate_lf_std_dps"] = _nan_if_empty(err_y, lambda _: np.sqrt(np.var(lf_y) + np.var(lf_z)))
    truth = read_truth(path, loop["tick"])  # the sim clock's true LOS rates; None on any other clock
    if truth is not None:
        true_y, true_z = truth
        terr_y = (loop["rate_cmd_el_dps"] - true_y)[keep].astype(float)
        terr_z = (loop["rate_cmd_az_dps"] - true_z)[keep].astype(float)
        m["los_rate_true_rms_dps"] = _nan_if_empty(terr_y, lambda _: np.sqrt(np.mean(terr_y**2 + terr_z**2)))
        tlf_y, tlf_z = (low_pass(e, LOS_BAND_HZ) for e in (terr_y, terr_z))
        m["los_rate_true_lf_std_dps"] = _nan_if_empty(terr_y, lambda _: np.sqrt(np.var(tlf_y) + np.var(tlf_z)))

    raw_all = loop["gyro_y_dps"].astype(float)
    lpf_all = low_pass(raw_all)  # filtered from the start, so the window sees a settled filter
    raw, lpf, kf = raw_all[keep], lpf_all[keep], loop["rate_fb_el_dps"].astype(float)[keep]
    if analysis == "static_noise":
        for name, x in (("raw", raw), ("lpf", lpf), ("kf", kf)):
            m[f"gyro_{name}_peak_dps"] = peak_per_record(x)
            m[f"gyro_{name}_std_dps"] = _nan_if_empty(x, np.std)
    elif analysis == "filter_lag":
        exc = config.get("excitation") or {}
        freq = float(exc.get("freq_hz", math.nan))
        if exc.get("axis", "el") != "el" or not math.isfinite(freq):
            raise ValueError(f"{path}: filter_lag needs a sine excitation on the elevation axis")
        m["lag_lpf_cycles"] = lag_cycles(raw, lpf, freq)
        m["lag_kf_cycles"] = lag_cycles(raw, kf, freq)
    return m


def log_health(path: Path, settle_s: float, u_max: float, *, data: LogData | None = None) -> tuple[float, float | None]:
    """(fraction of the samples with either drive at its limit, fraction of valid tracking frames or None when the
    session did not track) after ``settle_s`` (``data``: the log already read with :func:`hil.log.read_log`)."""
    data = read_log(path) if data is None else data
    loop, image = data.groups["loop"], data.groups.get("image") or {}
    t = loop["t_s"]
    t0 = float(t[0]) if t.size else 0.0
    keep = (t - t0) >= settle_s
    n = int(keep.sum())
    sat = 0.0
    if n:
        at_limit = np.zeros(n, dtype=bool)
        for axis in ("el", "az"):
            at_limit |= np.abs(loop[f"drive_{axis}_counts"][keep].astype(float)) >= u_max - 1.0
        sat = float(at_limit.mean())
    valid = None
    config = data.attrs.get("config") or {}
    tracking = isinstance(config, dict) and bool((config.get("tracking") or {}).get("enabled"))
    if tracking and image and "t_exposure_s" in image and image["t_exposure_s"].size:
        frames = (image["t_exposure_s"] - t0) >= settle_s
        if frames.any():
            valid = float((image["track_valid"][frames] > 0).mean())
    return sat, valid
