"""The motor and its driver as the logs see them: the armature current, the current limit, the torque ripple."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np


def armature_current_a(drive_counts: np.ndarray, rate_dps: np.ndarray, motor: Mapping[str, Any]) -> np.ndarray:
    """The armature current (A) a drive makes at the motor's rate, ``i = (clip(u V_count, bus) - K_e w) / R``, from
    the plant file's motor (``motor_<axis>``); the inductance's lag (L / R ~0.1 ms) left out."""
    volts = np.clip(drive_counts * motor["volts_per_count"], -motor["bus_voltage_v"], motor["bus_voltage_v"])
    return (volts - motor["back_emf_v_s_per_rad"] * np.radians(rate_dps)) / motor["resistance_ohm"]


def drive_at_current_limit(drive_counts: np.ndarray, rate_dps: np.ndarray, motor: Mapping[str, Any],
                           current_limit_a: float) -> tuple[np.ndarray, int]:
    """The drive the plant received where the driver held the current at ``current_limit_a``: on those ticks the drive
    (counts, as a float) whose current is the limit (:func:`armature_current_a` inverted), elsewhere the commanded
    one; and how many ticks were limited. The driver's limit acts inside the power stage, so the log's commanded
    drive is not the plant's input there: a few limited ticks bias an FRF of the command (hidden plant 14: 20 ticks
    at 64 Hz moved k_m by +1 % and read a 355 Hz gyro pole as a pinned 303 +- 15 Hz)."""
    i = armature_current_a(drive_counts, rate_dps, motor)
    limited = np.abs(i) > current_limit_a
    if not limited.any():
        return np.asarray(drive_counts, dtype=float), 0
    held = (np.clip(i, -current_limit_a, current_limit_a) * motor["resistance_ohm"]
            + motor["back_emf_v_s_per_rad"] * np.radians(rate_dps)) / motor["volts_per_count"]
    return np.where(limited, held, drive_counts), int(np.count_nonzero(limited))


def drive_with_ripple(drive_counts: np.ndarray, rate_dps: np.ndarray, angle_deg: np.ndarray,
                      motor: Mapping[str, Any], ripple: Mapping[str, Any]) -> np.ndarray:
    """The drive (counts, as a float) whose current makes the torque the motor made: the plant file's torque ripple
    ``K_t i (1 + a sin(N th_m))`` (docs/emulator.md, "Torque ripple"; ``th_m`` the motor-side angle the encoder
    reads) taken into the drive, ``u + a sin(N th_m) (u - K_e w / V_count)``. Over an ident sweep the axis turns a few
    ripple periods, so the loop's gain wanders by ``+-a`` with the sweep's frequency; read as the plant's, the
    wander moves the gyro's pole and the delay with it (hidden plant 54: the elevation's total delay +4.4 us over
    nine recordings)."""
    a = float(ripple.get("amplitude_fraction") or 0.0)
    u = np.asarray(drive_counts, dtype=float)
    if a == 0.0:
        return u
    n = float(ripple["periods_per_rev"])
    emf_counts = motor["back_emf_v_s_per_rad"] * np.radians(rate_dps) / motor["volts_per_count"]
    return u + a * np.sin(n * np.radians(angle_deg)) * (u - emf_counts)
