"""`hil demo` as a new user runs it while the machine is busy: N processes spinning beside it.

    .venv/bin/python benchmarks/demo_beside_hogs.py [--hogs 2] [--repeat 3]

Reports, per run, the demo's exit code, its faults, and the host stalls it counted (the bench's own
late looks, and the emulator's clock running late, which it announces with CLOCK_LATE). Results go in
docs/performance.md ("The loop thread").
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HIL = [sys.executable, "-m", "hil"]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_session import start_hogs  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hogs", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    hogs = start_hogs(args.hogs)
    print(f"# hil demo beside {args.hogs} CPU hogs, {args.repeat} runs")
    print("| run | exit code | wall s | faults | host stalls (emulator or its bytes held up) | longest silence ms | "
          "late / missed cycles |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    try:
        for r in range(1, args.repeat + 1):
            out = Path(tempfile.mkdtemp(prefix="hil-demo-"))
            t0 = time.monotonic()
            demo = subprocess.run([*HIL, "demo", "--out", str(out)], cwd=ROOT, capture_output=True, text=True,
                                  check=False)
            wall = time.monotonic() - t0
            logs = sorted(out.glob("*.h5"))
            if not logs:
                print(f"| {r} | {demo.returncode} | {wall:.1f} | no log: {demo.stderr.strip()[-200:]} | | | |")
                continue
            rep = subprocess.run([*HIL, "report", str(logs[0]), "--json"], cwd=ROOT, capture_output=True, text=True,
                                 check=False)
            s = json.loads(rep.stdout)
            print(f"| {r} | {demo.returncode} | {wall:.1f} | {s['faults']} | {s['host_stalls']} "
                  f"({s.get('host_stalls_emulator', 0)}) | {s['host_stall_max_ms']:.1f} | {s['late_cycles']} / "
                  f"{s['missed_cycles']} |", flush=True)
    finally:
        for h in hogs:
            h.kill()


if __name__ == "__main__":
    main()
