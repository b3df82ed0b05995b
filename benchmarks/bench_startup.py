#!/usr/bin/env python3
"""A whole `hil run` process on the sim clock against the same session on lockstep, side by side in one run.

    .venv/bin/python benchmarks/bench_startup.py [--seconds 20] [--repeat 5] [--session FILE] [--peer DIR] [--json PATH]

Each round runs, one after the other, ``python -m hil run SESSION --loopback --clock lockstep --json`` and the same
with ``--clock sim``, as whole processes (interpreter start, imports, the emulator's start for lockstep, the
session, the log, the summary), and ``python -c "import hil.cli, hil.session"`` (the import floor). ``--peer DIR``:
another checkout of the bench (an older commit, say) run the same way in the same rounds, interleaved, so that both
meet the same machine. The session is copied with the profiles it names into a scratch directory, its
``duration_s`` set to ``--seconds``.

Target (docs/performance.md, "Start-up"): a 20 s session on the sim clock, as a whole process, at least 5x faster
than on lockstep. The exit status is non-zero only if a run fails, never on speed.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SESSION = Path("profiles/sessions/swing-1deg-1hz-eso.yaml")


def scratch_session(tree: Path, session: Path, seconds: float, where: Path) -> Path:
    """``tree``'s profiles copied under ``where``, and the session among them with ``duration_s: seconds``."""
    profiles = where / "profiles"
    shutil.copytree(tree / "profiles", profiles)
    path = where / session
    text, n = re.subn(r"(?m)^duration_s:.*$", f"duration_s: {seconds:g}", path.read_text())
    if n != 1:
        raise SystemExit(f"{session}: no top-level duration_s line to set")
    path.write_text(text)
    return path


def timed(cmd: list[str], cwd: Path) -> tuple[float, float]:
    """(wall s, CPU s: user + system of the process and every process it waited for) of ``cmd`` run in ``cwd``."""
    r0, t0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(cwd)},
                          check=False)
    wall, r1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    if proc.returncode != 0:
        said = proc.stderr.strip() or proc.stdout.strip()
        raise SystemExit(f"{' '.join(cmd)} (in {cwd}): exit {proc.returncode}: {said[-600:]}")
    if "--json" in cmd and json.loads(proc.stdout).get("status") != "completed":
        raise SystemExit(f"{' '.join(cmd)}: {proc.stdout[-400:]}")
    return wall, cpu


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="the session's duration_s")
    ap.add_argument("--repeat", type=int, default=5, help="rounds")
    ap.add_argument("--session", type=Path, default=SESSION, help="a session file, relative to each tree")
    ap.add_argument("--peer", type=Path, action="append", default=[], help="another checkout to run beside this one")
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args()
    trees = [ROOT, *(p.resolve() for p in args.peer)]
    walls: dict[str, list[float]] = {}
    cpus: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory(prefix="hil-startup-") as tmp:
        sessions = {tree: scratch_session(tree, args.session, args.seconds, Path(tmp) / f"t{i}")
                    for i, tree in enumerate(trees)}

        def measure(key: str, cmd: list[str], tree: Path) -> None:
            wall, cpu = timed(cmd, tree)
            walls.setdefault(key, []).append(wall)
            cpus.setdefault(key, []).append(cpu)

        for r in range(args.repeat):
            for i, tree in enumerate(trees):
                name = "this tree" if i == 0 else str(tree)
                out = Path(tmp) / f"out{i}-{r}"
                for clock in ("lockstep", "sim"):
                    cmd = [sys.executable, "-m", "hil", "run", str(sessions[tree]), "--loopback", "--clock", clock,
                           "--json", "--out", str(out / clock)]
                    measure(f"{name}: {clock}", cmd, tree)
                measure(f"{name}: import hil.cli, hil.session", [sys.executable, "-c", "import hil.cli, hil.session"],
                        tree)
            print(f"round {r + 1}/{args.repeat}: " + ", ".join(f"{k} {v[-1]:.2f} s" for k, v in walls.items()),
                  flush=True)
    print(f"\n{args.seconds:g} s session, {args.repeat} rounds, medians of the whole process (CPU: user + system, "
          "its children included):")
    print("| tree: what | wall s | CPU s | wall of each round |\n| --- | ---: | ---: | --- |")
    for key, values in walls.items():
        print(f"| {key} | {statistics.median(values):.2f} | {statistics.median(cpus[key]):.2f} | "
              f"{', '.join(f'{v:.2f}' for v in values)} |")
    figures: dict[str, float] = {k: statistics.median(v) for k, v in walls.items()}
    for i, tree in enumerate(trees):
        name = "this tree" if i == 0 else str(tree)
        ratio = figures[f"{name}: lockstep"] / figures[f"{name}: sim"]
        cpu_ratio = statistics.median(cpus[f"{name}: lockstep"]) / statistics.median(cpus[f"{name}: sim"])
        figures[f"{name}: lockstep / sim"] = ratio
        print(f"{name}: lockstep / sim = {ratio:.2f}x in wall time, {cpu_ratio:.2f}x in CPU time (target >= 5x)")
    if args.json:
        args.json.write_text(json.dumps({"seconds": args.seconds, "repeat": args.repeat, "walls_s": walls,
                                         "cpus_s": cpus, "medians": figures}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
