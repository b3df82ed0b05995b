"""Serial links to the boards: pyserial-asyncio-fast underneath, the protocol codec on top.

Incoming bytes are decoded chunk by chunk in ``data_received`` and each frame is handed to the
link's ``on_frame`` callback right there, so a reaction (such as DRIVE_CMD k for GYRO_SAMPLE k)
is written within the same event-loop callback that read the sample: no timer is involved.

A link given a capture (hil.link: ``SerialLink.open(..., capture=...)``) records every chunk it reads and every
frame it writes, with its time; the realtime loop thread records what it reads and writes on the link's behalf.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import serial
import serial_asyncio_fast

from hil.link._ports import open_refusal, set_exclusive
from hil.protocol import CATALOGUE, LINE_RATE_BAUD, Ack, Board, Decoder, Encoder, Frame, LockstepAck, Nack
from hil.protocol.framing import frame_seq

if TYPE_CHECKING:
    from hil.link._capture import Capture, LinkCapture

DEFAULT_BAUD = LINE_RATE_BAUD
RETRY_INTERVAL_S = 0.05  # docs/protocol.md section 6: resend after 50 ms without a reply ...
MAX_RESENDS = 3  # ... at most 3 times


class LinkError(RuntimeError):
    """A link could not be opened, or a request got no good answer."""


def board_of(name: str) -> Board | None:
    """The board a link name designates ("servo" -> Board.SERVO), None for any other name."""
    board = Board.__members__.get(name.upper())
    return None if board is None or board is Board.HOST else board


class Link(ABC):
    """One board's link, whatever carries its frames (as python-can's ``BusABC`` is any CAN interface): the codec,
    each decoded frame handed to whoever waits for it and then to ``on_frame``, requests with resends, the closing.

    A backend implements :meth:`_write` (one encoded frame out), :meth:`close` and :attr:`is_open`; it hands what
    it reads to :meth:`feed` (bytes) or :meth:`deliver` (decoded frames) and calls :meth:`_closed_with` once when
    the link is gone. :class:`SerialLink` is the serial port's (real boards, the emulator's ptys);
    ``hil.session.SimLink`` the in-process lab's of the ``sim`` clock. The session does not know which it has.

    The link knows its board (``board``, by default from the link name: "servo", "driver",
    "image", "hexapod"), so its decoder delivers only what that board may send the host
    (:meth:`Decoder.for_link`); a link of another name decodes everything. ``retry_interval_s``
    and ``max_resends`` govern :meth:`request`'s resends (lockstep emulation sets a longer interval).
    ``capture``: this link's handle on a capture file (hil.link), None for none. ``acknowledge``: answer every
    read that brought frames with LOCKSTEP_ACK (a lockstep emulator's world waits for it; docs/protocol.md).
    """

    def __init__(self, name: str, on_frame: Callable[[Frame], None] | None = None, src: int = Board.HOST,
                 board: int | None = None, *, capture: LinkCapture | None = None) -> None:
        self.name = name
        self.on_frame = on_frame
        self.encoder = Encoder(src)
        self.board = board_of(name) if board is None else Board(board)
        self.decoder = Decoder() if self.board is None else Decoder.for_link(self.board, "host")
        self.retry_interval_s = RETRY_INTERVAL_S
        self.max_resends = MAX_RESENDS
        self.port = ""
        self.closed = asyncio.get_running_loop().create_future()
        self._lost_exc: Exception | None = None
        self._waiters: list[tuple[Callable[[Frame], bool], asyncio.Future[Frame]]] = []
        self.capture = capture
        self.write_lock = threading.Lock()  # sequence number, stamp and write of one frame, whichever thread (_write)
        self.acknowledge = False

    # what a backend provides --------------------------------------------------------------------
    @property
    @abstractmethod
    def is_open(self) -> bool:
        """Frames can be sent: opened and not closed or lost."""

    @abstractmethod
    def _write(self, data: bytes) -> None:
        """Write one encoded frame (the link is open); called with :attr:`write_lock` held."""

    @abstractmethod
    def close(self) -> None:
        """Close the link; :meth:`_closed_with` follows (at once or from the event loop)."""

    @property
    def fd(self) -> int | None:
        """The file descriptor under the link, which the realtime loop thread reads and writes itself; None for a
        backend without one (the ``sim`` clock's passes objects) and for a closed link. A backend over a file
        descriptor overrides it."""
        return None

    def pause_reading(self) -> None:
        """Stop reading for the event loop while the realtime loop thread reads :attr:`fd` itself
        (:meth:`resume_reading` gives it back). Only a backend over a file descriptor can."""
        raise LinkError(f"{self.name}: this link has no file descriptor for the loop thread to read")

    def resume_reading(self) -> None:  # noqa: B027  (a backend without a file descriptor never paused)
        """Read for the event loop again after :meth:`pause_reading` (nothing, once the link is closed)."""

    # receiving ----------------------------------------------------------------------------------
    def feed(self, data: bytes) -> None:
        """Bytes read from the board: each frame decoded and delivered, then (``acknowledge``) LOCKSTEP_ACK of the
        last one, once its handlers have run."""
        last = None
        for frame in self.decoder.feed(data):
            self.deliver(frame)
            last = frame
        if last is not None and self.acknowledge and self.is_open and self.board is not None:
            self.send(LockstepAck(last.seq), self.board)  # handled, not just read: after the frames' handlers

    def deliver(self, frame: Frame) -> None:
        """One decoded frame to whoever waits for it, then to ``on_frame``. The realtime loop thread, which reads the
        servo link itself while it runs (LoopThread), hands every frame but GYRO_SAMPLE here on the event loop."""
        if self._waiters:
            self._wake_waiters(frame)
        if self.on_frame is not None:
            self.on_frame(frame)

    def lost(self, exc: Exception | None) -> None:
        """The link failed where the event loop was not reading it (the realtime loop thread reads the servo link):
        close it, and let ``closed`` carry ``exc`` as a read failure of the transport would."""
        self._lost_exc = exc
        self.close()

    def _closed_with(self, exc: Exception | None) -> None:
        """The link is gone (``exc``: why, None for a plain close): ``closed`` completes, waiters fail."""
        exc = exc or self._lost_exc
        if self.capture is not None:
            self.capture.note(event="close", reason=str(exc) if exc is not None else "")
        if not self.closed.done():
            self.closed.set_result(exc)
        for _, fut in self._waiters:
            if not fut.done():
                fut.set_exception(LinkError(f"{self.name}: link lost ({exc or 'closed'})"))
        self._waiters.clear()

    # sending -------------------------------------------------------------------------------------
    def send(self, message: Any, dst: int) -> int:
        """Encode and write one message; returns the sequence number it went out with."""
        if not self.is_open:
            raise LinkError(f"{self.name}: link is closed")
        with self.write_lock:
            data = self.encoder.encode(message, dst)
            self._write(data)
        return frame_seq(data)

    def _wake_waiters(self, frame: Frame) -> None:
        keep = []
        for predicate, fut in self._waiters:
            if fut.done():
                continue
            if predicate(frame):
                fut.set_result(frame)
            else:
                keep.append((predicate, fut))
        self._waiters = keep

    def expect(self, predicate: Callable[[Frame], bool]) -> asyncio.Future[Frame]:
        """A future for the next frame satisfying ``predicate`` (registered at once, before any send)."""
        fut: asyncio.Future[Frame] = asyncio.get_running_loop().create_future()
        self._waiters.append((predicate, fut))
        return fut

    async def wait_for(self, predicate: Callable[[Frame], bool], timeout_s: float) -> Frame:
        """The next frame satisfying ``predicate``; LinkError after ``timeout_s``."""
        return await self._within(self.expect(predicate), timeout_s)

    async def _within(self, fut: asyncio.Future[Frame], timeout_s: float) -> Frame:
        try:
            return await asyncio.wait_for(fut, timeout_s)
        except TimeoutError:
            raise LinkError(f"{self.name}: no answer within {timeout_s * 1e3:.0f} ms") from None

    async def request(self, message: Any, dst: int, reply: type, timeout_s: float = 0.5) -> Any:
        """Send ``message`` and return the ``reply`` message that answers it.

        Without an answer the same frame (same sequence number, so the board can tell a resend
        and re-send its stored reply instead of acting twice) goes out again every
        ``retry_interval_s``, at most ``max_resends`` times (docs/protocol.md section 6).
        ``timeout_s`` is the most the call waits in all, from the first try; it is stretched to
        ``(max_resends + 1) * retry_interval_s`` when shorter, so every try gets its interval.
        A late answer to any try completes the request. Then LinkError, naming the tries.

        For commands answered with ACK/NACK, a NACK for this frame raises LinkError naming the
        error code, axis, value and limit.
        """
        spec = CATALOGUE.spec(message)
        if not self.is_open:
            raise LinkError(f"{self.name}: link is closed")
        seq = -1  # set just before the first write (a link that answers within the write is answered to it)

        def matches(frame: Frame) -> bool:
            msg = frame.message
            if isinstance(msg, Ack | Nack):
                return msg.msg_id == spec.msg_id and msg.seq == seq
            return isinstance(msg, reply)

        fut = self.expect(matches)
        misaddressed_before = self.decoder.counters.misaddressed
        loop = asyncio.get_running_loop()
        interval_s = self.retry_interval_s
        total_s = max(timeout_s, (self.max_resends + 1) * interval_s)
        t0 = loop.time()
        try:
            with self.write_lock:
                data = self.encoder.encode(message, dst)
                seq = frame_seq(data)
                self._write(data)
            for k in range(self.max_resends + 1):
                if k:  # a resend: the same frame again
                    if fut.done():
                        break
                    if not self.is_open:
                        raise LinkError(f"{self.name}: link is closed")
                    with self.write_lock:
                        self._write(data)
                until = t0 + (total_s if k == self.max_resends else (k + 1) * interval_s)
                await asyncio.wait((fut,), timeout=max(0.0, until - loop.time()))
            if not fut.done():
                raise LinkError(f"{self.name}: {spec.name} got no answer after {self.max_resends + 1} tries "
                                f"({(loop.time() - t0) * 1e3:.0f} ms){self._misaddressed_hint(misaddressed_before)}")
        finally:
            if not fut.done():
                fut.cancel()
        frame = fut.result()
        if isinstance(frame.message, Nack):
            n = frame.message
            raise LinkError(
                f"{self.name}: {spec.name} refused: {n.error.name if hasattr(n.error, 'name') else n.error}"
                f" (axis {n.axis}, value {n.value:g}, limit {n.limit:g})"
            )
        return frame.message

    def _misaddressed_hint(self, misaddressed_before: int) -> str:
        """What to add to a no-answer error when frames for or from other nodes came in meanwhile."""
        n = self.decoder.counters.misaddressed - misaddressed_before
        last = self.decoder.last_misaddressed
        if n <= 0 or last is None:
            return ""
        return (f"; meanwhile {n} frame(s) from node {last[0]:#04x} to node {last[1]:#04x} were dropped as "
                f"misaddressed: is the right board on {self.port or 'this port'}?")


class SerialLink(Link, asyncio.Protocol):
    """A link over a serial port (pyserial-asyncio-fast): a real board's RS422 adapter, or an emulator's pty.
    Open with :meth:`open`; incoming bytes are decoded in ``data_received``, so a reaction (DRIVE_CMD k for
    GYRO_SAMPLE k) is written within the same event-loop callback that read the sample."""

    def __init__(self, name: str, on_frame: Callable[[Frame], None] | None = None, src: int = Board.HOST,
                 board: int | None = None, *, capture: LinkCapture | None = None) -> None:
        super().__init__(name, on_frame, src, board, capture=capture)
        self.transport: asyncio.Transport | None = None

    @classmethod
    async def open(
        cls, name: str, port: str, baudrate: int = DEFAULT_BAUD, on_frame: Callable[[Frame], None] | None = None,
        *, board: int | None = None, capture: Capture | None = None,
    ) -> SerialLink:
        """Open ``port`` (a device such as /dev/ttyUSB0, or an emulator's pty) to ``board``
        (default: the board the link name designates). With ``capture``, the link's bytes go to that capture
        file under the link's name, from the moment it is open.

        The port is opened for this link alone (hil.link): pyserial's advisory lock on the device, then the tty's
        exclusive-use flag (TIOCEXCL), cleared again by :meth:`close`. Claim it first (hil.link.claim_ports) to
        refuse a second bench by name before anything is opened."""
        loop = asyncio.get_running_loop()
        handle = None if capture is None else capture.link(name)
        try:
            _, link = await serial_asyncio_fast.create_serial_connection(
                loop, lambda: cls(name, on_frame, board=board, capture=handle), port, baudrate=baudrate,
                exclusive=True)
        except serial.SerialException as exc:
            cause = open_refusal(exc) if isinstance(exc.errno, int) else str(exc)
            raise LinkError(f"{name}: cannot open {port}: {cause}") from None
        except OSError as exc:
            raise LinkError(f"{name}: cannot open {port}: {open_refusal(exc)}") from None
        await asyncio.sleep(0)  # let connection_made run
        assert isinstance(link, cls)  # the protocol the factory above made
        link.port = port
        ser = getattr(link.transport, "serial", None)
        if ser is not None:
            try:
                set_exclusive(ser.fd, True)
            except OSError as exc:
                link.close()
                raise LinkError(f"{name}: {port}: cannot take it for exclusive use: {exc.strerror or exc}") from None
            ser.reset_input_buffer()  # bytes the board sent while nobody listened are stale: drop them
        return link

    @property
    def is_open(self) -> bool:
        return self.transport is not None

    @property
    def fd(self) -> int | None:
        """The port's file descriptor (the realtime loop thread reads and writes it itself), None once closed."""
        ser = getattr(self.transport, "serial", None)
        fd = getattr(ser, "fd", None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    def pause_reading(self) -> None:
        if self.transport is None:
            raise LinkError(f"{self.name}: closed")
        self.transport.pause_reading()

    def resume_reading(self) -> None:
        if self.transport is not None:
            self.transport.resume_reading()

    # asyncio.Protocol ------------------------------------------------------------------------
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        if self.capture is not None:  # before any byte: a decoder of the capture starts afresh here
            ser = getattr(transport, "serial", None)
            self.capture.note(event="open", port=getattr(ser, "port", None), baudrate=getattr(ser, "baudrate", None))

    def data_received(self, data: bytes) -> None:
        if self.capture is not None:
            self.capture.rx(data)
        self.feed(data)

    def connection_lost(self, exc: Exception | None) -> None:
        self.transport = None
        self._closed_with(exc)

    def _write(self, data: bytes) -> None:
        """Write ``data`` (the transport is open), and capture it, stamped before the write. Call with
        :attr:`write_lock` held: two threads write the driver link (the realtime loop thread its DRIVE_CMDs), and
        the lock keeps each frame's sequence number, stamp and write together, so the frames go out in the order of
        their sequence numbers and the capture's stamps in the order of the bytes."""
        assert self.transport is not None
        capture = self.capture
        if capture is None:
            self.transport.write(data)
            return
        t_ns = time.monotonic_ns()
        self.transport.write(data)
        capture.tx(data, t_ns)

    def close(self) -> None:
        """Close the port, its exclusive-use flag cleared first (an emulator's pty outlives the link)."""
        if self.transport is None:
            return
        ser = getattr(self.transport, "serial", None)
        fd = getattr(ser, "fd", None)
        if fd is not None:
            with contextlib.suppress(OSError):
                set_exclusive(fd, False)
        self.transport.close()
