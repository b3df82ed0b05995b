"""The 1 kHz hot path against its floor: a realtime session beside a bare pty ping-pong and a lean responder.

    .venv/bin/python benchmarks/bench_session.py [--seconds 20] [--repeat 3] [--controller eso_kf] [--no-mqtt]
        [--loop-cpu N --emulator-cpu N | --unpinned] [--floor-seconds 10] [--hogs 0]

Each repeat runs, back to back and placed alike (the loop's end on the loop CPU, the board's end on the emulator
CPU, from profiles/sessions/demo.yaml unless overridden):

1. floor: two bare processes ping-ponging 40 bytes over a pty at 1 kHz (no Python work but the calls);
2. lean responder: the same emulator, answered by one thread that waits in ``select`` on the four ptys, frames the
   servo bytes with a minimal framer, checks the GYRO_SAMPLE's CRC and takes its tick, and writes DRIVE_CMD with one
   ``struct.pack``, ``crc_hqx`` and ``os.write``; the other boards' bytes are read and dropped (a board link nobody
   reads fills its pty, and the emulator's writes to it then stall its clock by milliseconds): the best a Python
   responder does here;
3. the session: the demo session (ESO+KF, tracking, logging, MQTT on a broker started here), the loop in its thread.

Reported per repeat: board-measured GYRO_SAMPLE k written -> DRIVE_CMD k received (p50/p99/p99.9, as the emulated
servo board measured it) for 2 and 3, the floor's round trip, the ratios to the floor, the bench's own
sample-in -> command-out, late and missed cycles, host stalls, and CPU use. ``--hogs N`` runs N busy processes
beside everything (a loaded machine). Results go in docs/performance.md ("The loop thread").
"""

from __future__ import annotations

import argparse
import asyncio
import os
import pty
import resource
import select
import subprocess
import sys
import tempfile
import time
import tty
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.config import PROFILES, PortConfig, SessionConfig, load_session  # noqa: E402
from hil.log import read_log  # noqa: E402
from hil.session import EmulatorProcess, Session  # noqa: E402
from hil.session import _host as host  # noqa: E402
from hil.telemetry import MqttConfig  # noqa: E402
from tests.telemetry.broker import MqttBroker  # noqa: E402


def cpu_s(who: int) -> float:
    r = resource.getrusage(who)
    return r.ru_utime + r.ru_stime


def pty_floor(seconds: float, cpu: int | None, echo_cpu: int | None) -> np.ndarray:
    """Round trips (us) of 40 bytes between this process (on ``cpu``) and a forked echo (on ``echo_cpu``) over a
    pty, one per ms."""
    n = max(1, round(seconds * 1000))
    parent, child = pty.openpty()
    for fd in (parent, child):
        tty.setraw(fd)
    previous = os.sched_getaffinity(0)
    pid = os.fork()
    if pid == 0:  # the echo
        if echo_cpu is not None:
            os.sched_setaffinity(0, {echo_cpu})
        try:
            for _ in range(n):
                select.select([child], [], [])
                os.write(child, os.read(child, 64))
        finally:
            os._exit(0)
    if cpu is not None:
        os.sched_setaffinity(0, {cpu})
    rtt = np.empty(n)
    t = time.perf_counter()
    for i in range(n):
        t += 1e-3
        while (left := t - time.perf_counter()) > 0:
            if left > 3e-4:
                time.sleep(left - 3e-4)
        t0 = time.perf_counter()
        os.write(parent, b"x" * 40)
        select.select([parent], [], [])
        os.read(parent, 64)
        rtt[i] = (time.perf_counter() - t0) * 1e6
    os.waitpid(pid, 0)
    os.close(parent)
    os.close(child)
    os.sched_setaffinity(0, previous)
    return rtt


def quantiles(x: np.ndarray) -> list[float]:
    return [float(v) for v in np.percentile(x, [50, 99, 99.9])] if x.size else [float("nan")] * 3


def board_latencies(frames: list) -> np.ndarray:  # type: ignore[type-arg]
    """Board-measured latencies (us) from LOOP_TIMING frames (0xFFFF: no command came)."""
    from hil.protocol import NO_LATENCY_US, LoopTiming

    out = [v for f in frames if type(f.message) is LoopTiming for v in f.message.latency_us if v != NO_LATENCY_US]
    return np.asarray(out, dtype=float)


