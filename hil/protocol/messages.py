"""The message catalogue: every message the bench and its boards exchange, declared once.

Encoders, decoders, fingerprints and the tables in docs/protocol.md are all derived from
these declarations (the ``hil protocol docs`` command regenerates the tables).

Board-frame conventions (used by the field docs below):
- gyro axes are those of the elevation (inner) frame: x along the line of sight, y along
  the elevation axis, z completing the right-handed frame (the azimuth axis at el = 0);
- positive drive counts turn an axis in its positive angle direction.
"""

from __future__ import annotations

from enum import IntEnum, IntFlag
from typing import Annotated, NamedTuple

from hil.protocol.wire import Catalogue, boolean, char, f32, i16, i32, u8, u16, u32

PROTOCOL_VERSION = 1
CATALOGUE = Catalogue(PROTOCOL_VERSION, title="HIL stabilized-platform bench protocol")


class Board(IntEnum):
    """Node ids on the links (header src/dst) and board types (IDENT)."""

    HOST = 0x01  # the bench (the paper's "upper computer")
    SERVO = 0x10  # servo-control board: gyro, encoders, the 1 kHz clock
    DRIVER = 0x20  # motor driver board
    IMAGE = 0x30  # image-processing board: miss distance
    HEXAPOD = 0x40  # six-axis swing table controller


LINKS = tuple(board.name.lower() for board in Board if board is not Board.HOST)  # one link per board, in id order


class BoardState(IntEnum):
    BOOT = 0
    READY = 1
    RUNNING = 2
    FAULT = 3


class ErrorCode(IntEnum):
    """NACK reasons. The NACK's `axis`, `value` and `limit` say which axis and which limit."""

    UNKNOWN_MESSAGE = 1  # the board does not implement this message id
    BAD_VALUE = 2  # a field is outside what the board accepts (value, limit given)
    BAD_STATE = 3  # not allowed in the board's current state
    NOT_ENABLED = 4  # drive command while the driver is disabled
    FAULT_LATCHED = 5  # a latched fault must be cleared first
    ENVELOPE_POSITION = 6  # hexapod profile exceeds the axis position limit
    ENVELOPE_RATE = 7  # hexapod profile exceeds the axis rate limit
    ENVELOPE_ACCEL = 8  # hexapod profile exceeds the axis acceleration limit
    PROFILE_INCOMPLETE = 9  # START before every segment of the profile was loaded
    PROFILE_TOO_LONG = 10  # more segments than the controller holds


class StreamMode(IntEnum):
    IDLE = 0  # no GYRO_SAMPLE stream
    STREAM = 1  # GYRO_SAMPLE at the configured rate


class DriveFault(IntFlag):
    OVERCURRENT_AZ = 0x01
    OVERCURRENT_EL = 0x02
    STALE_COMMAND = 0x04  # no DRIVE_CMD within the stale timeout: output forced to zero
    UNDERVOLTAGE = 0x08
    OVERTEMPERATURE = 0x10


class AxisMask(IntFlag):
    AZ = 0x01
    EL = 0x02
    BOTH = 0x03


class TrackMode(IntEnum):
    OFF = 0
    TRACK = 1


class HexAxis(IntEnum):
    X = 0  # mm
    Y = 1  # mm
    Z = 2  # mm
    ROLL = 3  # deg
    PITCH = 4  # deg
    YAW = 5  # deg


class HexapodState(IntEnum):
    IDLE = 0
    LOADED = 1
    RUNNING = 2
    STOPPING = 3
    FAULT = 4


NO_AXIS = 0xFF  # NACK.axis when the error concerns no particular axis
NO_LATENCY_US = 0xFFFF  # LOOP_TIMING: no DRIVE_CMD arrived for that tick


# --- common to every board (sender or receiver None = any board) ---------------------------


@CATALOGUE.message(
    0x01, sender=Board.HOST, receiver=None, rate="on request", reply="IDENT", name="IDENT_REQ"
)
class IdentRequest(NamedTuple):
    """Ask a board who it is. Sent by the host to any board (dst = the board's id)."""


@CATALOGUE.message(0x02, sender=None, receiver=Board.HOST, rate="on IDENT_REQ and at boot")
class Ident(NamedTuple):
    """Who a board is and which catalogue it was built against (schema-mismatch check)."""

    board: Annotated[Board, u8(doc="board type (Board enum)", enum=Board)]
    protocol_version: Annotated[int, u8(doc="header version byte the firmware speaks")]
    firmware_version: Annotated[str, char(16, doc="firmware version text, e.g. 1.4.2")]
    catalogue_fingerprint: Annotated[int, u32(doc="CRC-32 of the catalogue layout it was built from")]
    serial_number: Annotated[int, u32(doc="board serial number")]


