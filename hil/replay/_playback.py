"""Capture playback (docs/capture.md): the player thread and the board's answers it reads, which share the
capture's timing.

**Capture playback** (:func:`replay_capture`, ``hil replay CAPTURE``; :func:`play_capture` to given
ports): the frames the bench sent in a capture (hil.link), written again, byte for byte, to a board's or an
emulator's ports with their original timing, by one thread that sleeps in select() (reading what comes in), then
spins, to each write's time. What comes back is decoded and counted: commands answered (ACK, NACK, IDENT), samples,
the board's timing reports. The stream starts only when the replayed SERVO_MODE STREAM asks for it; a write that
followed a sample in the capture goes out as long after the replayed stream's sample of the same tick
(``timing="samples"``), so DRIVE_CMD k answers sample k however the board is paced (a lockstep emulator waits for
each), or at its original time from the first write (``timing="clock"``). The board's rules apply as to the bench,
in either timing: the replay stops sending when the board stops streaming (a watchdog on the samples' arrival) or
latches a driver fault, and whatever it left enabled, streaming or swinging it then disables, stops and idles, and
sends nothing else. A capture that ends with a sample after its last write (a session killed mid-run) is played to
that sample: the safe end waits for it, so it cannot reach the board before the step that answers the last write.

:func:`replay_capture` (``_replay_capture``) is what ``hil replay CAPTURE`` calls (through hil.api): the ports or a
fresh emulator, then :func:`play_capture`.
"""

from __future__ import annotations

import contextlib
import math
import os
import select
import threading
import time
import zlib
from array import array
from collections import Counter, deque
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hil.link import (
    Capture,
    CaptureReader,
    PortClaims,
    PortUnavailable,
    claim_ports,
    find_capture,
    link_decoder,
    set_exclusive,
    time_ordered,
)
from hil.protocol import (
    CATALOGUE,
    LINE_RATE_BAUD,
    NO_LATENCY_US,
    Ack,
    AxisMask,
    Board,
    DriveDisable,
    DriveEnable,
    DriveStatus,
    Encoder,
    GyroSample,
    HexapodStart,
    HexapodStop,
    Ident,
    IdentRequest,
    LockstepAck,
    LoopTiming,
    Nack,
    ServoMode,
    StreamMode,
)
from hil.replay._controller import ReplayError

SPIN_S = 200e-6  # the last part of each wait is a spin that keeps polling the ports, the rest a select() sleep
FIRST_SAMPLE_WAIT_S = 2.0  # how long the replay waits for the stream the replayed SERVO_MODE STREAM starts
WATCHDOG_S = 0.1  # no awaited sample this long (beyond the capture's own gap): the board stopped; so does the replay
LINGER_S = 0.5  # after the last frame, replies are awaited this long
SAMPLE_TIMES_KEPT = 4096  # arrival times of the latest samples kept (4 s of stream), whatever the replay's length
_REPLY_ACK = {spec.msg_id for spec in CATALOGUE if spec.reply in ("ACK", "ACK/NACK")}
_NAMES = {spec.msg_id: spec.name for spec in CATALOGUE}
_ID = {spec.cls: spec.msg_id for spec in CATALOGUE}
Timing = str  # "samples" | "clock"


