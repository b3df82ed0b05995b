#!/usr/bin/env python3
"""What the wire costs the shipped controllers (docs/emulator.md, "What the wire costs the controllers").

    .venv/bin/python benchmarks/wire_costs.py [--seconds 8] [--seed 1] [--json PATH]

For each plant (the default and the paper preset) and each shipped controller (profiles/controllers/*.yaml), three
labs: the wire off (``links.wire_time: false``), the wire at 921 600 baud and at 2 000 000 baud. Each lab runs two
sim sessions of the shipped swing session (``profiles/sessions/swing-1deg-1hz-eso[-paper-000].yaml``, seed 1):

- the swing with tracking, ``--seconds`` long: the elevation rate error's std (deg/s) and the miss distance's std
  (px, both axes) over the last half, and whether the loop stays stable: the run completes without a fault, the
  drive is saturated in under 1 % of the ticks, and the rate error's rms over the last quarter is under 2 deg/s
  and at most twice that of the second quarter (an oscillation that grows fails it);
- the platform at rest with a 100 Hz, 2 deg/s sine on the elevation rate command: the phase of the elevation
  rate loop at 100 Hz, from the rate command (the sine included) to the gyro (deg, negative: lag), and of the
  plant with its wire, from the drive to the gyro.

With ``--campaigns``: the shipped campaigns (profiles/campaigns/, the tuning studies left out) run twice, on their
own lab with the wire and without it, and each verdict (every cell's thresholds, every acceptance rule) is printed
side by side with the primary metrics' means.

Runs in one process on the sim clock (the same world as lockstep). Exit status non-zero only if a run cannot start.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.campaign import load_campaign, run_campaign
from hil.config import PROFILES, SessionConfig, load_session, read_yaml_mapping
from hil.protocol import LINE_RATE_BAUD
from hil.session import emulator_for_plant, run

PLANTS = {"default": ("swing-1deg-1hz-eso.yaml", "default.yaml"),
          "paper-000": ("swing-1deg-1hz-eso-paper-000.yaml", "paper-000.yaml")}
U_MAX = 32767


def lab_file(tmp: Path, emulator: str, wire: bool) -> Path:
    """The shipped emulator config ``emulator`` with the wire on or off."""
    base = PROFILES / "emulator" / emulator
    plant = base.parent / read_yaml_mapping(base)["plant"]
    return emulator_for_plant(plant, tmp, base=base, wire_time=wire)


def config(session: str, controller: Path, lab: Path, *, baud: int, seconds: float, seed: int,
           **fields: Any) -> SessionConfig:
    data = load_session(PROFILES / "sessions" / session).model_dump()
    ports = {n: {"port": f"/dev/emulated-{n}", "baudrate": baud} for n in ("servo", "driver", "image", "hexapod")}
    data.update(duration_s=seconds, seed=seed, controller=str(controller), ports=ports,
                emulator={**data["emulator"], "config": lab, "clock": "sim"}, **fields)
    return SessionConfig.model_validate(data)


def phase_deg(x: np.ndarray, y: np.ndarray, freq_hz: float) -> float:
    n = len(x) - len(x) % round(1000 / freq_hz)
    e = np.exp(-2j * np.pi * freq_hz * np.arange(n) / 1000.0)
    return float(np.degrees(np.angle(np.sum(y[:n] * e) / np.sum(x[:n] * e))))


def swing(cfg: SessionConfig, out: Path) -> dict[str, Any]:
    result = run(cfg, clock="sim", out=out)
    row: dict[str, Any] = {"status": result.status}
    if result.log_path is None:
        return {**row, "stable": False}
    loop, image = result.log.loop, result.log.image
    n = len(loop)
    err = loop["rate_err_el_dps"].to_numpy()
    drive = loop[["drive_az_counts", "drive_el_counts"]].to_numpy()
    q = n // 4
    rms = [float(np.sqrt(np.mean(err[a:b] ** 2))) if b > a else float("nan") for a, b in ((q, 2 * q), (3 * q, n))]
    saturated = float(np.mean(np.abs(drive) >= U_MAX - 1)) if n else 1.0
    half = image.iloc[len(image) // 2:]
    row.update(rate_err_el_std_dps=float(np.std(err[n // 2:])) if n else float("nan"),
               miss_std_px=float(np.hypot(half["miss_x_px"].std(), half["miss_y_px"].std())) if len(half) else None,
               saturated=saturated, rms_q2_dps=rms[0], rms_q4_dps=rms[1])
    row["stable"] = bool(result.status == "completed" and saturated < 0.01 and rms[1] < 2.0 and rms[1] <= 2 * rms[0])
    return row


def phases(cfg: SessionConfig, out: Path) -> dict[str, Any]:
    result = run(cfg, clock="sim", out=out)
    if result.log_path is None or result.status != "completed":
        return {"loop_phase_100hz_deg": None, "plant_phase_100hz_deg": None}
    loop = result.log.loop.iloc[500:]
    gyro = loop["gyro_y_dps"].to_numpy()
    return {"loop_phase_100hz_deg": phase_deg(loop["rate_cmd_el_dps"].to_numpy(), gyro, 100.0),
            "plant_phase_100hz_deg": phase_deg(loop["drive_el_counts"].to_numpy(float), gyro, 100.0)}


def campaigns(tmp: Path, jobs: int) -> list[dict[str, Any]]:
    """Each shipped campaign with the wire and without it: its verdicts and primary metrics."""
    rows = []
    for path in sorted((PROFILES / "campaigns").glob("*.yaml")):
        if path.stem.startswith("tune-"):
            continue
        base = load_campaign(path)
        session = load_session(base.session)
        for wire in (True, False):
            lab = lab_file(tmp, Path(session.emulator.config).name, wire)
            emulator = {**base.overrides.get("emulator", {}), "config": str(lab)}
            cfg = base.model_copy(update={"overrides": {**base.overrides, "emulator": emulator}})
            result = run_campaign(cfg, tmp / f"{path.stem}-{'wire' if wire else 'nowire'}", jobs=jobs)
            means = {f"{p.label} / {c.label} / {m}": result.mean(p.label, c.label, m)
                     for p in cfg.profiles for c in cfg.controllers for m in cfg.verdict_metrics}
            row = {"campaign": path.stem, "wire": wire, "passed": result.passed,
                   "cells_failed": [f"{c.cell_id}: {'; '.join(c.failures) or c.status}" for c in result.cells
                                    if not c.passed],
                   "rules": {r.rule: r.passed for r in result.acceptance}, "means": means}
            rows.append(row)
            print(json.dumps(row), flush=True)
    print("\n| campaign | verdict, wire on | verdict, wire off | what differs |")
    print("| --- | --- | --- | --- |")
    for on, off in zip(rows[::2], rows[1::2], strict=True):
        differs = [r for r in on["rules"] if on["rules"][r] != off["rules"].get(r)]
        differs += [f"cells failed: {', '.join(on['cells_failed'])}" for _ in [0] if on["cells_failed"]]
        print(f"| {on['campaign']} | {'pass' if on['passed'] else 'FAIL'} | {'pass' if off['passed'] else 'FAIL'} | "
              f"{'; '.join(differs) or '-'} |")
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--campaigns", action="store_true", help="the shipped campaigns' verdicts, wire on and off")
    ap.add_argument("--jobs", type=int, default=2, help="--campaigns: cells at once")
    ap.add_argument("--bauds", default="921600,2000000",
                    help="the labs with the wire on, by line rate, comma-separated (the wire off is always one)")
    ap.add_argument("--controllers", default="", help="only these shipped controllers (file stems, comma-separated)")
    ap.add_argument("--plants", default=",".join(PLANTS), help="only these plants")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    labs = {"off": (False, LINE_RATE_BAUD), **{b: (True, int(b)) for b in args.bauds.split(",") if b}}
    chosen = {c for c in args.controllers.split(",") if c}
    if args.campaigns:
        with tempfile.TemporaryDirectory() as tmp_dir:
            found = campaigns(Path(tmp_dir), args.jobs)
        if args.json:
            args.json.write_text(json.dumps(found, indent=1))
        return 0
    rows = []
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        for plant, (session, emulator) in PLANTS.items():
            if plant not in args.plants.split(","):
                continue
            for controller in sorted((PROFILES / "controllers").glob("*.yaml")):
                if chosen and controller.stem not in chosen:
                    continue
                for lab, (wire, baud) in labs.items():
                    path = lab_file(tmp, emulator, wire)
                    out = tmp / f"{plant}-{controller.stem}-{lab}"
                    row = {"plant": plant, "controller": controller.stem, "wire": lab}
                    row.update(swing(config(session, controller, path, baud=baud, seconds=args.seconds, seed=args.seed),
                                     out / "swing"))
                    row.update(phases(config(session, controller, path, baud=baud, seconds=3.0, seed=args.seed,
                                             profile=str(PROFILES / "swing" / "static.yaml"),
                                             tracking={"enabled": False},
                                             excitation={"axis": "el", "amplitude_dps": 2.0, "freq_hz": 100.0}),
                                      out / "sine"))
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    print("\n| plant | controller | wire | rate loop phase at 100 Hz | plant phase at 100 Hz | rate err el std | "
          "miss std | stable |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        def f(v: Any, fmt: str) -> str:
            return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, fmt)
        print(f"| {r['plant']} | {r['controller']} | {r['wire']} | {f(r['loop_phase_100hz_deg'], '.1f')} deg | "
              f"{f(r['plant_phase_100hz_deg'], '.1f')} deg | {f(r.get('rate_err_el_std_dps'), '.3f')} deg/s | "
              f"{f(r.get('miss_std_px'), '.2f')} px | {'yes' if r['stable'] else 'NO'} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
