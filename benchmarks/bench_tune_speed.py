#!/usr/bin/env python3
"""A `hil tune` study on this tree against the same study on another checkout (an older commit), one after the other
in one run: wall time, the best trial, and the tuned gains' objective on held-out seeds.

    .venv/bin/python benchmarks/bench_tune_speed.py --peer DIR [--trials 200] [--workers 2] [--no-wire] [--json PATH]

Each tree runs its own ``benchmarks/bench_tune.py`` (the study on ``--campaign``'s cells, then the baseline, the
shipped and the tuned gains on the study's seeds and on held-out seeds 3-5 at 20 s) with the same arguments, as a
process of its own with that tree first on the path. ``--no-wire``: this tree's cells run on an emulated lab with
``links.wire_time: false``, the lab of a checkout from before the wire was modelled, so that both studies tune the
same loop (the peer's campaign file is used as it is).

Targets (docs/performance.md, docs/tuning.md; the peer is commit 526ca0f): at least 5x less wall time for the study,
the best held-out value within 2 % of the peer's. The exit status is non-zero only if a run fails, never on speed.
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

import yaml

ROOT = Path(__file__).resolve().parents[1]
CAMPAIGN = Path("profiles/campaigns/tune-eso-kf-miss-3deg.yaml")


def unwired_campaign(tree: Path, campaign: Path, where: Path) -> Path:
    """``campaign`` of ``tree`` with its paths absolute and its cells on an emulator without the wire's time."""
    path = tree / campaign
    data = yaml.safe_load(path.read_text())
    session_path = (path.parent / data["session"]).resolve()
    session = yaml.safe_load(session_path.read_text())
    emulator_path = (session_path.parent / session["emulator"]["config"]).resolve()
    emulator = yaml.safe_load(emulator_path.read_text())
    emulator["plant"] = str((emulator_path.parent / emulator["plant"]).resolve())
    emulator.setdefault("links", {})["wire_time"] = False
    (where / "emulator.yaml").write_text(yaml.safe_dump(emulator, sort_keys=False))
    data["session"] = str(session_path)
    for p in data["profiles"]:
        p["path"] = str((path.parent / p["path"]).resolve())
    overrides = data.setdefault("overrides", {})
    overrides["emulator"] = {**overrides.get("emulator", {}), "config": str(where / "emulator.yaml")}
    out = where / path.name
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def run_tree(tree: Path, campaign: Path, args: argparse.Namespace, out: Path) -> dict:
    report = out / "bench_tune.json"
    cmd = [sys.executable, str(tree / "benchmarks" / "bench_tune.py"), "--campaign", str(campaign),
           "--trials", str(args.trials), "--workers", str(args.workers), "--seed", str(args.seed),
           "--out", str(out / "study"), "--json", str(report)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=tree, env={**os.environ, "PYTHONPATH": str(tree)}, text=True, check=False)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: bench_tune.py exited {proc.returncode}")
    return {"tree": str(tree), "process_wall_s": wall, **json.loads(report.read_text())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--peer", type=Path, required=True, help="the other checkout (e.g. a worktree of 526ca0f)")
    ap.add_argument("--campaign", type=Path, default=CAMPAIGN, help="relative to each tree")
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-wire", action="store_true", help="this tree's cells without the wire's time")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    runs = {}
    with tempfile.TemporaryDirectory(prefix="hil-tune-speed-") as tmp:
        for name, tree in (("peer", args.peer.resolve()), ("this tree", ROOT)):
            where = Path(tmp) / name.replace(" ", "-")
            where.mkdir()
            campaign = (unwired_campaign(tree, args.campaign, where) if name == "this tree" and args.no_wire
                        else tree / args.campaign)
            runs[name] = run_tree(tree, campaign, args, where)
            print(f"{name}: {json.dumps(runs[name], default=str)[:2000]}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(runs, indent=2, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
