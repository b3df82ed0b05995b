#!/usr/bin/env python3
"""Speed of the emulator's plant (firmware_stub.plant.Plant) alone, in-process: simulated seconds per wall second.

    .venv/bin/python benchmarks/bench_plant.py [--seconds 5] [--repeat 5] [--json PATH]

Each case runs ``--seconds`` of simulated time (1 ms ticks) ``--repeat`` times on a fresh plant; the table gives
the median and best wall time per tick and the median speed as a multiple of real time. Inputs (drive and carrier
motion) are precomputed, so only ``Plant.step_tick`` is timed (plus the loop that calls it). The garbage collector
is off while the clock runs. Cases:

* at rest: drive 0, the same CarrierMotion object every tick (the carrier is derived once);
* swing: 1 deg / 1 Hz on hexapod pitch and yaw (a new CarrierMotion every tick), a 1 Hz drive on both axes;
* the swing again with a 0.1 ms internal step (10 sub-steps per tick): the difference to the 0.2 ms case is the
  cost of 5 sub-steps, which splits a tick's cost into sub-steps and per-tick work;
* the swing with gyro_dps / encoders_deg / miss_px read every tick, as a board would (miss_px at 100 Hz).

Target (docs/performance.md): >= 200x real time with the default 0.2 ms internal step. Exit status is non-zero
only if a case fails to run, never on speed.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import platform
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

from firmware_stub.plant import DEFAULT_PLANT_CONFIG, CarrierMotion, Plant, PlantConfig, load_plant_config

TICK_S = Plant.TICK_S


def swing(n: int, amplitude_deg: float = 1.0, freq_hz: float = 1.0) -> list[CarrierMotion]:
    """Pitch and yaw ``amplitude_deg`` sine at ``freq_hz``, evaluated at mid-tick."""
    w = 2.0 * math.pi * freq_hz
    out = []
    for k in range(n):
        t = (k + 0.5) * TICK_S
        a = amplitude_deg * math.sin(w * t)
        ad = amplitude_deg * w * math.cos(w * t)
        add = -amplitude_deg * w * w * math.sin(w * t)
        z = (0.0, 0.0, 0.0, 0.0)
        out.append(CarrierMotion((*z, a, a), (*z, ad, ad), (*z, add, add)))
    return out


def drive(n: int) -> list[float]:
    return [2000.0 * math.sin(2.0 * math.pi * k * TICK_S) for k in range(n)]


def run_case(make: Callable[[], Plant], n: int, carriers: list[CarrierMotion], us: list[float],
             read_outputs: bool) -> float:
    """Wall seconds for ``n`` ticks on a fresh plant."""
    plant = make()
    step = plant.step_tick
    gc.disable()
    try:
        t0 = time.perf_counter()
        if read_outputs:
            gyro, enc, miss = plant.gyro_dps, plant.encoders_deg, plant.miss_px
            for k in range(n):
                u = us[k]
                step(u, u, carriers[k])
                gyro()
                enc()
                if k % 10 == 0:
                    miss()
        else:
            for k in range(n):
                u = us[k]
                step(u, u, carriers[k])
        return time.perf_counter() - t0
    finally:
        gc.enable()


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="simulated seconds per run")
    ap.add_argument("--repeat", type=int, default=5, help="runs per case (median and best reported)")
    ap.add_argument("--json", type=str, default=None, help="also write the results here")
    args = ap.parse_args(argv)
    n = round(args.seconds / TICK_S)
    cfg = load_plant_config(DEFAULT_PLANT_CONFIG)
    fine = PlantConfig.model_validate({**cfg.model_dump(), "internal_step_s": 1e-4})
    rest = [CarrierMotion.at_rest()] * n
    sw = swing(n)
    zeros = [0.0] * n
    dr = drive(n)
    cases: dict[str, tuple[PlantConfig, list[CarrierMotion], list[float], bool]] = {
        "at rest, drive 0 (h = 0.2 ms)": (cfg, rest, zeros, False),
        "1 deg/1 Hz pitch+yaw swing, 1 Hz drive (h = 0.2 ms)": (cfg, sw, dr, False),
        "same, h = 0.1 ms (10 sub-steps)": (fine, sw, dr, False),
        "swing + gyro/encoders every tick, miss at 100 Hz": (cfg, sw, dr, True),
    }
    results: dict[str, Any] = {"python": platform.python_version(), "ticks": n, "repeat": args.repeat, "cases": {}}
    print(f"python {platform.python_version()}, {args.seconds:g} simulated s ({n} ticks) per run, "
          f"{args.repeat} runs per case")
    print(f"{'case':52s} {'median us/tick':>15s} {'best us/tick':>13s} {'x real time':>12s}")
    for name, (c, carriers, us, read) in cases.items():
        walls = [run_case(lambda c=c: Plant(c, seed=1), n, carriers, us, read) for _ in range(args.repeat)]
        med, best = statistics.median(walls), min(walls)
        r = {"median_us_per_tick": med / n * 1e6, "best_us_per_tick": best / n * 1e6,
             "x_real_time": n * TICK_S / med}
        results["cases"][name] = r
        print(f"{name:52s} {r['median_us_per_tick']:15.2f} {r['best_us_per_tick']:13.2f} {r['x_real_time']:11.0f}x")
    c = results["cases"]
    coarse = c["1 deg/1 Hz pitch+yaw swing, 1 Hz drive (h = 0.2 ms)"]["median_us_per_tick"]
    sub = (c["same, h = 0.1 ms (10 sub-steps)"]["median_us_per_tick"] - coarse) / 5.0
    results["us_per_sub_step"] = sub
    results["us_per_tick_outside_sub_steps"] = coarse - 5.0 * sub
    rest_us = c["at rest, drive 0 (h = 0.2 ms)"]["median_us_per_tick"]
    print(f"\nwhere the time goes (swing, h = 0.2 ms): 5 sub-steps x {sub:.2f} us = {5 * sub:.2f} us; "
          f"per-tick work {coarse - 5 * sub:.2f} us, of which deriving a new carrier ~{coarse - rest_us:.2f} us")
    x_rt = c["1 deg/1 Hz pitch+yaw swing, 1 Hz drive (h = 0.2 ms)"]["x_real_time"]
    print(f"target >= 200x real time (swing, h = 0.2 ms): {x_rt:.0f}x, {'met' if x_rt >= 200 else 'MISSED'}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=2)
    return results


if __name__ == "__main__":
    main()
    sys.exit(0)
