"""`hil doctor`'s checks that need the boards to answer (docs/service.md, "Is the hardware ready?"): each board
answers IDENT with the catalogue fingerprint this bench expects, and a listen to the servo board's GYRO_SAMPLE stream
reports its rate and jitter. The ports' own checks (device, holder, latency timer, baud rate) are hil.link's.

The ports are taken as a session takes them: claimed (hil.link.claim_ports, the lock naming this process), then
opened as :class:`~hil.link.SerialLink` for exclusive use; the boards are asked through the session's own clients
(:meth:`BoardClient.identify`, :meth:`ServoBoard.configure` and :meth:`ServoBoard.start_stream`). Nothing here enables
the motor driver or moves the hexapod: the only command that starts anything is the servo board's SERVO_MODE
STREAM, and SERVO_MODE IDLE follows it on every way out (an error, a timeout, a cancellation), before the ports are
closed and released. HOST_ALIVE goes to every board while the stream runs, so no board's host timer expires in the
middle of the listen (docs/protocol.md, "Host liveness"); the boards' own protection is not relied on.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import os
import time
from collections.abc import Mapping
from typing import Any

from hil.boards._clients import (
    BoardClient,
    DriverBoard,
    FingerprintMismatch,
    ImageBoard,
    Interlock,
    ProtocolHexapod,
    ServoBoard,
)
from hil.link import Finding, LinkError, PortClaims, PortUnavailable, SerialLink, claim_ports
from hil.protocol import CATALOGUE, ClockLate, Frame, GyroSample

IDENT_TIMEOUT_S = 0.5  # IDENT_REQ, its resends included (hil.link.Link.request)
LISTEN_S = 2.0  # the servo stream's listen
STREAM_HZ = 1000  # the servo board's sample rate (SERVO_CONFIG, as the session configures it)
RATE_TOLERANCE = 0.01  # the measured rate may differ from STREAM_HZ by this share
WATCHDOG_MS = 5.0  # the session's default safety.watchdog_ms: a longer gap between samples would trip it
HOST_ALIVE_S = 0.1  # HOST_ALIVE this often while the stream runs (as the session sends it)
CLOSE_TIMEOUT_S = 2.0  # the transport closes its port in an executor: wait this long for it
CLIENTS: dict[str, type[BoardClient]] = {"servo": ServoBoard, "driver": DriverBoard, "image": ImageBoard,
                                         "hexapod": ProtocolHexapod}
HOLDER = "hil doctor"  # the session name in the ports' lock files while the doctor holds them
U32_SPAN = 1 << 32  # GYRO_SAMPLE.t_us wraps at 2**32 us
PTY_MAJORS = range(136, 144)  # Linux: the device numbers of pseudo-terminals' follower sides (/dev/pts/N)


async def check_boards(ports: Mapping[str, str], bauds: Mapping[str, int], *, listen_s: float = LISTEN_S,
                       ident_timeout_s: float = IDENT_TIMEOUT_S, watchdog_ms: float = WATCHDOG_MS,
                       claimed: bool = False) -> list[Finding]:
    """Ask each board who it is, then listen to the servo stream: an ``ident`` :class:`Finding` per link of
    ``ports`` (link name -> device, at ``bauds[name]``; the links are servo, driver, image and hexapod), then, if
    ``ports`` has the servo link, one ``servo stream`` finding (:func:`listen_to_stream`, ``listen_s`` long, a gap
    longer than ``watchdog_ms`` failing it; the arrivals are not judged when the servo port is a pseudo-terminal,
    :func:`is_pty`).

    Each port is claimed and opened as a session opens it, and closed and released before this returns, whatever
    happens; a port that cannot be claimed or opened is that link's failed ``ident`` finding. ``ident_timeout_s``:
    the most IDENT_REQ waits for its answer (its resends included). ``claimed``: this process already holds the
    ports' claims (`hil serve`'s worker, between items); they are then opened without claiming them again."""
    if not (math.isfinite(listen_s) and listen_s > 0):
        raise ValueError(f"listen_s={listen_s!r}: not a finite number of seconds above 0")
    if not (math.isfinite(ident_timeout_s) and ident_timeout_s > 0):
        raise ValueError(f"ident_timeout_s={ident_timeout_s!r}: not a finite number of seconds above 0")
    unknown = sorted(set(ports) - set(CLIENTS))
    if unknown:
        raise ValueError(f"ports={unknown!r}: not a board's link (the links are {', '.join(CLIENTS)})")
    held = _Held(claimed)
    clients: dict[str, BoardClient] = {}
    findings: list[Finding] = []
    try:
        for name, port in ports.items():
            finding, client = await held.ident(name, port, bauds[name], timeout_s=ident_timeout_s)
            findings.append(finding)
            if client is not None:
                clients[name] = client
        if "servo" in ports:
            servo = clients.get("servo")
            if isinstance(servo, ServoBoard):
                findings.append(await listen_to_stream(
                    servo, listen_s, watchdog_ms=watchdog_ms, judge_arrivals=not is_pty(ports["servo"]),
                    keep_alive=list(clients.values())))
            else:
                findings.append(Finding("servo", "servo stream", False,
                                        "not listened to: the servo board did not identify (its ident check says "
                                        "why)"))
    finally:
        await held.release()
    return findings


def is_pty(port: str) -> bool:
    """Is ``port`` (or the device it links to) a pseudo-terminal, as the emulator's ports are? The emulator shares
    this PC's CPUs with the bench, so a busy PC delays its samples: its gaps say nothing of a link (a loopback
    session forgives them in the same way, ``safety.emulator_stall_grace_ms``)."""
    try:
        return os.major(os.stat(port).st_rdev) in PTY_MAJORS
    except OSError:
        return False


class _Held:
    """The ports the doctor holds (claimed, then opened) and the interlock of its board clients."""

    def __init__(self, claimed: bool = False) -> None:
        self.claimed = claimed  # the ports are this process's already (hil serve's worker)
        self.interlock = Interlock()  # closed on the way out: nothing here streams again once the doctor is done
        self.claims: list[PortClaims] = []
        self.links: list[SerialLink] = []

    async def ident(self, name: str, port: str, baud: int, *,
                    timeout_s: float) -> tuple[Finding, BoardClient | None]:
        """One link's ``ident`` finding and, when the board answered as expected, its client (its link open)."""
        try:
            if not self.claimed:
                self.claims.append(claim_ports({name: port}, HOLDER))
        except PortUnavailable as exc:
            return Finding(name, "ident", False, f"not asked: {exc}"), None
        try:
            link = await SerialLink.open(name, port, baud)
        except LinkError as exc:
            return Finding(name, "ident", False, f"not asked: {exc}"), None
        self.links.append(link)
        client = CLIENTS[name](link, self.interlock)
        counters = link.decoder.counters
        before = (counters.bytes, counters.frames_ok, counters.misaddressed)
        try:
            ident = await client.identify(timeout_s)
        except FingerprintMismatch as exc:
            return Finding(name, "ident", False, str(exc), _ident_values(client, exc)), None
        except LinkError as exc:
            if "no answer" not in str(exc):  # it answered, and is not the board this link expects
                return Finding(name, "ident", False, str(exc)), None
            return Finding(name, "ident", False, _no_answer(link, baud, timeout_s=timeout_s, before=before)), None
        kind = getattr(ident.board, "name", str(ident.board)).lower()
        return Finding(name, "ident", True,
                       f"{kind} board, firmware {ident.firmware_version!r}, serial {ident.serial_number}, catalogue "
                       f"{ident.catalogue_fingerprint:#010x} (protocol v{ident.protocol_version}) as this bench "
                       "expects", _ident_values(client, None)), client

    async def release(self) -> None:
        """Close every link (waiting for their ports to close) and release every claim. Never raises."""
        self.interlock.close("hil doctor done")
        for link in self.links:
            link.close()
        closing = [link.closed for link in self.links if not link.closed.done()]
        if closing:
            await asyncio.wait(closing, timeout=CLOSE_TIMEOUT_S)
        for claim in self.claims:
            claim.release()