@CATALOGUE.message(0x03, sender=None, receiver=Board.HOST, rate="1 Hz")
class Heartbeat(NamedTuple):
    """Board health: uptime and its own receive error counters (cumulative since boot)."""

    uptime_ms: Annotated[int, u32("ms", "time since boot (wraps after 49.7 days)")]
    state: Annotated[BoardState, u8(doc="BoardState", enum=BoardState)]
    rx_frames: Annotated[int, u32(doc="frames received with a good CRC")]
    rx_crc_errors: Annotated[int, u32(doc="frames dropped for a bad CRC")]
    rx_bad_frames: Annotated[int, u32(doc="frames dropped for a bad length or unknown id")]
    rx_overruns: Annotated[int, u32(doc="UART overrun or framing errors")]
    tx_dropped: Annotated[int, u32(doc="frames the board could not send (buffer full)")]


@CATALOGUE.message(0x04, sender=None, receiver=Board.HOST, rate="reply")
class Ack(NamedTuple):
    """A command was accepted."""

    msg_id: Annotated[int, u8(doc="id of the accepted message")]
    seq: Annotated[int, u16(doc="sequence number of the accepted frame")]


@CATALOGUE.message(0x05, sender=None, receiver=Board.HOST, rate="reply")
class Nack(NamedTuple):
    """A command was refused; nothing it asked for was done."""

    msg_id: Annotated[int, u8(doc="id of the refused message")]
    seq: Annotated[int, u16(doc="sequence number of the refused frame")]
    error: Annotated[ErrorCode, u8(doc="ErrorCode", enum=ErrorCode)]
    axis: Annotated[int, u8(doc="axis concerned (HexAxis, or 0 = az / 1 = el), 0xFF = none")]
    value: Annotated[float, f32(doc="offending value, in the unit of the limit")]
    limit: Annotated[float, f32(doc="the limit it broke")]


@CATALOGUE.message(0x06, sender=Board.HOST, receiver=None, rate="10 Hz on a link the host is otherwise quiet on")
class HostAlive(NamedTuple):
    """The host is alive. No reply. Any frame from the host resets a board's host timer; a board that hears
    nothing from the host for its host timeout protects itself (docs/protocol.md, "Host liveness")."""

    uptime_ms: Annotated[int, u32("ms", "time since the host's session started (wraps after 49.7 days)")]


@CATALOGUE.message(0x07, sender=Board.HOST, receiver=None,
                   rate="lockstep emulation only: after each read that brought board frames")
class LockstepAck(NamedTuple):
    """Lockstep emulation only: the host has handled every frame this board sent on this link up to ``seq``. The
    emulated world waits for it before the tick's GYRO_SAMPLE, so the host handles the other boards' frames of a
    tick before its sample, whatever order the ptys deliver them in (docs/protocol.md, "Host liveness"). Never sent
    to a real board, never answered."""

    seq: Annotated[int, u16(doc="sequence number of the last frame from this board the host has handled")]


# --- servo-control board --------------------------------------------------------------------


@CATALOGUE.message(0x10, sender=Board.SERVO, receiver=Board.HOST, rate="1 kHz")
class GyroSample(NamedTuple):
    """One gyro and encoder sample: the bench's loop clock. The host answers with DRIVE_CMD(tick)."""

    t_us: Annotated[int, u32("us", "board time of the sample (wraps after 71.6 min)")]
    tick: Annotated[int, u32(doc="sample counter, +1 per sample, from 0 at STREAM")]
    rate_x_dps: Annotated[float, i32("deg/s", "gyro rate about x (line of sight)", scale=1e-6)]
    rate_y_dps: Annotated[float, i32("deg/s", "gyro rate about y (elevation axis)", scale=1e-6)]
    rate_z_dps: Annotated[float, i32("deg/s", "gyro rate about z (azimuth axis at el = 0)", scale=1e-6)]
    az_deg: Annotated[float, i32("deg", "azimuth encoder angle", scale=1e-6)]
    el_deg: Annotated[float, i32("deg", "elevation encoder angle", scale=1e-6)]


@CATALOGUE.message(0x11, sender=Board.HOST, receiver=Board.SERVO, rate="on change", reply="ACK/NACK")
class ServoConfig(NamedTuple):
    """Servo-board settings; NACK(BAD_VALUE) names the first field it cannot honour."""

    sample_rate_hz: Annotated[int, u16("Hz", "GYRO_SAMPLE rate (1000 on every board so far)")]
    gyro_filter_hz: Annotated[int, u16("Hz", "board-side gyro low-pass cut-off, 0 = raw")]
    late_threshold_us: Annotated[int, u16("us", "DRIVE_CMD later than this after its sample counts late")]


