"""The boards as the session sees them: one small client per board over a :class:`~hil.link.Link`.

A real board on /dev/ttyUSB0 and an emulated one on a pty are the same thing here: a serial port
speaking the protocol, so the session never knows which it has. The hexapod sits behind its own
:class:`HexapodDriver` interface, chosen by name in the session file and found through the entry-point group
``hil.hexapod_drivers``, so a vendor controller (typically an ASCII command set over TCP or serial) or a
pure-software table is a package of its own, installed beside the bench, without touching the session
(docs/hexapod-drivers.md).
"""

from __future__ import annotations

import abc
import asyncio
import contextlib
import time
from collections.abc import Awaitable, Callable, Sequence
from importlib.metadata import EntryPoint, entry_points
from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict

from hil.link import Link, LinkError
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
    HexapodState,
    HexapodStatus,
    HexapodStop,
    HostAlive,
    Ident,
    IdentRequest,
    Nack,
    Pose,
    ServoConfig,
    ServoMode,
    StreamMode,
    TrackCmd,
    TrackMode,
)
from hil.protocol.swing import Segment, segments_to_messages


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

    def __init__(self, link: Link, interlock: Interlock | None = None) -> None:
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
        if self.link.is_open:
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

    def stop_stream_now(self) -> None:
        """Write SERVO_MODE IDLE at once, without waiting for the ACK: the sim clock's wind-down answers the loop's
        last sample with it, so the world, which does not wait for a DRIVE_CMD, stops at that tick
        (hil.session.TickWindDown)."""
        if self.link.is_open:
            self.link.send(ServoMode(StreamMode.IDLE), Board.SERVO)


class DriverBoard(BoardClient):
    board_id = Board.DRIVER

    async def enable(self, clear_faults: bool = True) -> None:
        self.interlock.check("DRIVE_ENABLE")
        await self.command(DriveEnable(AxisMask.BOTH, clear_faults))

    async def disable(self) -> None:
        await self.command(DriveDisable(AxisMask.BOTH))

    def disable_now(self) -> None:
        """Write DRIVE_DISABLE at once, without waiting for the ACK (watchdog and signal paths)."""
        if self.link.is_open:
            self.link.send(DriveDisable(AxisMask.BOTH), Board.DRIVER)

    def drive(self, tick: int, az_counts: int, el_counts: int) -> None:
        """DRIVE_CMD for sample ``tick``: the 1 kHz hot path."""
        self.link.send(DriveCmd(tick, az_counts, el_counts), Board.DRIVER)


class ImageBoard(BoardClient):
    board_id = Board.IMAGE

    async def track(self, enabled: bool, gate_px: int = 0) -> None:
        await self.command(TrackCmd(TrackMode.TRACK if enabled else TrackMode.OFF, gate_px))


_STOP_ID = CATALOGUE.spec(HexapodStop()).msg_id
_START_ID = CATALOGUE.spec(HexapodStart()).msg_id
HEXAPOD_DRIVERS = "hil.hexapod_drivers"  # the entry-point group a hexapod driver registers in (docs/hexapod-drivers.md)

PoseCallback = Callable[[float, tuple[float, ...]], None]  # (t_profile_s, pose6: x y z mm, roll pitch yaw deg)


