"""Receiver rules beyond framing (docs/protocol.md, "Sequence numbers" and "Receiving"): sequence
classification, the version counter, and per-link addressing."""

from __future__ import annotations

import pytest

from hil.log.schema import LINK_COUNTERS
from hil.protocol import (
    CATALOGUE,
    Ack,
    Board,
    Decoder,
    DriveCmd,
    DriveStatus,
    Encoder,
    Frame,
    GyroSample,
    HostAlive,
    Ident,
    IdentRequest,
    ServoMode,
    StreamMode,
    encode_frame,
)
from hil.protocol.framing import link_message_ids

SERVO, HOST = int(Board.SERVO), int(Board.HOST)


def gyro(seq: int, src: int = SERVO, dst: int = HOST) -> bytes:
    return encode_frame(GyroSample(seq, seq, 0.0, 0.0, 0.0, 0.0, 0.0), src=src, dst=dst, seq=seq)


def seqs_out(decoder: Decoder, seqs: list[int]) -> list[int]:
    return [f.seq for f in decoder.feed(b"".join(gyro(s) for s in seqs))]


# --- sequence numbers ------------------------------------------------------------------------------------


def test_a_duplicate_is_delivered_and_counted_not_65535_lost_frames() -> None:
    decoder = Decoder()
    assert seqs_out(decoder, [7, 8, 8, 9]) == [7, 8, 8, 9]
    c = decoder.counters
    assert c.duplicates == {SERVO: 1} and c.frames_lost == {} and c.seq_gaps == {}
    assert c.errors() == 0 and c.frames_ok == 4


def test_a_step_back_is_reordering_and_does_not_move_last_back() -> None:
    decoder = Decoder()
    # 100 arrives, then 97 (3 back), then 101 follows 100 in order
    assert seqs_out(decoder, [99, 100, 97, 101]) == [99, 100, 97, 101]
    c = decoder.counters
    assert c.reordered == {SERVO: 1} and c.frames_lost == {} and c.seq_gaps == {}
    assert c.errors() == 1


def test_half_the_number_space_back_is_reordering_one_more_is_a_gap() -> None:
    decoder = Decoder()
    seqs_out(decoder, [40000, 40000 - 32768])  # d = 32768: a step back
    assert decoder.counters.reordered == {SERVO: 1} and decoder.counters.frames_lost == {}
    decoder = Decoder()
    seqs_out(decoder, [40000, 40000 - 32769])  # d = 32767: forward, 32766 frames skipped
    assert decoder.counters.frames_lost == {SERVO: 32766} and decoder.counters.reordered == {}


@pytest.mark.parametrize("last", [1, 3, 1000, 65000, 65534])
def test_a_jump_back_to_zero_is_a_restart_without_loss(last: int) -> None:
    decoder = Decoder()
    assert seqs_out(decoder, [last - 1, last, 0, 1, 2]) == [last - 1, last, 0, 1, 2]
    c = decoder.counters
    assert c.restarts == {SERVO: 1} and c.frames_lost == {} and c.seq_gaps == {} and c.reordered == {}
    assert c.errors() == 0


def test_the_wrap_from_65535_to_0_is_in_order() -> None:
    decoder = Decoder()
    seqs_out(decoder, [65534, 65535, 0, 1])
    c = decoder.counters
    assert c.restarts == {} and c.frames_lost == {} and c.errors() == 0


def test_a_real_gap_counts_the_frames_it_skipped() -> None:
    decoder = Decoder()
    seqs_out(decoder, [10, 11, 15, 16, 20])
    c = decoder.counters
    assert c.seq_gaps == {SERVO: 2} and c.frames_lost == {SERVO: 3 + 3} and c.errors() == 2


def test_note_restart_takes_the_next_number_as_a_fresh_start() -> None:
    decoder = Decoder()
    seqs_out(decoder, [500, 501])
    decoder.note_restart(SERVO)
    seqs_out(decoder, [3, 4])  # the board restarted and its first frames were not seen
    decoder.note_restart(0x20)  # another source: no effect on the servo's count
    seqs_out(decoder, [6])
    c = decoder.counters
    assert c.reordered == {} and c.restarts == {} and c.seq_gaps == {SERVO: 1} and c.frames_lost == {SERVO: 1}


def test_sequences_are_tracked_per_source() -> None:
    decoder = Decoder()
    stream = gyro(5) + gyro(9, src=0x20) + gyro(6) + gyro(9, src=0x20) + gyro(0, src=0x20)
    assert len(decoder.feed(stream)) == 5
    c = decoder.counters
    assert c.duplicates == {0x20: 1} and c.restarts == {0x20: 1} and c.seq_gaps == {}


# --- version ---------------------------------------------------------------------------------------------


def test_a_wrong_version_is_counted_and_the_next_frame_comes_out() -> None:
    bad = bytearray(gyro(1))
    bad[2] = 2
    decoder = Decoder()
    assert seqs_out(decoder, [0]) == [0]
    assert [f.seq for f in decoder.feed(bytes(bad) + gyro(2))] == [2]
    c = decoder.counters
    assert c.bad_versions == 1 and c.bad_lengths == 0 and c.unknown_ids == 0 and c.crc_errors == 0
    assert c.bytes_discarded == len(bad) and c.frames_lost == {SERVO: 1}
    assert c.errors() == 2 and c.totals()["bad_frames"] == 1


