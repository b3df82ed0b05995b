"""One board's serial link: a pty behind a stable path, the board's codec, and the faults it injects.

The host opens ``path``, a symlink in the emulator's run directory to the current pty (like a udev
``/dev/serial/by-id`` link), so a disconnect (pty closed, a new one made) is followed by a reopen of
the same path. Faults apply to what the board sends; every one is recorded with its tick
(:class:`FaultRecorder`) so a test can compare what the host saw with what happened.

Timing of faults is in simulated ticks (1 ms), so a scheduled fault hits the same tick in lockstep
and in realtime runs, and the continuous faults draw from a per-link RNG seeded from the emulator's
seed: the same seed and the same traffic give the same corrupted bytes.
"""

from __future__ import annotations

import errno
import json
import math
import os
import random
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any

from firmware_stub.config import LinkFaults, LinkName
from firmware_stub.pty_port import PtyPort
from hil.protocol import SYNC, Decoder, Encoder, Frame

MAX_RECORDS = 200_000  # beyond this, faults are counted but no longer listed


@dataclass(frozen=True)
class FaultRecord:
    tick: int  # simulated ms since the emulator started
    link: str
    kind: str  # bit_flip, byte_drop, garbage, stall, latency_spike, reset, disconnect, reconnect, ... board events
    detail: dict[str, Any] = field(default_factory=dict)
    wall_s: float = 0.0  # time.time() when it happened

    @property
    def t_s(self) -> float:
        return self.tick * 1e-3

    def as_dict(self) -> dict[str, Any]:
        return {"t_s": round(self.t_s, 3), **asdict(self)}


class FaultRecorder:
    """Every injected fault and every safety-relevant board event, in order, optionally as JSON lines."""

    def __init__(self, log_path: Path | None = None) -> None:
        self.records: list[FaultRecord] = []
        self.dropped = 0
        self.now_tick = 0
        self._file: IO[str] | None = log_path.open("w") if log_path else None

    def record(self, link: str, kind: str, **detail: Any) -> None:
        rec = FaultRecord(self.now_tick, link, kind, detail, time.time())
        if len(self.records) < MAX_RECORDS:
            self.records.append(rec)
        else:
            self.dropped += 1
        if self._file:
            self._file.write(json.dumps(rec.as_dict()) + "\n")

    def flush(self) -> None:
        if self._file:
            self._file.flush()

    def close(self) -> None:
        if self._file:
            self._file.close()
            self._file = None


@dataclass
class LinkStats:
    tx_frames: int = 0
    tx_bytes: int = 0
    bits_flipped: int = 0
    bytes_dropped: int = 0
    garbage_bytes: int = 0
    frames_suppressed: int = 0  # not sent: stall or disconnect
    tx_overflow_bytes: int = 0  # the pty was full (nobody reading): lost, as a UART would lose them
    resets: int = 0
    disconnects: int = 0


class _Countdown:
    """Bernoulli(p) events over a stream of trials, drawn as geometric gaps (cheap for tiny p)."""

    def __init__(self, rng: random.Random, p: float) -> None:
        self.rng = rng
        self.set_rate(p)

    def set_rate(self, p: float) -> None:
        self.p = p
        self.left = self._gap()

    def _gap(self) -> int:
        if self.p <= 0:
            return 1 << 62
        if self.p >= 1:
            return 0
        return int(math.log(1.0 - self.rng.random()) / math.log(1.0 - self.p))

    def hits(self, n: int) -> list[int]:
        """Indices in [0, n) of the trials that hit."""
        out = []
        pos = self.left
        while pos < n:
            out.append(pos)
            pos += 1 + self._gap()
        self.left = pos - n
        return out