class HexapodOptions(BaseModel):
    """Base of a driver's options: the session's ``hexapod`` section without its ``driver`` key. As every config
    model of the bench: unknown fields refused, immutable, NaN and infinities refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class HexapodDriver(abc.ABC):
    """A six-axis swing table, as the session drives it (docs/hexapod-drivers.md).

    A session names its driver in ``hexapod: {driver: NAME, ...options}``; NAME is looked up in the entry-point
    group ``hil.hexapod_drivers`` (:func:`load_hexapod_driver`), where the bench's own :class:`ProtocolHexapod` is
    ``protocol``. The session validates the options with :attr:`Options`, builds the driver with :meth:`create`,
    and calls it from its event loop only: :meth:`identify` at connect, :meth:`load` before the gimbal is armed,
    :meth:`start`, then :meth:`stop` and :meth:`wait_home` at the end (``stop`` also on every fault and signal).
    It holds the driver behind a :class:`GuardedHexapod`, so once the session has begun to end, ``load`` and
    ``start`` never reach the driver again. A driver moves the table only when ``start`` is called.

    The driver reports each pose it learns of through :attr:`on_pose`, from the session's event loop, and a loss
    of its own connection through :attr:`on_fault` (the session then disarms as for a lost link).
    """

    Options: ClassVar[type[HexapodOptions]] = HexapodOptions
    uses_link: ClassVar[bool] = False  # True: the session opens the bench's hexapod link (ports.hexapod) for it
    on_pose: PoseCallback | None = None
    on_fault: Callable[[str], None] | None = None

    @classmethod
    def create(cls, options: HexapodOptions, link: Link | None, interlock: Interlock) -> HexapodDriver:
        """The driver of one session. ``options``: an instance of :attr:`Options`. ``link``: the bench's hexapod
        link, opened, if :attr:`uses_link` (else None). ``interlock``: the session's (it is enforced on ``load``
        and ``start`` whatever the driver does). Default: ``cls(options)``."""
        return cls(options)  # type: ignore[call-arg]

    @abc.abstractmethod
    async def identify(self) -> Any:
        """Connect if needed and check that the controller is the one expected; raise LinkError naming why not."""

    @abc.abstractmethod
    async def load(self, segments: Sequence[Segment]) -> None:
        """Upload a profile; raises LinkError naming the limit if the controller refuses it."""

    @abc.abstractmethod
    async def start(self) -> None:
        """Start the loaded profile (profile time 0 is now)."""

    @abc.abstractmethod
    async def stop(self) -> None:
        """Ramp down and return home. Accepted in any state, also when nothing moves, and on every path out."""

    @property
    @abc.abstractmethod
    def running(self) -> bool:
        """True while the table moves: swinging, or ramping down after ``stop``."""

    @property
    def swinging(self) -> bool:
        """True while the loaded profile runs (not ramping down after ``stop`` or a timeout of its own, not at
        rest). Default: ``running``, for a controller that tells no difference."""
        return self.running

    async def await_status(self, timeout_s: float) -> None:
        """Until the controller next reports its state, at most ``timeout_s`` (a driver built anew, after its link
        was reopened, knows it only then)."""
        await self._next_state(timeout_s)

    @property
    def state(self) -> str:
        """The controller's state in a word, for the log."""
        return "running" if self.running else "idle"

    @property
    def connected(self) -> bool:
        """False once the driver's connection is gone (``stop`` is then not attempted)."""
        return True

    async def wait_home(self, timeout_s: float) -> bool:
        """Wait until the table rests (``running`` false), at most ``timeout_s``; True if it does."""
        give_up = time.monotonic() + timeout_s
        while self.running:
            left = give_up - time.monotonic()
            if left <= 0:
                return False
            await self._next_state(left)
        return True

    async def _next_state(self, left_s: float) -> None:
        """Wait for the state to change, or a while (at most ``left_s``): a poll every 10 ms, unless the driver
        is told of changes."""
        await asyncio.sleep(min(left_s, 0.01))

    def handle(self, frame: Frame) -> None:  # noqa: B027 (an optional hook)
        """A frame from the bench's hexapod link (drivers that set :attr:`uses_link`)."""

    def alive(self, uptime_ms: int) -> None:  # noqa: B027 (an optional hook)
        """Called every 0.1 s with the bench's HOST_ALIVE (the realtime clock and real boards, not lockstep or
        sim): a keep-alive of the driver's own goes here."""

    def ident_dict(self) -> dict[str, Any]:
        """What the log records of the controller (its ``ident`` attribute): firmware, serial number, address."""
        return {}

    async def close(self) -> None:  # noqa: B027 (an optional hook)
        """The session is over: release the connection, stop timers (after ``stop``; never moves anything)."""


