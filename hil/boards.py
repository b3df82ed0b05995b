"""The boards as the session sees them: one small client per board over a :class:`~hil.transport.SerialLink`.

A real board on /dev/ttyUSB0 and an emulated one on a pty are the same thing here: a serial port
speaking the protocol, so the session never knows which it has. The hexapod sits behind its own
:class:`HexapodDriver` interface, so a vendor controller (typically an ASCII command set over TCP or
serial) can be added by implementing four methods, without touching the session.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Sequence
from typing import Any

from hil.protocol import (
    CATALOGUE,
    Ack,
    AxisMask,
    Board,
    DriveCmd,
    DriveDisable,
    DriveEnable,
    Frame,
    HexapodStart,
    HexapodStop,
    HostAlive,
    Ident,
    IdentRequest,
    Pose,
    ServoConfig,
    ServoMode,
    StreamMode,
    TrackCmd,
    TrackMode,
)
from hil.protocol.swing import Segment, segments_to_messages
from hil.transport import LinkError, SerialLink


class FingerprintMismatch(LinkError):
    """The board's firmware was built from another message catalogue: refuse to talk to it."""


class InterlockClosed(LinkError):
    """A command that would move something was refused because the session has disarmed for good."""


class Interlock:
    """The session's one-way door (docs/reliability.md): once :meth:`close` is called, no board client
    sharing it will enable the driver, start the gyro stream or start the hexapod again, on any path.

    Every board of a session holds the same interlock; the commands that move hardware call
    :meth:`check` before they write anything, and nothing reopens it."""

    def __init__(self) -> None:
        self.reason: str | None = None

    @property
    def closed(self) -> bool:
        return self.reason is not None

    def close(self, reason: str) -> None:
        if self.reason is None:
            self.reason = reason

    def check(self, action: str) -> None:
        if self.reason is not None:
            raise InterlockClosed(f"{action} refused: the session has disarmed ({self.reason})")


class BoardClient:
    """One board on one link: identification and acknowledged commands."""

    board_id: Board

    def __init__(self, link: SerialLink, interlock: Interlock | None = None) -> None:
        self.link = link
        self.ident: Ident | None = None
        self.interlock = interlock or Interlock()

    @property
    def name(self) -> str:
        return self.link.name

    async def identify(self, timeout_s: float = 1.0) -> Ident:
        """IDENT_REQ -> IDENT; refuses a board built from another catalogue (FingerprintMismatch)."""
        ident: Ident = await self.link.request(IdentRequest(), self.board_id, Ident, timeout_s)
        if ident.board != self.board_id:
            kind = getattr(ident.board, "name", ident.board)
            raise LinkError(f"{self.name}: the board on {self.link.port} is a {kind} board, not "
                            f"{self.board_id.name}: check the port assignment")
        if ident.catalogue_fingerprint != CATALOGUE.fingerprint or ident.protocol_version != CATALOGUE.protocol_version:
            raise FingerprintMismatch(
                f"{self.name}: firmware {ident.firmware_version!r} speaks catalogue "
                f"{ident.catalogue_fingerprint:#010x} (protocol v{ident.protocol_version}), this bench "
                f"{CATALOGUE.fingerprint:#010x} (protocol v{CATALOGUE.protocol_version}): update one of them")
        self.ident = ident
        return ident

    async def command(self, message: Any, timeout_s: float = 0.5) -> Ack:
        return await self.link.request(message, self.board_id, Ack, timeout_s)

    def alive(self, uptime_ms: int) -> None:
        """HOST_ALIVE: keeps the board's host timer from expiring (docs/protocol.md, "Host liveness")."""
        if self.link.transport is not None:
            self.link.send(HostAlive(uptime_ms & 0xFFFFFFFF), self.board_id)

    def ident_dict(self) -> dict[str, Any]:
        i = self.ident
        if i is None:
            return {}
        return {"board": self.board_id.name, "port": self.link.port, "firmware_version": i.firmware_version,
                "protocol_version": i.protocol_version, "catalogue_fingerprint": f"{i.catalogue_fingerprint:#010x}",
                "serial_number": i.serial_number}


class ServoBoard(BoardClient):
    board_id = Board.SERVO

    async def configure(self, late_threshold_us: int = 1000, gyro_filter_hz: int = 0) -> None:
        await self.command(ServoConfig(1000, gyro_filter_hz, late_threshold_us))

    async def start_stream(self) -> None:
        self.interlock.check("SERVO_MODE STREAM")
        await self.command(ServoMode(StreamMode.STREAM))

    async def stop_stream(self) -> None:
        await self.command(ServoMode(StreamMode.IDLE))


class DriverBoard(BoardClient):
    board_id = Board.DRIVER

    async def enable(self, clear_faults: bool = True) -> None:
        self.interlock.check("DRIVE_ENABLE")
        await self.command(DriveEnable(AxisMask.BOTH, clear_faults))

    async def disable(self) -> None:
        await self.command(DriveDisable(AxisMask.BOTH))

    def disable_now(self) -> None:
        """Write DRIVE_DISABLE at once, without waiting for the ACK (watchdog and signal paths)."""
        if self.link.transport is not None:
            self.link.send(DriveDisable(AxisMask.BOTH), Board.DRIVER)

    def drive(self, tick: int, az_counts: int, el_counts: int) -> None:
        """DRIVE_CMD for sample ``tick``: the 1 kHz hot path."""
        self.link.send(DriveCmd(tick, az_counts, el_counts), Board.DRIVER)


class ImageBoard(BoardClient):
    board_id = Board.IMAGE

    async def track(self, enabled: bool, gate_px: int = 0) -> None:
        await self.command(TrackCmd(TrackMode.TRACK if enabled else TrackMode.OFF, gate_px))


class HexapodDriver(abc.ABC):
    """A six-axis swing table. Implement these for a vendor controller; poses go to ``on_pose``."""

    name = "hexapod"
    on_pose: Callable[[float, tuple[float, ...]], None] | None = None  # (t_profile_s, pose6)

    @abc.abstractmethod
    async def identify(self) -> Any: ...

    @abc.abstractmethod
    async def load(self, segments: Sequence[Segment]) -> None:
        """Upload a profile; raises LinkError naming the limit if the controller refuses it."""

    @abc.abstractmethod
    async def start(self) -> None: ...

    @abc.abstractmethod
    async def stop(self) -> None:
        """Ramp down and return home."""

    def ident_dict(self) -> dict[str, Any]:
        return {}


class ProtocolHexapod(BoardClient, HexapodDriver):
    """A hexapod controller speaking this bench's protocol (as the emulator's does)."""

    board_id = Board.HEXAPOD

    def handle(self, frame: Frame) -> None:
        msg = frame.message
        if type(msg) is Pose and self.on_pose is not None:
            self.on_pose(msg.t_ms / 1000, msg[1:])

    async def load(self, segments: Sequence[Segment]) -> None:
        for msg in segments_to_messages(list(segments)):
            await self.command(msg)

    async def start(self) -> None:
        self.interlock.check("HEXAPOD_START")
        await self.command(HexapodStart())

    async def stop(self) -> None:
        await self.command(HexapodStop())
