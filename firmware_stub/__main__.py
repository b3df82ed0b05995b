"""Run the emulated lab: ``python -m firmware_stub`` (also ``hil emulate``).

Prints one JSON line with the ports map (board -> serial port path, plus the control socket),
writes the same map to ``--ports-file`` if given, runs until SIGINT/SIGTERM (or ``--seconds`` of
simulated time), then prints one JSON line with its summary, removes the ports file and its run
directory, and exits 0. A bad config exits 2 with one line naming the file and field.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from pathlib import Path

from firmware_stub.config import ConfigError, load_emulator_config
from firmware_stub.emulator import Emulator
from hil.protocol import CATALOGUE


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m firmware_stub", description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=None, help="emulator YAML (default profiles/emulator/default.yaml)")
    ap.add_argument("--clock", choices=["realtime", "lockstep"], default=None, help="override the config's clock")
    ap.add_argument("--seed", type=int, default=None, help="override the config's seed")
    ap.add_argument("--ports-file", type=Path, default=None, help="also write the ports map (JSON) here")
    ap.add_argument("--fault-log", type=Path, default=None, help="write every fault and board event here (JSONL)")
    ap.add_argument("--seconds", type=float, default=None, help="stop after this much simulated time")
    ap.add_argument("--rt-priority", type=int, default=0,
                    help="run the board clock SCHED_FIFO at this priority (1-99; 0 = normal scheduling)")
    ap.add_argument("--cpu", type=int, default=None,
                    help="pin the emulator to this CPU, an index into the CPUs it may use (-1 = the last)")
    ap.add_argument("--fingerprint", type=lambda s: int(s, 0), default=CATALOGUE.fingerprint,
                    help="catalogue fingerprint the boards claim (emulates firmware built from another catalogue)")
    return ap.parse_args(argv)


def pin_to_cpu(index: int) -> None:
    """Pin this process (before it starts any thread) to the CPU ``index`` names among those it may use."""
    cpus = sorted(os.sched_getaffinity(0))
    if not -len(cpus) <= index < len(cpus):
        print(f"warning: --cpu {index}: this process may use CPUs {cpus}; running unpinned", file=sys.stderr)
        return
    os.sched_setaffinity(0, {cpus[index]})


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.cpu is not None:
        pin_to_cpu(args.cpu)
    try:
        config = load_emulator_config(args.config, clock=args.clock, seed=args.seed)
        emulator = Emulator(config, fault_log=args.fault_log, fingerprint=args.fingerprint)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    def on_signal(signum: int, _frame: object) -> None:
        emulator.request_stop()

    if args.rt_priority:
        try:  # children (none today) would not inherit it
            os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(args.rt_priority))
        except (PermissionError, OSError) as exc:
            print(f"warning: --rt-priority {args.rt_priority}: {exc.strerror or exc}; running at normal priority",
                  file=sys.stderr)
    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    ports_file: Path | None = args.ports_file
    try:
        ports = emulator.ports()
        if ports_file:
            tmp = ports_file.with_name(ports_file.name + ".tmp")
            tmp.write_text(json.dumps(ports, indent=2) + "\n")
            os.replace(tmp, ports_file)
        print(json.dumps(ports), flush=True)
        emulator.run(max_ticks=None if args.seconds is None else round(args.seconds * 1000))
        print(json.dumps(emulator.summary()), flush=True)
    finally:
        emulator.close()
        if ports_file:
            ports_file.unlink(missing_ok=True)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


if __name__ == "__main__":
    sys.exit(main())