class ProtocolHexapod(BoardClient, HexapodDriver):
    """A hexapod controller speaking this bench's protocol (as the emulator's does), on the bench's hexapod link:
    the ``protocol`` driver, and the default."""

    board_id = Board.HEXAPOD
    uses_link = True

    def __init__(self, link: Link, interlock: Interlock | None = None) -> None:
        super().__init__(link, interlock)
        self.hex_state: int = HexapodState.IDLE  # the last HEXAPOD_STATUS
        self._changed = asyncio.Event()
        # stop_now, start_now: (the frame's seq, its message id, what its ACK calls, what its NACK calls)
        self._confirm: tuple[int, int, Callable[[], None], Callable[[str], None] | None] | None = None

    @classmethod
    def create(cls, options: HexapodOptions, link: Link | None, interlock: Interlock) -> ProtocolHexapod:
        if link is None:
            raise LinkError("hexapod: the protocol driver needs the bench's hexapod link")
        return cls(link, interlock)

    def handle(self, frame: Frame) -> None:
        msg = frame.message
        kind = type(msg)
        if kind is HexapodStatus:
            self.hex_state = msg.state
            self._changed.set()
        elif kind is Pose and self.on_pose is not None:
            self.on_pose(msg.t_ms / 1000, msg[1:])
        elif kind in (Ack, Nack) and self._confirm is not None and msg.seq == self._confirm[0] \
                and msg.msg_id == self._confirm[1]:
            _, _, confirmed, refused = self._confirm
            self._confirm = None
            if kind is Ack:
                confirmed()
            elif refused is not None:
                refused(f"{getattr(msg.error, 'name', msg.error)} (value {msg.value:g}, limit {msg.limit:g})")

    @property
    def running(self) -> bool:
        return self.hex_state in (HexapodState.RUNNING, HexapodState.STOPPING)

    @property
    def swinging(self) -> bool:
        return self.hex_state == HexapodState.RUNNING

    async def await_status(self, timeout_s: float) -> None:
        """Until the next HEXAPOD_STATUS (every 100 ms), at most ``timeout_s``."""
        self._changed.clear()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._changed.wait(), timeout_s)

    @property
    def state(self) -> str:
        try:
            return HexapodState(self.hex_state).name
        except ValueError:
            return str(self.hex_state)

    @property
    def connected(self) -> bool:
        return self.link.is_open

    async def _next_state(self, left_s: float) -> None:
        """Until the next HEXAPOD_STATUS (checked at least every 0.1 s)."""
        self._changed.clear()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._changed.wait(), min(left_s, 0.1))

    async def load(self, segments: Sequence[Segment]) -> None:
        for msg in segments_to_messages(list(segments)):
            await self.command(msg)

    async def start(self) -> None:
        self.interlock.check("HEXAPOD_START")
        await self.command(HexapodStart())

    async def stop(self) -> None:
        await self.command(HexapodStop())

    def stop_now(self, confirmed: Callable[[], None]) -> None:
        """HEXAPOD_STOP written at once, from code that cannot wait (a lockstep or sim wind-down acts between a
        GYRO_SAMPLE and its DRIVE_CMD: hil.session.TickWindDown); ``confirmed()`` is called from :meth:`handle` with its
        ACK. The ACK follows every frame the controller sent before the STOP, so :attr:`running` is then its state
        as of the STOP. A later call replaces the callback of one still unanswered. LinkError if the link is closed."""
        self._confirm = (self.link.send(HexapodStop(), self.board_id), _STOP_ID, confirmed, None)

    def start_now(self, confirmed: Callable[[], None], refused: Callable[[str], None]) -> None:
        """HEXAPOD_START written at once through the interlock, from code that cannot wait (a lockstep or sim session
        starts its swing between the GYRO_SAMPLE that ended its start pose phase and that sample's DRIVE_CMD:
        hil.session.TickSwingStart); ``confirmed()`` is called from :meth:`handle` with its ACK, ``refused(why)``
        with its NACK. InterlockClosed once the session has disarmed; LinkError if the link is closed."""
        self.interlock.check("HEXAPOD_START")
        self._confirm = (self.link.send(HexapodStart(), self.board_id), _START_ID, confirmed, refused)