@CATALOGUE.message(0x12, sender=Board.HOST, receiver=Board.SERVO, rate="on change", reply="ACK/NACK")
class ServoMode(NamedTuple):
    """Start or stop the GYRO_SAMPLE stream (tick restarts at 0 on STREAM)."""

    mode: Annotated[StreamMode, u8(doc="StreamMode", enum=StreamMode)]


@CATALOGUE.message(0x13, sender=Board.SERVO, receiver=Board.HOST, rate="100 Hz")
class LoopTiming(NamedTuple):
    """Per-tick latency from GYRO_SAMPLE k written to DRIVE_CMD k received, as the board measured it."""

    first_tick: Annotated[int, u32(doc="tick of latency_us[0]")]
    latency_us: Annotated[tuple[int, ...], u16("us", "one per tick; 0xFFFF = no command arrived", count=10)]
    late_total: Annotated[int, u32(doc="ticks whose command came after late_threshold_us, since STREAM")]
    missing_total: Annotated[int, u32(doc="ticks that never got a command, since STREAM")]


@CATALOGUE.message(0x14, sender=Board.SERVO, receiver=Board.HOST, rate="after a late sample (emulators only)")
class ClockLate(NamedTuple):
    """The board's own sample clock fired late: GYRO_SAMPLE ``tick``, just before this frame in the same write, went
    out ``late_us`` after its due time. A board with a hardware timer never sends it; an emulator its host OS did not
    run does, so a bench beside it can tell a stall of the host they share from a board that went silent
    (docs/protocol.md, "Host liveness")."""

    tick: Annotated[int, u32(doc="tick of the late GYRO_SAMPLE just before it")]
    late_us: Annotated[int, u32("us", "how long after its due time that sample went out")]


# --- motor driver board ---------------------------------------------------------------------


@CATALOGUE.message(0x20, sender=Board.HOST, receiver=Board.DRIVER, rate="1 kHz")
class DriveCmd(NamedTuple):
    """Motor command for both axes, held (zero-order hold) until the next one."""

    tick: Annotated[int, u32(doc="tick of the GYRO_SAMPLE this command answers")]
    az_counts: Annotated[int, i16("counts", "azimuth DAC command")]
    el_counts: Annotated[int, i16("counts", "elevation DAC command")]


@CATALOGUE.message(0x21, sender=Board.HOST, receiver=Board.DRIVER, rate="on change", reply="ACK/NACK")
class DriveEnable(NamedTuple):
    """Enable the power stage of the given axes (output starts at zero)."""

    axes: Annotated[AxisMask, u8(doc="AxisMask", enum=AxisMask)]
    clear_faults: Annotated[bool, boolean("1 = clear latched faults first")]


@CATALOGUE.message(0x22, sender=Board.HOST, receiver=Board.DRIVER, rate="on change", reply="ACK")
class DriveDisable(NamedTuple):
    """Disable the power stage of the given axes: output to zero at once. Always accepted."""

    axes: Annotated[AxisMask, u8(doc="AxisMask", enum=AxisMask)]


@CATALOGUE.message(0x23, sender=Board.DRIVER, receiver=Board.HOST, rate="100 Hz")
class DriveStatus(NamedTuple):
    """Power-stage state and measurements."""

    last_tick: Annotated[int, u32(doc="tick of the last DRIVE_CMD applied")]
    enabled: Annotated[AxisMask, u8(doc="AxisMask of enabled axes", enum=AxisMask)]
    faults: Annotated[DriveFault, u8(doc="DriveFault flags: OVERCURRENT_* latched until DRIVE_ENABLE clear_faults = 1; "
                                         "STALE_COMMAND set while the stale timeout holds the output at zero",
                                     enum=DriveFault)]
    az_current_a: Annotated[float, i16("A", "azimuth motor current", scale=1e-3)]
    el_current_a: Annotated[float, i16("A", "elevation motor current", scale=1e-3)]
    bus_voltage_v: Annotated[float, u16("V", "DC bus voltage", scale=1e-2)]
    stale_commands: Annotated[int, u32(doc="times the stale-command timeout zeroed the output")]


# --- image-processing board -------------------------------------------------------------------


@CATALOGUE.message(0x30, sender=Board.IMAGE, receiver=Board.HOST, rate="camera rate (100 Hz)")
class MissDistance(NamedTuple):
    """Target offset from the boresight in the latest processed frame."""

    frame: Annotated[int, u32(doc="camera frame counter")]
    t_exposure_us: Annotated[int, u32("us", "mid-exposure time on the servo board's t_us clock")]
    miss_x_px: Annotated[float, i32("px", "horizontal miss distance (+ = target right)", scale=1e-3)]
    miss_y_px: Annotated[float, i32("px", "vertical miss distance (+ = target up)", scale=1e-3)]
    track_valid: Annotated[bool, boolean("1 = target found; 0 = miss_x/miss_y meaningless")]


