"""A servo board streaming GYRO_SAMPLE at 1 kHz on a pty, for the protocol self-test.

    python -m firmware_stub.loopback_board --ticks 3000 --seed 1

Prints one JSON line with the port map (``{"servo": "/dev/pts/N"}``), serves one session, then
prints one JSON line with its summary and exits. The session: the host sends IDENT_REQ (answered
with IDENT) and SERVO_MODE STREAM (answered with ACK); the board then streams ``--ticks``
samples and, for each, measures the time from writing GYRO_SAMPLE k to receiving DRIVE_CMD k on
the same link. Seeded faults: garbage bursts between frames and single-bit flips inside frames,
each recorded, so the host can check that exactly the untouched frames reached it.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
import time
from dataclasses import asdict, dataclass, field

from firmware_stub.boards import percentiles_us
from firmware_stub.clock import wait_until
from firmware_stub.pty_port import PtyPort
from hil.protocol import (
    CATALOGUE,
    NO_AXIS,
    SYNC,
    Ack,
    Board,
    Decoder,
    DriveCmd,
    Encoder,
    ErrorCode,
    GyroSample,
    Ident,
    IdentRequest,
    Nack,
    ServoMode,
    StreamMode,
)

FIRMWARE_VERSION = "stub-loopback-1"
TICK_S = 1e-3


@dataclass
class BoardSummary:
    ticks_sent: int = 0
    corrupted_ticks: list[int] = field(default_factory=list)
    garbage_bursts: int = 0
    garbage_bytes: int = 0
    commands_received: int = 0
    missing_commands: int = 0
    late_commands: int = 0  # DRIVE_CMD k later than 1 ms after GYRO_SAMPLE k
    latency_us: dict[str, float] = field(default_factory=dict)
    pacing_late_us: dict[str, float] = field(default_factory=dict)
    rx_counters: dict = field(default_factory=dict)
    error: str = ""


class LoopbackBoard:
    def __init__(
        self, ticks: int, seed: int, garbage_rate: float, flip_rate: float, fingerprint: int = CATALOGUE.fingerprint
    ) -> None:
        self.fingerprint = fingerprint
        self.port = PtyPort()
        self.ticks = ticks
        self.rng = random.Random(seed)
        self.garbage_rate = garbage_rate
        self.flip_rate = flip_rate
        self.encoder = Encoder(Board.SERVO)
        self.decoder = Decoder()
        self.streaming = False
        self.written_at = [0.0] * ticks
        self.latency_s: list[float | None] = [None] * ticks
        self.summary = BoardSummary()

    def reply(self, message: object) -> None:
        self.port.write(self.encoder.encode(message, Board.HOST))

    def on_readable(self, t_rx: float) -> None:
        for frame in self.decoder.feed(self.port.read()):
            msg = frame.message
            if isinstance(msg, DriveCmd):
                self.summary.commands_received += 1
                k = msg.tick
                if 0 <= k < self.ticks and self.written_at[k] and self.latency_s[k] is None:
                    self.latency_s[k] = t_rx - self.written_at[k]
            elif isinstance(msg, IdentRequest):
                self.reply(Ident(Board.SERVO, CATALOGUE.protocol_version, FIRMWARE_VERSION, self.fingerprint, 1))
            elif isinstance(msg, ServoMode):
                self.streaming = msg.mode == StreamMode.STREAM
                self.reply(Ack(0x12, frame.seq))
            else:
                spec = CATALOGUE.spec(msg)
                self.reply(Nack(spec.msg_id, frame.seq, ErrorCode.UNKNOWN_MESSAGE, NO_AXIS, 0.0, 0.0))

    def garbage(self) -> bytes:
        burst = bytearray(self.rng.randbytes(self.rng.randint(1, 32)))
        if self.rng.random() < 0.5:  # a false sync word, to exercise the receiver's resync
            at = self.rng.randrange(len(burst))
            burst[at : at + 2] = SYNC
        return bytes(burst)

    def wait_for_stream(self, timeout_s: float) -> bool:
        give_up = time.perf_counter() + timeout_s
        while not self.streaming:
            now = time.perf_counter()
            if now > give_up:
                return False
            wait_until(min(now + 0.05, give_up), {self.port.master_fd: self.on_readable})
        return True

    def stream(self) -> None:
        t0 = time.perf_counter() + 2 * TICK_S
        pacing_late: list[float] = []
        for k in range(self.ticks):
            deadline = t0 + k * TICK_S
            pacing_late.append(wait_until(deadline, {self.port.master_fd: self.on_readable}) * 1e6)
            t = deadline - t0
            sample = GyroSample(
                t_us=int(t * 1e6),
                tick=k,
                rate_x_dps=round(0.02 * self.rng.gauss(), 6),
                rate_y_dps=round(math.sin(2 * math.pi * t) + 0.02 * self.rng.gauss(), 6),
                rate_z_dps=round(0.5 * math.cos(2 * math.pi * t) + 0.02 * self.rng.gauss(), 6),
                az_deg=round(0.5 / (2 * math.pi) * math.sin(2 * math.pi * t), 6),
                el_deg=round(-math.cos(2 * math.pi * t) / (2 * math.pi), 6),
            )
            frame = bytearray(self.encoder.encode(sample, Board.HOST))
            if self.rng.random() < self.flip_rate:
                frame[self.rng.randrange(len(frame))] ^= 1 << self.rng.randrange(8)
                self.summary.corrupted_ticks.append(k)
            if self.rng.random() < self.garbage_rate:
                burst = self.garbage()
                self.port.write(burst)
                self.summary.garbage_bursts += 1
                self.summary.garbage_bytes += len(burst)
            self.port.write(bytes(frame))
            self.written_at[k] = time.perf_counter()
        self.summary.ticks_sent = self.ticks
        wait_until(time.perf_counter() + 0.05, {self.port.master_fd: self.on_readable})  # trailing commands
        self.summary.pacing_late_us = percentiles_us(pacing_late)

    def finish(self) -> BoardSummary:
        got = [lat * 1e6 for lat in self.latency_s if lat is not None]
        s = self.summary
        s.missing_commands = self.ticks - len(got) if s.ticks_sent else 0
        s.late_commands = sum(1 for lat in got if lat > 1000.0)
        s.latency_us = percentiles_us(got)
        s.rx_counters = self.decoder.counters.as_dict()
        return s


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=3000, help="GYRO_SAMPLEs to stream (1 kHz)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--garbage-rate", type=float, default=0.01, help="chance of a garbage burst before a frame")
    ap.add_argument("--flip-rate", type=float, default=0.005, help="chance of one flipped bit in a frame")
    ap.add_argument("--connect-timeout", type=float, default=10.0, help="seconds to wait for SERVO_MODE STREAM")
    ap.add_argument(
        "--fingerprint",
        type=lambda text: int(text, 0),
        default=CATALOGUE.fingerprint,
        help="catalogue fingerprint to claim in IDENT (emulates firmware built from another catalogue)",
    )
    args = ap.parse_args(argv)
    board = LoopbackBoard(args.ticks, args.seed, args.garbage_rate, args.flip_rate, args.fingerprint)
    print(json.dumps({"servo": board.port.path}), flush=True)
    try:
        if board.wait_for_stream(args.connect_timeout):
            board.stream()
        else:
            board.summary.error = f"no SERVO_MODE STREAM within {args.connect_timeout} s"
        print(json.dumps(asdict(board.finish())), flush=True)
    finally:
        board.port.close()
    return 0 if not board.summary.error else 1


if __name__ == "__main__":
    sys.exit(main())
