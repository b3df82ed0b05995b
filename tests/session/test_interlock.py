"""The session's interlock: once closed, no board client enables, streams or swings again, and the session's
background tasks cannot fail silently."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from hil.boards import DriverBoard, Interlock, InterlockClosed, ProtocolHexapod, ServoBoard
from hil.protocol import CATALOGUE, Ack


class RecordingLink:
    """Stands in for a link (hil.link._transport.Link): records what would have been written, ACKs every command."""

    name, port, is_open = "fake", "/dev/null", True

    def __init__(self) -> None:
        self.sent: list[Any] = []

    async def request(self, message: Any, dst: int, reply: type, timeout_s: float = 0.5) -> Any:
        self.sent.append(message)
        return Ack(CATALOGUE.spec(message).msg_id, len(self.sent) - 1)

    def send(self, message: Any, dst: int) -> int:
        self.sent.append(message)
        return len(self.sent) - 1


def test_a_closed_interlock_refuses_every_command_that_moves_something() -> None:
    interlock = Interlock()
    links = {name: RecordingLink() for name in ("servo", "driver", "hexapod")}
    servo = ServoBoard(links["servo"], interlock)  # type: ignore[arg-type]
    driver = DriverBoard(links["driver"], interlock)  # type: ignore[arg-type]
    hexapod = ProtocolHexapod(links["hexapod"], interlock)  # type: ignore[arg-type]

    async def main() -> None:
        await servo.start_stream()
        await driver.enable()
        await hexapod.start()
        assert [len(link.sent) for link in links.values()] == [1, 1, 1]
        interlock.close("session completed")
        interlock.close("a later reason does not replace the first")
        for action in (servo.start_stream, driver.enable, hexapod.start):
            with pytest.raises(InterlockClosed, match=r"refused: the session has disarmed \(session completed\)"):
                await action()
        # what makes things safe still goes through
        await driver.disable()
        await servo.stop_stream()
        await hexapod.stop()
        driver.disable_now()

    asyncio.run(main())
    names = [[type(m).__name__ for m in link.sent] for link in links.values()]
    assert names == [["ServoMode", "ServoMode"], ["DriveEnable", "DriveDisable", "DriveDisable"],
                     ["HexapodStart", "HexapodStop"]]
    assert links["servo"].sent[1].mode == 0  # IDLE


def test_a_background_task_that_fails_ends_the_session_as_a_fault(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from hil.session import Session
    from tests.factories import session_config

    session = Session(session_config(duration_s=1.0), {}, tmp_path)

    async def broken() -> None:
        await asyncio.sleep(0)
        raise ValueError("the hexapod's status went missing")

    async def main() -> str:
        session._finished = asyncio.get_running_loop().create_future()
        session._spawn(broken(), "status poll")
        return await asyncio.wait_for(session._finished, 1.0)

    assert asyncio.run(main()) == "fault"
    assert session.stop_reason == "status poll failed: ValueError: the hexapod's status went missing"
    assert session.interlock.closed  # and from then on nothing enables, streams or swings
