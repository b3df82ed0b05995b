"""The emulated lab inside the bench's own process: the world side of the ``sim`` clock (docs/emulator.md, "Clocks").

The same :class:`~firmware_stub.emulator.Emulator`, boards and plant as ``lockstep``; only the links differ. A
:class:`MessageLink` passes each message as an object instead of bytes on a pty, after its wire round trip
(:meth:`hil.protocol.MessageSpec.roundtrip`: the encoder's range checks and raw values, then the decoder), so the
host receives exactly the values a frame would have carried, and sequence numbers advance as on the wire.

:class:`SimWorld` advances the world as ``Emulator._run_lockstep`` does, without waiting: one tick, then the
boards' output in the order they wrote it, handed to the host's callback; the host's DRIVE_CMD k (sent from that
callback) releases tick k + 1. For the same seed, config and commands the host therefore sees the same messages
as over ptys in lockstep. Faults on the bytes of a link (bit errors, garbage, stalls) need real bytes: a config
with link faults is refused here (use ``lockstep``).

Like every module of ``firmware_stub``, this one uses nothing of ``hil`` but the protocol.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from firmware_stub.config import ConfigError, EmulatorConfig, LinkFaults, LinkName
from firmware_stub.emulator import Emulator
from firmware_stub.link import BoardLink, FaultRecorder
from firmware_stub.plant import Plant
from hil.protocol import CATALOGUE, Frame

Outbox = list[tuple[LinkName, Frame]]


class MessageLink(BoardLink):
    """A board's end of an in-process link: no pty; what the board sends goes to a shared outbox as a
    :class:`Frame` whose message went through its wire round trip."""

    def __init__(self, name: LinkName, board_id: int, run_dir: Path, faults: LinkFaults, *, seed: int,
                 recorder: FaultRecorder, byte_time_s: float = 0.0) -> None:
        super().__init__(name, board_id, run_dir, faults, seed=seed, recorder=recorder, byte_time_s=byte_time_s)
        self.outbox: Outbox = []
        self._roundtrip = CATALOGUE.roundtrips()

    def _open(self) -> None:
        self.port = None  # nothing to open: messages pass in-process

    def send(self, message: Any, dst: int, tick: int) -> bool:
        msg = self._roundtrip[type(message)](message)
        enc = self.encoder
        seq = enc.take_seq()
        self.stats.tx_frames += 1
        self.outbox.append((self.name, Frame(self.board_id, dst, seq, msg)))
        return True

    def receive(self) -> list[Frame]:
        return []  # the host's frames arrive through SimWorld.from_host


def check_sim_config(config: EmulatorConfig) -> None:
    """Refuse what only real bytes can emulate: ConfigError, one line naming the field."""
    for name in LinkName:
        if config.link_faults(name) != LinkFaults():
            raise ConfigError(f"links.{name.value}: link faults need bytes on a pty; run with --clock lockstep "
                              "(the sim clock passes messages in-process)")
    if config.faults:
        raise ConfigError(f"faults[0]: scheduled {config.faults[0].kind} faults need bytes on a pty; run with "
                          "--clock lockstep (the sim clock passes messages in-process)")


class SimWorld:
    """The lockstep world without ptys or waiting. ``to_host(link, frame)`` receives every board frame;
    the host calls :meth:`from_host` (a frame) or :meth:`from_host_bytes` (an encoded frame) to answer."""

    def __init__(self, config: EmulatorConfig, to_host: Callable[[LinkName, Frame], None]) -> None:
        check_sim_config(config)
        self.emu = Emulator(config, link_factory=MessageLink, control=False)
        self.outbox: Outbox = []
        for link in self.emu.links.values():
            assert isinstance(link, MessageLink)
            link.outbox = self.outbox
        self.to_host = to_host
        self._driver_inbox = self.emu.inbox[LinkName.DRIVER]
        self.unanswered = 0  # samples the host did not answer (lockstep would have waited, then advanced)

    @property
    def streaming(self) -> bool:
        return self.emu.servo.streaming

    @property
    def plant(self) -> Plant:
        """The world's plant: in this process, its true state (:meth:`Plant.truth`) is there to read."""
        return self.emu.plant

    def from_host(self, link: LinkName, frame: Frame) -> None:
        """A frame from the host, handled as the emulator handles what it reads from a pty."""
        emu = self.emu
        emu.inbox[link].append((frame, time.perf_counter()))
        emu.drain(link)

    def from_host_bytes(self, link: LinkName, data: bytes) -> None:
        """Encoded frames from the host (commands with replies), decoded by the board link's own decoder."""
        emu = self.emu
        t_rx = time.perf_counter()
        emu.inbox[link].extend((frame, t_rx) for frame in emu.links[link].decoder.feed(data))
        emu.drain(link)

    def deliver(self) -> None:
        """Hand every frame the boards have sent to the host, in the order they sent them (replies the host's
        handlers provoke meanwhile included)."""
        out, to_host = self.outbox, self.to_host
        i = 0
        while i < len(out):
            link, frame = out[i]
            i += 1
            to_host(link, frame)
        out.clear()

    def tick(self) -> bool:
        """One lockstep tick (``Emulator._run_lockstep``'s body): advance the world, deliver its output, let the
        host's DRIVE_CMD for the sample release the next tick. False (nothing done) while the stream is off."""
        emu = self.emu
        servo = emu.servo
        if not servo.streaming:
            return False
        held = self._driver_inbox  # driver frames held back by the last release (usually none)
        emu.step()
        servo.on_written(time.perf_counter())
        emu.released = False
        k = servo.last_delivered
        emu.awaiting = k
        if held:
            emu.drain(LinkName.DRIVER)
        self.deliver()
        if k is not None and not emu.released and servo.streaming:
            self.unanswered += 1
        emu.awaiting = None
        emu.released = False
        if held:
            emu.drain(LinkName.DRIVER)
        return True

    def summary(self) -> dict[str, Any]:
        return {**self.emu.summary(), "clock": "sim", "unanswered_samples": self.unanswered}

    def close(self) -> None:
        self.emu.close()
