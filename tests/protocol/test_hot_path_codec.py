"""The realtime loop thread's codec: the precompiled DRIVE_CMD encoder, the GYRO_SAMPLE fast path of the decoder, and
sequence numbers taken atomically by two threads on one link. Each must give exactly what the general codec gives."""

from __future__ import annotations

import random
import struct
import threading

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.protocol import Board, Decoder, DriveCmd, Encoder, GyroSample, HostAlive, LoopTiming
from hil.protocol.framing import FramePacker, frame_seq

I16 = st.integers(-32768, 32767)


@settings(max_examples=300, deadline=None)
@given(tick=st.integers(0, 2**32 - 1), az=I16, el=I16, start=st.integers(0, 0xFFFF))
def test_the_packed_drive_cmd_is_the_encoders_frame_byte_for_byte(tick: int, az: int, el: int, start: int) -> None:
    packing, reference = Encoder(Board.HOST), Encoder(Board.HOST)
    packing.next_seq = reference.next_seq = start
    pack = FramePacker(DriveCmd, packing, Board.DRIVER).pack
    assert pack(tick, az, el) == reference.encode(DriveCmd(tick, az, el), Board.DRIVER)
    assert packing.next_seq == reference.next_seq == (start + 1) & 0xFFFF


def test_the_packer_shares_the_encoders_count_and_refuses_what_it_cannot_pack() -> None:
    enc = Encoder(Board.HOST)
    pack = FramePacker(DriveCmd, enc, Board.DRIVER).pack
    seqs = [frame_seq(pack(1, 0, 0)), frame_seq(enc.encode(HostAlive(5), Board.DRIVER)), frame_seq(pack(2, 0, 0))]
    assert seqs == [0, 1, 2]
    with pytest.raises(struct.error):  # no range checks, but struct never wraps a value silently
        pack(3, 40000, 0)
    with pytest.raises(ValueError, match="rate_x_dps"):  # scaled fields need the range-checked encoder
        FramePacker(GyroSample, enc, Board.HOST)
    with pytest.raises(ValueError, match="latency_us"):  # so do arrays
        FramePacker(LoopTiming, Encoder(Board.SERVO), Board.HOST)


def test_two_threads_sending_on_one_link_never_share_a_sequence_number() -> None:
    enc = Encoder(Board.HOST)
    pack = FramePacker(DriveCmd, enc, Board.DRIVER).pack
    got: list[list[int]] = [[], []]
    n = 20_000

    def loop_thread() -> None:
        got[0].extend(frame_seq(pack(k, 1, -1)) for k in range(n))

    def event_loop() -> None:
        got[1].extend(frame_seq(enc.encode(HostAlive(k), Board.DRIVER)) for k in range(n))

    threads = [threading.Thread(target=loop_thread), threading.Thread(target=event_loop)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    together = got[0] + got[1]
    assert len(together) == 2 * n
    # 40000 numbers out of a 16-bit count: each value at most once per wrap, every value of 0..40000 mod 65536 used
    assert sorted(together) == sorted(k & 0xFFFF for k in range(2 * n))
    assert got[0] == sorted(got[0]) and got[1] == sorted(got[1])  # each thread's numbers increase


def _stream(rng: random.Random) -> bytes:
    """GYRO_SAMPLEs (some resent, some skipped), LOOP_TIMINGs, garbage and corrupted frames, as a servo link sends."""
    enc = Encoder(Board.SERVO)
    parts = []
    for k in range(400):
        r = rng.random()
        if r < 0.03:
            enc.next_seq = (enc.next_seq + rng.choice([-1, 2, 7])) & 0xFFFF  # a resend, or lost frames
        frame = enc.encode(GyroSample(k * 1000, k, 0.25 * k, -1.5, 3.0, 10.0, -2.0), Board.HOST)
        if r > 0.97:
            frame = frame[:20] + bytes([frame[20] ^ 0x10]) + frame[21:]  # a bit error: a CRC failure
        parts.append(frame)
        if k % 10 == 0:
            parts.append(enc.encode(LoopTiming(k, (1, 2, 3, 4, 5, 6, 7, 8, 9, 10), 0, 0), Board.HOST))
        if rng.random() < 0.02:
            parts.append(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 12))))
        if rng.random() < 0.01:
            parts.append(Encoder(Board.DRIVER).encode(HostAlive(1), Board.HOST))  # another board's frame: refused
    return b"".join(parts)


@pytest.mark.parametrize("seed", range(6))
def test_the_fast_path_gives_what_feed_gives_on_any_chunking(seed: int) -> None:
    rng = random.Random(seed)
    data = _stream(rng)
    plain, fast_decoder = Decoder.for_link(Board.SERVO), Decoder.for_link(Board.SERVO)
    fast = fast_decoder.fast_feed(GyroSample)
    a, b = [], []
    pos = 0
    sizes = [37, 37, 37, 61, 1, 5, 74, 100, 24]  # whole samples mostly, as the thread reads them, and odd cuts
    while pos < len(data):
        n = rng.choice(sizes)
        a += plain.feed(data[pos : pos + n])
        b += fast(data[pos : pos + n])
        pos += n
    assert b == a and len(a) > 300
    assert fast_decoder.counters == plain.counters and fast_decoder.pending == plain.pending
    assert plain.counters.crc_errors > 0 and plain.counters.frames_lost  # the stream exercised the odd paths


def test_the_fast_path_needs_a_decoder_that_knows_its_link() -> None:
    with pytest.raises(ValueError, match="for_link"):
        Decoder().fast_feed(GyroSample)
    with pytest.raises(ValueError, match="DriveCmd"):
        Decoder.for_link(Board.SERVO).fast_feed(DriveCmd)  # not a message the servo link carries to the host