class Quantiles:
    """Quantiles of non-negative integers (here: ns) in fixed memory, however many are added: a log-linear
    histogram (HDR-like) exact below 128 and with buckets 1/64 of their value wide above (a quantile is its bucket's
    middle: within 0.8 %); count and maximum exact."""

    SUB = 64  # buckets per power of two, above 2 * SUB
    SIZE = 2 * SUB + 57 * SUB  # values up to 2**63

    __slots__ = ("buckets", "count", "max")

    def __init__(self) -> None:
        self.buckets = array("q", bytes(8 * self.SIZE))
        self.count = 0
        self.max = 0

    def add(self, value: int) -> None:
        v = max(0, int(value))
        if v < 2 * self.SUB:
            i = v
        else:
            shift = v.bit_length() - self.SUB.bit_length()  # v >> shift in [SUB, 2 * SUB)
            i = 2 * self.SUB + (shift - 1) * self.SUB + (v >> shift) - self.SUB
        self.buckets[i] += 1
        self.count += 1
        self.max = max(self.max, v)

    def _bounds(self, i: int) -> tuple[int, int]:
        if i < 2 * self.SUB:
            return i, i
        shift, top = divmod(i - 2 * self.SUB, self.SUB)
        shift += 1
        lo = (top + self.SUB) << shift
        return lo, lo + (1 << shift) - 1

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (0..1, nearest rank), NaN when empty."""
        if not self.count:
            return math.nan
        rank = max(1, math.ceil(q * self.count))
        seen = 0
        for i, n in enumerate(self.buckets):
            seen += n
            if seen >= rank:
                lo, hi = self._bounds(i)
                return float(min((lo + hi) / 2, self.max))
        return float(self.max)


@dataclass
class _Tx:
    """One write of the capture: when, on which link, the bytes and their frames; ``anchor`` the sample (stream
    number, tick) it followed and ``offset_ns`` how long after that sample's arrival it went out (``anchor`` None:
    before the first sample, ``offset_ns`` from the first write); ``gap_ns`` the capture's wait for that sample
    after the one before it. ``end``: no write, but the sample the capture received after its last write."""

    t_ns: int
    link: str
    data: bytes
    frames: list[tuple[int, int, Any]]  # (msg_id, seq, message) of the frames the write holds
    anchor: tuple[int, int] | None = None
    offset_ns: int = 0
    gap_ns: int = 0
    end: bool = False


@dataclass
class LinkPlayback:
    """One link's side of a playback: what went out, what came back, what the capture itself had."""

    sent: Counter = field(default_factory=Counter)  # message name -> frames written
    received: Counter = field(default_factory=Counter)  # message name -> frames decoded
    captured_rx: Counter = field(default_factory=Counter)  # message name -> frames the bench received in the capture
    acked: int = 0
    nacked: int = 0
    unanswered: int = 0
    nacks: Counter = field(default_factory=Counter)  # "MESSAGE: ERROR" -> count
    write_stalls: int = 0  # writes the port did not take whole within 50 ms
    decoder_errors: int = 0


@dataclass
class PlaybackResult:
    """What :func:`play_capture` sent and got back. ``commands``: frames expecting an ACK/NACK or IDENT, counted
    once however often the capture resent them; ``samples_*``: the replayed stream's GYRO_SAMPLEs compared, tick by
    tick, with the capture's first stream (equal in lockstep with the same seed and config; near in real time)."""

    capture: Path
    ports: dict[str, str]
    timing: str
    links: dict[str, LinkPlayback]
    frames_sent: int
    frames_in_capture: int
    commands: int
    answered: int
    stream_started: bool
    samples: int
    samples_compared: int
    samples_equal: int
    samples_lost: int  # samples a write was timed from that the replay never received
    first_differing_tick: int  # the first tick of the first stream whose sample differs from the capture's, -1: none
    loop_timing: dict[str, int]  # ticks reported, missing (0xFFFF), late_total and missing_total of the last report
    drive_enabled_seen: bool  # a DRIVE_STATUS said an axis was enabled
    drive_last_tick: int  # DRIVE_STATUS last_tick: the last DRIVE_CMD the driver applied
    stopped: str  # "" when the capture played to its end, else why the replay stopped early
    safe_end: list[str]  # what the replay sent at the end to leave the boards safe
    duration_s: float
    lateness_us: dict[str, float]  # how late the writes went out against their schedule: p50, p99, max
    record: Path | None = None  # the replay's own capture (what it sent and received), if asked for
    emulator: dict[str, Any] | None = None  # the fresh emulator replay_capture started: config, clock, seed

    def as_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in vars(self).items() if k != "links"}
        out["capture"], out["record"] = str(self.capture), str(self.record) if self.record else None
        out["links"] = {name: {"sent": dict(lp.sent), "received": dict(lp.received),
                               "captured_rx": dict(lp.captured_rx), "acked": lp.acked, "nacked": lp.nacked,
                               "unanswered": lp.unanswered, "nacks": dict(lp.nacks), "write_stalls": lp.write_stalls,
                               "decoder_errors": lp.decoder_errors} for name, lp in self.links.items()}
        return out


