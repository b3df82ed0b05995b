"""Protocol self-test over a pseudo-terminal: the bench against a streaming emulated servo board.

The board (``firmware_stub.loopback_board``, its own process) streams GYRO_SAMPLE at 1 kHz with
seeded garbage bursts and bit flips; the bench answers each sample with DRIVE_CMD(tick) from the
callback that decoded it. Passing means: the IDENT fingerprint matches, every frame the board
did not corrupt arrived exactly once and in order, no corrupted frame got through, and every
sample that arrived was answered.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from hil.link._transport import LinkError, SerialLink
from hil.protocol import CATALOGUE, Ack, Board, DriveCmd, Frame, GyroSample, Ident, IdentRequest, ServoMode, StreamMode


@dataclass
class SelftestReport:
    ticks: int
    ident: dict[str, Any] = field(default_factory=dict)
    board: dict[str, Any] = field(default_factory=dict)
    frames_received: int = 0
    lost_untouched: list[int] = field(default_factory=list)  # uncorrupted ticks that never arrived
    corrupted_delivered: list[int] = field(default_factory=list)  # corrupted ticks that got through
    duplicates: int = 0
    out_of_order: int = 0
    bench_reaction_us: dict[str, float] = field(default_factory=dict)  # frame decoded -> DRIVE_CMD written
    counters: dict[str, Any] = field(default_factory=dict)
    failures: list[str] = field(default_factory=list)
    wall_s: float = 0.0

    @property
    def passed(self) -> bool:
        return not self.failures


def _percentiles_us(ns: list[int]) -> dict[str, float]:
    if not ns:
        return {}
    s = sorted(ns)
    return {q: round(s[min(len(s) - 1, int(p * len(s)))] / 1e3, 1) for q, p in (("p50", 0.5), ("p99", 0.99))} | {
        "max": round(s[-1] / 1e3, 1)
    }


async def run_selftest(
    *,
    ticks: int = 3000,
    seed: int = 1,
    garbage_rate: float = 0.01,
    flip_rate: float = 0.005,
    progress: Callable[[int], None] | None = None,
    board_args: tuple[str, ...] = (),
) -> SelftestReport:
    report = SelftestReport(ticks=ticks)
    started = time.perf_counter()
    board = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "firmware_stub.loopback_board",
        "--ticks", str(ticks), "--seed", str(seed),
        "--garbage-rate", str(garbage_rate), "--flip-rate", str(flip_rate), *board_args,
        stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip
    assert board.stdout is not None
    received: list[int] = []
    reaction_ns: list[int] = []
    link: SerialLink | None = None
    try:
        ports = json.loads(await asyncio.wait_for(board.stdout.readline(), 10))

        def on_frame(frame: Frame) -> None:
            msg = frame.message
            if isinstance(msg, GyroSample):
                t0 = time.perf_counter_ns()
                assert link is not None
                link.send(DriveCmd(msg.tick, 0, 0), Board.DRIVER)
                reaction_ns.append(time.perf_counter_ns() - t0)
                received.append(msg.tick)

        link = await SerialLink.open("servo", ports["servo"], on_frame=on_frame)
        ident = await link.request(IdentRequest(), Board.SERVO, Ident)
        report.ident = {
            "board": ident.board.name,
            "firmware_version": ident.firmware_version,
            "catalogue_fingerprint": f"{ident.catalogue_fingerprint:#010x}",
        }
        if ident.catalogue_fingerprint != CATALOGUE.fingerprint:
            report.failures.append(
                f"catalogue mismatch: board {ident.catalogue_fingerprint:#010x} (firmware {ident.firmware_version}), "
                f"bench {CATALOGUE.fingerprint:#010x}"
            )
            return report
        await link.request(ServoMode(StreamMode.STREAM), Board.SERVO, Ack)
        while board.returncode is None:
            if progress:
                progress(len(received))
            with contextlib.suppress(TimeoutError):  # a UI refresh tick only; the loop runs in on_frame
                await asyncio.wait_for(board.wait(), 0.1)
        if progress:
            progress(len(received))
        report.board = json.loads((await board.stdout.read()).decode().strip().splitlines()[-1])
    finally:
        if link is not None:
            report.counters = link.decoder.counters.as_dict()
            link.close()
        if board.returncode is None:
            board.terminate()
            await board.wait()
    report.wall_s = time.perf_counter() - started
    _judge(report, received, reaction_ns)
    return report


def _judge(report: SelftestReport, received: list[int], reaction_ns: list[int]) -> None:
    b = report.board
    if b.get("error"):
        report.failures.append(f"board: {b['error']}")
        return
    corrupted = set(b["corrupted_ticks"])
    got = set(received)
    report.frames_received = len(received)
    report.duplicates = len(received) - len(got)
    report.out_of_order = sum(1 for a, c in itertools.pairwise(received) if c <= a)
    report.lost_untouched = sorted(set(range(b["ticks_sent"])) - corrupted - got)
    report.corrupted_delivered = sorted(corrupted & got)
    report.bench_reaction_us = _percentiles_us(reaction_ns)
    if report.lost_untouched:
        report.failures.append(f"{len(report.lost_untouched)} uncorrupted frames lost: {report.lost_untouched[:10]}")
    if report.corrupted_delivered:
        report.failures.append(f"corrupted frames delivered: {report.corrupted_delivered[:10]}")
    if report.duplicates or report.out_of_order:
        report.failures.append(f"{report.duplicates} duplicates, {report.out_of_order} out of order")
    if b["missing_commands"] != len(corrupted):
        report.failures.append(
            f"board missed {b['missing_commands']} DRIVE_CMDs; expected exactly the {len(corrupted)} corrupted ticks"
        )


def main_sync(**kwargs: Any) -> SelftestReport:
    try:
        return asyncio.run(run_selftest(**kwargs))
    except LinkError as exc:
        report = SelftestReport(ticks=kwargs.get("ticks", 0))
        report.failures.append(str(exc))
        return report