def _ident_values(client: BoardClient, mismatch: FingerprintMismatch | None) -> dict[str, Any]:
    values: dict[str, Any] = {"expected_fingerprint": f"{CATALOGUE.fingerprint:#010x}",
                              "expected_protocol_version": CATALOGUE.protocol_version}
    if mismatch is None:
        values.update(client.ident_dict())
    return values


def _no_answer(link: SerialLink, baud: int, *, timeout_s: float, before: tuple[int, int, int]) -> str:
    """What to say of a board that did not answer IDENT_REQ, with what the link did hear meanwhile (``before``: its
    decoder's bytes, frames and misaddressed frames before the request)."""
    name, port, counters = link.name, link.port, link.decoder.counters
    heard, frames, misaddressed = (counters.bytes - before[0], counters.frames_ok - before[1],
                                   counters.misaddressed - before[2])
    if misaddressed:
        heard_what = (f"; {misaddressed} frame(s) for or from another node came meanwhile: is the right board on "
                      f"{port}?")
    elif heard and not frames:
        heard_what = (f"; {heard} bytes came meanwhile and not one frame: a baud rate mismatch, or another device "
                      "on this port")
    else:
        heard_what = "; not a byte came meanwhile" if not heard else ""
    return (f"{name}: no answer to IDENT_REQ on {port} within {timeout_s * 1e3:.0f} ms: check the wiring (the board "
            f"powered, its cable on this port, RS422 pairs the right way round) and that both ends run at {baud} "
            f"baud{heard_what}")


