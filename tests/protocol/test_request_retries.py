"""Command retries (docs/protocol.md section 6): the host resends the same frame, then gives up.

The board here is in memory: a transport whose ``write`` hands the host's bytes to a board-side
decoder and answers at once, the way the emulator's boards do (a board that sees the msg id and
sequence number of the command it last handled re-sends its stored reply without acting again).
"""

from __future__ import annotations

import asyncio
import re
from typing import Any

import pytest

from hil.link import LinkError, SerialLink
from hil.protocol import Ack, Board, Decoder, Encoder, Ident, IdentRequest, Nack, ServoMode, StreamMode
from hil.protocol.messages import ErrorCode


class MemoryBoard(asyncio.Transport):
    """A servo board behind a link: loses the first ``drop_commands`` frames the host writes and the
    first ``drop_replies`` replies it sends; ``refuse`` answers NACK."""

    def __init__(self, link: SerialLink, *, drop_commands: int = 0, drop_replies: int = 0, refuse: bool = False):
        super().__init__()
        self.link = link
        self.drop_commands = drop_commands
        self.drop_replies = drop_replies
        self.refuse = refuse
        self.written: list[bytes] = []  # every frame the host wrote, lost or not
        self.actions = 0  # commands acted upon
        self.decoder = Decoder.for_link(Board.SERVO, "board")
        self.encoder = Encoder(Board.SERVO)
        self.last: tuple[int, int, bytes] | None = None  # (msg id, seq, reply frame) of the last command
        link.connection_made(self)

    def write(self, data: Any) -> None:
        self.written.append(bytes(data))
        if len(self.written) <= self.drop_commands:
            return
        for frame in self.decoder.feed(data):
            msg_id = bytes(data)[5]
            if self.last is not None and self.last[:2] == (msg_id, frame.seq):
                self.reply(self.last[2])  # a resend: the stored reply again, no action
                continue
            self.actions += 1
            if isinstance(frame.message, IdentRequest):
                answer: Any = Ident(Board.SERVO, 1, "mem-1.0", 0, 1)
            elif self.refuse:
                answer = Nack(msg_id, frame.seq, ErrorCode.BAD_STATE, 0xFF, 1.0, 0.0)
            else:
                answer = Ack(msg_id, frame.seq)
            raw = self.encoder.encode(answer, Board.HOST)
            self.last = (msg_id, frame.seq, raw)
            self.reply(raw)

    def reply(self, raw: bytes) -> None:
        if self.drop_replies > 0:
            self.drop_replies -= 1
            return
        self.link.data_received(raw)

    def close(self) -> None:
        self.link.connection_lost(None)

    def is_closing(self) -> bool:
        return False


def run(coro_fn: Any) -> Any:
    async def main() -> Any:
        link = SerialLink("servo")
        return await coro_fn(link)

    return asyncio.run(main())


@pytest.mark.parametrize("drops", [0, 1, 2, 3])
def test_the_same_frame_is_resent_until_answered(drops: int) -> None:
    async def go(link: SerialLink) -> tuple[Ack, MemoryBoard]:
        board = MemoryBoard(link, drop_commands=drops)
        link.retry_interval_s = 0.01
        return await link.request(ServoMode(StreamMode.STREAM), Board.SERVO, Ack), board

    ack, board = run(go)
    assert len(board.written) == drops + 1
    assert len(set(board.written)) == 1  # byte for byte: the same sequence number every time
    assert ack == Ack(0x12, 0) and board.actions == 1


def test_a_lost_reply_is_resent_by_the_board_without_acting_twice() -> None:
    async def go(link: SerialLink) -> tuple[Ack, Ack, MemoryBoard]:
        board = MemoryBoard(link, drop_replies=2)
        link.retry_interval_s = 0.01
        first = await link.request(ServoMode(StreamMode.STREAM), Board.SERVO, Ack)
        second = await link.request(ServoMode(StreamMode.IDLE), Board.SERVO, Ack)  # a new command: a new seq
        return first, second, board

    first, second, board = run(go)
    assert first == Ack(0x12, 0) and second == Ack(0x12, 1)
    assert len(board.written) == 3 + 1 and board.actions == 2
    assert board.written[0] == board.written[1] == board.written[2] != board.written[3]
    assert board.decoder.counters.duplicates == {Board.HOST: 2}  # the board saw the resends as duplicates


