"""Acceptance of ``hil fit`` on hidden plants (docs/fit.md, "Hidden plants"): for each seed, a plant drawn inside
the documented ranges (``hil.fit.ranges.draw_plant``), the logs a lab would record on it (static, an ident sweep per
axis, 1 and 3 deg swings; ``hil.fit.record``), the fit, then per parameter the error against the hidden value and
the acceptance campaign (ESO, ESO+KF, high-gain ESO+KF at 1 and 3 deg) on the hidden plant and on the twin.

    .venv/bin/python benchmarks/fit_hidden_plants.py --seeds 11 12 13 [--out runs/fit-hidden] [--campaign-s 10]
        [--no-level]   (the ident sweeps run once as planned, not levelled as `hil ident` and `hil fit --record` do)
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from firmware_stub.plant import DEFAULT_PLANT_CONFIG
from hil.fit.ranges import draw_plant, dump_plant, get_param, load_plant_dict
from hil.fit.record import campaign_on_plant, record_platform_logs
from hil.fit.twin import fit_logs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[11, 12, 13])
    ap.add_argument("--out", type=Path, default=Path("runs/fit-hidden"))
    ap.add_argument("--campaign-s", type=float, default=10.0)
    ap.add_argument("--campaign-seeds", type=int, nargs="+", default=[1])
    ap.add_argument("--no-level", action="store_true", help="record each ident sweep once, as planned (not levelled)")
    args = ap.parse_args()
    base = load_plant_dict(DEFAULT_PLANT_CONFIG)
    summary = []
    for seed in args.seeds:
        t0 = time.perf_counter()
        work = args.out / f"plant-{seed}"
        hidden, _ = draw_plant(seed, base)
        hidden_path = dump_plant(hidden, work / f"hidden-{seed}.yaml", f"hidden plant, draw_plant({seed})")
        logs = record_platform_logs(hidden_path, work / "logs", level=not args.no_level)
        fit = fit_logs(logs)
        twin_path = fit.write(work / f"twin-{seed}.yaml")
        print(f"\n== plant {seed}: {len(logs)} logs, fit in {time.perf_counter() - t0:.0f} s")
        params = []
        for e in fit.estimates:
            true = get_param(hidden, e.name)
            err = (e.value / true - 1.0) if (e.value is not None and true not in (None, 0.0)) else math.nan
            params.append({"name": e.name, "status": e.status, "fitted": e.value, "sigma": e.sigma, "hidden": true,
                           "error": err})
            print(f"{e.name:40s} {e.status:6s} fitted {e.value!s:>22} hidden {true!s:>22} {err * 100:+7.1f} %")
        hid = campaign_on_plant(hidden_path, work / "on-hidden", seeds=tuple(args.campaign_seeds),
                                duration_s=args.campaign_s)
        twn = campaign_on_plant(twin_path, work / "on-twin", seeds=tuple(args.campaign_seeds),
                                duration_s=args.campaign_s)
        cells = []
        for key, h in hid.items():
            ratio = twn[key] / h if h else math.nan
            cells.append({"profile": key[0], "controller": key[1], "metric": key[2], "hidden": h, "twin": twn[key],
                          "ratio": ratio})
            print(f"{key[0]:14s} {key[1]:18s} {key[2]:22s} hidden {h:9.4f} twin {twn[key]:9.4f}  x{ratio:.3f}")
        worst = max(abs(c["ratio"] - 1.0) for c in cells)
        print(f"plant {seed}: worst campaign metric {worst * 100:.1f} % off; total {time.perf_counter() - t0:.0f} s")
        summary.append({"seed": seed, "params": params, "campaign": cells, "worst": worst,
                        "logs": [str(p) for p in logs]})  # the logs the fit read: refit them with hil fit
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1, default=str), encoding="utf-8")
    print()
    print(markdown(summary))


def markdown(summary: list[dict]) -> str:
    """The docs/fit.md table: per parameter and plant, the error of the fitted or weak value (or its status), then the
    campaign's worst metric."""
    seeds = [s["seed"] for s in summary]
    names = [p["name"] for p in summary[0]["params"]]
    lines = ["| parameter | " + " | ".join(f"plant {s}" for s in seeds) + " |",
             "| --- |" + " ---: |" * len(seeds)]
    for name in names:
        cells = []
        for s in summary:
            p = next(q for q in s["params"] if q["name"] == name)
            if p["status"] not in ("fitted", "weak"):
                cells.append(p["status"])
            elif p["error"] is None or not math.isfinite(p["error"]):
                cells.append("-")
            else:
                cells.append(f"{p['error'] * 100:+.1f} %" + (" (weak)" if p["status"] == "weak" else ""))
        lines.append(f"| `{name}` | " + " | ".join(cells) + " |")
    lines.append("| **total loop delay (gyro lag + delay; the wire's is the same in both)** | "
                 + " | ".join(_total_delay_error(s) for s in summary) + " |")
    worst = []
    for s in summary:
        c = max(s["campaign"], key=lambda c: abs(c["ratio"] - 1.0))
        worst.append(f"{(c['ratio'] - 1.0) * 100:+.1f} % ({c['controller']}, {c['profile']}, {c['metric']})")
    lines.append("| **campaign: worst metric, twin vs hidden** | " + " | ".join(worst) + " |")
    return "\n".join(lines)


def _total_delay_error(plant: dict) -> str:
    """The fitted loop delay against the hidden one: ``1 / (2 pi bandwidth) + delay``, in microseconds."""
    p = {q["name"]: q for q in plant["params"]}

    def total(key: str) -> float:
        return 1.0 / (2.0 * math.pi * float(p["gyro.bandwidth_hz"][key])) + float(p["gyro.delay_s"][key])

    return f"{(total('fitted') - total('hidden')) * 1e6:+.0f} us"


if __name__ == "__main__":
    main()
