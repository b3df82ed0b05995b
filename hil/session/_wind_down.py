"""The tick-driven wind-down of a lockstep or sim session (:class:`TickWindDown`): the last rows reproducible."""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Any, Protocol

from hil.boards import ProtocolHexapod, ServoBoard
from hil.link import LinkError
from hil.protocol import GyroSample
from hil.session._control_loop import ControlLoop


class WindingSession(Protocol):
    """What the wind-down asks of its :class:`hil.session.Session` (which imports this module)."""

    def disarm_watchdog(self) -> None: ...
    def event(self, kind: str, **detail: Any) -> None: ...
    def fault(self, reason: str, *, recoverable: bool = True) -> None: ...
    def swing_began(self) -> None: ...


HEXAPOD_HOME_S = 5.0  # wind-down: the hexapod ramps down (1 s on the emulator) and rests within this


class TickWindDown:
    """The wind-down of a lockstep or sim session, by the boards' ticks: reproducible to the last row.

    A lockstep world steps when DRIVE_CMD k comes in. A frame the bench writes on another link is sure to be handled
    before that step only if the world has answered it by then, and the bench reads the hexapod's link and the
    servo's in either order; so no step of the wind-down may depend on when the event loop gets to it. Each is
    taken in the loop's sample handler, at a tick fixed by the session's duration, the tick's DRIVE_CMD held until
    the hexapod's ACK is back (the world waits for it):

    - the first sample after the duration, then every :attr:`CHECK_TICKS` samples: HEXAPOD_STOP (the first stops
      the swing; later ones change nothing). Its ACK follows every HEXAPOD_STATUS sent before it, so the table's
      state read then is its state at that tick; the held DRIVE_CMD goes out after it;
    - once a check finds the table at rest (or :attr:`HOME_TICKS` after the first stop), the next sample is the
      loop's last, logged unarmed and not answered: the world waits there while the session's shutdown disables
      the driver, stops the swing and the stream. Without a swing (``hexapod`` None) that is the first sample after
      the duration.

    The sim clock's world (``world_waits`` false) handles each frame as it is sent and delivers the replies within
    the tick, so the same frames reach it at the same ticks; but it does not wait for an answer, so the last sample
    is answered with SERVO_MODE IDLE, which stops it where lockstep's waits."""

    CHECK_TICKS = 10  # the hexapod's POSE period
    HOME_TICKS = round(HEXAPOD_HOME_S * 1000)

    def __init__(self, session: WindingSession, loop: ControlLoop, servo: ServoBoard,
                 hexapod: ProtocolHexapod | None, *, world_waits: bool) -> None:
        self.session = session
        self.loop = loop
        self.servo = servo
        self.hexapod = hexapod
        self.world_waits = world_waits
        self.done: asyncio.Future[bool] = asyncio.get_running_loop().create_future()
        self.first_tick: int | None = None  # the first stop's
        self.next_check = 0
        self.holding = False
        self.held: tuple[int, int, int] | None = None  # the DRIVE_CMD waiting for the hexapod's ACK
        self.last_sample = hexapod is None  # the table rests: the next sample is the loop's last
        self._on_sample, self._drive = loop.on_sample, loop.drive
        loop.on_sample = self.on_sample  # type: ignore[method-assign]
        loop.drive = self.drive

    def drive(self, tick: int, az_counts: int, el_counts: int) -> None:
        if self.holding:
            self.held = (tick, az_counts, el_counts)
        else:
            self._drive(tick, az_counts, el_counts)

    def on_sample(self, g: GyroSample, t_rx: int | None = None) -> None:
        if self.done.done():
            self._on_sample(g, t_rx)
            return
        self.held = None  # an ACK that did not come before the world moved on (a lockstep timeout): too late now
        if self.last_sample:
            self.loop.armed = False
            self._on_sample(g, t_rx)
            self.session.disarm_watchdog()  # no sample comes after this one
            if not self.world_waits:
                with contextlib.suppress(LinkError, OSError):  # else the shutdown stops it
                    self.servo.stop_stream_now()
            self.done.set_result(True)
            return
        check = self.first_tick is None or g.tick - self.next_check >= 0
        self.holding = check
        try:
            self._on_sample(g, t_rx)
        finally:
            self.holding = False
        if self.held is None:  # not a check, or the loop did not drive (a fault or a signal disarmed it)
            return
        if self.first_tick is None:
            self.first_tick = g.tick
        self.next_check = g.tick + self.CHECK_TICKS
        try:
            assert self.hexapod is not None
            self.hexapod.stop_now(self._confirmed)
        except (LinkError, OSError) as exc:
            self._give_up(f"HEXAPOD_STOP not sent: {exc}")

    def _confirmed(self) -> None:
        """The hexapod's ACK: its state is the one at the held sample's tick."""
        if self.held is None or self.done.done():
            return
        if not self.loop.armed:  # a fault or a signal since the sample: nothing more to drive
            self._give_up()
            return
        assert self.hexapod is not None
        if self.held[0] == self.first_tick:
            self.session.event("state", state="swing stopping")
        if not self.hexapod.running:
            self.last_sample = True
        elif self.held[0] - (self.first_tick or 0) >= self.HOME_TICKS:
            self.session.event("info", hexapod=f"still {self.hexapod.state} {HEXAPOD_HOME_S:g} s after the stop")
            self.last_sample = True
        held, self.held = self.held, None
        try:
            self._drive(*held)
        except (LinkError, OSError) as exc:
            self._give_up(f"DRIVE_CMD not sent: {exc}")

    def _give_up(self, why: str = "") -> None:
        """The wind-down cannot go on by ticks (``why``, logged; none when a fault or a signal disarmed the loop): the
        loop drives as it did while it is armed, and :meth:`wait` returns False."""
        if why and not self.done.done():
            self.session.event("info", wind_down=why)
        held, self.held = self.held, None
        if held is not None and self.loop.armed:
            with contextlib.suppress(LinkError, OSError):
                self._drive(*held)
        if not self.done.done():
            self.done.set_result(False)

    async def wait(self) -> bool:
        """Until the loop's last sample (True), or until the loop stops driving before it (a fault, a signal) or no
        sample comes for HEXAPOD_HOME_S (False). Wall time only keeps this from waiting forever."""
        loop = self.loop
        cycles, quiet_since = -1, time.monotonic()
        while not self.done.done():
            if not loop.armed:
                self._give_up()
                break
            if loop.stats.cycles != cycles:
                cycles, quiet_since = loop.stats.cycles, time.monotonic()
            elif time.monotonic() - quiet_since > HEXAPOD_HOME_S:
                self._give_up(f"no sample for {HEXAPOD_HOME_S:g} s")
                break
            await asyncio.wait((self.done,), timeout=0.1)
        return self.done.result()