def test_no_answer_after_four_tries_is_a_link_error() -> None:
    async def go(link: SerialLink) -> tuple[float, MemoryBoard, str]:
        board = MemoryBoard(link, drop_commands=4)
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        with pytest.raises(LinkError) as err:
            await link.request(ServoMode(StreamMode.STREAM), Board.SERVO, Ack, timeout_s=0.1)
        return loop.time() - t0, board, str(err.value)

    elapsed_s, board, message = run(go)
    assert len(board.written) == 4 and len(set(board.written)) == 1
    assert re.fullmatch(r"servo: SERVO_MODE got no answer after 4 tries \((\d+) ms\)", message), message
    assert elapsed_s >= 4 * 0.05  # the default interval: every try had its 50 ms (timeout_s 0.1 is stretched)


def test_timeout_s_is_the_whole_budget_and_a_late_answer_still_counts() -> None:
    """4 tries 10 ms apart, then the wait goes on until timeout_s: an answer at 150 ms completes."""

    async def go(link: SerialLink) -> tuple[Ident, MemoryBoard]:
        board = MemoryBoard(link, drop_commands=10)
        link.retry_interval_s = 0.01
        late = Encoder(Board.SERVO).encode(Ident(Board.SERVO, 1, "late", 0, 2), Board.HOST)
        asyncio.get_running_loop().call_later(0.15, link.data_received, late)
        return await link.request(IdentRequest(), Board.SERVO, Ident, timeout_s=1.0), board

    ident, board = run(go)
    assert ident.firmware_version == "late" and len(board.written) == 4


def test_a_nack_is_not_retried() -> None:
    async def go(link: SerialLink) -> MemoryBoard:
        board = MemoryBoard(link, refuse=True)
        with pytest.raises(LinkError, match=r"servo: SERVO_MODE refused: BAD_STATE \(axis 255, value 1, limit 0\)"):
            await link.request(ServoMode(StreamMode.STREAM), Board.SERVO, Ack)
        return board

    board = run(go)
    assert len(board.written) == 1


@pytest.mark.parametrize("stray_before", [True, False], ids=["before", "during"])
def test_no_answer_names_misaddressed_frames_seen_meanwhile(stray_before: bool) -> None:
    """A driver board on the servo port: its frames come from 0x20, the host's servo link drops them."""

    async def go(link: SerialLink) -> str:
        MemoryBoard(link, drop_commands=4)
        link.retry_interval_s = 0.01
        link.port = "/dev/ttyUSB0"
        stray = Encoder(Board.DRIVER).encode(Ident(Board.DRIVER, 1, "drv", 0, 3), Board.HOST)
        if stray_before:
            link.data_received(stray)
        else:
            asyncio.get_running_loop().call_later(0.005, link.data_received, stray)
        with pytest.raises(LinkError) as err:
            await link.request(IdentRequest(), Board.SERVO, Ident, timeout_s=0.0)
        assert link.decoder.counters.misaddressed == 1
        return str(err.value)

    message = run(go)
    assert message.startswith("servo: IDENT_REQ got no answer after 4 tries")
    hint = "; meanwhile 1 frame(s) from node 0x20 to node 0x01 were dropped as misaddressed: is the right board on "
    assert message.endswith(hint + "/dev/ttyUSB0?") != stray_before, message


def test_the_link_name_selects_the_boards_decoder() -> None:
    async def go(_: SerialLink) -> list[Any]:
        links = [SerialLink("driver"), SerialLink("bench-probe"), SerialLink("probe", board=Board.IMAGE)]
        return [(link.board, link.decoder.src, link.decoder.dst) for link in links]

    assert run(go) == [(Board.DRIVER, 0x20, 0x01), (None, None, None), (Board.IMAGE, 0x30, 0x01)]
