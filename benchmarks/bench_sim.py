#!/usr/bin/env python3
"""The ``sim`` session clock against ``lockstep``, side by side in one run: the same session, seed and config.

    .venv/bin/python benchmarks/bench_sim.py [--seconds 20] [--repeat 3] [--session FILE] [--json PATH]

Each repeat runs the session once with ``--clock lockstep`` (the emulator in its own process, the full protocol
over ptys) and once with ``--clock sim`` (hil.session._sim: boards and plant in the bench's process), both with logging.
The loop time of a run is read from its own log: the host's clock (``/loop/t_host_ns``) from the first sample
to the last sample of the session's duration, so interpreter start, handshake, log creation and the wind-down
are left out of both. The whole call (``run_sim_session`` / emulator start to stop) is reported beside it.

Targets (issue "plant v2", docs/performance.md): sim >= 50x real time with logging, and >= 5x faster than
lockstep. The exit status is non-zero only if a run fails, never on speed.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.config import PROFILES, PortConfig, SessionConfig, load_session
from hil.log.reader import read_log
from hil.session import EmulatorProcess, Session, run_sim_session


def loop_seconds(log: Path, ticks: int) -> float:
    """Host wall time from the first sample to sample ``ticks - 1``, from the log."""
    t = np.asarray(read_log(log).groups["loop"]["t_host_ns"])
    if len(t) < ticks:
        raise RuntimeError(f"{log}: {len(t)} samples, expected {ticks}")
    return float(t[ticks - 1] - t[0]) / 1e9


def run_lockstep(config: SessionConfig, out: Path) -> tuple[Path, float]:
    t0 = time.perf_counter()
    with EmulatorProcess(config.emulator.config, clock="lockstep", seed=config.seed) as emu:
        ports = {n: PortConfig(port=p) for n, p in emu.ports.items() if n != "control"}
        result = asyncio.run(Session(config, ports, out, watchdog_ms=1000.0, lockstep=True).run())
    if result.status != "completed" or result.log_path is None:
        raise RuntimeError(f"lockstep run: {result.status}: {result.message}")
    return result.log_path, time.perf_counter() - t0


def run_sim(config: SessionConfig, out: Path) -> tuple[Path, float]:
    t0 = time.perf_counter()
    result, _ = asyncio.run(run_sim_session(config, out))
    if result.status != "completed" or result.log_path is None:
        raise RuntimeError(f"sim run: {result.status}: {result.message}")
    return result.log_path, time.perf_counter() - t0


def _null_drive(tick: int, az_counts: int, el_counts: int) -> None:
    """Takes DRIVE_CMD and does nothing: the floor leaves out the world's handling of it."""


def loop_floor_us(config: SessionConfig, ticks: int, out: Path) -> float:
    """The bench's own per-sample code alone: ``ControlLoop.on_sample`` on recorded-like samples, armed, with a
    real SessionLog and a driver that does nothing. Any clock that runs the bench's ControlLoop pays this much
    per tick, whatever the world costs: its real-time multiple is at most 1e6 / this."""
    from hil.log import SessionLog
    from hil.protocol import GyroSample
    from hil.session import ControlLoop

    out.mkdir(parents=True, exist_ok=True)
    with SessionLog(out / "floor.h5", attrs={"config": {}, "ident": {}, "seed": 0}) as log:
        loop = ControlLoop(config, _null_drive, log, telemetry=None, duration_ticks=10**9, on_done=lambda: None)
        loop.armed = True
        rng = np.random.default_rng(0)
        rates = (rng.standard_normal((ticks, 3)) * 0.05).round(6).tolist()
        samples = [GyroSample(k * 1000, k, x, y, z, 0.0, 0.0) for k, (x, y, z) in enumerate(rates)]
        on_sample = loop.on_sample
        t0 = time.perf_counter()
        for g in samples:
            on_sample(g)
        return (time.perf_counter() - t0) / ticks * 1e6