class _Port:
    """One link's port: pyserial opens it (baud rate, raw mode), the fd does the rest."""

    def __init__(self, name: str, path: str, baudrate: int) -> None:
        import serial  # noqa: PLC0415  (loaded only when a port is opened)

        self.name = name
        self.path = path
        try:
            self.ser = serial.Serial(path, baudrate=baudrate, timeout=0, exclusive=True)
            set_exclusive(self.ser.fd, True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise ReplayError(f"{name}: cannot open {path}: {exc}") from None
        self.ser.reset_input_buffer()
        self.fd: int = self.ser.fd
        os.set_blocking(self.fd, False)

    def write(self, data: bytes, give_up_s: float = 0.05) -> int:
        """Write all of ``data`` unless the port stays full ``give_up_s``; returns the bytes written."""
        view, done = memoryview(data), 0
        deadline = time.monotonic() + give_up_s
        while done < len(data):
            try:
                done += os.write(self.fd, view[done:])
            except BlockingIOError:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                select.select((), (self.fd,), (), left)
            except OSError:
                break
        return done

    def close(self) -> None:
        with contextlib.suppress(OSError):
            set_exclusive(self.fd, False)
        with contextlib.suppress(Exception):
            self.ser.close()


@dataclass
class _Captured:
    """What a playback needs to know of a capture before it starts (one streamed pass): the links the bench sent
    on and how many frames, the frames it received by link and name, a CRC-32 of each sample of the first stream
    by tick, and the header. The writes themselves are streamed again while playing (:func:`_writes`)."""

    tx_frames: Counter  # link -> frames the bench sent on it (its LOCKSTEP_ACKs aside)
    acknowledged: set[str]  # links the bench acknowledged in lockstep: the replay acknowledges on them too
    rx_counts: dict[str, Counter]
    samples: array
    meta: dict[str, Any]


class _Streams:
    """Numbers the streams of GYRO_SAMPLE (a stream that starts again at tick 0 is the next one), so a sample is
    known by (stream, tick) in the capture and in the replay alike."""

    def __init__(self) -> None:
        self.stream = -1
        self.last_tick: int | None = None

    def key(self, tick: int) -> tuple[int, int]:
        if self.last_tick is None or tick < self.last_tick or (tick == 0 and self.last_tick != 0):
            self.stream += 1
        self.last_tick = tick
        return self.stream, tick


def _scan_capture(path: Path) -> _Captured:
    reader = CaptureReader(path)
    tx_dec = {name: link_decoder(name, "tx") for name in reader.links}
    rx_dec = {name: link_decoder(name, "rx") for name in reader.links}
    tx_frames: Counter = Counter()
    acknowledged: set[str] = set()
    rx_counts: dict[str, Counter] = {name: Counter() for name in reader.links}
    samples = array("q")
    streams = _Streams()
    for rec in time_ordered(reader):
        if rec.direction == "tx":
            for f in tx_dec[rec.link].feed(rec.data):
                if type(f.message) is LockstepAck:
                    acknowledged.add(rec.link)
                else:
                    tx_frames[rec.link] += 1
        elif rec.direction == "rx":
            for f in rx_dec[rec.link].feed(rec.data):
                msg = f.message
                rx_counts[rec.link][_NAMES[_ID[type(msg)]]] += 1
                if type(msg) is GyroSample:
                    key = streams.key(msg.tick)
                    if key[0] == 0 and msg.tick == len(samples):
                        samples.append(_sample_key(msg))
    if reader.end == "corrupt":
        raise ReplayError(f"{path}: {reader.problem}")
    return _Captured(+tx_frames, acknowledged, rx_counts, samples, reader.meta)


def _writes(path: Path, links: set[str]) -> Iterator[_Tx]:
    """The capture's writes on ``links`` in time order, each timed from the last sample the bench had received
    before it (streamed: memory stays bounded whatever the capture's length). When a sample came after the last
    write (a capture cut mid-run), a last ``_Tx`` with ``end`` set names it: the board's answer to that write."""
    reader = CaptureReader(path)
    tx_dec = {name: link_decoder(name, "tx") for name in links}
    servo = link_decoder("servo", "rx")
    streams = _Streams()
    last: tuple[int, int] | None = None
    last_t = prev_t = 0
    first: int | None = None
    tail: _Tx | None = None  # the first sample after the latest write
    for rec in time_ordered(reader):
        if rec.direction == "rx" and rec.link == "servo":
            for f in servo.feed(rec.data):
                if type(f.message) is GyroSample:
                    last, prev_t, last_t = streams.key(f.message.tick), last_t, rec.t_ns
                    if tail is None and first is not None:
                        tail = _Tx(rec.t_ns, "", b"", [], last, 0, last_t - prev_t if prev_t else 0, end=True)
        elif rec.direction == "tx" and rec.link in links:
            # the bench's LOCKSTEP_ACKs answered the captured boards' frames: the player acknowledges its own
            frames = [(_ID[type(f.message)], f.seq, f.message) for f in tx_dec[rec.link].feed(rec.data)
                      if type(f.message) is not LockstepAck]
            if not frames:  # the bench writes each frame on its own: a write of acknowledgements only
                continue
            tail = None
            if first is None:
                first = rec.t_ns
            if last is None:
                yield _Tx(rec.t_ns, rec.link, rec.data, frames, None, rec.t_ns - first, 0)
            else:
                gap = last_t - prev_t if prev_t else 0
                yield _Tx(rec.t_ns, rec.link, rec.data, frames, last, rec.t_ns - last_t, gap)
    if tail is not None:
        yield tail


def _sample_key(g: GyroSample) -> int:
    return zlib.crc32(repr(tuple(g)).encode())


class CapturePlayer:
    """Plays one capture's host-side frames to ``ports`` (link name -> device path); see :func:`play_capture`."""

    def __init__(self, capture: Path, ports: Mapping[str, str], *, baudrate: int = LINE_RATE_BAUD,
                 timing: Timing = "samples", watchdog_s: float = WATCHDOG_S, linger_s: float = LINGER_S,
                 record_dir: Path | None = None, links: set[str] | None = None) -> None:

        if timing not in ("samples", "clock"):
            raise ReplayError(f"timing {timing!r}: samples or clock")
        self.capture = find_capture(Path(capture))
        cap = _scan_capture(self.capture)
        self.meta = cap.meta
        used = set(cap.tx_frames)
        self.link_names = sorted(used if links is None else used & set(links))
        missing = [name for name in self.link_names if name not in ports]
        if missing:
            raise ReplayError(f"no port for link(s) {', '.join(missing)} (the capture sent on "
                              f"{', '.join(self.link_names)})")
        self.frames_in_capture = sum(cap.tx_frames[name] for name in self.link_names)
        if not self.frames_in_capture:
            raise ReplayError(f"{self.capture}: the capture holds nothing the bench sent")
        self.ports = {name: str(ports[name]) for name in self.link_names}
        self.baudrate = baudrate
        self.timing = timing
        self.watchdog_s = watchdog_s
        self.linger_s = linger_s
        self.record_dir = record_dir
        self.captured_samples = cap.samples
        # the bench acknowledged on these links (a lockstep world waits for it): the player does as it did
        self._acknowledge = {name: Encoder(Board.HOST) for name in cap.acknowledged & set(self.link_names)}
        self.links = {name: LinkPlayback(captured_rx=cap.rx_counts.get(name, Counter())) for name in self.link_names}
        self._stop = threading.Event()
        self._wake_r = self._wake_w = -1
        self._sample_rx: dict[tuple[int, int], int] = {}  # (stream, tick) -> when the replay received it
        self._sample_order: deque[tuple[int, int]] = deque()  # its keys, oldest first: SAMPLE_TIMES_KEPT at most
        self._forgotten: tuple[tuple[int, int], int] | None = None  # the newest sample whose time was let go
        self._latest: tuple[int, int] | None = None
        self._streams = _Streams()
        self._first_wait: int | None = None
        self.stopped = ""
        self.first_sample_rx: int | None = None
        self.last_sample_rx = 0
        self.samples = self.samples_compared = self.samples_equal = self.samples_lost = 0
        self.first_differing_tick = -1
        self.timing_report = {"ticks_reported": 0, "missing": 0, "late_total": 0, "missing_total": 0}
        self.drive_enabled_seen = False
        self.drive_last_tick = -1
        self._expect: set[tuple[str, int, int]] = set()  # (link, msg_id, seq): frames that expect a reply
        self._answered: set[tuple[str, int, int]] = set()
        self._last_seq: dict[str, int] = {}
        self._state = {"enabled": False, "streaming": False, "swinging": False}
        self.lateness = Quantiles()  # how late each write went out against its schedule, ns
        self.safe_end: list[str] = []
        self.record: Capture | None = None

    # --- control ---------------------------------------------------------------------------------------------

    def stop(self, reason: str = "stopped") -> None:
        """Stop sending captured frames (any thread); the replay then leaves the boards safe."""
        if not self.stopped:
            self.stopped = reason
        self._stop.set()
        if self._wake_w >= 0:
            with contextlib.suppress(OSError):
                os.write(self._wake_w, b"x")

    def run(self) -> PlaybackResult:
        """Open the ports, play in a thread of its own, return what came of it. Ctrl-C stops it safely."""
        ports: dict[str, _Port] = {}
        t0 = time.monotonic()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        claims: PortClaims | None = None
        try:
            try:  # owned, as a session owns its ports: a port another bench holds is refused by name
                claims = claim_ports({name: self.ports[name] for name in self.link_names}, f"replay {self.capture}")
            except PortUnavailable as exc:
                raise ReplayError(str(exc)) from None
            for name in self.link_names:
                ports[name] = _Port(name, self.ports[name], self.baudrate)
            if self.record_dir is not None:
                self.record = Capture.create(self.record_dir, f"replay-{self.capture.stem}",
                                             links=self.link_names, meta={"replay_of": str(self.capture)})
            player = threading.Thread(target=self._main, args=(ports,), name="hil-replay", daemon=True)
            player.start()
            try:
                while player.is_alive():
                    player.join(0.1)
            except KeyboardInterrupt:
                self.stop("interrupted")
                player.join(5.0)
        finally:
            for port in ports.values():
                port.close()
            if claims is not None:
                claims.release()
            if self.record is not None:
                self.record.close()
            for fd in (self._wake_r, self._wake_w):
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._wake_r = self._wake_w = -1
        for key in self._expect - self._answered:
            self.links[key[0]].unanswered += 1
        lat = self.lateness
        return PlaybackResult(
            capture=self.capture, ports=dict(self.ports), timing=self.timing, links=self.links,
            frames_sent=sum(sum(lp.sent.values()) for lp in self.links.values()),
            frames_in_capture=self.frames_in_capture,
            commands=len(self._expect), answered=len(self._answered),
            stream_started=self.first_sample_rx is not None, samples=self.samples,
            samples_compared=self.samples_compared, samples_equal=self.samples_equal, samples_lost=self.samples_lost,
            first_differing_tick=self.first_differing_tick,
            loop_timing=dict(self.timing_report), drive_enabled_seen=self.drive_enabled_seen,
            drive_last_tick=self.drive_last_tick, stopped=self.stopped, safe_end=self.safe_end,
            duration_s=round(time.monotonic() - t0, 3),
            lateness_us={"p50": lat.quantile(0.5) / 1e3, "p99": lat.quantile(0.99) / 1e3,
                         "max": lat.max / 1e3 if lat.count else math.nan},
            record=None if self.record is None else self.record.path)

    # --- the player thread: pacing and reading in one loop -------------------------------------------------------

    def _main(self, ports: dict[str, _Port]) -> None:
        self._ports = ports
        self._decoders = {name: link_decoder(name, "rx") for name in ports}
        self._by_fd = {port.fd: name for name, port in ports.items()}
        self._fds = [*self._by_fd, self._wake_r]
        try:
            self._play(ports)
        except Exception as exc:  # whatever happened, the boards are left safe
            self.stop(f"replay failed: {type(exc).__name__}: {exc}")
        finally:
            self._safe_end(ports)
            give_up = time.monotonic_ns() + int(self.linger_s * 1e9)  # the replies still due
            self._serve(give_up, lambda: self._expect <= self._answered, stoppable=False)
            for name, dec in self._decoders.items():
                self.links[name].decoder_errors = dec.counters.errors()

    def _serve(self, until_ns: int, done: Any = None, *, stoppable: bool = True) -> bool:
        """Read and handle what the boards send until ``time.monotonic_ns() >= until_ns`` or ``done()`` holds (True
        then). Sleeps in select() (which wakes for incoming bytes, read and stamped as they come) to SPIN_S before
        ``until_ns``, then spins, still polling the ports: a write is timed to tens of microseconds."""
        spin_ns = int(SPIN_S * 1e9)
        fds, wake, by_fd = self._fds, self._wake_r, self._by_fd
        while True:
            if done is not None and done():
                return True
            left = until_ns - time.monotonic_ns()
            if left <= 0 or (stoppable and self._stop.is_set()):
                return False
            timeout = min((left - spin_ns) / 1e9, 0.05) if left > spin_ns else 0.0
            try:
                ready = select.select(fds, (), (), timeout)[0]
            except (OSError, ValueError):
                return False
            for fd in ready:
                if fd == wake:
                    with contextlib.suppress(OSError):
                        os.read(wake, 64)
                    continue
                try:
                    data = os.read(fd, 65536)
                except BlockingIOError:
                    continue
                except OSError:
                    fds.remove(fd)
                    continue
                t_ns = time.monotonic_ns()
                name = by_fd[fd]
                if self.record is not None:
                    self.record.link(name).rx(data, t_ns)
                last = None
                for frame in self._decoders[name].feed(data):
                    self._on_frame(name, frame.message, t_ns)
                    last = frame
                if last is not None and name in self._acknowledge:
                    self._ack(name, last.seq)

    def _ack(self, link: str, seq: int) -> None:
        """LOCKSTEP_ACK of what the player has handled on ``link`` up to ``seq`` (docs/protocol.md, "Host liveness"),
        numbered apart from the captured frames it plays."""
        data = self._acknowledge[link].encode(LockstepAck(seq), Board[link.upper()])
        port = self._ports[link]
        if port.write(data) and self.record is not None:
            self.record.link(link).tx(data)

    def _play(self, ports: dict[str, _Port]) -> None:
        first: int | None = None
        start = time.monotonic_ns()
        for tx in _writes(self.capture, set(self.link_names)):
            if first is None:
                first = tx.t_ns
            if self._stop.is_set():
                return
            if tx.end:  # the capture's end: the sample that answered its last write, before the safe end
                if tx.anchor is not None and self._state["streaming"]:
                    self._await_tail(tx.anchor, tx.gap_ns)
                return
            if self.timing == "samples" and tx.anchor is not None:
                t_anchor = self._await_sample(tx.anchor, tx.gap_ns)
                if t_anchor is None:
                    return
                due = t_anchor + tx.offset_ns
                self._serve(due)
            else:
                due = start + (tx.t_ns - first)
                self._serve(due)
                if tx.anchor is not None and self.first_sample_rx is None:  # clock timing: the stream must start
                    if not self._await_first():
                        return
                    waited = max(0, time.monotonic_ns() - due)  # the schedule moves by the wait
                    start += waited
                    due += waited
                if tx.anchor is not None and not self._stream_alive(tx):
                    return
            if self._stop.is_set():
                return
            self.lateness.add(time.monotonic_ns() - due)
            self._send(ports[tx.link], tx.link, tx.data, tx.frames)

    def _await_tail(self, key: tuple[int, int], gap_ns: int) -> None:
        """After the last write: wait for the sample ``key`` the capture received after it (or a later one), so the
        safe end cannot reach the board before the step that answers that write and change or suppress the sample.
        Gives up quietly after the capture's gap before it plus ``watchdog_s``: the capture is played either way."""
        give_up = self.last_sample_rx + gap_ns + int(self.watchdog_s * 1e9)
        self._serve(give_up, lambda: self._latest is not None and self._latest >= key)

    def _await_first(self) -> bool:
        """Clock timing: wait up to FIRST_SAMPLE_WAIT_S for the stream's first sample; False (stopped) if none."""
        give_up = time.monotonic_ns() + int(FIRST_SAMPLE_WAIT_S * 1e9)
        if self._serve(give_up, lambda: self.first_sample_rx is not None):
            return True
        if not self._stop.is_set():
            self.stop("no GYRO_SAMPLE: the servo board did not start its stream")
        return False

    def _stream_alive(self, tx: _Tx) -> bool:
        """Clock timing's watchdog, before a write the capture made ``tx.offset_ns`` after a sample: False (and the
        replay stops) when the replay's stream has been silent longer than the capture's was at this write, plus
        the capture's gap before that sample, plus ``watchdog_s``. Not while the replay itself has idled the
        stream (a replayed SERVO_MODE IDLE)."""
        if not self._state["streaming"] or self.first_sample_rx is None:
            return True
        silence = time.monotonic_ns() - self.last_sample_rx
        if silence <= tx.offset_ns + tx.gap_ns + int(self.watchdog_s * 1e9):
            return True
        self.stop(f"watchdog: no GYRO_SAMPLE for {silence / 1e6:.0f} ms (the capture's last sample was "
                  f"{tx.offset_ns / 1e6:.0f} ms old at this write)")
        return False

    def _await_sample(self, key: tuple[int, int], gap_ns: int) -> int | None:
        """When the replay received the sample ``key``. If a later one came instead, it was lost: the latest
        arrival stands in. None (and the replay stops) when none came in time: the first within
        FIRST_SAMPLE_WAIT_S, later ones within the capture's own gap before it plus ``watchdog_s``."""
        while True:
            t = self._sample_rx.get(key)
            if t is not None:
                while self._sample_order and self._sample_order[0] < key:  # older ones are never awaited again
                    self._sample_rx.pop(self._sample_order.popleft(), None)
                return t
            if self._forgotten is not None and key <= self._forgotten[0]:  # came so long ago its time was let go
                return self._forgotten[1]  # a later sample's time: the write is overdue either way
            if self._stop.is_set():
                return None
            if self._latest is not None and self._latest > key:
                self.samples_lost += 1
                return self.last_sample_rx
            now = time.monotonic_ns()
            if self.first_sample_rx is None:
                if self._first_wait is None:
                    self._first_wait = now + int(FIRST_SAMPLE_WAIT_S * 1e9)
                give_up = self._first_wait
                why = "no GYRO_SAMPLE: the servo board did not start its stream"
            else:
                give_up = self.last_sample_rx + gap_ns + int(self.watchdog_s * 1e9)
                why = f"watchdog: no GYRO_SAMPLE for {(now - self.last_sample_rx) / 1e6:.0f} ms (stream " \
                      f"{key[0]}, tick {key[1]} awaited)"
            if now >= give_up:
                self.stop(why)
                return None
            self._serve(give_up, lambda: key in self._sample_rx or (self._latest is not None and self._latest > key))

    def _send(self, port: _Port, link: str, data: bytes, frames: list[tuple[int, int, Any]]) -> None:
        lp = self.links[link]
        for msg_id, seq, msg in frames:  # registered before the write: a reply may come at once
            if msg_id in _REPLY_ACK or msg_id == _ID[IdentRequest]:
                self._expect.add((link, msg_id, seq))
            self._last_seq[link] = seq
            self._track_state(msg)
        n = port.write(data)
        if self.record is not None and n:
            self.record.link(link).tx(data[:n])
        if n < len(data):
            lp.write_stalls += 1
            return
        for msg_id, _, _ in frames:
            lp.sent[_NAMES[msg_id]] += 1

    def _track_state(self, msg: Any) -> None:
        kind, st = type(msg), self._state
        if kind is DriveEnable:
            st["enabled"] = True
        elif kind is DriveDisable:
            st["enabled"] = False
        elif kind is ServoMode:
            st["streaming"] = msg.mode == StreamMode.STREAM
        elif kind is HexapodStart:
            st["swinging"] = True
        elif kind is HexapodStop:
            st["swinging"] = False

    def _safe_end(self, ports: dict[str, _Port]) -> None:
        """Disable, stop and idle whatever the replay left on: new frames, numbered after the link's last."""
        plan = (("enabled", "driver", DriveDisable(AxisMask.BOTH), Board.DRIVER),
                ("swinging", "hexapod", HexapodStop(), Board.HEXAPOD),
                ("streaming", "servo", ServoMode(StreamMode.IDLE), Board.SERVO))
        for flag, link, msg, dst in plan:
            if not self._state[flag] or link not in ports:
                continue
            enc = Encoder(Board.HOST)
            enc.next_seq = self._last_seq.get(link, -1) + 1
            seq = enc.next_seq
            data = enc.encode(msg, dst)
            self.safe_end.append(_NAMES[_ID[type(msg)]])
            with contextlib.suppress(OSError):
                self._send(ports[link], link, data, [(_ID[type(msg)], seq, msg)])

    def _on_frame(self, link: str, msg: Any, t_ns: int) -> None:
        lp = self.links[link]
        kind = type(msg)
        lp.received[_NAMES[_ID[kind]]] += 1
        if kind is GyroSample:
            key = self._streams.key(msg.tick)
            self.samples += 1
            if key[0] == 0 and msg.tick < len(self.captured_samples):
                self.samples_compared += 1
                if _sample_key(msg) == self.captured_samples[msg.tick]:
                    self.samples_equal += 1
                elif self.first_differing_tick < 0:
                    self.first_differing_tick = msg.tick
            self.last_sample_rx = t_ns
            if self.first_sample_rx is None:
                self.first_sample_rx = t_ns
            self._sample_rx[key] = t_ns
            self._sample_order.append(key)
            self._latest = key
            while len(self._sample_order) > SAMPLE_TIMES_KEPT:  # bounded, whether or not writes await them
                old = self._sample_order.popleft()
                t_old = self._sample_rx.pop(old, None)
                if t_old is not None:
                    self._forgotten = (old, t_old)
        elif kind is Ack or kind is Nack:
            reply = (link, msg.msg_id, msg.seq)
            err = "" if kind is Ack else f"{_NAMES.get(msg.msg_id, hex(msg.msg_id))}: " \
                                         f"{getattr(msg.error, 'name', msg.error)}"
            if reply in self._expect and reply not in self._answered:
                self._answered.add(reply)
                if kind is Ack:
                    lp.acked += 1
                else:
                    lp.nacked += 1
            if err:  # also a NACK to a frame that expects none (DRIVE_CMD while the driver is disabled)
                lp.nacks[err] += 1
        elif kind is Ident:
            waiting = sorted(k for k in self._expect - self._answered if k[0] == link and k[1] == _ID[IdentRequest])
            if waiting:
                self._answered.add(waiting[0])
                lp.acked += 1
        elif kind is LoopTiming:
            t = self.timing_report
            t["ticks_reported"] += len(msg.latency_us)
            t["missing"] += sum(1 for v in msg.latency_us if v == NO_LATENCY_US)
            t["late_total"], t["missing_total"] = msg.late_total, msg.missing_total
        elif kind is DriveStatus:
            self.drive_last_tick = msg.last_tick
            if msg.enabled:
                self.drive_enabled_seen = True
            if msg.faults & 0x03:
                self.stop(f"driver fault {msg.faults:#04x}: overcurrent latched")


def play_capture(capture: Path, ports: Mapping[str, str], **kwargs: Any) -> PlaybackResult:
    """Play ``capture``'s host-side frames to ``ports`` (link name -> serial device or emulator pty) and count what
    comes back (see the module docstring). ``timing="samples"`` (default): a write that followed a GYRO_SAMPLE in the
    capture goes out as long after the replayed stream's sample of the same tick, so the board sees the same
    answers to the same samples even where it runs at another pace (lockstep); ``"clock"``: every write at its
    original time from the first (the stream's start awaited, as in samples timing, the schedule moving by that
    wait). Either way the replay stops when the stream does (``watchdog_s`` beyond the capture's own silence) and
    leaves the boards safe. Other keywords: ``baudrate``, ``watchdog_s``, ``linger_s``, ``record_dir`` (write
    the replay's own capture there), ``links`` (only these links). Blocks until done; Ctrl-C stops it, leaving the
    boards safe."""
    return CapturePlayer(capture, ports, **kwargs).run()