def lean_responder(config: SessionConfig, seconds: float, cpu: int | None) -> dict:  # type: ignore[type-arg]
    """The emulator of ``config`` answered by the leanest Python responder (see the module docstring)."""
    import struct
    import threading
    from binascii import crc_hqx

    import serial

    from hil.protocol import (
        CATALOGUE,
        Board,
        Decoder,
        Encoder,
        GyroSample,
        HostAlive,
        LoopTiming,
        ServoMode,
        StreamMode,
    )

    emulator = EmulatorProcess(config.emulator.config, clock="realtime", seed=config.seed,
                               extra_args=config.emulator.process_args())
    ports = emulator.start()
    servo = serial.Serial(ports["servo"], 921_600, timeout=None)
    driver = serial.Serial(ports["driver"], 921_600, timeout=0)
    others = [driver] + [serial.Serial(ports[name], 921_600, timeout=0) for name in ("image", "hexapod")]
    sfd, dfd = servo.fd, driver.fd
    host = Encoder(Board.HOST)
    header = struct.Struct("<2sBBBBHBIhh")
    decoder = Decoder.for_link(Board.SERVO)
    gyro_id = next(spec for spec in CATALOGUE if spec.cls is GyroSample).msg_id
    timing_id = next(spec for spec in CATALOGUE if spec.cls is LoopTiming).msg_id
    frames: list = []  # type: ignore[type-arg]
    end = time.monotonic() + seconds

    def respond() -> None:
        if cpu is not None:
            os.sched_setaffinity(0, {cpu})
        seq = 0
        alive_at = 0.0
        buf = b""
        timing: list[bytes] = []  # LOOP_TIMING frames, decoded after the run
        fds = [sfd] + [o.fd for o in others]
        while time.monotonic() < end:
            ready = select.select(fds, [], [], 0.1)[0]
            for fd in ready[1:] if ready and ready[0] == sfd else ready:
                os.read(fd, 4096)  # the other boards' frames, read as the session reads them, and dropped
            if not ready or ready[0] != sfd:
                continue
            buf += os.read(sfd, 4096)
            while len(buf) >= 9:  # a minimal framer: the pty may cut or join frames
                if buf[0] != 0xEB or buf[1] != 0x90:
                    start = buf.find(b"\xeb\x90", 1)
                    buf = buf[start:] if start >= 0 else buf[-1:]
                    continue
                n = buf[8] + 11
                if len(buf) < n:
                    break
                if crc_hqx(buf[2 : n - 2], 0xFFFF) == buf[n - 2] | buf[n - 1] << 8:
                    if buf[5] == gyro_id:
                        tick = int.from_bytes(buf[13:17], "little")  # the payload's second field
                        body = header.pack(b"\xeb\x90", 1, Board.HOST, Board.DRIVER, 0x20, seq, 8, tick, 0, 0)
                        os.write(dfd, body + crc_hqx(body[2:], 0xFFFF).to_bytes(2, "little"))
                        seq = (seq + 1) & 0xFFFF
                    elif buf[5] == timing_id:
                        timing.append(buf[:n])
                    buf = buf[n:]
                else:
                    buf = buf[1:]
            now = time.monotonic()
            if now - alive_at > 0.1:  # the servo board's host timer (docs/protocol.md, "Host liveness")
                os.write(sfd, host.encode(HostAlive(0), Board.SERVO))
                alive_at = now
        frames.extend(decoder.feed(b"".join(timing)))

    try:
        os.write(sfd, host.encode(ServoMode(StreamMode.STREAM), Board.SERVO))
        worker = threading.Thread(target=respond, name="lean-responder")
        worker.start()
        worker.join()
        os.write(sfd, host.encode(ServoMode(StreamMode.IDLE), Board.SERVO))
    finally:
        servo.close()
        for o in others:
            o.close()
        summary = emulator.stop()
    lat = board_latencies(frames)
    return {"board_us": quantiles(lat), "n": int(lat.size), "pacing": summary.get("servo", {}).get("pacing_late_us")}