class TickSwingStart:
    """The swing's start in a lockstep or sim session with the emulated hexapod, at the sample that ended the start
    pose phase: reproducible, as :class:`TickWindDown` is, for the same reason. HEXAPOD_START goes out from the
    sample's handler and that sample's DRIVE_CMD is held until the hexapod's ACK is back (the lockstep world waits
    for it; the sim world answers within the tick), so the table starts at that tick on every run and on both
    clocks. A NACK ends the session as a fault; an ACK that has not come by the next sample (a lockstep timeout) too.
    """

    def __init__(self, session: WindingSession, loop: ControlLoop, hexapod: ProtocolHexapod) -> None:
        self.session = session
        self.loop = loop
        self.held: tuple[int, int, int] | None = None
        self.waiting = True
        self._drive = loop.drive
        loop.drive = self.drive
        try:
            hexapod.start_now(self._confirmed, self._refused)
        except (LinkError, OSError) as exc:
            self._end(f"HEXAPOD_START not sent: {exc}")

    def drive(self, tick: int, az_counts: int, el_counts: int) -> None:
        if not self.waiting:
            self._drive(tick, az_counts, el_counts)
        elif self.held is None:
            self.held = (tick, az_counts, el_counts)
        else:  # the world moved on without the ACK
            self._end(f"HEXAPOD_START: no ACK by tick {tick}")

    def _confirmed(self) -> None:
        if not self.waiting:
            return
        self._release()
        self.session.swing_began()
        held, self.held = self.held, None
        if held is not None and self.loop.armed:
            try:
                self._drive(*held)
            except (LinkError, OSError) as exc:
                self.session.fault(f"DRIVE_CMD not sent: {exc}")

    def _refused(self, why: str) -> None:
        self._end(f"HEXAPOD_START refused: {why}")

    def _release(self) -> None:
        self.waiting = False
        self.loop.drive = self._drive

    def _end(self, reason: str) -> None:
        if self.waiting:
            self._release()
            self.held = None
            self.session.fault(reason, recoverable=False)
