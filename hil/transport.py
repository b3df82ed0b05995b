"""Serial links to the boards: pyserial-asyncio-fast underneath, the protocol codec on top.

Incoming bytes are decoded chunk by chunk in ``data_received`` and each frame is handed to the
link's ``on_frame`` callback right there, so a reaction (such as DRIVE_CMD k for GYRO_SAMPLE k)
is written within the same event-loop callback that read the sample: no timer is involved.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

import serial
import serial_asyncio_fast

from hil.protocol import CATALOGUE, Ack, Board, Decoder, Encoder, Frame, Nack

DEFAULT_BAUD = 921_600


class LinkError(RuntimeError):
    """A link could not be opened, or a request got no good answer."""


class SerialLink(asyncio.Protocol):
    """One board's link. Open with :meth:`open`; frames go to ``on_frame`` as they decode."""

    def __init__(self, name: str, on_frame: Callable[[Frame], None] | None = None, src: int = Board.HOST) -> None:
        self.name = name
        self.on_frame = on_frame
        self.encoder = Encoder(src)
        self.decoder = Decoder()
        self.transport: asyncio.Transport | None = None
        self.port = ""
        self.closed = asyncio.get_running_loop().create_future()
        self._waiters: list[tuple[Callable[[Frame], bool], asyncio.Future[Frame]]] = []

    @classmethod
    async def open(
        cls, name: str, port: str, baudrate: int = DEFAULT_BAUD, on_frame: Callable[[Frame], None] | None = None
    ) -> SerialLink:
        """Open ``port`` (a device such as /dev/ttyUSB0, or an emulator's pty)."""
        loop = asyncio.get_running_loop()
        try:
            _, link = await serial_asyncio_fast.create_serial_connection(
                loop, lambda: cls(name, on_frame), port, baudrate=baudrate
            )
        except (serial.SerialException, OSError) as exc:
            raise LinkError(f"{name}: cannot open {port}: {exc}") from None
        await asyncio.sleep(0)  # let connection_made run
        link.port = port
        ser = getattr(link.transport, "serial", None)
        if ser is not None:  # bytes the board sent while nobody listened are stale: drop them
            ser.reset_input_buffer()
        return link

    # asyncio.Protocol ------------------------------------------------------------------------
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        for frame in self.decoder.feed(data):
            if self._waiters:
                self._wake_waiters(frame)
            if self.on_frame is not None:
                self.on_frame(frame)

    def connection_lost(self, exc: Exception | None) -> None:
        self.transport = None
        if not self.closed.done():
            self.closed.set_result(exc)
        for _, fut in self._waiters:
            if not fut.done():
                fut.set_exception(LinkError(f"{self.name}: link lost ({exc or 'closed'})"))
        self._waiters.clear()

    # sending -------------------------------------------------------------------------------------
    def send(self, message: Any, dst: int) -> int:
        """Encode and write one message; returns the sequence number it went out with."""
        if self.transport is None:
            raise LinkError(f"{self.name}: link is closed")
        seq = self.encoder.next_seq
        self.transport.write(self.encoder.encode(message, dst))
        return seq

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

        For commands answered with ACK/NACK, a NACK for this frame raises LinkError naming the
        error code, axis, value and limit.
        """
        spec = CATALOGUE.spec(message)
        answered: list[int] = []

        def matches(frame: Frame) -> bool:
            msg = frame.message
            if isinstance(msg, Ack | Nack):
                return msg.msg_id == spec.msg_id and msg.seq == answered[0]
            return isinstance(msg, reply)

        fut = self.expect(matches)
        answered.append(self.send(message, dst))
        frame = await self._within(fut, timeout_s)
        if isinstance(frame.message, Nack):
            n = frame.message
            raise LinkError(
                f"{self.name}: {spec.name} refused: {n.error.name if hasattr(n.error, 'name') else n.error}"
                f" (axis {n.axis}, value {n.value:g}, limit {n.limit:g})"
            )
        return frame.message

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()