class BoardLink:
    """A board's end of its serial link. ``send`` applies the faults; ``receive`` decodes what came in."""

    def __init__(self, name: LinkName, board_id: int, run_dir: Path, faults: LinkFaults, *, seed: int,
                 recorder: FaultRecorder, byte_time_s: float = 0.0) -> None:
        """``byte_time_s``: a byte's time on the wire (10 bits at the line's rate; 0: no wire time)."""
        self.name = name
        self.byte_time_s = byte_time_s
        self.board_id = board_id
        self.path = run_dir / name.value
        self.recorder = recorder
        self.rng = random.Random(f"{seed}:{name.value}")
        self.stats = LinkStats()
        self.encoder = Encoder(board_id)
        self.decoder = Decoder()
        self.port: PtyPort | None = None
        self._flip = _Countdown(self.rng, 0.0)
        self._drop = _Countdown(self.rng, 0.0)
        self.faults = faults
        self.set_faults(faults)
        self.stalled_until = -1  # tick
        self.held_until = -1
        self.held = bytearray()
        self.reconnect_at = -1
        self._deferred: bytearray | None = None
        # lockstep: the host acknowledges what it has handled (LOCKSTEP_ACK); None: nothing to wait for
        self.host_acks = False  # the host has acknowledged on this link since it was (re)opened
        self.sent_seq: int | None = None  # the last frame written intact, until the host acknowledges it
        self._open()

    # --- the pty behind the path -------------------------------------------------------------------

    def _open(self) -> None:
        self.port = PtyPort()
        os.set_blocking(self.port.master_fd, False)
        tmp = self.path.with_suffix(".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(self.port.path)
        tmp.replace(self.path)  # atomic: the host never sees the path missing during a reconnect

    @property
    def fd(self) -> int | None:
        return self.port.master_fd if self.port else None

    @property
    def connected(self) -> bool:
        return self.port is not None

    def close(self) -> None:
        if self.port:
            self.port.close()
            self.port = None
        self.path.unlink(missing_ok=True)

    def disconnect(self, duration_ticks: int, now_tick: int) -> None:
        """Close the pty (the host's reads fail) and make a new one behind the path after duration_ticks."""
        if self.port:
            self.port.close()
            self.port = None
        self.stats.disconnects += 1
        self.reconnect_at = now_tick + max(1, duration_ticks)
        self.decoder.reset()
        self.host_acks, self.sent_seq = False, None
        self.recorder.record(self.name, "disconnect", duration_ms=duration_ticks)

    # --- faults ------------------------------------------------------------------------------------

    def set_faults(self, faults: LinkFaults) -> None:
        self.faults = faults
        self._flip.set_rate(faults.bit_error_rate)
        self._drop.set_rate(faults.drop_byte_rate)

    def stall(self, duration_ticks: int, now_tick: int) -> None:
        self.stalled_until = max(self.stalled_until, now_tick + duration_ticks)
        self.recorder.record(self.name, "stall", duration_ms=duration_ticks, until_tick=self.stalled_until)

    def latency_spike(self, duration_ticks: int, now_tick: int) -> None:
        self.held_until = max(self.held_until, now_tick + duration_ticks)
        self.recorder.record(self.name, "latency_spike", duration_ms=duration_ticks, until_tick=self.held_until)

    def garbage(self, n_bytes: int, reason: str = "scheduled") -> None:
        burst = bytearray(self.rng.randbytes(n_bytes))
        if n_bytes >= 2 and self.rng.random() < 0.5:  # a false sync word exercises the host's resync
            at = self.rng.randrange(n_bytes - 1)
            burst[at : at + 2] = SYNC
        self.stats.garbage_bytes += n_bytes
        self.recorder.record(self.name, "garbage", n_bytes=n_bytes, reason=reason)
        self._write(bytes(burst))

    def on_tick(self, tick: int) -> None:
        """Release held output and reconnect when due (called once per simulated tick)."""
        if self.reconnect_at >= 0 and tick >= self.reconnect_at:
            self.reconnect_at = -1
            self._open()
            self.recorder.record(self.name, "reconnect", path=str(self.port.path if self.port else ""))
        if self.held and tick >= self.held_until:
            data, self.held = bytes(self.held), bytearray()
            self._write(data)

    def busy_until(self) -> int:
        """Last tick of a stall, hold or disconnect in progress (-1 when the link is delivering)."""
        if self.port is None:
            return self.reconnect_at
        return max(self.stalled_until, self.held_until if self.held or self.held_until > 0 else -1)

    # --- lockstep acknowledgements -----------------------------------------------------------------

    def on_host_ack(self, seq: int) -> None:
        """LOCKSTEP_ACK: the host has handled this link's frames up to ``seq``."""
        self.host_acks = True
        if seq == self.sent_seq:
            self.sent_seq = None

    @property
    def unacknowledged(self) -> bool:
        """Lockstep: a frame went out intact that a host which acknowledges has not acknowledged yet."""
        return self.host_acks and self.sent_seq is not None

    def forget_acks(self) -> None:
        """The host did not acknowledge in time: wait for it again only once it acknowledges again."""
        self.host_acks, self.sent_seq = False, None

    # --- traffic -----------------------------------------------------------------------------------

    def wire_s(self, n_bytes: int) -> float:
        """Seconds ``n_bytes`` take on this link's wire (0 with the wire's time off)."""
        return n_bytes * self.byte_time_s

    @property
    def pending_bytes(self) -> int:
        """Bytes the board has queued since :meth:`defer` and not yet written."""
        return len(self._deferred) if self._deferred is not None else 0

    def send(self, message: Any, dst: int, tick: int) -> bool:
        """Encode and send one message; False when it did not go out intact (stalled, disconnected,
        corrupted or dropped in part)."""
        frame = self.encoder.encode(message, dst)
        if self.port is None or tick < self.stalled_until:
            self.stats.frames_suppressed += 1
            return False
        intact = True
        f = self.faults
        if f.garbage_rate and self.rng.random() < f.garbage_rate:
            self.garbage(self.rng.randint(1, f.garbage_max_bytes), reason="garbage_rate")
        if f.bit_error_rate or f.drop_byte_rate:
            data = bytearray(frame)
            seq = int.from_bytes(frame[6:8], "little")
            for bit in self._flip.hits(len(data) * 8):
                data[bit >> 3] ^= 1 << (bit & 7)
                self.stats.bits_flipped += 1
                self.recorder.record(self.name, "bit_flip", msg_id=frame[5], seq=seq, byte=bit >> 3, bit=bit & 7)
                intact = False
            dropped = self._drop.hits(len(data))
            for i in reversed(dropped):
                del data[i]
                self.stats.bytes_dropped += 1
                self.recorder.record(self.name, "byte_drop", msg_id=frame[5], seq=seq, byte=i)
                intact = False
            frame = bytes(data)
        self.stats.tx_frames += 1
        if tick < self.held_until:
            self.held += frame
            return False  # not on the wire yet
        sent = self._write(frame) and intact
        # only an intact frame is worth waiting for: the host acknowledges frames it could decode
        self.sent_seq = int.from_bytes(frame[6:8], "little") if sent else None
        return sent

    def defer(self) -> None:
        """Queue what the board sends until :meth:`flush` (realtime: computed early, written on the deadline)."""
        self._deferred = bytearray()

    def flush(self) -> None:
        data, self._deferred = self._deferred, None
        if data:
            self._write(bytes(data))

    def _write(self, data: bytes) -> bool:
        if self._deferred is not None:
            self._deferred += data
            return True
        if self.port is None:
            return False
        view = memoryview(data)
        try:
            while view:
                view = view[os.write(self.port.master_fd, view) :]
        except BlockingIOError:
            self.stats.tx_overflow_bytes += len(view)
            return False
        except OSError as exc:
            if exc.errno not in (errno.EIO, errno.EBADF):
                raise
            return False
        self.stats.tx_bytes += len(data)
        return True

    def receive(self) -> list[Frame]:
        """Decode whatever the host has sent (call when the fd is readable)."""
        if self.port is None:
            return []
        try:
            data = os.read(self.port.master_fd, 65536)
        except (BlockingIOError, OSError):
            return []
        return self.decoder.feed(data)

    def reset_codec(self) -> None:
        """A board reboot: sequence numbers restart at 0, half-received frames are forgotten."""
        self.encoder = Encoder(self.board_id)
        self.decoder.reset()
        self.sent_seq = None
        self.stats.resets += 1