# --- addressing ------------------------------------------------------------------------------------------


def test_link_messages_follow_the_catalogue_directions() -> None:
    names = {i: CATALOGUE.by_id[i].name for i in range(256) if i in CATALOGUE.by_id}

    def named(board: Board, side: str) -> set[str]:
        return {names[i] for i in link_message_ids(board, side)}  # type: ignore[arg-type]

    common_up = {"IDENT", "HEARTBEAT", "ACK", "NACK"}
    common_down = {"IDENT_REQ", "HOST_ALIVE", "LOCKSTEP_ACK"}
    assert named(Board.SERVO, "host") == common_up | {"GYRO_SAMPLE", "LOOP_TIMING", "CLOCK_LATE"}
    assert named(Board.SERVO, "board") == common_down | {"SERVO_CONFIG", "SERVO_MODE"}
    assert named(Board.DRIVER, "host") == common_up | {"DRIVE_STATUS"}
    assert named(Board.DRIVER, "board") == common_down | {"DRIVE_CMD", "DRIVE_ENABLE", "DRIVE_DISABLE"}
    assert named(Board.IMAGE, "host") == common_up | {"MISS_DISTANCE"}
    assert named(Board.IMAGE, "board") == common_down | {"TRACK_CMD"}
    assert named(Board.HEXAPOD, "host") == common_up | {"POSE", "HEXAPOD_STATUS"}
    assert named(Board.HEXAPOD, "board") == common_down | {"PROFILE_LOAD", "HEXAPOD_START", "HEXAPOD_STOP"}
    every = set(names.values())
    sides = [named(b, s) for b in (Board.SERVO, Board.DRIVER, Board.IMAGE, Board.HEXAPOD) for s in ("host", "board")]
    assert set().union(*sides) == every  # every message travels on some link
    with pytest.raises(ValueError, match="side 'both'"):
        link_message_ids(Board.SERVO, "both")  # type: ignore[arg-type]


def test_the_hosts_servo_decoder_drops_misaddressed_and_wrong_link_frames() -> None:
    board = Encoder(Board.SERVO)
    status = DriveStatus(0, 0, 0, 0, 0, 0, 0)
    stream = [
        board.encode(Ident(Board.SERVO, 1, "1.0", 0, 7), HOST),  # seq 0: delivered
        board.encode(status, HOST),  # seq 1: a driver message on the servo link
        encode_frame(Ack(0x12, 4), src=0x20, dst=HOST, seq=2),  # another board's frame
        board.encode(Ack(0x12, 4), 0x30),  # seq 2: for another node
        board.encode(IdentRequest(), HOST),  # seq 3: a host -> board message coming up
        board.encode(Ack(0x12, 4), HOST),  # seq 4: delivered
    ]
    decoder = Decoder.for_link(Board.SERVO, "host")
    out = decoder.feed(b"".join(stream))
    assert out == [Frame(SERVO, HOST, 0, Ident(Board.SERVO, 1, "1.0", 0, 7)), Frame(SERVO, HOST, 4, Ack(0x12, 4))]
    c = decoder.counters
    assert (c.misaddressed, c.wrong_link, c.frames_ok) == (2, 2, 2)
    assert decoder.last_misaddressed == (SERVO, 0x30)
    # consumed whole, in step: no resync, no discarded byte, no sequence gap from the servo
    assert c.bytes_in_frames == c.bytes == sum(map(len, stream)) and c.bytes_discarded == 0 and c.resyncs == 0
    assert c.seq_gaps == {} and c.errors() == 4 and c.totals()["rejected"] == 4


def test_the_boards_side_is_the_mirror() -> None:
    host = Encoder(Board.HOST)
    stream = [
        host.encode(ServoMode(StreamMode.STREAM), Board.SERVO),
        host.encode(HostAlive(5), Board.SERVO),
        host.encode(DriveCmd(1, 2, 3), Board.SERVO),  # a driver command on the servo link
        host.encode(ServoMode(StreamMode.IDLE), Board.DRIVER),  # for another board
    ]
    decoder = Decoder.for_link(Board.SERVO, "board")
    assert [type(f.message) for f in decoder.feed(b"".join(stream))] == [ServoMode, HostAlive]
    assert (decoder.counters.wrong_link, decoder.counters.misaddressed) == (1, 1)


def test_a_decoder_without_a_link_accepts_everything() -> None:
    stream = [gyro(0, src=0x77, dst=0x66), encode_frame(DriveStatus(0, 0, 0, 0, 0, 0, 0), src=HOST, dst=SERVO, seq=0)]
    decoder = Decoder()
    assert len(decoder.feed(b"".join(stream))) == 2
    assert decoder.counters.errors() == 0


def test_totals_name_the_log_columns() -> None:
    decoder = Decoder()
    seqs_out(decoder, [1, 1, 5, 3, 0])
    totals = decoder.counters.totals()
    assert tuple(totals) == LINK_COUNTERS
    assert (totals["duplicates"], totals["frames_lost"], totals["reordered"], totals["restarts"]) == (1, 3, 1, 1)
