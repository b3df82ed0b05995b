"""The four boards of the lab (seed 000, Fig. 7), each speaking the protocol on its own link.

Every board answers IDENT_REQ with IDENT (firmware version, catalogue fingerprint), sends IDENT when
it boots, a HEARTBEAT every second, ACK/NACK to commands, and its periodic messages on the world's
1 ms tick. The boards read and drive one shared :class:`~firmware_stub.plant.Plant` through the
:class:`World` they live in (the emulator).

What every board does with a frame from its link (:meth:`EmulatedBoard.receive`): drop and count
what is not from the host, not addressed to it, or not a message the host sends on its link; note
that the host is alive (the host timer, docs/protocol.md "Host liveness"); answer a resent command
(same id and sequence number as the last one) with the stored reply without acting again; else
handle it. When the host timer expires the board records ``host_timeout`` and puts itself in its
safe state (:meth:`EmulatedBoard.protect`, one small override per board).
"""

from __future__ import annotations

import math
from array import array
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, Protocol

from firmware_stub.config import ClockMode, EmulatorConfig
from firmware_stub.link import BoardLink, FaultRecorder
from hil.protocol import (
    CATALOGUE,
    NO_AXIS,
    NO_LATENCY_US,
    Ack,
    AxisMask,
    Board,
    BoardState,
    ClockLate,
    DriveCmd,
    DriveDisable,
    DriveEnable,
    DriveFault,
    DriveStatus,
    ErrorCode,
    Frame,
    GyroSample,
    Heartbeat,
    HexapodStart,
    HexapodState,
    HexapodStatus,
    HexapodStop,
    HostAlive,
    Ident,
    IdentRequest,
    LockstepAck,
    LoopTiming,
    MessageSpec,
    MissDistance,
    Nack,
    Pose,
    ProfileLoad,
    ServoConfig,
    ServoMode,
    StreamMode,
    TrackCmd,
    TrackMode,
    frame_size,
)
from hil.protocol.swing import (
    ZERO6,
    Envelope,
    Profile,
    Segment,
    Vec6,
    check_envelope,
    profile_end_s,
    segment_from_message,
)

if TYPE_CHECKING:
    from firmware_stub.plant import Plant

FIRMWARE_VERSION = "emu-1.0.0"
TICKS_PER_S = 1000
U32 = 0xFFFFFFFF


def host_messages(board: Board) -> dict[type, MessageSpec]:
    """The messages the host sends on ``board``'s link, by type (the catalogue's sender and receiver)."""
    return {spec.cls: spec for spec in CATALOGUE if spec.sender == Board.HOST and spec.receiver in (None, board)}


@dataclass
class DroppedFrames:
    """Frames with a good CRC that a board drops unanswered (docs/protocol.md section 4, step 6; counted
    since the emulator started)."""

    misaddressed: int = 0  # the source is not the host (0x01), or the destination is not this board
    wrong_link: int = 0  # a message the host does not send to this board (e.g. DRIVE_CMD on the servo link)


class World(Protocol):
    """What the boards see of the emulator that hosts them."""

    tick: int  # simulated ms since start; the plant is at t = tick ms
    deadline: float | None  # realtime: perf_counter() time the current tick's sample is due
    plant: Plant
    config: EmulatorConfig
    recorder: FaultRecorder
    servo: ServoBoard
    driver: DriverBoard
    drive_delay_s: float  # lockstep and sim: when DRIVE_CMD k acts after tick k (the wire and the host; 0: off)


