"""The link budget as numbers (docs/protocol.md, "Link budget"): each periodic message's rate, and from the
catalogue's frame sizes the load each link direction carries and the wire delay of the 1 kHz loop.

A message's ``rate`` in the catalogue is its documentation ("1 kHz", "camera rate (100 Hz)", "10 Hz and on
change"); the number the budget computes with is :data:`PERIODIC_HZ` (a test checks that the two agree).
`hil doctor`, the emulator's link settings and the generated table of docs/protocol.md all count from here.
"""

from __future__ import annotations

from typing import NamedTuple

from hil.protocol import messages as m
from hil.protocol.framing import BITS_PER_BYTE, frame_size, wire_time_s
from hil.protocol.wire import Catalogue, MessageSpec

# The periodic messages' rates, frames per second; a message sent on demand (a command, a reply) is not here.
PERIODIC_HZ: dict[type, float] = {
    m.Heartbeat: 1.0,
    m.HostAlive: 10.0,
    m.GyroSample: 1000.0,
    m.LoopTiming: 100.0,
    m.DriveCmd: 1000.0,
    m.DriveStatus: 100.0,
    m.MissDistance: 100.0,
    m.Pose: 100.0,
    m.HexapodStatus: 10.0,
}


class Periodic(NamedTuple):
    """One periodic message: its link direction, the bytes of one frame on the wire and the frames per second."""

    name: str
    direction: str  # "servo → host"; "any board" for HEARTBEAT (every board sends it) and HOST_ALIVE (every board's)
    frame_bytes: int
    rate_hz: float

    @property
    def bits_per_s(self) -> float:
        """Bit times per second on the wire (8N1: 10 per byte)."""
        return self.frame_bytes * self.rate_hz * BITS_PER_BYTE


def node(board: m.Board | None) -> str:
    """A link's end as the budget names it: ``servo``, ``host``; ``any board`` for a message of every board."""
    return "any board" if board is None else board.name.lower()


def direction(spec: MessageSpec) -> str:
    """The link direction a message travels: ``"servo → host"``."""
    return f"{node(spec.sender)} → {node(spec.receiver)}"  # type: ignore[arg-type]


def periodic_rate_hz(spec: MessageSpec) -> float | None:
    """A periodic message's rate (:data:`PERIODIC_HZ`), None for one sent on demand."""
    return PERIODIC_HZ.get(spec.cls)


def periodic_messages(cat: Catalogue = m.CATALOGUE) -> list[Periodic]:
    """The catalogue's periodic messages, in catalogue order."""
    out = []
    for s in cat:
        hz = periodic_rate_hz(s)
        if hz is not None:
            out.append(Periodic(s.name, direction(s), frame_size(s), hz))
    return out


def periodic_load_bits_per_s(cat: Catalogue = m.CATALOGUE) -> dict[str, float]:
    """The periodic messages' load per link direction (``"servo → host"``), bits/s on the wire (8N1: 10 bit times
    per byte): what a link's baud rate must carry."""
    load: dict[str, float] = {}
    for s in cat:
        hz = periodic_rate_hz(s)
        if hz is not None and s.sender is not None and s.receiver is not None:
            load[direction(s)] = load.get(direction(s), 0.0) + frame_size(s) * hz * BITS_PER_BYTE
    return load


def loop_wire_delay_s(servo_baud: float, driver_baud: float, cat: Catalogue = m.CATALOGUE) -> float:
    """What the wire adds to every cycle of the 1 kHz loop: GYRO_SAMPLE's wire time on the servo link plus
    DRIVE_CMD's on the driver link (s)."""
    return wire_time_s(cat.by_type[m.GyroSample], servo_baud) + wire_time_s(cat.by_type[m.DriveCmd], driver_baud)