class _Samples:
    """The arrival time (host clock, ns) and tick of each GYRO_SAMPLE while :attr:`listening`, and the CLOCK_LATEs
    (the board wrote a sample late by its own clock)."""

    def __init__(self) -> None:
        self.arrivals_ns: list[int] = []
        self.ticks: list[int] = []
        self.board_us: list[int] = []
        self.clock_late = 0
        self.listening = True

    def on_frame(self, frame: Frame) -> None:
        if not self.listening:
            return
        kind = type(frame.message)
        if kind is GyroSample:
            self.arrivals_ns.append(time.perf_counter_ns())
            self.ticks.append(frame.message.tick)
            self.board_us.append(frame.message.t_us)
        elif kind is ClockLate:
            self.clock_late += 1


async def listen_to_stream(servo: ServoBoard, listen_s: float = LISTEN_S, *, watchdog_ms: float = WATCHDOG_MS,
                           judge_arrivals: bool = True, keep_alive: list[BoardClient] | None = None) -> Finding:
    """Start the servo board's stream as the session does (SERVO_CONFIG at 1 kHz, SERVO_MODE STREAM), listen
    ``listen_s``, stop it (SERVO_MODE IDLE, on every way out) and report the stream: its rate by the board's clock
    (the ticks over the samples' board time), the rate the bench received it at (the samples over the time from the
    first to the last, host clock), samples lost (gaps in the board's tick counter), the inter-arrival times' p50
    and p99, their difference (the jitter) and the longest gap.

    It passes when the board's rate is within 1 % of 1 kHz, no sample was lost, the board acknowledged the stop,
    and (``judge_arrivals``) the received rate is within 1 % of 1 kHz too and the longest gap at most
    ``watchdog_ms`` (a session's watchdog would trip on a longer one). ``judge_arrivals=False`` reports the
    arrivals without judging them: for the emulator's pseudo-terminals, whose timing is this PC's load's
    (:func:`is_pty`). ``keep_alive``: the boards (``servo`` among them or not) that get HOST_ALIVE every 0.1 s
    meanwhile. Nothing else is commanded: the motor driver stays as it is (disabled unless a session runs, and
    then the port would be held)."""
    link = servo.link
    samples = _Samples()
    previous, link.on_frame = link.on_frame, samples.on_frame
    boards = list(dict.fromkeys([servo, *(keep_alive or [])]))
    t0 = time.monotonic()
    failure = ""
    try:
        await servo.configure()
        await servo.start_stream()
        loop = asyncio.get_running_loop()
        until = loop.time() + listen_s
        while (left := until - loop.time()) > 0:
            uptime_ms = round((time.monotonic() - t0) * 1000)
            for board in boards:
                with contextlib.suppress(LinkError, OSError):
                    board.alive(uptime_ms)
            await asyncio.sleep(min(HOST_ALIVE_S, left))
    except LinkError as exc:
        failure = f"the stream did not start: {exc}"
    finally:
        samples.listening = False
        stopped = await _stop_stream(servo)
        link.on_frame = previous
    return _stream_finding(samples, listen_s, failure, stopped,
                           watchdog_ms=watchdog_ms if judge_arrivals else None)