class EmulatedBoard:
    """Common behaviour; a board adds ``handlers`` for its commands, overrides ``power_on``/``on_tick``,
    and ``protect`` (its safe state when the host falls silent)."""

    board_id: Board
    state: BoardState = BoardState.BOOT

    def __init__(self, world: World, link: BoardLink, fingerprint: int = CATALOGUE.fingerprint) -> None:
        self.world = world
        self.link = link
        self.fingerprint = fingerprint
        self.serial_number = world.config.boards.serial_base + int(self.board_id)
        self.boot_tick = 0
        self.handlers: dict[type, Callable[[Frame, float], None]] = {
            IdentRequest: self._on_ident_request, HostAlive: self._on_host_alive, LockstepAck: self._on_lockstep_ack}
        self.accepted = host_messages(self.board_id)
        timeout_ms = world.config.boards.host_timeout_ms
        self.host_timeout_ticks = max(1, round(timeout_ms)) if timeout_ms > 0 else 0  # 0: never
        self.dropped = DroppedFrames()
        self.resent_replies = 0  # resent commands answered from memory
        self.host_timeouts = 0
        self.uncounted_rx_frames = 0  # LOCKSTEP_ACK, and in lockstep HOST_ALIVE: kept out of HEARTBEAT.rx_frames
        self._count_host_alive = world.config.clock is not ClockMode.LOCKSTEP
        self.power_on()

    # --- life cycle ----------------------------------------------------------------------------------

    def power_on(self) -> None:
        """State at power-on (and after a reset): the host timer unarmed, no command remembered."""
        self.state = BoardState.READY
        self.host_heard_tick: int | None = None  # world tick of the last host frame; None: timer not armed
        self._forget_command()

    def _forget_command(self) -> None:
        self._last_command: tuple[int, int] | None = None  # (msg_id, seq) of the last command handled
        self._last_reply: Any = None  # its ACK/NACK (IDENT for IDENT_REQ)

    def reboot(self) -> None:
        self.link.reset_codec()
        self.boot_tick = self.world.tick
        self.power_on()
        self.world.recorder.record(self.link.name, "reset")
        self.send(self.ident())

    def ident(self) -> Ident:
        return Ident(self.board_id, CATALOGUE.protocol_version, FIRMWARE_VERSION, self.fingerprint, self.serial_number)

    # --- traffic -------------------------------------------------------------------------------------

    def send(self, message: Any) -> bool:
        return self.link.send(message, Board.HOST, self.world.tick)

    def reply(self, frame: Frame, message: Any) -> None:
        """Send the reply to ``frame``; kept for a resend when ``frame`` is the command being handled."""
        if (CATALOGUE.spec(frame.message).msg_id, frame.seq) == self._last_command:
            self._last_reply = message
        self.send(message)

    def ack(self, frame: Frame) -> None:
        self.reply(frame, Ack(CATALOGUE.spec(frame.message).msg_id, frame.seq))

    def nack(self, frame: Frame, error: ErrorCode, axis: int = NO_AXIS, value: float = 0.0, limit: float = 0.0) -> None:
        self.reply(frame, Nack(CATALOGUE.spec(frame.message).msg_id, frame.seq, error, axis, value, limit))

    def receive(self, frame: Frame, t_rx: float) -> bool:
        """One frame from the link. False when dropped (counted): not for this board, not from the host,
        or not a message the host sends on this link. Otherwise the host timer restarts, and a resent
        command (same msg_id and seq as the last one) gets the stored reply again instead of a second
        action; any other frame is handled."""
        message = frame.message
        kind = type(message)
        if kind is LockstepAck or (kind is HostAlive and not self._count_host_alive):
            self.uncounted_rx_frames += 1
        if frame.dst != self.board_id or frame.src != Board.HOST:
            self.dropped.misaddressed += 1
            return False
        spec = self.accepted.get(type(message))
        if spec is None:
            self.dropped.wrong_link += 1
            return False
        self.host_heard_tick = self.world.tick
        if spec.reply:  # a command: remember it, or recognise its resend
            key = (spec.msg_id, frame.seq)
            if key == self._last_command:
                if self._last_reply is not None:
                    self.resent_replies += 1
                    self.send(self._last_reply)
                return True
            self._last_command, self._last_reply = key, None
        self.handle(frame, t_rx)
        return True

    def handle(self, frame: Frame, t_rx: float) -> None:
        handler = self.handlers.get(type(frame.message))
        if handler is None:
            self.nack(frame, ErrorCode.UNKNOWN_MESSAGE)
        else:
            handler(frame, t_rx)

    def _on_ident_request(self, frame: Frame, t_rx: float) -> None:
        self.reply(frame, self.ident())

    def _on_host_alive(self, frame: Frame, t_rx: float) -> None:
        """No reply, no action: receiving it restarted the host timer."""

    def _on_lockstep_ack(self, frame: Frame, t_rx: float) -> None:
        """No reply: the host has handled this board's frames up to ``seq`` (the lockstep world waits for it)."""
        self.link.on_host_ack(frame.message.seq)

    # --- host liveness -------------------------------------------------------------------------------

    def check_host_timer(self, tick: int) -> int:
        """Realtime: protect if the host has been silent for the host timeout at world tick ``tick``;
        returns the next tick worth checking again."""
        heard = self.host_heard_tick
        if heard is None:
            return tick + self.host_timeout_ticks
        if tick - heard < self.host_timeout_ticks:
            return heard + self.host_timeout_ticks
        self.host_lost(tick - heard, self.host_timeout_ticks)
        return tick + self.host_timeout_ticks

    def host_lost(self, silence_ms: float, timeout_ms: float) -> None:
        """The host timer expired: record it, disarm the timer, forget the last command, protect."""
        self.host_timeouts += 1
        self.host_heard_tick = None
        self._forget_command()
        self.world.recorder.record(self.link.name, "host_timeout", silence_ms=silence_ms, timeout_ms=timeout_ms)
        self.protect()

    def protect(self) -> None:
        """The board's safe state when the host is gone (kept until the host commands it again)."""

    def counters(self) -> dict[str, Any]:
        """For the emulator's summary: frames dropped, resends answered, host timeouts, timer armed."""
        return {"dropped": asdict(self.dropped), "resent_replies": self.resent_replies,
                "host_timeouts": self.host_timeouts, "host_armed": self.host_heard_tick is not None}

    def on_tick(self, tick: int) -> None:
        """Periodic output after the plant has advanced to ``tick``."""
        if (tick - self.boot_tick) % TICKS_PER_S == 0:
            c = self.link.decoder.counters
            self.send(Heartbeat((tick - self.boot_tick) & U32, self.state, c.frames_ok - self.uncounted_rx_frames,
                                c.crc_errors, c.bad_lengths + c.unknown_ids, 0, self.link.stats.tx_overflow_bytes))


