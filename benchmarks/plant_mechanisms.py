#!/usr/bin/env python3
"""What each plant mechanism does to the closed loop: the table behind docs/emulator.md ("Mechanisms in the loop").

    .venv/bin/python benchmarks/plant_mechanisms.py [--seconds 6] [--seeds 1 2] [--out docs/plant-mechanisms.md]

Starts from profiles/plant/rigid.yaml and switches on one mechanism at a time, with the values of
profiles/plant/default.yaml and, for most, once more at the stressed end of its plausible range (then all of
them: default.yaml itself). Each variant runs the shipped swing session (tracking on) at 1 deg and 3 deg / 1 Hz
with the plain ESO, and at 1 deg with ESO+KF at the same observer gain, on the ``sim`` clock (hil.session._sim), and
reports per variant (median over the seeds):

- miss std at 1 and 3 deg and their ratio (a torque-authority limit makes the miss grow with the swing);
- the elevation rate error std of the plain ESO, and how much ESO+KF at the same gain improves it (seed 000's
  premise: gyro noise limits the observer gain);
- the plain ESO's drive ripple (a structural mode is excited by it) and its peak drive at 3 deg (authority);
- the rms rate error within 20 ms of a reversal of the gimbal's rate relative to the carrier (friction);
- the LOS rate error below 20 Hz (the carrier-disturbance band, without the gyro's white noise).

Everything is measured, nothing is fitted; the numbers depend on the seeds given.
"""

from __future__ import annotations

import argparse
import asyncio
import copy
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.campaign.metrics import compute_metrics
from hil.config import PROFILES, SessionConfig, load_session
from hil.log.reader import read_log
from hil.session import run_sim_session

PLANTS = PROFILES / "plant"
# variant -> (what it shows, patch over rigid.yaml). "typical" patches take default.yaml's section; the others
# put the mechanism at the stressed end of its plausible range (docs/emulator.md, "Mechanisms").
TYPICAL = "typical"
VARIANTS: dict[str, dict[str, Any]] = {
    "rigid (every mechanism off)": {},
    "structure, typical (250 / 300 Hz, zeta 0.05)": {"structure": TYPICAL},
    "structure, 110 Hz el / 150 Hz az, zeta 0.03": {"structure": {
        "az": {"mode_hz": 150.0, "damping_ratio": 0.03, "motor_inertia_fraction": 0.3},
        "el": {"mode_hz": 110.0, "damping_ratio": 0.03, "motor_inertia_fraction": 0.3}}},
    "LuGre friction, typical (stiction 1.25-1.28 x Coulomb)": {"friction": TYPICAL},
    "LuGre friction, stiction = Coulomb (presliding only)": {"friction": "lugre:1.0"},
    "LuGre friction, stiction 1.5 x Coulomb": {"friction": "lugre:1.5"},
    "current limit, typical (3 A az / 2 A el)": {"drive": TYPICAL},
    "current limit, 1.8 A az / 1.2 A el": {"drive": {"az": {"current_limit_a": 1.8}, "el": {"current_limit_a": 1.2}}},
    "cable, typical (1 / 0.5 N m/rad)": {"cable": TYPICAL},
    "cable, 5 N m/rad": {"cable": {"az": {"stiffness_n_m_per_rad": 5.0, "damping_n_m_s_per_rad": 0.05},
                                   "el": {"stiffness_n_m_per_rad": 5.0, "damping_n_m_s_per_rad": 0.05}}},
    "pivot, typical (0.25 m above the centre)": {"mount": TYPICAL},
    "pivot, 0.5 m above the centre": {"mount": {"pivot_offset_m": [0.0, 0.0, -0.5]}},
    "coloured gyro noise, typical": {"gyro": TYPICAL},
    "torque ripple, typical (2 %)": {"ripple": TYPICAL},
    "torque ripple, 5 %": {"ripple": {"az": {"amplitude_fraction": 0.05, "periods_per_rev": 64},
                                      "el": {"amplitude_fraction": 0.05, "periods_per_rev": 48}}},
    "default.yaml (every mechanism, typical)": {"*": TYPICAL},
}
SETTLE_S = 1.5
REVERSAL_WINDOW_S = 0.02


def plant_variant(patch: dict[str, Any]) -> dict[str, Any]:
    rigid = yaml.safe_load((PLANTS / "rigid.yaml").read_text())
    typical = yaml.safe_load((PLANTS / "default.yaml").read_text())
    if "*" in patch:
        return typical
    out = copy.deepcopy(rigid)
    for key, value in patch.items():
        if isinstance(value, str) and value.startswith("lugre:"):  # typical LuGre with another stiction ratio
            section = copy.deepcopy(typical["friction"])
            for axis in section.values():
                axis["stiction_n_m"] = axis["coulomb_n_m"] * float(value.split(":")[1])
            out[key] = section
        else:
            out[key] = typical[key] if value == TYPICAL else value
    if "structure" in patch and "friction" not in patch:  # the tanh model's numerical smoothing must suit the
        for axis in out["friction"].values():             # lighter motor side (PlantConfig says how much)
            axis["smoothing_rate_dps"] = max(axis["smoothing_rate_dps"], 0.25)
    return out