def session_case(config: SessionConfig, work: Path, capture_dir: Path | None = None) -> dict:  # type: ignore[type-arg]
    cpu_self0, cpu_kids0, wall0 = cpu_s(resource.RUSAGE_SELF), cpu_s(resource.RUSAGE_CHILDREN), time.monotonic()
    emulator = EmulatorProcess(config.emulator.config, clock="realtime", seed=config.seed,
                               extra_args=config.emulator.process_args())
    ports = emulator.start()
    try:
        session = Session(config, {n: PortConfig(port=p) for n, p in ports.items() if n != "control"}, work,
                          emulated=True, capture_dir=capture_dir)
        result = asyncio.run(session.run())
    finally:
        emu = emulator.stop()
    wall = time.monotonic() - wall0
    log = read_log(result.log_path)
    timing = log.groups["timing"]["board_latency_us"]
    answered = timing[np.isfinite(timing)]
    loop = log.groups["loop"]
    return {
        "status": f"{result.status} {result.message}".strip(), "cycles": int(loop["tick"].size),
        "board_us": quantiles(answered), "bench_us": quantiles(np.asarray(loop["latency_us"], dtype=float)),
        "late": int(np.sum(answered > 1000)), "missed": int(np.sum(~np.isfinite(timing))),
        "tick_gaps": int(loop["tick_gap"].sum()), "faults": len(result.stats.faults),
        "recoveries": result.stats.recoveries, "host_stalls": result.stats.host_stalls,
        "clock_late": result.stats.clock_late, "telemetry": result.telemetry,
        "cpu_bench_pct": 100 * (cpu_s(resource.RUSAGE_SELF) - cpu_self0) / wall,
        "cpu_children_pct": 100 * (cpu_s(resource.RUSAGE_CHILDREN) - cpu_kids0) / wall,
        "pacing": emu.get("servo", {}).get("pacing_late_us"),
    }


