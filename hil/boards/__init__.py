"""The boards as the session sees them: one client per board over a :class:`~hil.link.Link`.

``ServoBoard`` (gyro and encoders, the loop's clock), ``DriverBoard`` (the power stage), ``ImageBoard`` (miss
distance) and the hexapod: ``HexapodDriver`` is a table's interface, ``ProtocolHexapod`` the bench's own protocol
(entry point ``hil.boards:ProtocolHexapod``, docs/hexapod-drivers.md), ``GuardedHexapod`` holds it to the one-way
safety rule through the session's ``Interlock``. ``check_boards`` and ``listen_to_stream`` are `hil doctor`'s checks
that need the boards to answer (IDENT and its catalogue fingerprint, the servo stream's rate and jitter);
``wait_for_rest`` the boards' rest state measured (a service's check before each item)."""

from hil.boards._clients import (
    HEXAPOD_DRIVERS,
    DriverBoard,
    GuardedHexapod,
    HexapodDriver,
    HexapodOptions,
    ImageBoard,
    Interlock,
    InterlockClosed,
    ProtocolHexapod,
    ServoBoard,
    installed_hexapod_drivers,
    load_hexapod_driver,
)
from hil.boards._doctor import check_boards, listen_to_stream
from hil.boards._rest import REST_TIMEOUT_S, RestState, wait_for_rest

__all__ = [
    "HEXAPOD_DRIVERS",
    "REST_TIMEOUT_S",
    "DriverBoard",
    "GuardedHexapod",
    "HexapodDriver",
    "HexapodOptions",
    "ImageBoard",
    "Interlock",
    "InterlockClosed",
    "ProtocolHexapod",
    "RestState",
    "ServoBoard",
    "check_boards",
    "installed_hexapod_drivers",
    "listen_to_stream",
    "load_hexapod_driver",
    "wait_for_rest",
]