def world_floor_us(config: SessionConfig, ticks: int) -> float:
    """The sim world alone (hil-free side: boards and plant, the session's swing running) with a host that answers
    each GYRO_SAMPLE with a ready DRIVE_CMD object and does nothing else: what the boards' logic and the plant cost
    per tick whatever the bench does."""
    from firmware_stub.config import LinkName, load_emulator_config
    from firmware_stub.sim import SimWorld
    from hil.protocol import (
        AxisMask,
        Board,
        DriveCmd,
        DriveEnable,
        Frame,
        GyroSample,
        HexapodStart,
        ServoMode,
        StreamMode,
    )
    from hil.protocol.swing import segments_to_messages

    seq = [0]

    def frame(dst: int, msg: object) -> Frame:
        seq[0] = (seq[0] + 1) & 0xFFFF
        return Frame(Board.HOST, dst, seq[0], msg)

    def to_host(link: object, f: Frame) -> None:
        if type(f.message) is GyroSample:
            world.from_host(LinkName.DRIVER, frame(Board.DRIVER, DriveCmd(f.message.tick, 100, -100)))

    world = SimWorld(load_emulator_config(config.emulator.config, clock="lockstep", seed=config.seed), to_host)
    for msg in segments_to_messages(config.profile.protocol_segments()):
        world.from_host(LinkName.HEXAPOD, frame(Board.HEXAPOD, msg))
    world.from_host(LinkName.DRIVER, frame(Board.DRIVER, DriveEnable(AxisMask.BOTH, True)))
    world.from_host(LinkName.HEXAPOD, frame(Board.HEXAPOD, HexapodStart()))
    world.from_host(LinkName.SERVO, frame(Board.SERVO, ServoMode(StreamMode.STREAM)))
    world.deliver()
    tick = world.tick
    for _ in range(1000):
        tick()
    t0 = time.perf_counter()
    for _ in range(ticks):
        tick()
    us = (time.perf_counter() - t0) / ticks * 1e6
    world.close()
    return us


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="session duration (simulated)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--session", type=Path, default=PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    config = load_session(args.session).model_copy(update={"duration_s": args.seconds})
    ticks = round(args.seconds * 1000)
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="bench-sim-") as tmp:
        asyncio.run(run_sim_session(config.model_copy(update={"duration_s": 0.2}), Path(tmp) / "warm"))
        for k in range(args.repeat):
            lock_log, lock_wall = run_lockstep(config, Path(tmp) / f"lockstep-{k}")
            sim_log, sim_wall = run_sim(config, Path(tmp) / f"sim-{k}")
            lock_s, sim_s = loop_seconds(lock_log, ticks), loop_seconds(sim_log, ticks)
            rows.append({"lockstep_loop_s": lock_s, "sim_loop_s": sim_s, "lockstep_call_s": lock_wall,
                         "sim_call_s": sim_wall, "sim_x_realtime": args.seconds / sim_s,
                         "lockstep_x_realtime": args.seconds / lock_s, "sim_vs_lockstep": lock_s / sim_s,
                         "sim_us_per_tick": sim_s / ticks * 1e6})
            r = rows[-1]
            print(f"run {k + 1}: lockstep loop {lock_s:.3f} s ({r['lockstep_x_realtime']:.1f}x real time), "
                  f"sim loop {sim_s:.3f} s ({r['sim_x_realtime']:.1f}x, {r['sim_us_per_tick']:.1f} us/tick); "
                  f"sim {r['sim_vs_lockstep']:.2f}x faster; whole calls {lock_wall:.2f} s / {sim_wall:.2f} s",
                  flush=True)
        floor_us = loop_floor_us(config, ticks, Path(tmp) / "floor")
    world_us = world_floor_us(config, ticks)
    med = {key: statistics.median(r[key] for r in rows) for key in rows[0]}
    print(f"floors: the bench's own ControlLoop.on_sample alone (null driver, real log) {floor_us:.1f} us per "
          f"sample; the sim world alone (boards and plant, the swing on, a host that only answers) {world_us:.1f} us "
          f"per tick; together {floor_us + world_us:.1f} us, at most {1e3 / (floor_us + world_us):.0f}x real time "
          f"with no glue at all; the glue between them (links, round trips, dispatch) is the other "
          f"{med['sim_us_per_tick'] - floor_us - world_us:.1f} us")
    print(f"\nmedian of {len(rows)}: sim {med['sim_x_realtime']:.1f}x real time ({med['sim_us_per_tick']:.1f} us per "
          f"tick, target >= 50x), {med['sim_vs_lockstep']:.2f}x faster than lockstep (target >= 5x); lockstep "
          f"{med['lockstep_x_realtime']:.1f}x real time")
    if args.json:
        args.json.write_text(json.dumps({"session": str(args.session), "seconds": args.seconds, "runs": rows,
                                         "median": med, "loop_floor_us": floor_us, "world_floor_us": world_us,
                                         "python": platform.python_version()}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