def reversal_rms_dps(log: Path) -> float:
    """rms elevation rate error within REVERSAL_WINDOW_S of a reversal of the gimbal's rate relative to the
    carrier (from the encoder), after SETTLE_S: where friction changes sign."""
    loop = read_log(log).groups["loop"]
    t = np.asarray(loop["t_s"], float)
    t = t - t[0]
    el = np.asarray(loop["el_deg"], float)
    err = np.asarray(loop["rate_err_el_dps"], float)
    keep = t >= SETTLE_S
    rate = np.gradient(np.convolve(el, np.ones(20) / 20, mode="same"), t)
    flips = np.flatnonzero(np.diff(np.sign(rate)) != 0)
    near = np.zeros_like(keep)
    for i in flips:
        near |= np.abs(t - t[i]) <= REVERSAL_WINDOW_S
    a = err[keep & near]
    return float(np.sqrt(np.mean(a * a))) if len(a) >= 10 else float("nan")


def run(config: SessionConfig, out: Path) -> dict[str, float]:
    result, _ = asyncio.run(run_sim_session(config, out))
    if result.status != "completed" or result.log_path is None:
        return {"status_fault": 1.0}
    m = compute_metrics(result.log_path, "control", SETTLE_S)
    m["reversal_rms_dps"] = reversal_rms_dps(result.log_path)
    loop = read_log(result.log_path).groups["loop"]
    m["drive_el_peak_counts"] = float(np.max(np.abs(np.asarray(loop["drive_el_counts"], float))))
    return m


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--out", type=Path, default=None, help="also write the table (Markdown) here")
    args = ap.parse_args()
    base = load_session(PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml")
    rows = []
    with tempfile.TemporaryDirectory(prefix="plant-mech-") as tmp_s:
        tmp = Path(tmp_s)
        for label, patch in VARIANTS.items():
            plant = tmp / f"plant-{len(rows)}.yaml"
            plant.write_text(yaml.safe_dump(plant_variant(patch)))
            emu = yaml.safe_load((PROFILES / "emulator" / "default.yaml").read_text())
            emu["plant"] = str(plant)
            emu_path = tmp / f"emulator-{len(rows)}.yaml"
            emu_path.write_text(yaml.safe_dump(emu))
            cells: dict[tuple[str, str], list[dict[str, float]]] = {}
            for controller, swing in (("eso", "swing-1deg-1hz"), ("eso", "swing-3deg-1hz"),
                                      ("eso_kf", "swing-1deg-1hz")):
                for seed in args.seeds:
                    data = base.model_dump(mode="json")
                    data.update(duration_s=args.seconds, seed=seed, controller={"name": controller, "params": {}},
                                profile=str(PROFILES / "swing" / f"{swing}.yaml"),
                                emulator={**data["emulator"], "config": str(emu_path), "clock": "sim"})
                    cfg = SessionConfig.model_validate(data)
                    cells.setdefault((controller, swing), []).append(run(cfg, tmp / "logs"))

            def med(controller: str, swing: str, metric: str, cells=cells) -> float:
                return statistics.median(c.get(metric, float("nan")) for c in cells[(controller, swing)])

            faults = sum(int(c.get("status_fault", 0)) for v in cells.values() for c in v)
            one, three = "swing-1deg-1hz", "swing-3deg-1hz"
            m1, m3 = med("eso", one, "miss_std_px"), med("eso", three, "miss_std_px")
            e_eso, e_kf = med("eso", one, "rate_err_el_std_dps"), med("eso_kf", one, "rate_err_el_std_dps")
            rows.append([label, f"{m1:.2f}", f"{m3:.2f}", f"{m3 / m1:.2f}", f"{e_eso:.3f}",
                         f"{100 * (1 - e_kf / e_eso):.0f} %", f"{med('eso', one, 'drive_ripple_el_counts'):.0f}",
                         f"{med('eso', three, 'drive_el_peak_counts'):.0f}",
                         f"{med('eso', one, 'reversal_rms_dps'):.3f}",
                         f"{med('eso', one, 'los_rate_lf_std_dps'):.4f}", str(faults)])
            print(" | ".join(rows[-1]), flush=True)
    head = ["plant", "miss std 1 deg (px)", "miss std 3 deg (px)", "3 / 1 deg", "EL rate err std, ESO (deg/s)",
            "ESO+KF vs ESO (same gain), EL rate err std", "EL drive ripple, ESO (counts)",
            "EL drive peak, ESO 3 deg (counts)", "EL rate err rms at reversals, ESO (deg/s)",
            "LOS rate std < 20 Hz, ESO (deg/s)", "faulted runs"]
    table = "\n".join(["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
                      + ["| " + " | ".join(r) + " |" for r in rows])
    print()
    print(table)
    if args.out:
        args.out.write_text(f"Seeds {args.seeds}, {args.seconds:g} s sessions, first {SETTLE_S:g} s left out; "
                            f"`python benchmarks/plant_mechanisms.py --seconds {args.seconds:g} --seeds "
                            f"{' '.join(map(str, args.seeds))}`.\n\n{table}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
