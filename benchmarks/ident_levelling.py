"""`hil ident` with its defaults on hidden plants (docs/ident.md, "Levelling"): for each seed, a plant drawn inside the
plausible ranges (``hil.fit.ranges.draw_plant``), `hil ident` on each axis as a user runs it (sim clock, no option),
and per axis the coherent band, the passes, the k_m error, and the loop delay against the hidden plant's (the
gyro's lag and delay and the wire's); the first pass's band beside it shows what the levelling added. The session's
controller is the shipped ESO; where `hil ident` refuses it (the loop oscillates by itself on that plant), the row
says so and the next row is PI + LPF, the gentler controller the refusal names.

    .venv/bin/python benchmarks/ident_levelling.py --seeds 21 22 23 24 25 [--axes el az]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

from firmware_stub.config import load_emulator_config
from firmware_stub.plant import DEFAULT_PLANT_CONFIG
from hil import api
from hil.fit.ranges import draw_plant, dump_plant, load_plant_dict
from hil.fit.record import session_on_plant


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[21, 22, 23, 24, 25])
    ap.add_argument("--axes", nargs="+", default=["el", "az"], choices=["el", "az"])
    args = ap.parse_args()
    wire_s = load_emulator_config().drive_delay_s()
    rows = []
    print("| plant | axis | controller | first sweep's band (Hz) | levelled band (Hz) | passes | k_m error | gyro "
          "bandwidth (hidden) | loop delay error | structural mode |")
    print("| --- | --- | --- | --- | --- | ---: | ---: | --- | ---: | ---: |")
    for seed in args.seeds:
        hidden, values = draw_plant(seed, load_plant_dict(DEFAULT_PLANT_CONFIG))
        for axis in args.axes:
            for controller in ("eso", "pi_lpf"):  # the shipped session's ESO; PI + LPF where `hil ident` refuses it
                with tempfile.TemporaryDirectory() as tmp:
                    work = Path(tmp)
                    plant = dump_plant(hidden, work / "hidden.yaml")
                    session = session_on_plant(plant, work, name=f"hidden-{seed}", swing=None, controller=controller)
                    t0 = time.perf_counter()
                    try:
                        done = api.ident(session, axis=axis, clock="sim", out=work / "ident")  # type: ignore[arg-type]
                    except ValueError as exc:
                        print(f"| {seed} | {axis} | {controller} | refused: {str(exc).split(': ', 2)[-1][:90]}... "
                              "| | | | | | |", flush=True)
                        continue
                    seconds = time.perf_counter() - t0
                fit, band = done.fit, done.band_hz
                k_m = values[f"motor_{axis}.k_m_dps2_per_count"]
                bw_hz, gyro_delay_s = values["gyro.bandwidth_hz"], values["gyro.delay_s"]
                true_ms = (1.0 / (2.0 * math.pi * bw_hz) + gyro_delay_s + wire_s) * 1e3
                fitted_ms = fit.model_delay_s * 1e3 + (0.0 if fit.gyro_bandwidth_hz is None
                                                       else 1e3 / (2.0 * math.pi * fit.gyro_bandwidth_hz))
                first = done.passes[0].band_hz
                shown_bw = "above band" if fit.gyro_bandwidth_hz is None else f"{fit.gyro_bandwidth_hz:.0f}"
                rows.append((seed, axis, fit.k_m_dps2_per_count / k_m - 1.0, fitted_ms - true_ms))
                print(f"| {seed} | {axis} | {controller} | {_band(first)} | {_band(band)} | {len(done.passes)} | "
                      f"{(fit.k_m_dps2_per_count / k_m - 1.0) * 100:+.1f} % | {shown_bw} ({bw_hz:.0f}) | "
                      f"{(fitted_ms - true_ms):+.2f} ms | {values[f'structure.{axis}.mode_hz']:.0f} Hz |", flush=True)
                print(f"<!-- {seed} {axis} {controller}: {seconds:.0f} s, {done.report['levelling']} -->", flush=True)
                break
    worst_km = max(abs(r[2]) for r in rows)
    worst_td = max(abs(r[3]) for r in rows)
    print(f"\nworst k_m error {worst_km * 100:.1f} %, worst loop delay error {worst_td:.2f} ms over {len(rows)} sweeps")


def _band(band: tuple[float, float] | None) -> str:
    return "none" if band is None else f"{band[0]:.3g}-{band[1]:.3g}"


if __name__ == "__main__":
    main()