def percentiles_us(values: array | list[float]) -> dict[str, float]:
    """p50/p99/p99.9/max of values already in microseconds."""
    if not len(values):
        return {}
    s = sorted(values)

    def pick(q: float) -> float:
        return round(s[min(len(s) - 1, int(q * len(s)))], 1)

    return {"p50": pick(0.5), "p99": pick(0.99), "p99.9": pick(0.999), "max": round(s[-1], 1)}


class ServoBoard(EmulatedBoard):
    """The clock master: GYRO_SAMPLE every tick while streaming, LOOP_TIMING every 10 ticks (after that
    tick's sample, so the host reads the sample first).

    Loop timing is the ground truth for the bench's 1 kHz claims: for each sample k, the time from
    the board writing GYRO_SAMPLE k to the driver receiving DRIVE_CMD k (one clock: both boards
    live in this process). LOOP_TIMING for ticks k-20..k-11 goes out at tick k, so a command up to
    10 ms late is still measured; a tick with no command by then counts as missing.
    """

    board_id = Board.SERVO
    WINDOW = 64  # ticks of write times kept (>= 20 needed)
    CLOCK_LATE_S = 1e-3  # realtime: a sample written this long after its due time is followed by CLOCK_LATE

    def __init__(self, world: World, link: BoardLink, fingerprint: int = CATALOGUE.fingerprint) -> None:
        super().__init__(world, link, fingerprint)
        self.handlers.update({ServoMode: self._on_mode, ServoConfig: self._on_config})
        self.latencies_us = array("d")  # every measured latency since the emulator started (for summaries)
        self.pacing_late_us = array("d")  # realtime: how late each sample write was against its deadline
        self.clock_late = 0  # CLOCK_LATE frames sent (realtime samples computed over CLOCK_LATE_S late)

    def power_on(self) -> None:
        super().power_on()
        self.streaming = False
        self.stream_tick = 0  # tick number of the next sample
        self.late_threshold_us = 1000
        self.gyro_filter_hz = 0
        self._filter_state: list[float] | None = None
        self._reset_timing()

    def _reset_timing(self) -> None:
        self.written_at = [0.0] * self.WINDOW
        self.latency_s: list[float | None] = [None] * self.WINDOW
        self.late_total = 0
        self.missing_total = 0
        self.samples_sent = 0
        self.last_delivered: int | None = None  # tick of the last sample that went out intact
        self._unwritten: int | None = None  # slot of a sample computed but not yet written

    def _on_mode(self, frame: Frame, t_rx: float) -> None:
        msg: ServoMode = frame.message
        self._set_stream(msg.mode == StreamMode.STREAM, "host")
        self.ack(frame)

    def _set_stream(self, on: bool, cause: str) -> None:
        """Start (tick from 0) or stop the GYRO_SAMPLE stream; recorded when it starts or stops."""
        if on or self.streaming:
            self.world.recorder.record(self.link.name, "servo_stream", streaming=on, cause=cause)
        self.streaming = on
        if on:
            self.stream_tick = 0
            self._reset_timing()
        self.state = BoardState.RUNNING if on else BoardState.READY

    def protect(self) -> None:
        """Host gone: stop streaming, as SERVO_MODE(IDLE) does."""
        if self.streaming:
            self._set_stream(False, "host_timeout")

    def _on_config(self, frame: Frame, t_rx: float) -> None:
        msg: ServoConfig = frame.message
        if msg.sample_rate_hz != TICKS_PER_S:
            self.nack(frame, ErrorCode.BAD_VALUE, NO_AXIS, msg.sample_rate_hz, TICKS_PER_S)
            return
        if msg.gyro_filter_hz and not 1 <= msg.gyro_filter_hz <= 450:
            self.nack(frame, ErrorCode.BAD_VALUE, NO_AXIS, msg.gyro_filter_hz, 450)
            return
        self.gyro_filter_hz = msg.gyro_filter_hz
        self._filter_state = None
        self.late_threshold_us = msg.late_threshold_us
        self.ack(frame)

    def note_command(self, tick: int, t_rx: float) -> None:
        """The driver received DRIVE_CMD(tick) at perf time t_rx."""
        if 0 <= self.stream_tick - 1 - tick < self.WINDOW - 1:
            slot = tick % self.WINDOW
            if self.latency_s[slot] is None and self.written_at[slot]:
                # never negative: a command read while its sample's write was still being stamped (the two
                # stamps come from different threads) came back within the write itself
                self.latency_s[slot] = max(0.0, t_rx - self.written_at[slot])

    def _gyro(self) -> tuple[float, float, float]:
        rates = self.world.plant.gyro_dps()
        if not self.gyro_filter_hz:
            return rates
        a = math.exp(-2 * math.pi * self.gyro_filter_hz / TICKS_PER_S)
        if self._filter_state is None:
            self._filter_state = list(rates)
        st = self._filter_state
        for i in range(3):
            st[i] = a * st[i] + (1 - a) * rates[i]
        return st[0], st[1], st[2]

    def on_tick(self, tick: int) -> None:
        super().on_tick(tick)
        if not self.streaming:
            return
        k = self.stream_tick
        rx, ry, rz = self._gyro()
        az, el = self.world.plant.encoders_deg()
        slot = k % self.WINDOW
        self.latency_s[slot] = None
        self.written_at[slot] = 0.0
        sample = GyroSample((tick * 1000) & U32, k & U32, rx, ry, rz, az, el)
        delivered = self.send(sample)
        self._unwritten = slot
        self.last_delivered = k if delivered else None
        self.samples_sent += 1
        self.stream_tick = k + 1
        if k >= 20 and k % 10 == 0:  # after the sample: the time-critical frame is first on the wire
            self._report_timing(k - 20)

    def announce_late(self, late_s: float) -> None:
        """Realtime, just before the tick's output is written ``late_s`` after its deadline: if that is over
        CLOCK_LATE_S, CLOCK_LATE for the sample goes out right behind it, in the same write (docs/protocol.md,
        "Host liveness"): this process was not run in time, the board itself was not silent."""
        if late_s > self.CLOCK_LATE_S and self._unwritten is not None and self.last_delivered is not None:
            self.clock_late += 1
            self.send(ClockLate(self.last_delivered & U32, min(round(late_s * 1e6), U32)))

    def on_written(self, t_perf: float, wire_s: float = 0.0) -> None:
        """The tick's output has been written to the pty (realtime: at the deadline, plus ``wire_s``, its wire time:
        the sample's first byte left at ``t_perf - wire_s``)."""
        if self._unwritten is not None:
            t_first = t_perf - wire_s
            self.written_at[self._unwritten] = t_first
            self._unwritten = None
            if self.world.deadline is not None:
                self.pacing_late_us.append((t_first - self.world.deadline) * 1e6)

    def _report_timing(self, first: int) -> None:
        values = []
        for k in range(first, first + 10):
            lat = self.latency_s[k % self.WINDOW]
            if lat is None:
                self.missing_total += 1
                values.append(NO_LATENCY_US)
                continue
            us = lat * 1e6
            self.latencies_us.append(us)
            if self.world.deadline is None:  # lockstep: the world waited for it; the latency is the modelled one
                values.append(round(self.world.drive_delay_s * 1e6))
                continue
            if us > self.late_threshold_us:
                self.late_total += 1
            values.append(max(0, min(int(us), NO_LATENCY_US - 1)))
        self.send(LoopTiming(first & U32, tuple(values), self.late_total, self.missing_total))

    def summary(self) -> dict[str, Any]:
        return {
            "samples_sent": self.samples_sent,
            "late_commands": self.late_total,
            "missing_commands": self.missing_total,
            "latency_us": percentiles_us(self.latencies_us),
            "pacing_late_us": percentiles_us(self.pacing_late_us),
            "clock_late": self.clock_late,
        }


