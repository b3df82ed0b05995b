"""A minimal synchronous host for emulator tests: raw fds on the board ports, the protocol's codec.

Deliberately not the bench's transport (hil.link._transport): these tests check the emulator against the
protocol alone. Every byte received is kept per link, so two runs can be compared byte for byte.
"""

from __future__ import annotations

import contextlib
import os
import select
import termios
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

from firmware_stub.config import EmulatorConfig, load_emulator_config
from firmware_stub.emulator import Emulator
from hil.protocol import Ack, Board, Decoder, Encoder, Frame, HostAlive, Nack

BOARD_OF = {"servo": Board.SERVO, "driver": Board.DRIVER, "image": Board.IMAGE, "hexapod": Board.HEXAPOD}


class HostPort:
    def __init__(self, name: str, path: str) -> None:
        self.name, self.path = name, path
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        self.encoder = Encoder(Board.HOST)
        self.decoder = Decoder()
        self.raw = bytearray()
        self.frames: list[Frame] = []
        self.hangups = 0
        self.cursor = 0  # frames[:cursor] already consumed by a test's stream loop

    def send(self, message: Any) -> int:
        seq = self.encoder.next_seq
        os.write(self.fd, self.encoder.encode(message, BOARD_OF[self.name]))
        return seq

    def pump(self) -> list[Frame]:
        """Read what is there; returns the new frames (also appended to self.frames)."""
        new: list[Frame] = []
        while True:
            try:
                data = os.read(self.fd, 65536)
            except BlockingIOError:
                break
            except OSError:  # EIO: the board side closed (disconnect)
                self.hangups += 1
                break
            if not data:  # EOF: hung up
                self.hangups += 1
                break
            self.raw += data
            new += self.decoder.feed(data)
        self.frames += new
        return new

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self.fd)

    def reopen(self) -> None:
        self.close()
        self.frames.clear()
        self.cursor = 0
        self.fd = os.open(self.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        termios.tcflush(self.fd, termios.TCIFLUSH)  # what the board sent while nobody listened


class Host:
    """All four ports; ``wait`` pumps every port until a predicate on one port's new frames holds."""

    def __init__(self, ports: dict[str, str], host_alive_period_s: float | None = None) -> None:
        """``host_alive_period_s``: send HOST_ALIVE on every port this often while pumping (realtime runs that
        last longer than the boards' host timeout); keep it None in lockstep, where it would shift the host's
        sequence numbers and so the bytes of the ACKs."""
        self.ports = {name: HostPort(name, path) for name, path in ports.items() if name in BOARD_OF}
        self.host_alive_period_s = host_alive_period_s
        self._next_alive = time.monotonic()

    def __getitem__(self, name: str) -> HostPort:
        return self.ports[name]

    def pump_all(self, timeout_s: float = 0.0) -> None:
        if self.host_alive_period_s is not None and time.monotonic() >= self._next_alive:
            self._next_alive = time.monotonic() + self.host_alive_period_s
            for p in self.ports.values():
                with contextlib.suppress(OSError):  # a port the test closed
                    p.send(HostAlive(0))
        fds = [p.fd for p in self.ports.values()]
        with contextlib.suppress(OSError, ValueError):
            select.select(fds, [], [], timeout_s)
        for p in self.ports.values():
            p.pump()

    def wait(self, name: str, match: Callable[[Frame], bool], timeout_s: float = 2.0, since: int = 0) -> Frame:
        """The first frame on a port, from index ``since`` of everything received, that matches."""
        port = self.ports[name]
        start = since
        give_up = time.monotonic() + timeout_s
        while True:
            for frame in port.frames[start:]:
                if match(frame):
                    return frame
            start = len(port.frames)
            if time.monotonic() > give_up:
                raise TimeoutError(f"{name}: no matching frame within {timeout_s} s")
            self.pump_all(0.01)

    def request(self, name: str, message: Any, timeout_s: float = 2.0) -> Any:
        """Send a command; return its ACK or NACK."""
        since = len(self.ports[name].frames)
        seq = self.ports[name].send(message)
        frame = self.wait(name, lambda f: isinstance(f.message, Ack | Nack) and f.message.seq == seq, timeout_s, since)
        return frame.message

    def close(self) -> None:
        for p in self.ports.values():
            p.close()


@contextlib.contextmanager
def running_emulator(config: EmulatorConfig | None = None, **overrides: Any) -> Iterator[Emulator]:
    """An emulator serving from a background thread of this process (tests reach its internals)."""
    config = config or load_emulator_config(**overrides)
    emu = Emulator(config)
    thread = threading.Thread(target=emu.run, name="emulator", daemon=True)
    thread.start()
    try:
        yield emu
    finally:
        emu.request_stop()
        thread.join(timeout=5)
        emu.close()

