"""Run the emulated lab: ``python -m firmware_stub`` (also ``hil emulate``).

Prints one JSON line with the ports map (board -> serial port path, plus the control socket),
writes the same map to ``--ports-file`` if given, runs until SIGINT/SIGTERM (or ``--seconds`` of
simulated time), then prints one JSON line with its summary, removes the ports file and its run
directory, and exits 0. A bad config exits 2 with one line naming the file and field.
"""

from __future__ import annotations

import argparse
import fcntl
import gc
import json
import math
import os
import shutil
import signal
import sys
import tempfile
from pathlib import Path
from typing import NoReturn

from firmware_stub.config import ConfigError, EmulatorConfig, LinkName, load_emulator_config
from firmware_stub.emulator import Emulator
from firmware_stub.plant import PlantConfigError, load_plant_config
from hil.protocol import CATALOGUE

MAX_SECONDS = 24 * 3600.0  # --seconds: the longest run in simulated time


class BadInput(ValueError):
    """A bad option or config: one line on stderr, exit 2, nothing created."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        """A bad option is one line (no usage block), exit 2."""
        print(f"error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = _Parser(prog="python -m firmware_stub", description=__doc__.splitlines()[0])
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
    ap.add_argument("--baud", action="append", default=[], metavar="LINK=RATE",
                    help="a link's line rate, bit/s (repeat per link; default the config's links.LINK.baudrate)")
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


def _writable_file(path: Path, option: str) -> None:
    """``path`` can be created or replaced: its directory exists and is writable, and it is not a directory."""
    if path.exists() and not path.is_file():
        raise BadInput(f"{option} {path}: exists and is not a regular file")
    parent = path.absolute().parent
    if not parent.is_dir():
        raise BadInput(f"{option} {path}: no directory {parent}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise BadInput(f"{option} {path}: {parent} is not writable")


def parse_bauds(items: list[str]) -> dict[str, int]:
    """``--baud servo=921600`` options as link -> rate; BadInput naming the option for a malformed one."""
    bauds: dict[str, int] = {}
    for item in items:
        name, _, rate = item.partition("=")
        if name not in {link.value for link in LinkName} or not rate.isdigit():
            raise BadInput(f"--baud {item}: expected LINK=RATE with LINK one of "
                           f"{', '.join(link.value for link in LinkName)} and RATE in bit/s")
        bauds[name] = int(rate)
    return bauds


def check_inputs(args: argparse.Namespace) -> EmulatorConfig:
    """Validate every option, the config and the plant file it names, before anything is created (the
    Emulator makes its run directory and ptys at once): BadInput or ConfigError (one line) if one is bad."""
    if args.seconds is not None and not (math.isfinite(args.seconds) and 0 < args.seconds <= MAX_SECONDS):
        raise BadInput(f"--seconds: {args.seconds!r} is not in (0, {MAX_SECONDS:g}]")
    if args.seed is not None and not 0 <= args.seed < 2**32:
        raise BadInput(f"--seed: {args.seed} is not in 0..{2**32 - 1}")
    if not 0 <= args.rt_priority <= 99:
        raise BadInput(f"--rt-priority: {args.rt_priority} is not in 0..99")
    if not 0 <= args.fingerprint < 2**32:
        raise BadInput(f"--fingerprint: {args.fingerprint:#x} is not a 32-bit number")
    for option, path in (("--ports-file", args.ports_file), ("--fault-log", args.fault_log)):
        if path is not None:
            _writable_file(path, option)
    config = load_emulator_config(args.config, clock=args.clock, seed=args.seed, baudrates=parse_bauds(args.baud))
    try:
        load_plant_config(config.plant)
    except PlantConfigError as exc:
        raise ConfigError(f"{args.config or 'the emulator config'}: plant: {exc}") from None
    return config


def hold_ports_file(ports_file: Path) -> int:
    """Own ``ports_file`` for this emulator's life: a ``flock`` on ``PORTS_FILE.lock`` that names our pid, so a second
    emulator given the same file is refused (BadInput naming the first) instead of pointing its benches at other
    boards. Returns the lock's descriptor (the kernel lets go when this process ends, however it ends)."""
    lock = ports_file.with_name(ports_file.name + ".lock")
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip() or "?"
            os.close(fd)
            raise BadInput(f"--ports-file {ports_file}: in use by the emulator with pid {holder}; stop it first, "
                           "or give another file") from None
        try:  # the file we locked is still the one at the path (a previous holder may have just removed it)
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
            return fd
        os.close(fd)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        config = check_inputs(args)
        ports_lock = hold_ports_file(args.ports_file) if args.ports_file else None
    except (BadInput, ConfigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.cpu is not None:
        pin_to_cpu(args.cpu)
    run_dir = Path(tempfile.mkdtemp(prefix="hil-emu-"))  # ours, so it goes whatever happens below
    try:
        emulator = Emulator(config, run_dir=run_dir, fault_log=args.fault_log, fingerprint=args.fingerprint)
    except BaseException:
        shutil.rmtree(run_dir, ignore_errors=True)
        if ports_lock is not None:
            args.ports_file.with_name(args.ports_file.name + ".lock").unlink(missing_ok=True)
        raise

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
        # Everything built so far (numba, pydantic, numpy, the plant) lives as long as the process: moved to the
        # permanent generation, a full collection during the run traverses only what the run allocates. Without
        # it one took ~37 ms here, longer than the bench's watchdog (docs/performance.md, "Plant v2").
        gc.freeze()
        emulator.run(max_ticks=None if args.seconds is None else round(args.seconds * 1000))
        print(json.dumps(emulator.summary()), flush=True)
    finally:
        emulator.close()
        shutil.rmtree(run_dir, ignore_errors=True)
        if ports_file:
            ports_file.unlink(missing_ok=True)
        if ports_lock is not None and ports_file:
            ports_file.with_name(ports_file.name + ".lock").unlink(missing_ok=True)  # still held: nobody has it
            os.close(ports_lock)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


if __name__ == "__main__":
    sys.exit(main())