AXES = ((AxisMask.AZ, DriveFault.OVERCURRENT_AZ, "az"), (AxisMask.EL, DriveFault.OVERCURRENT_EL, "el"))
_AZ, _EL = int(AxisMask.AZ), int(AxisMask.EL)


class DriverBoard(EmulatedBoard):
    """Motor driver: zero-order hold of DRIVE_CMD, enable/disable, stale-command timeout, current limit.

    Output per axis = the last command if the axis is enabled, has no latched fault and the last
    command is younger than ``stale_timeout_ms``; otherwise 0. A current above ``current_limit_a``
    for ``overcurrent_trip_ms`` latches OVERCURRENT on that axis and disables it until
    DRIVE_ENABLE(clear_faults=1). DRIVE_CMD while nothing is enabled is ignored (NACK NOT_ENABLED at
    most every 100 ms, so a 1 kHz stream does not flood the link).
    """

    board_id = Board.DRIVER

    def __init__(self, world: World, link: BoardLink, fingerprint: int = CATALOGUE.fingerprint) -> None:
        super().__init__(world, link, fingerprint)
        self.handlers.update({DriveCmd: self._on_cmd, DriveEnable: self._on_enable, DriveDisable: self._on_disable})
        cfg = world.config.boards.driver
        self.stale_ticks = max(1, round(cfg.stale_timeout_ms))
        self.trip_ticks = round(cfg.overcurrent_trip_ms)
        self.current_limit_a = cfg.current_limit_a
        self.bus_voltage_v = cfg.bus_voltage_v
        self.stale_commands = 0
        self._rx_wire_s = {cls: link.wire_s(frame_size(spec)) for cls, spec in self.accepted.items()}
        self.arrived_s = -math.inf  # perf_counter() time the last host frame's last byte arrived
        self.acted_s = -math.inf  # ... that of the last command that changed the output (realtime: it acts then)

    def power_on(self) -> None:
        super().power_on()
        self.enabled = AxisMask(0)
        self._en = 0  # int(self.enabled): the 1 kHz paths test plain ints, not IntFlag members
        self.faults = DriveFault(0)
        self.cmd = [0, 0]
        self.last_cmd_at = -1  # world tick of the last DRIVE_CMD
        self.last_cmd_tick: int | None = None  # its tick field
        self.stale = False
        self.over_ticks = [0, 0]
        self._last_nack_tick = -(10**9)

    def handle(self, frame: Frame, t_rx: float) -> None:
        """Realtime: a frame acts when its last byte arrives, its wire time after it was read; the emulator splits
        the tick's hold where the last command that changed the output arrived (``acted_s``)."""
        self.arrived_s = t_rx + self._rx_wire_s.get(type(frame.message), 0.0)
        super().handle(frame, t_rx)

    def _on_cmd(self, frame: Frame, t_rx: float) -> None:
        msg: DriveCmd = frame.message
        self.world.servo.note_command(msg.tick, self.arrived_s)
        self.last_cmd_tick = msg.tick
        en = self._en
        if not en:
            if self.world.tick - self._last_nack_tick >= 100:
                self._last_nack_tick = self.world.tick
                self.nack(frame, ErrorCode.NOT_ENABLED)
            return
        self.last_cmd_at = self.world.tick
        self.acted_s = self.arrived_s
        if self.stale:
            self.stale = False
            self.faults &= ~DriveFault.STALE_COMMAND
            self.world.recorder.record(self.link.name, "drive_fresh", tick_field=msg.tick)
        if en & _AZ:
            self.cmd[0] = msg.az_counts
        if en & _EL:
            self.cmd[1] = msg.el_counts

    def _on_enable(self, frame: Frame, t_rx: float) -> None:
        msg: DriveEnable = frame.message
        latched = [ax for mask, fault, ax in AXES if msg.axes & mask and self.faults & fault]
        if latched and not msg.clear_faults:
            self.nack(frame, ErrorCode.FAULT_LATCHED, 0 if latched[0] == "az" else 1)
            return
        if msg.clear_faults:
            self.faults = DriveFault(0)
            self.over_ticks = [0, 0]
        for i, (mask, _, _) in enumerate(AXES):
            if msg.axes & mask and not self.enabled & mask:
                self.cmd[i] = 0  # output starts at zero
        self.enabled |= msg.axes
        self._en = int(self.enabled)
        self.acted_s = self.arrived_s
        self.last_cmd_at = self.world.tick  # the stale timer starts now
        self.state = BoardState.RUNNING
        self.world.recorder.record(self.link.name, "drive_enable", axes=int(msg.axes), clear=bool(msg.clear_faults))
        self.ack(frame)

    def _on_disable(self, frame: Frame, t_rx: float) -> None:
        msg: DriveDisable = frame.message
        self.acted_s = self.arrived_s
        self._disable(AxisMask(msg.axes), "host")
        self.ack(frame)

    def protect(self) -> None:
        """Host gone: disable both axes (zero output) until DRIVE_ENABLE."""
        if self.enabled:
            self._disable(AxisMask.BOTH, "host_timeout")

    def _disable(self, axes: AxisMask, cause: str) -> None:
        for i, (mask, _, _) in enumerate(AXES):
            if axes & mask:
                self.cmd[i] = 0
        self.enabled &= ~axes
        self._en = int(self.enabled)
        if not self.enabled:
            self.state = BoardState.FAULT if self.faults & ~DriveFault.STALE_COMMAND else BoardState.READY
        self.world.recorder.record(self.link.name, "drive_disable", axes=int(axes), cause=cause)

    def output_counts(self) -> tuple[int, int]:
        """What the power stage applies over the coming tick."""
        en = self._en
        if not en:
            return 0, 0
        if self.world.tick - self.last_cmd_at > self.stale_ticks:
            if not self.stale:
                self.stale = True
                self.stale_commands += 1
                self.faults |= DriveFault.STALE_COMMAND
                self.world.recorder.record(self.link.name, "drive_stale", last_tick_field=self.last_cmd_tick)
            return 0, 0
        az = self.cmd[0] if en & _AZ else 0
        el = self.cmd[1] if en & _EL else 0
        return az, el

    def on_tick(self, tick: int) -> None:
        super().on_tick(tick)
        currents = self.world.plant.currents_a()
        limit = self.current_limit_a
        if self.trip_ticks >= 0 and (abs(currents[0]) > limit or abs(currents[1]) > limit or any(self.over_ticks)):
            for i, (mask, fault, ax) in enumerate(AXES):
                if abs(currents[i]) > limit:
                    self.over_ticks[i] += 1
                    if self.over_ticks[i] > self.trip_ticks and self._en & mask:
                        self.faults |= fault
                        self.world.recorder.record(self.link.name, "drive_overcurrent", axis=ax,
                                                   current_a=round(currents[i], 3), limit_a=self.current_limit_a)
                        self._disable(mask, "overcurrent")
                else:
                    self.over_ticks[i] = 0
        if tick % 10 == 0:
            self.send(DriveStatus((self.last_cmd_tick or 0) & U32, self.enabled, self.faults,
                                  _clamp(currents[0], 32.767), _clamp(currents[1], 32.767), self.bus_voltage_v,
                                  self.stale_commands))