def start_hogs(n: int) -> list[subprocess.Popen[bytes]]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--controller", default="eso_kf")
    ap.add_argument("--no-mqtt", action="store_true")
    ap.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO for the bench loop (and emulator + 1)")
    ap.add_argument("--loop-cpu", type=int, default=None, help="override host.loop_cpu (an index, -1 = the last)")
    ap.add_argument("--emulator-cpu", type=int, default=None, help="override emulator.cpu")
    ap.add_argument("--unpinned", action="store_true", help="no CPU placement at all")
    ap.add_argument("--floor-seconds", type=float, default=10.0, help="pty round trips per repeat")
    ap.add_argument("--hogs", type=int, default=0, help="busy processes running beside everything")
    ap.add_argument("--capture", action="store_true",
                    help="also run the session with every link captured (hil run --capture), right after the plain one")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="hil-bench-"))
    broker = None if args.no_mqtt else MqttBroker(work).start()
    data = load_session(PROFILES / "sessions" / "demo.yaml").model_dump()
    loop_cpu = None if args.unpinned else args.loop_cpu if args.loop_cpu is not None else data["host"]["loop_cpu"]
    emulator_cpu = (None if args.unpinned else args.emulator_cpu if args.emulator_cpu is not None
                    else data["emulator"]["cpu"])
    data.update(duration_s=args.seconds, controller={"name": args.controller, "params": {}},
                host={"rt_priority": args.rt_priority, "loop_cpu": loop_cpu},
                safety={**data["safety"], "on_fault": "recover", "max_recoveries": 100})
    data["emulator"] = {**data["emulator"], "rt_priority": args.rt_priority + 1 if args.rt_priority else 0,
                        "cpu": emulator_cpu}
    if broker is not None:
        data["mqtt"] = MqttConfig(host=broker.host, port=broker.port, bench_id="bench").model_dump()
    config = SessionConfig.model_validate(data)
    loop_cpu_number = None if loop_cpu is None else host.resolve_cpu(loop_cpu)
    emulator_cpu_number = None if emulator_cpu is None else host.resolve_cpu(emulator_cpu)
    print(f"# hot path vs floor: {args.repeat} x ({args.floor_seconds:.0f} s floor, {args.seconds:.0f} s lean "
          f"responder, {args.seconds:.0f} s session), {args.controller}, logging on, MQTT "
          f"{'off' if broker is None else broker.kind}, SCHED_FIFO {args.rt_priority or 'off'}, {args.hogs} CPU hogs "
          f"({os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}); loop CPU {loop_cpu_number}, emulator CPU "
          f"{emulator_cpu_number}")
    if broker is not None and broker.pid is not None and loop_cpu_number is not None:
        host.pin_process(broker.pid, set(host.allowed_cpus()) - {loop_cpu_number})
    hogs = start_hogs(args.hogs)
    rows = []
    captures: list[tuple[dict, dict]] = []  # type: ignore[type-arg]
    try:
        for r in range(args.repeat):
            floor = quantiles(pty_floor(args.floor_seconds, loop_cpu_number, emulator_cpu_number))
            lean = lean_responder(config, args.seconds, loop_cpu_number)
            sess = session_case(config, work)
            if args.capture:
                captured = session_case(config, work, capture_dir=work / "capture")
                captures.append((sess, captured))
                print(f"run {r + 1}: with capture: session {captured['board_us'][0]:.0f}/"
                      f"{captured['board_us'][1]:.0f} ({captured['status']}); bench-side "
                      f"{captured['bench_us'][0]:.0f}/{captured['bench_us'][1]:.0f}", flush=True)
            rows.append((floor, lean, sess))
            print(f"run {r + 1}: floor p50/p99 {floor[0]:.0f}/{floor[1]:.0f} us; lean {lean['board_us'][0]:.0f}/"
                  f"{lean['board_us'][1]:.0f}; session {sess['board_us'][0]:.0f}/{sess['board_us'][1]:.0f} "
                  f"({sess['status']}); bench-side {sess['bench_us'][0]:.0f}/{sess['bench_us'][1]:.0f}", flush=True)
    finally:
        for h in hogs:
            h.kill()
        if broker is not None:
            broker.stop()
    print("\n| run | floor p50 / p99 | lean responder p50 / p99 | session p50 / p99 / p99.9 | session / floor p50, "
          "p99 | lean / floor p50, p99 | bench-side p50 / p99 | late / missed / gaps | stalls (emulator late) | "
          "faults |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for i, (floor, lean, sess) in enumerate(rows, 1):
        b, lb, bs = sess["board_us"], lean["board_us"], sess["bench_us"]
        print(f"| {i} | {floor[0]:.0f} / {floor[1]:.0f} | {lb[0]:.0f} / {lb[1]:.0f} | {b[0]:.0f} / {b[1]:.0f} / "
              f"{b[2]:.0f} | {b[0] / floor[0]:.2f}, {b[1] / floor[1]:.2f} | {lb[0] / floor[0]:.2f}, "
              f"{lb[1] / floor[1]:.2f} | {bs[0]:.0f} / {bs[1]:.0f} | {sess['late']} / {sess['missed']} / "
              f"{sess['tick_gaps']} | {sess['host_stalls']} ({sess['clock_late']} CLOCK_LATE) | {sess['faults']} |")
    if captures:
        print("\n| run | session p50 / p99 | with capture p50 / p99 | ratio p50, p99 | bench-side p50 / p99 | "
              "with capture bench-side p50 / p99 | missed (plain / capture) |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        for i, (plain, cap) in enumerate(captures, 1):
            b, c = plain["board_us"], cap["board_us"]
            print(f"| {i} | {b[0]:.0f} / {b[1]:.0f} | {c[0]:.0f} / {c[1]:.0f} | {c[0] / b[0]:.2f}, {c[1] / b[1]:.2f} | "
                  f"{plain['bench_us'][0]:.0f} / {plain['bench_us'][1]:.0f} | {cap['bench_us'][0]:.0f} / "
                  f"{cap['bench_us'][1]:.0f} | {plain['missed']} / {cap['missed']} |")
    last = rows[-1][2]
    if last["telemetry"]:
        t = last["telemetry"]
        print(f"\ntelemetry (last run): published {t['published']}, dropped {t['dropped']}, "
              f"reconnects {t['reconnects']}")
    print(f"CPU (last run): bench process {last['cpu_bench_pct']:.0f} % of a core, children "
          f"{last['cpu_children_pct']:.0f} %; emulator pacing lateness us {last['pacing']}")


if __name__ == "__main__":
    main()
