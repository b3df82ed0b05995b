"""Emulator benchmarks (issue 3): lockstep speed over ptys, and realtime pacing of GYRO_SAMPLE writes.

    .venv/bin/python benchmarks/bench_emulator.py [--lockstep-seconds 10] [--realtime-seconds 60]

The emulator runs as users run it (`python -m firmware_stub`, its own process); this process is a
trivial host that answers every GYRO_SAMPLE k with DRIVE_CMD k (a rate damper). Targets: lockstep
>= 5x real time; realtime pacing lateness reported as p50/p99/p99.9 (the board's own measurement).
Results go in docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import subprocess
import sys
import time

from hil.protocol import (
    Ack,
    AxisMask,
    Board,
    Decoder,
    DriveCmd,
    DriveEnable,
    Encoder,
    GyroSample,
    HostAlive,
    ServoMode,
    StreamMode,
)


class TrivialHost:
    def __init__(self, ports: dict[str, str], host_alive: bool) -> None:
        """``host_alive``: HOST_ALIVE on the servo link every 100 ms (realtime: the board's host timeout would stop
        the stream; lockstep: the world's own wait judges the host, and HOST_ALIVE would only add bytes)."""
        self.host_alive = host_alive
        self.fds = {name: os.open(ports[name], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK) for name in ("servo", "driver")}
        self.enc = {name: Encoder(Board.HOST) for name in self.fds}
        self.dec = {name: Decoder() for name in self.fds}
        self.early: list[GyroSample] = []  # samples that arrived while waiting for an ACK: answered first

    def send(self, name: str, msg: object, dst: int) -> None:
        os.write(self.fds[name], self.enc[name].encode(msg, dst))

    def command(self, name: str, msg: object, dst: int) -> None:
        self.send(name, msg, dst)
        give_up = time.monotonic() + 5
        while time.monotonic() < give_up:
            select.select([self.fds[name]], [], [], 0.05)
            try:
                frames = self.dec[name].feed(os.read(self.fds[name], 65536))
            except BlockingIOError:
                continue
            self.early += [f.message for f in frames if type(f.message) is GyroSample]
            if any(isinstance(f.message, Ack) for f in frames):
                return
        raise TimeoutError(f"{name}: no ACK to {msg!r}")

    def serve(self, n_samples: int) -> tuple[int, float]:
        """Answer samples until n_samples arrived; returns (samples, wall seconds)."""
        self.command("driver", DriveEnable(AxisMask.BOTH, True), Board.DRIVER)
        self.command("servo", ServoMode(StreamMode.STREAM), Board.SERVO)
        servo, got, t0 = self.fds["servo"], 0, time.perf_counter()
        # a lockstep emulator waits (up to its 1 s timeout) for the command of a sample that came with the ACK
        pending, self.early = self.early, []
        next_alive = time.monotonic()
        while got < n_samples:
            if self.host_alive and time.monotonic() >= next_alive:
                next_alive += 0.1
                self.send("servo", HostAlive(0), Board.SERVO)
            for g in pending:
                u_el = max(-30000, min(30000, int(-3000 * g.rate_y_dps)))
                u_az = max(-30000, min(30000, int(-3000 * g.rate_z_dps)))
                self.send("driver", DriveCmd(g.tick, u_az, u_el), Board.DRIVER)
                got += 1
            select.select([servo], [], [], 0.1)
            try:
                data = os.read(servo, 65536)
            except BlockingIOError:
                pending = []
                continue
            pending = [f.message for f in self.dec["servo"].feed(data) if type(f.message) is GyroSample]
        return got, time.perf_counter() - t0

    def close(self) -> None:
        for fd in self.fds.values():
            os.close(fd)


def run_emulator(clock: str, n_samples: int) -> tuple[dict, float]:
    proc = subprocess.Popen([sys.executable, "-m", "firmware_stub", "--clock", clock], stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout is not None
    ports = json.loads(proc.stdout.readline())
    host = TrivialHost(ports, host_alive=clock == "realtime")
    try:
        _, wall = host.serve(n_samples)
    finally:
        host.close()
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    return json.loads(out.strip().splitlines()[-1]), wall


def cpu_note() -> str:
    return f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lockstep-seconds", type=float, default=10.0)
    ap.add_argument("--realtime-seconds", type=float, default=60.0)
    ap.add_argument("--runs", type=int, default=3, help="lockstep runs (median reported)")
    args = ap.parse_args()
    print(f"# emulator benchmark ({cpu_note()})")

    n = round(args.lockstep_seconds * 1000)
    speeds = []
    for _ in range(args.runs):
        summary, wall = run_emulator("lockstep", n)
        speeds.append(n / 1000 / wall)
    speeds.sort()
    print(f"lockstep over ptys, trivial host: {speeds[len(speeds) // 2]:.1f}x real time "
          f"(runs: {', '.join(f'{s:.1f}' for s in speeds)}; target >= 5x)  "
          f"timeouts {summary['lockstep_timeouts']}")

    n = round(args.realtime_seconds * 1000)
    summary, wall = run_emulator("realtime", n)
    servo = summary["servo"]
    pacing, latency = servo["pacing_late_us"], servo["latency_us"]
    print(f"realtime, {args.realtime_seconds:.0f} s ({servo['samples_sent']} samples in {wall:.1f} s wall)")
    print(f"  GYRO_SAMPLE write lateness vs its deadline, us: p50 {pacing['p50']}  p99 {pacing['p99']}  "
          f"p99.9 {pacing['p99.9']}  max {pacing['max']}")
    print(f"  GYRO k written -> DRIVE_CMD k received (this trivial Python host), us: p50 {latency['p50']}  "
          f"p99 {latency['p99']}  p99.9 {latency['p99.9']}  late {servo['late_commands']}  "
          f"missing {servo['missing_commands']}")


if __name__ == "__main__":
    main()