async def _stop_stream(servo: ServoBoard) -> str:
    """SERVO_MODE IDLE: written at once (it goes out even if this task is cancelled again), then confirmed with an
    acknowledged one. '' when the board acknowledged it, else why not."""
    with contextlib.suppress(LinkError, OSError):
        servo.stop_stream_now()
    try:
        await servo.stop_stream()
    except (LinkError, OSError) as exc:
        return f"the stream's stop (SERVO_MODE IDLE) was not acknowledged: {exc}"
    return ""


def _stream_finding(samples: _Samples, listen_s: float, failure: str, stopped: str, *,
                    watchdog_ms: float | None) -> Finding:
    """The ``servo stream`` finding of what :class:`_Samples` collected (``watchdog_ms`` None: the arrivals are
    reported, not judged)."""
    arrivals, ticks = samples.arrivals_ns, samples.ticks
    n = len(arrivals)
    board_s = ((samples.board_us[-1] - samples.board_us[0]) % U32_SPAN) / 1e6 if n >= 2 else 0.0  # t_us wraps
    if n < 2 or board_s <= 0 or arrivals[-1] <= arrivals[0]:
        why = failure or (f"{n} GYRO_SAMPLE in {listen_s:g} s after SERVO_MODE STREAM was acknowledged: the board "
                          "does not stream (is it the servo board's firmware, with its gyro connected?)")
        return Finding("servo", "servo stream", False, "; ".join(filter(None, [why, stopped])), {"samples": n})
    board_hz = (ticks[-1] - ticks[0]) / board_s
    span_s = (arrivals[-1] - arrivals[0]) / 1e9
    received_hz = (n - 1) / span_s
    gaps_us = sorted((b - a) / 1e3 for a, b in itertools.pairwise(arrivals))
    p50, p99, longest = _pick(gaps_us, 0.5), _pick(gaps_us, 0.99), gaps_us[-1]
    lost = sum(b - a - 1 for a, b in itertools.pairwise(ticks) if b - a > 1)
    values = {"board_rate_hz": round(board_hz, 1), "received_rate_hz": round(received_hz, 1), "samples": n,
              "span_s": round(span_s, 3), "lost": lost, "gap_us_p50": round(p50, 1), "gap_us_p99": round(p99, 1),
              "jitter_us": round(p99 - p50, 1), "max_gap_ms": round(longest / 1e3, 2),
              "clock_late": samples.clock_late, "stopped": not stopped}
    detail = (f"{board_hz:.1f} Hz by the board's clock, received at {received_hz:.1f} Hz ({n} samples in "
              f"{span_s:.2f} s, {lost} lost); inter-arrival p50 {p50:.0f} us, p99 {p99:.0f} us, jitter (p99 - p50) "
              f"{p99 - p50:.0f} us, max gap {longest / 1e3:.1f} ms")
    if samples.clock_late:
        detail += f"; the board reported {samples.clock_late} sample(s) late by its own clock (CLOCK_LATE)"
    if watchdog_ms is None:
        detail += "; a pseudo-terminal (the emulator, sharing this PC's CPUs): the arrivals are not judged"
    problems = [failure] if failure else []
    if abs(board_hz - STREAM_HZ) > RATE_TOLERANCE * STREAM_HZ:
        problems.append(f"the board samples at {board_hz:.1f} Hz, not within {RATE_TOLERANCE:.0%} of {STREAM_HZ} "
                        "Hz: its firmware or its configuration (SERVO_CONFIG) is off")
    if lost:
        problems.append(f"{lost} sample(s) lost: the line is too slow or noisy (link errors), or the board skips "
                        "ticks")
    if watchdog_ms is not None and abs(received_hz - STREAM_HZ) > RATE_TOLERANCE * STREAM_HZ:
        problems.append(f"received at {received_hz:.1f} Hz, not within {RATE_TOLERANCE:.0%} of {STREAM_HZ} Hz: the "
                        "samples arrive late or bunched (the adapter's latency timer, this PC's load)")
    if watchdog_ms is not None and longest > watchdog_ms * 1e3:
        problems.append(f"a gap of {longest / 1e3:.1f} ms would trip a session's watchdog "
                        f"(safety.watchdog_ms={watchdog_ms:g}): check the adapter's latency timer and what else "
                        "runs on this PC")
    if stopped:
        problems.append(stopped)
    return Finding("servo", "servo stream", not problems, "; ".join([detail, *problems]), values)


def _pick(sorted_values: list[float], q: float) -> float:
    return sorted_values[min(len(sorted_values) - 1, int(q * len(sorted_values)))]
