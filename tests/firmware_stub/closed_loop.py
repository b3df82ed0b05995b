"""Closed-loop harness for calibrating the plant: plant + a registry controller per axis, in-process, no ptys.

    .venv/bin/python -m tests.firmware_stub.closed_loop [--seconds 10] [--seed 1]

prints the calibration table of docs/emulator.md: static gyro peak, and the rate error of each controller under the
paper's 1 deg / 1 Hz swing (seed 000 Table 1).

Per 1 ms tick k: read the gyro sample of t_k, step the controllers with rate command 0 (elevation loop on gyro y,
azimuth loop on gyro z, the cross-elevation axis), apply their drive over [t_k, t_k+1] with the carrier evaluated
at mid-tick. The rate error is the measured gyro rate (what the paper plots as "speed fluctuation"); the true
inertial LOS rate is reported beside it.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

import numpy as np

from firmware_stub.plant import DEFAULT_PLANT_CONFIG, CarrierMotion, Plant, PlantConfig, load_plant_config
from hil.control.registry import build_controller

PAPER_TABLE1 = {"eso": (0.32, 0.72), "eso_kf": (0.17, 0.28), "eso_kf_high_gain": (0.11, 0.19)}  # std, +- range


def swing_carrier(t_s: float, amplitude_deg: float, freq_hz: float, pitch: bool, yaw: bool) -> CarrierMotion:
    """Hexapod sine on pitch and/or yaw, ``amplitude_deg`` at ``freq_hz``, at time ``t_s``."""
    w = 2.0 * math.pi * freq_hz
    a = amplitude_deg * math.sin(w * t_s)
    ad = amplitude_deg * w * math.cos(w * t_s)
    add = -amplitude_deg * w * w * math.sin(w * t_s)
    py, yy = (1.0 if pitch else 0.0), (1.0 if yaw else 0.0)
    return CarrierMotion(
        (0.0, 0.0, 0.0, 0.0, a * py, a * yy),
        (0.0, 0.0, 0.0, 0.0, ad * py, ad * yy),
        (0.0, 0.0, 0.0, 0.0, add * py, add * yy),
    )


@dataclass(frozen=True)
class AxisStats:
    std_dps: float  # std of the measured gyro rate (the rate error, command 0)
    range_dps: float  # half the peak-to-peak: the paper's "+-" value
    true_std_dps: float  # std of the true inertial LOS rate
    true_range_dps: float
    drive_std_counts: float


def _stats(meas: np.ndarray, true: np.ndarray, drive: np.ndarray) -> AxisStats:
    return AxisStats(
        std_dps=float(np.std(meas)),
        range_dps=float(np.ptp(meas) / 2.0),
        true_std_dps=float(np.std(true)),
        true_range_dps=float(np.ptp(true) / 2.0),
        drive_std_counts=float(np.std(drive)),
    )


def run_closed_loop(
    controller: str,
    *,
    config: PlantConfig | None = None,
    seconds: float = 6.0,
    settle_s: float = 1.0,
    amplitude_deg: float = 1.0,
    freq_hz: float = 1.0,
    pitch: bool = True,
    yaw: bool = True,
    seed: int = 1,
) -> dict[str, AxisStats]:
    """Run both axes closed-loop (rate command 0) under the swing; statistics over ``seconds`` after ``settle_s``.

    Returns ``{"el": AxisStats, "az": AxisStats}``.
    """
    cfg = config or load_plant_config(DEFAULT_PLANT_CONFIG)
    plant = Plant(cfg, seed=seed)
    c_el, c_az = build_controller(controller, {}), build_controller(controller, {})
    n_settle, n = round(settle_s / Plant.TICK_S), round(seconds / Plant.TICK_S)
    rec = np.empty((n, 6))
    for k in range(n_settle + n):
        _, gy, gz = plant.gyro_dps()
        if k >= n_settle:
            tr = plant.truth()
            rec[k - n_settle] = (gy, tr["los_rate_y_dps"], c_el.u_counts, gz, tr["los_rate_z_dps"], c_az.u_counts)
        u_el = c_el.step(0.0, gy)
        u_az = c_az.step(0.0, gz)
        plant.step_tick(u_az, u_el, swing_carrier((k + 0.5) * Plant.TICK_S, amplitude_deg, freq_hz, pitch, yaw))
    return {"el": _stats(rec[:, 0], rec[:, 1], rec[:, 2]), "az": _stats(rec[:, 3], rec[:, 4], rec[:, 5])}


def static_gyro_peak(config: PlantConfig | None = None, *, records: int = 20, seed: int = 1) -> dict[str, float]:
    """Static gyro (no motion, drive 0): per 1 s record (1000 samples) the peak ``max |x - mean(x)|`` of the raw
    elevation gyro; returns the median peak over ``records`` records and the overall std."""
    cfg = config or load_plant_config(DEFAULT_PLANT_CONFIG)
    plant = Plant(cfg, seed=seed)
    rest = CarrierMotion.at_rest()
    ys = np.empty(records * 1000)
    for k in range(ys.size):
        plant.step_tick(0.0, 0.0, rest)
        ys[k] = plant.gyro_dps()[1]
    rec = ys.reshape(records, 1000)
    peaks = np.max(np.abs(rec - rec.mean(axis=1, keepdims=True)), axis=1)
    return {"peak_dps": float(np.median(peaks)), "std_dps": float(np.std(rec - rec.mean(axis=1, keepdims=True))),
            "half_ptp_dps": float(np.median(np.ptp(rec, axis=1) / 2.0))}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    st = static_gyro_peak(seed=args.seed)
    print(f"static gyro (el axis, 1 s records): peak max|x - mean| {st['peak_dps']:.3f} deg/s (paper +-0.102), "
          f"half peak-to-peak {st['half_ptp_dps']:.3f}, std {st['std_dps']:.4f}")
    print(f"\n1 deg / 1 Hz pitch + yaw swing, rate command 0, {args.seconds:g} s after 1 s settling (deg/s):")
    print(f"{'controller':18s} {'axis':4s} {'std':>6s} {'+-range':>8s} {'paper std':>9s} {'paper +-':>8s} "
          f"{'true std':>8s} {'true +-':>8s} {'drive std':>9s}")
    for name, (pstd, prange) in PAPER_TABLE1.items():
        res = run_closed_loop(name, seconds=args.seconds, seed=args.seed)
        for axis, s in res.items():
            print(f"{name:18s} {axis:4s} {s.std_dps:6.3f} {s.range_dps:8.3f} {pstd:9.2f} {prange:8.2f} "
                  f"{s.true_std_dps:8.3f} {s.true_range_dps:8.3f} {s.drive_std_counts:9.0f}")


if __name__ == "__main__":
    main()
