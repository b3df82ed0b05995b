#!/usr/bin/env python3
"""`hil fit --targets` as a whole command: wall time, trials complete and pruned, the best objective.

    .venv/bin/python benchmarks/bench_fit_targets.py [--trials 248] [--targets FILE] [--seed 0] [--peer DIR]
                                                      [--json PATH]

Runs ``python -m hil fit --targets FILE --trials N --json`` in a scratch directory with a study of its own, this tree
first; ``--peer DIR``: then the same command on another checkout (an older commit, say), one after the other in one
run, so both meet the same machine. The peer's options are the ones every tree has (no ``--jobs``): it runs with
its own defaults.

Target (docs/performance.md, "Paper targets"): 248 trials of ``profiles/targets/seed-000.yaml`` in under 10
minutes on 2 cores. The exit status is non-zero only if a run fails, never on speed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARGETS = Path("profiles/targets/seed-000.yaml")


def run_tree(tree: Path, targets: Path, trials: int, seed: int, where: Path) -> dict[str, object]:
    """The command on ``tree`` (first on the path), its outcome and wall time."""
    cmd = [sys.executable, "-m", "hil", "fit", "--targets", str(tree / targets), "--trials", str(trials),
           "--seed", str(seed), "--out", str(where / "plant.yaml"), "--report-dir", str(where), "--study", "bench",
           "--json"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=tree, capture_output=True, text=True, check=False,
                          env={**os.environ, "PYTHONPATH": str(tree)})
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} (in {tree}): exit {proc.returncode}: {proc.stderr.strip()[-600:]}")
    result = json.loads(proc.stdout)
    return {"wall_s": round(wall, 1), "study_wall_s": round(float(result["wall_s"]), 1), "trials": result["trials"],
            "complete": result["complete"], "pruned": result.get("pruned", 0), "failed": result["failed"],
            "best_trial": result["best_trial"], "best_value": result["best_value"],
            "verify_objective": result.get("verify_objective")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=248)
    ap.add_argument("--targets", type=Path, default=TARGETS, help="relative to each tree")
    ap.add_argument("--seed", type=int, default=0, help="the sampler's seed")
    ap.add_argument("--peer", type=Path, help="another checkout, run after this tree")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    runs: dict[str, dict[str, object]] = {}
    trees = [("this tree", ROOT)] + ([("peer", args.peer.resolve())] if args.peer else [])
    with tempfile.TemporaryDirectory(prefix="hil-fit-targets-") as tmp:
        for name, tree in trees:
            where = Path(tmp) / name.replace(" ", "-")
            where.mkdir()
            runs[name] = run_tree(tree, args.targets, args.trials, args.seed, where)
            print(f"{name} ({tree}): {json.dumps(runs[name])}", flush=True)
    print(f"\n{args.trials} trials of {args.targets}:")
    print("| tree | whole command | study | complete / pruned / failed | best objective |")
    print("| --- | ---: | ---: | --- | ---: |")
    for name, r in runs.items():
        print(f"| {name} | {r['wall_s']} s | {r['study_wall_s']} s | {r['complete']} / {r['pruned']} / {r['failed']} "
              f"| {r['best_value']:.4g} (trial {r['best_trial']}) |")
    if args.json:
        args.json.write_text(json.dumps(runs, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
