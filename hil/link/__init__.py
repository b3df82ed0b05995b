"""The links: one serial line per board, the frames' capture on the wire, and the ports a bench owns.

``Link`` is the transport's interface (a backend implements ``_write``, ``is_open`` and ``close``; framing, resends
and requests are the base class's); ``SerialLink`` is the RS422 backend, the sim clock's ``SimLink`` lives with the
session. ``claim_ports`` takes a bench's ports exclusively (TIOCEXCL plus a lock naming the holder); ``Capture``
records every frame with its arrival time (docs/capture.md); ``main_sync`` is ``hil selftest``'s link check."""

from hil.link._capture import (
    LINKS,
    MAGIC,
    RECORD_OVERHEAD,
    RX,
    TX,
    Capture,
    CaptureDecode,
    CaptureError,
    CaptureReader,
    TimedFrame,
    decode_capture,
    find_capture,
    is_capture,
    link_decoder,
    time_ordered,
)
from hil.link._doctor import Finding, baud_budget, check_port, check_ports, wire_delay
from hil.link._ports import Holder, PortClaims, PortUnavailable, claim_ports, is_exclusive, set_exclusive
from hil.link._selftest import SelftestReport, main_sync
from hil.link._transport import Link, LinkError, SerialLink, board_of

__all__ = [
    "LINKS",
    "MAGIC",
    "RECORD_OVERHEAD",
    "RX",
    "TX",
    "Capture",
    "CaptureDecode",
    "CaptureError",
    "CaptureReader",
    "Finding",
    "Holder",
    "Link",
    "LinkError",
    "PortClaims",
    "PortUnavailable",
    "SelftestReport",
    "SerialLink",
    "TimedFrame",
    "baud_budget",
    "board_of",
    "check_port",
    "check_ports",
    "claim_ports",
    "decode_capture",
    "find_capture",
    "is_capture",
    "is_exclusive",
    "link_decoder",
    "main_sync",
    "set_exclusive",
    "time_ordered",
    "wire_delay",
]