class GuardedHexapod(HexapodDriver):
    """The session's hold on its driver, whichever it is.

    The interlock's one-way rule is enforced here, not left to the driver: once the session has begun to end,
    ``load`` and ``start`` raise :class:`InterlockClosed` without calling the driver (``stop``, ``wait_home`` and
    ``close`` always pass). A driver's own exceptions become :class:`LinkError` naming the driver, so the session's
    safety paths treat a failing vendor controller as they treat a lost link, and so is a call that does not return
    within :attr:`CALL_TIMEOUT_S` (``wait_home``: its own timeout plus that)."""

    CALL_TIMEOUT_S = 10.0

    def __init__(self, driver: HexapodDriver, interlock: Interlock, name: str) -> None:
        self.driver = driver
        self.interlock = interlock
        self.driver_name = name

    def replace(self, driver: HexapodDriver) -> None:
        """Another instance of the driver (its link was reopened by a recovery), with the same callbacks."""
        driver.on_pose, driver.on_fault = self.driver.on_pose, self.driver.on_fault
        self.driver = driver

    @property
    def uses_link(self) -> bool:  # type: ignore[override]  # the wrapped driver's class attribute, read per instance
        return self.driver.uses_link

    @property
    def on_pose(self) -> PoseCallback | None:
        return self.driver.on_pose

    @on_pose.setter
    def on_pose(self, callback: PoseCallback | None) -> None:
        self.driver.on_pose = callback

    @property
    def on_fault(self) -> Callable[[str], None] | None:
        return self.driver.on_fault

    @on_fault.setter
    def on_fault(self, callback: Callable[[str], None] | None) -> None:
        self.driver.on_fault = callback

    async def _call(self, what: str, step: Awaitable[Any], timeout_s: float | None = None) -> Any:
        """``step`` within ``timeout_s`` (default :attr:`CALL_TIMEOUT_S`): a driver that hangs (a vendor's TCP link
        gone quiet) must not keep a session from ending; its errors become one-line LinkErrors."""
        limit_s = self.CALL_TIMEOUT_S if timeout_s is None else timeout_s
        try:
            async with asyncio.timeout(limit_s):
                return await step
        except LinkError:
            raise
        except TimeoutError:
            raise LinkError(f"hexapod driver {self.driver_name!r}: {what}: no answer within {limit_s:g} s") from None
        except Exception as exc:
            raise LinkError(f"hexapod driver {self.driver_name!r}: {what}: {type(exc).__name__}: "
                            f"{' '.join(str(exc).split())}") from exc

    async def identify(self) -> Any:
        return await self._call("identify", self.driver.identify())

    async def load(self, segments: Sequence[Segment]) -> None:
        self.interlock.check("hexapod profile upload")
        await self._call("load", self.driver.load(segments))

    async def start(self) -> None:
        self.interlock.check("hexapod start")
        await self._call("start", self.driver.start())

    async def stop(self) -> None:
        await self._call("stop", self.driver.stop())

    async def wait_home(self, timeout_s: float) -> bool:
        return bool(await self._call("wait_home", self.driver.wait_home(timeout_s), timeout_s + self.CALL_TIMEOUT_S))

    async def close(self) -> None:
        await self._call("close", self.driver.close())

    async def await_status(self, timeout_s: float) -> None:
        await self._call("await_status", self.driver.await_status(timeout_s), timeout_s + self.CALL_TIMEOUT_S)

    @property
    def running(self) -> bool:
        return self.driver.running

    @property
    def swinging(self) -> bool:
        return self.driver.swinging

    @property
    def state(self) -> str:
        return self.driver.state

    @property
    def connected(self) -> bool:
        return self.driver.connected

    def handle(self, frame: Frame) -> None:
        self.driver.handle(frame)

    def alive(self, uptime_ms: int) -> None:
        self.driver.alive(uptime_ms)

    def ident_dict(self) -> dict[str, Any]:
        return {"driver": self.driver_name, **self.driver.ident_dict()}


def installed_hexapod_drivers() -> dict[str, EntryPoint]:
    """The hexapod drivers installed here: name -> entry point of the group ``hil.hexapod_drivers`` (of two with one
    name, the first on ``sys.path``). Read afresh at each call, so a package installed meanwhile is seen."""
    found: dict[str, EntryPoint] = {}
    for ep in entry_points(group=HEXAPOD_DRIVERS):
        found.setdefault(ep.name, ep)
    return found


def load_hexapod_driver(name: str) -> type[HexapodDriver]:
    """The driver class registered as ``name``; ValueError (one line: what is wrong, and the installed names) if
    none is, or it cannot be imported, or it is not a complete :class:`HexapodDriver`.

    ``protocol`` is registered by this project; from a source tree that was never installed (no entry points at
    all) it still resolves, to :class:`ProtocolHexapod`."""
    eps = installed_hexapod_drivers()
    ep = eps.get(name)
    if ep is None:
        if name == "protocol":
            return ProtocolHexapod
        installed = ", ".join(sorted({*eps, "protocol"}))
        raise ValueError(f"{name!r} is not an installed hexapod driver (installed: {installed})")
    where = f"{name!r} ({ep.value})"
    try:
        cls = ep.load()
    except Exception as exc:  # a third-party package's import error, whatever it is
        raise ValueError(f"{where} cannot be loaded: {type(exc).__name__}: {' '.join(str(exc).split())}") from None
    if not (isinstance(cls, type) and issubclass(cls, HexapodDriver)):
        raise ValueError(f"{where} is not a hil.boards.HexapodDriver subclass")
    if cls.__abstractmethods__:
        raise ValueError(f"{where} does not implement {', '.join(sorted(cls.__abstractmethods__))}")
    if not (isinstance(cls.Options, type) and issubclass(cls.Options, BaseModel)):
        raise ValueError(f"{where}: its Options is not a pydantic model")
    return cls
