"""Cells per second: the local engine vs a dask LocalCluster with as many workers, on the sim and lockstep clocks.

    .venv/bin/python benchmarks/bench_engines.py [--campaign profiles/campaigns/swing-rate-error.yaml]
        [--cells 6] [--duration 20] [--workers 2] [--clocks sim lockstep]

The campaign is cut to about ``--cells`` cells of ``--duration`` simulated seconds (seeds 1, 2, ... until the
matrix holds that many) and run into temporary directories (no report), once per engine and clock, the local
engine first. The dask cluster is started once, before the runs, and its start is timed apart: the table's
overhead is the steady state, the wall time of the same cells on the same number of workers (target: <= 10 %).
Every cell's control metrics are compared between the engines (the loop latency aside: the host's own).
Results go in docs/performance.md.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.campaign import load_campaign, run_campaign  # noqa: E402
from hil.campaign.engines import DaskEngine, Engine, LocalEngine  # noqa: E402
from hil.campaign.runner import cell_sessions  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--campaign", type=Path, default=ROOT / "profiles" / "campaigns" / "swing-rate-error.yaml")
    ap.add_argument("--cells", type=int, default=6, help="about this many cells (whole seeds)")
    ap.add_argument("--duration", type=float, default=20.0, help="simulated seconds per cell")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--clocks", nargs="+", choices=["sim", "lockstep"], default=["sim", "lockstep"])
    args = ap.parse_args()
    base = load_campaign(args.campaign)
    per_seed = len(base.profiles) * len(base.controllers)
    seeds = list(range(1, max(1, math.ceil(args.cells / per_seed)) + 1))
    config = base.model_copy(update={"duration_s": args.duration, "seeds": seeds})
    n_cells = len(config.cells())
    sim_s = n_cells * args.duration
    print(f"{config.name}: {n_cells} cells of {args.duration:g} s simulated, {args.workers} workers")

    t0 = time.perf_counter()
    dask = DaskEngine(workers=args.workers).open()
    start_s = time.perf_counter() - t0
    engines: dict[str, Engine] = {"local": LocalEngine(args.workers), "dask": dask}
    rows = []
    try:
        for clock in args.clocks:
            metrics: dict[str, dict[str, dict[str, float]]] = {}
            walls: dict[str, float] = {}
            for name, engine in engines.items():
                with tempfile.TemporaryDirectory() as tmp:
                    out = Path(tmp) / "out"
                    sessions = cell_sessions(config, out, clock=clock)
                    t0 = time.perf_counter()
                    result = run_campaign(config, out, jobs=args.workers, engine=engine, sessions=sessions)
                    walls[name] = time.perf_counter() - t0
                ok = sum(c.status == "completed" for c in result.cells)
                metrics[name] = {c.cell_id: {k: v for k, v in c.metrics.items() if k != "latency_p99_us"}
                                 for c in result.cells}
                over = 100.0 * (walls[name] - walls["local"]) / walls["local"]
                rows.append((clock, name, f"{ok}/{n_cells}", walls[name], n_cells / walls[name], sim_s / walls[name],
                             "" if name == "local" else f"{over:+.1f} %"))
            same = metrics["local"] == metrics["dask"]
            rows.append((clock, "same metrics", "yes" if same else "NO", math.nan, math.nan, math.nan, ""))
    finally:
        dask.close()

    print(f"dask LocalCluster start ({args.workers} workers): {start_s:.1f} s (not in the times below)")
    print(f"{'clock':9} {'engine':13} {'cells ok':>8} {'wall s':>8} {'cells/s':>8} {'sim s/s':>8} {'overhead':>9}")
    for clock, name, ok, wall, rate, speed, over in rows:
        if math.isnan(wall):
            print(f"{clock:9} {name:13} {ok:>8}")
            continue
        print(f"{clock:9} {name:13} {ok:>8} {wall:8.1f} {rate:8.3f} {speed:8.2f} {over:>9}")


if __name__ == "__main__":
    main()