@CATALOGUE.message(0x31, sender=Board.HOST, receiver=Board.IMAGE, rate="on change", reply="ACK/NACK")
class TrackCmd(NamedTuple):
    """Start or stop target tracking."""

    mode: Annotated[TrackMode, u8(doc="TrackMode", enum=TrackMode)]
    gate_px: Annotated[int, u16("px", "half-size of the search gate around the boresight; 0 = no gate (the whole "
                                      "field)")]


# --- hexapod controller ---------------------------------------------------------------------------


@CATALOGUE.message(0x40, sender=Board.HOST, receiver=Board.HEXAPOD, rate="on load", reply="ACK/NACK")
class ProfileLoad(NamedTuple):
    """One segment of a swing profile: a sinusoid on one axis, ramped in and out.

    A profile is `count` segments sent in index order (index 0 clears the previous profile).
    The pose is the sum of the active segments:
    amplitude * r(t) * sin(2 pi frequency (t - start) + phase) for start <= t < start + duration,
    where r ramps linearly 0 -> 1 over ramp_s at both ends. The controller checks the whole
    profile against its envelope when the last segment arrives and NACKs with the axis and limit.
    """

    # the wire's field names, shadowing tuple.index() and tuple.count() (a NamedTuple allows it)
    index: Annotated[int, u8(doc="segment index, 0..count-1")]  # type: ignore[assignment]
    count: Annotated[int, u8(doc="segments in the profile")]  # type: ignore[assignment]
    axis: Annotated[HexAxis, u8(doc="HexAxis", enum=HexAxis)]
    start_s: Annotated[float, f32("s", "segment start on the profile clock")]
    duration_s: Annotated[float, f32("s", "segment length")]
    amplitude: Annotated[float, f32("mm | deg", "mm for X/Y/Z, deg for ROLL/PITCH/YAW")]
    frequency_hz: Annotated[float, f32("Hz", "sine frequency")]
    phase_deg: Annotated[float, f32("deg", "sine phase at start_s")]
    ramp_s: Annotated[float, f32("s", "linear ramp in and out")]


@CATALOGUE.message(0x41, sender=Board.HOST, receiver=Board.HEXAPOD, rate="on command", reply="ACK/NACK")
class HexapodStart(NamedTuple):
    """Run the loaded profile from t = 0."""


@CATALOGUE.message(0x42, sender=Board.HOST, receiver=Board.HEXAPOD, rate="on command", reply="ACK")
class HexapodStop(NamedTuple):
    """Ramp down and return to the home pose. Always accepted."""


@CATALOGUE.message(0x43, sender=Board.HEXAPOD, receiver=Board.HOST, rate="100 Hz")
class Pose(NamedTuple):
    """Measured platform pose (upper platform relative to home)."""

    t_ms: Annotated[int, u32("ms", "profile clock, 0 at START")]
    x_mm: Annotated[float, f32("mm")]
    y_mm: Annotated[float, f32("mm")]
    z_mm: Annotated[float, f32("mm")]
    roll_deg: Annotated[float, f32("deg")]
    pitch_deg: Annotated[float, f32("deg")]
    yaw_deg: Annotated[float, f32("deg")]


@CATALOGUE.message(0x44, sender=Board.HEXAPOD, receiver=Board.HOST, rate="10 Hz and on change")
class HexapodStatus(NamedTuple):
    """Controller state."""

    state: Annotated[HexapodState, u8(doc="HexapodState", enum=HexapodState)]
    segments_loaded: Annotated[int, u8(doc="segments of the current profile received so far")]
    profile_time_ms: Annotated[int, u32("ms", "profile clock")]
    fault: Annotated[int, u8(doc="ErrorCode of the last fault, 0 = none")]


__all__ = [
    "CATALOGUE",
    "LINKS",
    "NO_AXIS",
    "NO_LATENCY_US",
    "PROTOCOL_VERSION",
    "Ack",
    "AxisMask",
    "Board",
    "BoardState",
    "ClockLate",
    "DriveCmd",
    "DriveDisable",
    "DriveEnable",
    "DriveFault",
    "DriveStatus",
    "ErrorCode",
    "GyroSample",
    "Heartbeat",
    "HexAxis",
    "HexapodStart",
    "HexapodState",
    "HexapodStatus",
    "HexapodStop",
    "HostAlive",
    "Ident",
    "IdentRequest",
    "LockstepAck",
    "LoopTiming",
    "MissDistance",
    "Nack",
    "Pose",
    "ProfileLoad",
    "ServoConfig",
    "ServoMode",
    "StreamMode",
    "TrackCmd",
    "TrackMode",
]