def _clamp(x: float, lim: float) -> float:
    return max(-lim, min(lim, x))


class ImageBoard(EmulatedBoard):
    """Image processing: MISS_DISTANCE of every camera frame, ``latency_frames`` frames after its exposure.

    Tracking is off at power-on (track_valid = 0, miss = 0) until TRACK_CMD(TRACK). With tracking on,
    track_valid is 1 while the target is in the field of view and, if ``gate_px`` > 0, inside the gate.
    It drives nothing, so a host timeout only records the event: tracking stays as the host left it.
    """

    board_id = Board.IMAGE

    def __init__(self, world: World, link: BoardLink, fingerprint: int = CATALOGUE.fingerprint) -> None:
        cam = world.plant.config.camera
        self.period_ticks = round(TICKS_PER_S / cam.frame_rate_hz)
        self.latency_frames = cam.latency_frames
        super().__init__(world, link, fingerprint)
        self.handlers[TrackCmd] = self._on_track

    def power_on(self) -> None:
        super().power_on()
        self.tracking = False
        self.gate_px = 0
        self.frame = 0
        self.pipeline: deque[MissDistance] = deque()

    def _on_track(self, frame: Frame, t_rx: float) -> None:
        msg: TrackCmd = frame.message
        self.tracking = msg.mode == TrackMode.TRACK
        self.gate_px = msg.gate_px
        self.state = BoardState.RUNNING if self.tracking else BoardState.READY
        self.ack(frame)

    def on_tick(self, tick: int) -> None:
        super().on_tick(tick)
        if tick % self.period_ticks:
            return
        x, y, in_view = self.world.plant.miss_px()
        valid = self.tracking and in_view and (not self.gate_px or (abs(x) <= self.gate_px and abs(y) <= self.gate_px))
        if not valid:
            x = y = 0.0
        self.pipeline.append(MissDistance(self.frame & U32, (tick * 1000) & U32, _clamp(x, 2e6), _clamp(y, 2e6), valid))
        self.frame += 1
        if len(self.pipeline) > self.latency_frames:
            self.send(self.pipeline.popleft())


