#!/usr/bin/env python3
"""What one campaign cell costs in a warm worker, this tree against another checkout, the two alternating in one run.

    .venv/bin/python benchmarks/bench_warm_cell.py [--peer DIR] [--cells 6] [--rounds 2] [--seconds 9] [--json PATH]

Each tree runs, in a process of its own with that tree first on the path, what a warm worker runs per cell
(:func:`hil.campaign.warm.run_cell_here`, then :func:`hil.log.prestart_writer`, as ``serve`` does) on the shipped
``swing-1deg-1hz-eso`` session on the sim clock, shortened to ``--seconds`` (a `hil fit --targets` trial's 9 s by
default): one cell to warm the process, then ``--cells`` timed cells. It reports per cell the wall time and the CPU
time of the process and every process it started (the log writer included, alive or ended), since on a 2-core
machine a study's two workers and their helpers share the CPU, so CPU is what bounds its wall time.

The exit status is non-zero only if a cell fails, never on speed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
SESSION = Path("profiles/sessions/swing-1deg-1hz-eso.yaml")

CHILD = r"""
import json, os, resource, sys, time
import psutil
from hil.campaign.warm import run_cell_here
from hil.log import prestart_writer

session, out, n = sys.argv[1], sys.argv[2], int(sys.argv[3])

def cpu_s():
    own = resource.getrusage(resource.RUSAGE_SELF)
    ended = resource.getrusage(resource.RUSAGE_CHILDREN)
    alive = 0.0
    for p in psutil.Process().children(recursive=True):
        try:
            t = p.cpu_times()
            alive += t.user + t.system
        except psutil.Error:
            pass
    return own.ru_utime + own.ru_stime + ended.ru_utime + ended.ru_stime + alive

def cell(i):
    record = run_cell_here(session, os.path.join(out, f"cell{i}"), analysis=None)
    prestart_writer()
    if record.get("status") != "completed":
        raise SystemExit(f"cell {i}: {record.get('status')}: {record.get('message')}")

prestart_writer()
cell(0)
c0, t0 = cpu_s(), time.perf_counter()
for i in range(1, n + 1):
    cell(i)
print(json.dumps({"cpu_s": (cpu_s() - c0) / n, "wall_s": (time.perf_counter() - t0) / n}))
"""


def session_file(tree: Path, seconds: float, where: Path) -> Path:
    """The tree's shipped session on the sim clock, ``seconds`` long, its paths absolute."""
    path = tree / SESSION
    data = yaml.safe_load(path.read_text())
    for key in ("controller", "profile", "hexapod_limits"):
        data[key] = str((path.parent / data[key]).resolve())
    data["emulator"] = {**data["emulator"], "config": str((path.parent / data["emulator"]["config"]).resolve()),
                        "clock": "sim"}
    data["duration_s"] = seconds
    data["logging"] = {**data.get("logging", {}), "dir": str(where / "runs")}
    out = where / "session.yaml"
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def run_tree(tree: Path, session: Path, cells: int, out: Path) -> dict[str, float]:
    proc = subprocess.run([sys.executable, "-c", CHILD, str(session), str(out), str(cells)], cwd=tree,
                          env={**os.environ, "PYTHONPATH": str(tree)}, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: {proc.stderr.strip()[-2000:] or proc.stdout.strip()[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--peer", type=Path, help="the other checkout (e.g. a worktree of an older commit)")
    ap.add_argument("--cells", type=int, default=6)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=9.0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    trees = {"this tree": ROOT, **({"peer": args.peer.resolve()} if args.peer else {})}
    results: dict[str, list[dict[str, float]]] = {name: [] for name in trees}
    with tempfile.TemporaryDirectory(prefix="hil-warm-cell-") as tmp:
        for r in range(args.rounds):
            for name, tree in reversed(trees.items()):  # the peer first in each round
                where = Path(tmp) / f"{name.replace(' ', '-')}-{r}"
                where.mkdir()
                got = run_tree(tree, session_file(tree, args.seconds, where), args.cells, where)
                results[name].append(got)
                print(f"round {r + 1}, {name} ({tree}): per cell {got['cpu_s']:.3f} s CPU, {got['wall_s']:.3f} s wall",
                      flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
