"""Wall time of a shipped campaign in lockstep with --jobs 1 and --jobs 2 (issue 6 benchmark).

    .venv/bin/python benchmarks/bench_campaign.py [--campaign profiles/campaigns/swing-rate-error.yaml]

Runs the whole campaign twice into temporary directories (no report), once per job count, and prints
the wall time, the simulated seconds per wall second and the speed-up. Each cell is a `hil run
--loopback` process pair (bench + emulator), so on 2 cores two jobs keep four processes busy.
Results go in docs/performance.md.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.campaign import load_campaign, run_campaign  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--campaign", type=Path, default=ROOT / "profiles" / "campaigns" / "swing-rate-error.yaml")
    ap.add_argument("--jobs", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()
    config = load_campaign(args.campaign)
    cells = config.cells()
    sim_s = len(cells) * (config.duration_s or 0.0)
    walls = {}
    for jobs in args.jobs:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            result = run_campaign(config, Path(tmp) / "out", jobs=jobs)
            walls[jobs] = time.perf_counter() - t0
        ok = sum(c.status == "completed" for c in result.cells)
        print(f"--jobs {jobs}: {len(cells)} cells ({ok} completed), {walls[jobs]:.1f} s wall, "
              f"{sim_s / walls[jobs]:.2f} simulated s per wall s, acceptance "
              f"{'PASS' if all(r.passed for r in result.acceptance) else 'FAIL'}")
    if 1 in walls:
        for jobs, wall in walls.items():
            if jobs != 1:
                print(f"speed-up with --jobs {jobs}: {walls[1] / wall:.2f}x")


if __name__ == "__main__":
    main()