def _vec6(values: Iterable[float]) -> Vec6:
    """The six values of one pose, rate or acceleration (HexAxis order) as a 6-tuple."""
    x, y, z, roll, pitch, yaw = values
    return x, y, z, roll, pitch, yaw


class HexapodBoard(EmulatedBoard):
    """Hexapod controller: profile upload with an envelope check, START/STOP, POSE at 100 Hz.

    The profile clock starts at the tick after START. STOP (or the end of the profile) ramps the
    motion to zero over ``stop_ramp_s`` (the end of the profile is already ramped by its segments),
    then the platform rests at home with the profile still loaded, ready for another START.
    """

    board_id = Board.HEXAPOD

    def __init__(self, world: World, link: BoardLink, envelope: Envelope,
                 fingerprint: int = CATALOGUE.fingerprint) -> None:
        self.envelope = envelope
        cfg = world.config.boards.hexapod
        self.max_segments = cfg.max_segments
        self.stop_ramp_ticks = max(1, round(cfg.stop_ramp_s * TICKS_PER_S))
        super().__init__(world, link, fingerprint)
        self.handlers.update({ProfileLoad: self._on_load, HexapodStart: self._on_start, HexapodStop: self._on_stop})

    def power_on(self) -> None:
        super().power_on()
        self.segments: list[Segment] = []
        self.profile = Profile(())
        self.expected = 0
        self.hex_state = HexapodState.IDLE
        self._moving = False  # RUNNING or STOPPING (the 1 kHz path tests a bool, not an enum)
        self.start_tick = 0
        self.stop_tick = 0
        self.end_ticks = 0
        self.fault = 0
        self.pose = ZERO6

    def _set_state(self, state: HexapodState) -> None:
        if state != self.hex_state:
            self.hex_state = state
            self._moving = state in (HexapodState.RUNNING, HexapodState.STOPPING)
            self.world.recorder.record(self.link.name, "hexapod_state", state=state.name)
            self._status()

    def _status(self) -> None:
        t = max(0, self.world.tick - self.start_tick) if self.hex_state in (HexapodState.RUNNING,
                                                                             HexapodState.STOPPING) else 0
        self.send(HexapodStatus(self.hex_state, len(self.segments), t & U32, self.fault))

    def _on_load(self, frame: Frame, t_rx: float) -> None:
        msg: ProfileLoad = frame.message
        if self.hex_state in (HexapodState.RUNNING, HexapodState.STOPPING):
            self.nack(frame, ErrorCode.BAD_STATE)
            return
        if msg.count > self.max_segments:
            self.nack(frame, ErrorCode.PROFILE_TOO_LONG, NO_AXIS, msg.count, self.max_segments)
            return
        if msg.index == 0:
            self.segments, self.expected = [], msg.count
            self._set_state(HexapodState.IDLE)
        if msg.index != len(self.segments) or msg.count != self.expected:
            self.nack(frame, ErrorCode.BAD_VALUE, NO_AXIS, msg.index, len(self.segments))
            return
        if msg.duration_s <= 0 or msg.start_s < 0 or msg.frequency_hz < 0 or msg.ramp_s < 0:
            self.nack(frame, ErrorCode.BAD_VALUE, msg.axis, msg.duration_s, 0.0)
            return
        self.segments.append(segment_from_message(msg))
        if len(self.segments) == self.expected:
            violation = check_envelope(self.segments, self.envelope)
            if violation:
                self.world.recorder.record(self.link.name, "envelope_reject", reason=violation.describe())
                self.segments, self.expected = [], 0
                self.fault = violation.error
                self.nack(frame, violation.error, violation.axis, violation.value, violation.limit)
                self._set_state(HexapodState.IDLE)
                return
            self.end_ticks = math.ceil(profile_end_s(self.segments) * TICKS_PER_S)
            self.profile = Profile(self.segments)
            self.fault = 0
            self._set_state(HexapodState.LOADED)
        self.ack(frame)

    def _on_start(self, frame: Frame, t_rx: float) -> None:
        if self.hex_state != HexapodState.LOADED:
            error = ErrorCode.PROFILE_INCOMPLETE if self.hex_state == HexapodState.IDLE else ErrorCode.BAD_STATE
            self.nack(frame, error, NO_AXIS, len(self.segments), self.expected)
            return
        self.start_tick = self.world.tick
        self._set_state(HexapodState.RUNNING)
        self.ack(frame)

    def _on_stop(self, frame: Frame, t_rx: float) -> None:
        self._stop()
        self.ack(frame)

    def _stop(self) -> None:
        """A running profile ramps to zero over ``stop_ramp_s``, then rests at home (LOADED)."""
        if self.hex_state == HexapodState.RUNNING:
            self.stop_tick = self.world.tick
            self._set_state(HexapodState.STOPPING)

    def protect(self) -> None:
        """Host gone: ramp home, as HEXAPOD_STOP does."""
        self._stop()

    def motion(self, tick: int) -> tuple[Vec6, Vec6, Vec6]:
        """Pose, rate, acceleration at the middle of the tick that starts at ``tick`` (before stepping)."""
        if not self._moving:
            return ZERO6, ZERO6, ZERO6
        t_s = (tick - self.start_tick + 0.5) / TICKS_PER_S
        pos, vel, acc = self.profile(t_s)
        if self.hex_state == HexapodState.STOPPING:
            # scale by s(t) falling 1 -> 0 over the stop ramp: p_s = s p, v_s = s v + s' p, a_s = s a + 2 s' v
            s_dot = -TICKS_PER_S / self.stop_ramp_ticks
            s = max(0.0, 1.0 + s_dot * (tick - self.stop_tick + 0.5) / TICKS_PER_S)
            pos, vel, acc = (_vec6(s * p for p in pos), _vec6(s * v + s_dot * p for v, p in zip(vel, pos, strict=True)),
                             _vec6(s * a + 2 * s_dot * v for a, v in zip(acc, vel, strict=True)))
        return pos, vel, acc

    def on_tick(self, tick: int) -> None:
        super().on_tick(tick)
        if self._moving and (
                (self.hex_state == HexapodState.RUNNING and tick - self.start_tick >= self.end_ticks)
                or (self.hex_state == HexapodState.STOPPING and tick - self.stop_tick >= self.stop_ramp_ticks)):
            self._set_state(HexapodState.LOADED)
        if tick % 10 == 0:
            t_ms = max(0, tick - self.start_tick) if self._moving else 0
            self.send(Pose(t_ms & U32, *self.pose))
        if tick % 100 == 0:
            self._status()
