"""Fuzz and robustness tests of the streaming Decoder (docs/protocol.md section 4, "Receiving").

The oracle is "the frames that really are in the stream": valid frames we put there. Where a
test mixes in garbage or corrupts frames, a stream that happens to contain some other complete,
CRC-valid frame outside the frames we placed (a 1-in-65536 CRC coincidence, or hypothesis
reassembling a frame from two fragments) is discarded with ``assume``; those tests also run
derandomized, so a CRC coincidence can never make them flaky.

Streams that end in garbage are followed by ``FLUSH``: MAX_FRAME bytes that hold no sync byte.
A false sync whose header passes the checks (a known id with its own length) makes the decoder
wait for the bytes it claims (at most ``Decoder.max_frame``); on a live link more bytes always
come, and the flush (more than enough) stands in for them.
"""

from __future__ import annotations

import itertools
import random
import struct
from binascii import crc_hqx
from collections.abc import Iterable, Sequence
from typing import Any

import pytest
from hypothesis import HealthCheck, assume, event, given, settings
from hypothesis import strategies as st

from hil.protocol import (
    CATALOGUE,
    HEADER_SIZE,
    MAX_FRAME,
    MAX_PAYLOAD,
    PROTOCOL_VERSION,
    SYNC,
    Ack,
    AxisMask,
    BoardState,
    Decoder,
    DriveCmd,
    DriveDisable,
    DriveStatus,
    Encoder,
    Frame,
    GyroSample,
    Heartbeat,
    LoopTiming,
    Pose,
    ServoConfig,
    TrackCmd,
    TrackMode,
    encode_frame,
)

NAMES = [spec.name for spec in CATALOGUE]
BY_NAME = {spec.name: spec for spec in CATALOGUE}
FLUSH = b"\x00" * MAX_FRAME
FUZZ = settings(derandomize=True, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

chunk_sizes = st.one_of(
    st.just([1]),
    st.lists(st.integers(1, 8), min_size=1, max_size=12),
    st.lists(st.integers(1, 300), min_size=1, max_size=12),
    st.just([1 << 20]),
)


# --- helpers ------------------------------------------------------------------------------------


def check_counters(decoder: Decoder, fed: int) -> None:
    c = decoder.counters
    assert c.bytes == fed
    assert c.bytes == c.bytes_in_frames + c.bytes_discarded + decoder.pending
    assert 0 <= decoder.pending < decoder.max_frame


def feed_in_chunks(
    decoder: Decoder, stream: bytes, sizes: Sequence[int], expected: Sequence[Frame] | None = None
) -> list[Frame]:
    """Feed ``stream`` in chunks of the given sizes (cycled); check counters after every call."""
    out: list[Frame] = []
    pos = 0
    k = 0
    while pos < len(stream):
        n = sizes[k % len(sizes)]
        k += 1
        out += decoder.feed(stream[pos : pos + n])
        pos += n
        check_counters(decoder, min(pos, len(stream)))
        if expected is not None:  # frames come out in order, never ahead of the stream
            assert out == list(expected[: len(out)])
    return out


def complete_frame_at(stream: bytes, p: int) -> bool:
    """Does a complete frame the receiver must accept (known or unknown id) start at ``p``?"""
    if stream[p : p + 2] != SYNC or len(stream) - p < HEADER_SIZE:
        return False
    ver, _src, _dst, msg_id, _seq, length = struct.unpack_from("<BBBBHB", stream, p + 2)
    spec = CATALOGUE.by_id.get(msg_id)
    if ver != PROTOCOL_VERSION or length > MAX_PAYLOAD or (spec is not None and length != spec.payload_size):
        return False
    end = p + HEADER_SIZE + length + 2
    return end <= len(stream) and crc_hqx(stream[p + 2 : end - 2], 0xFFFF) == int.from_bytes(
        stream[end - 2 : end], "little"
    )


def stray_frames(stream: bytes, placed: Iterable[tuple[int, int]]) -> list[int]:
    """Offsets of complete valid frames that lie outside the spans of the frames we placed."""
    inside = set()
    for start, end in placed:
        inside.update(range(start, end))
    out = []
    p = stream.find(SYNC)
    while p >= 0:
        if p not in inside and complete_frame_at(stream, p):
            out.append(p)
        p = stream.find(SYNC, p + 1)
    return out


@st.composite
def garbage(draw: Any, any_frame: st.SearchStrategy[tuple[bytes, Frame]]) -> bytes:
    """Noise: random bytes, sync-rich bytes, sync words, and fragments of real frames."""
    kind = draw(st.sampled_from(["binary", "sync-rich", "sync", "prefix", "slice"]))
    if kind == "binary":
        return draw(st.binary(max_size=64))
    if kind == "sync-rich":
        return bytes(draw(st.lists(st.sampled_from([0xEB, 0x90, 0x01, 0x00, 0x7F, 0xF0, 0xFF]), max_size=40)))
    if kind == "sync":
        return draw(st.sampled_from([b"\xeb", b"\x90", SYNC, SYNC + b"\x01", b"\xeb" + SYNC, SYNC * 3]))
    raw, _ = draw(any_frame)
    if kind == "prefix":  # a frame cut short: header and part of the payload
        return raw[: draw(st.integers(1, len(raw) - 1))]
    start = draw(st.integers(1, len(raw) - 1))
    return raw[start : draw(st.integers(start, len(raw)))]


# --- garbage and corruption -----------------------------------------------------------------------


def assert_exactly_the_placed_frames_come_out(
    stream: bytes, spans: list[tuple[int, int]], expected: list[Frame], sizes: Sequence[int]
) -> None:
    """Fed in ``sizes`` chunks, the decoder returns exactly ``expected`` and accounts for every byte."""
    decoder = Decoder()
    assert feed_in_chunks(decoder, stream, sizes, expected) == expected
    c = decoder.counters
    assert c.frames_ok == len(expected)
    assert c.bytes_in_frames == sum(end - start for start, end in spans)
    assert c.bytes_discarded == len(stream) - c.bytes_in_frames
    assert decoder.pending == 0


@pytest.mark.slow
@settings(FUZZ, max_examples=300)
@given(data=st.data())
def test_frames_survive_interleaved_garbage_and_any_chunking(any_frame: Any, data: Any) -> None:
    noise = garbage(any_frame)
    items = data.draw(st.lists(st.tuples(st.lists(noise, max_size=3), any_frame), max_size=10), label="items")
    tail = data.draw(st.lists(noise, max_size=3), label="tail")
    stream = b""
    expected: list[Frame] = []
    spans = []
    for noises, (raw, frame) in items:
        stream += b"".join(noises)
        spans.append((len(stream), len(stream) + len(raw)))
        stream += raw
        expected.append(frame)
    stream += b"".join(tail) + FLUSH
    event("stray frame in the garbage" if stray_frames(stream, spans) else "no stray frame")
    assume(not stray_frames(stream, spans))
    assert_exactly_the_placed_frames_come_out(stream, spans, expected, data.draw(chunk_sizes, label="chunk sizes"))


@pytest.mark.slow
@settings(FUZZ, max_examples=300)
@given(data=st.data())
def test_corrupted_frames_cost_only_themselves(any_frame: Any, data: Any) -> None:
    items = data.draw(st.lists(any_frame, min_size=2, max_size=10), label="frames")
    corrupt = data.draw(st.sets(st.integers(0, len(items) - 1), min_size=1), label="corrupted frames")
    stream = bytearray()
    expected: list[Frame] = []
    spans = []
    for i, (raw, frame) in enumerate(items):
        b = bytearray(raw)
        if i in corrupt:
            edits = data.draw(
                st.lists(
                    st.tuples(st.sampled_from(["xor", "drop"]), st.integers(0, len(b) - 1), st.integers(1, 255)),
                    min_size=1,
                    max_size=4,
                    unique_by=lambda e: e[1],
                ),
                label=f"edits of frame {i}",
            )
            for op, at, mask in sorted(edits, key=lambda e: -e[1]):  # from the end, so offsets stay valid
                if op == "xor":
                    b[at] ^= mask
                else:
                    del b[at]
            assert bytes(b) != raw
        else:
            spans.append((len(stream), len(stream) + len(b)))
            expected.append(frame)
        stream += b
    stream = bytes(stream) + FLUSH
    event("stray frame" if stray_frames(stream, spans) else "no stray frame")
    assume(not stray_frames(stream, spans))
    assert_exactly_the_placed_frames_come_out(stream, spans, expected, data.draw(chunk_sizes, label="chunk sizes"))


# --- chunk boundaries -------------------------------------------------------------------------------


def sample_frames(boundary_messages: dict[str, list[Any]], name: str) -> list[tuple[bytes, Frame]]:
    out = []
    for msg in boundary_messages[name]:
        # seq 0x90EB and src 0xEB put false sync words inside the header itself
        for src, dst, seq in ((0x10, 0x01, 0x90EB), (0xEB, 0x90, 0x0001)):
            out.append((encode_frame(msg, src=src, dst=dst, seq=seq), Frame(src, dst, seq, msg)))
    return out


@pytest.mark.parametrize("name", NAMES)
def test_frame_split_at_every_boundary(name: str, boundary_messages: dict[str, list[Any]]) -> None:
    for raw, frame in sample_frames(boundary_messages, name):
        n = len(raw)
        assert n == 11 + BY_NAME[name].payload_size
        for i in range(n + 1):
            for j in range(i, n + 1):  # three pieces: [:i], [i:j], [j:]
                decoder = Decoder()
                first = decoder.feed(raw[:i])
                assert first == ([frame] if i == n else [])
                assert decoder.pending == i % n
                second = decoder.feed(raw[i:j])
                assert second == ([frame] if j == n > i else [])
                third = decoder.feed(raw[j:])
                assert first + second + third == [frame]
                check_counters(decoder, n)
        decoder = Decoder()
        for k in range(n):  # one byte at a time
            got = decoder.feed(raw[k : k + 1])
            assert got == ([frame] if k == n - 1 else [])
            assert decoder.pending == (k + 1) % n
        assert decoder.counters.frames_ok == 1 and decoder.counters.errors() == 0


@pytest.mark.parametrize("name", NAMES)
def test_two_frames_split_at_every_boundary(name: str, boundary_messages: dict[str, list[Any]]) -> None:
    (a, fa), (b, fb) = sample_frames(boundary_messages, name)[:2]
    stream = a + b
    for i in range(len(stream) + 1):
        decoder = Decoder()
        first = decoder.feed(stream[:i])
        assert first == [fa, fb][: (i >= len(a)) + (i == len(stream))]
        assert first + decoder.feed(stream[i:]) == [fa, fb]
        check_counters(decoder, len(stream))
        assert decoder.pending == 0


@pytest.mark.parametrize("name", NAMES)
def test_truncated_frame_is_held_then_completed(name: str, boundary_messages: dict[str, list[Any]]) -> None:
    for raw, frame in sample_frames(boundary_messages, name):
        for k in range(1, len(raw) + 1):  # the frame without its last k bytes
            decoder = Decoder()
            assert decoder.feed(raw[:-k]) == []
            assert decoder.pending == len(raw) - k
            c = decoder.counters
            assert (c.frames_ok, c.crc_errors, c.bad_lengths, c.bytes_discarded) == (0, 0, 0, 0)
            assert decoder.feed(raw[-k:]) == [frame]
            assert decoder.pending == 0 and decoder.counters.frames_ok == 1 and decoder.counters.errors() == 0


# --- bad lengths are rejected at the header ------------------------------------------------------------


def header(msg_id: int, length: int, *, version: int = PROTOCOL_VERSION, src: int = 0x01, dst: int = 0x02) -> bytes:
    return SYNC + bytes([version, src, dst, msg_id, 0x34, 0x12, length])


BAD_HEADERS = [
    pytest.param(0x7F, MAX_PAYLOAD + 1, id="unknown-id-241"),
    pytest.param(0x7F, 0xFF, id="unknown-id-255"),
    pytest.param(0x10, MAX_PAYLOAD + 1, id="GYRO_SAMPLE-241"),
    pytest.param(0x10, 27, id="GYRO_SAMPLE-27"),
    pytest.param(0x10, 29, id="GYRO_SAMPLE-29"),
    pytest.param(0x10, MAX_PAYLOAD, id="GYRO_SAMPLE-240"),
    pytest.param(0x01, 1, id="IDENT_REQ-1"),
    pytest.param(0x13, 0, id="LOOP_TIMING-0"),
    pytest.param(0x13, 0xEB, id="LOOP_TIMING-0xEB"),
]


@pytest.mark.parametrize(("msg_id", "length"), BAD_HEADERS)
def test_bad_length_is_rejected_without_waiting_for_the_payload(msg_id: int, length: int) -> None:
    bad = header(msg_id, length)
    good_msg = GyroSample(1, 2, 0.5, 0.0, 0.0, 0.0, 0.0)
    good = encode_frame(good_msg, src=0x10, dst=0x01, seq=5)

    decoder = Decoder()
    assert decoder.feed(bad) == []
    assert decoder.counters.bad_lengths == 1
    assert decoder.pending == (1 if bad[-1] == 0xEB else 0)  # only a trailing EB may be kept
    check_counters(decoder, len(bad))

    decoder = Decoder()
    assert decoder.feed(bad + good) == [Frame(0x10, 0x01, 5, good_msg)]  # the same call: no waiting
    c = decoder.counters
    assert (c.bad_lengths, c.crc_errors, c.frames_ok, c.bytes_discarded, decoder.pending) == (1, 0, 1, len(bad), 0)


def test_wrong_version_is_rejected_without_waiting() -> None:
    good_msg = Ack(0x20, 7)
    good = encode_frame(good_msg, src=0x20, dst=0x01, seq=9)
    bad = header(0x7F, 200, version=2)
    decoder = Decoder()
    assert decoder.feed(bad + good) == [Frame(0x20, 0x01, 9, good_msg)]
    c = decoder.counters
    assert (c.bad_lengths, c.crc_errors, c.bytes_discarded, decoder.pending) == (0, 0, len(bad), 0)
    assert c.bad_versions == 1 and c.errors() == 1


no_sync = st.integers(0, 255).filter(lambda b: b != 0xEB)


bad_id_and_length = st.one_of(
    st.tuples(st.integers(0, 255), st.integers(MAX_PAYLOAD + 1, 255)),  # too long for any id
    st.sampled_from(list(CATALOGUE)).flatmap(  # a known id with a length other than its own
        lambda spec: st.tuples(
            st.just(spec.msg_id), st.integers(0, MAX_PAYLOAD).filter(lambda n: n != spec.payload_size)
        )
    ),
)


@given(id_and_length=bad_id_and_length, src=no_sync, dst=no_sync)
def test_any_bad_length_header_is_rejected_at_once(id_and_length: tuple[int, int], src: int, dst: int) -> None:
    msg_id, length = id_and_length
    spec = CATALOGUE.by_id.get(msg_id)
    assert length > MAX_PAYLOAD or (spec is not None and length != spec.payload_size)
    bad = header(msg_id, length, src=src, dst=dst)
    good_msg = DriveCmd(3, -1, 1)
    decoder = Decoder()
    assert decoder.feed(bad + encode_frame(good_msg, src=0x01, dst=0x20, seq=0)) == [Frame(0x01, 0x20, 0, good_msg)]
    assert decoder.counters.bad_lengths == 1
    assert decoder.pending == 0


# --- sync bytes in payloads and runs of sync bytes ----------------------------------------------------


def inner_frame_message() -> tuple[LoopTiming, bytes]:
    """A LOOP_TIMING whose latency_us array carries a complete, valid DRIVE_DISABLE frame."""
    inner = encode_frame(DriveDisable(AxisMask.BOTH), src=0x01, dst=0x20, seq=0x0102)
    assert len(inner) == 12
    words = struct.unpack("<6H", inner)
    return LoopTiming(0x0190EB, (*words, 0x90EB, 0xEB90, 0x01EB, 0xFFFF), 0x90EB, 0xEB), inner


SYNC_PAYLOAD_MESSAGES = [
    GyroSample(0x90EB, 0x0190EB, 0.0, 0.0, 0.0, 0.0, 0.0),
    GyroSample(0x90EB90EB, 0x90EB90EB, 0.037099, -0.000001, 0.0, 0.0, 0.0),
    DriveCmd(0x0190EB, -0x6F15, 0x90EB - 0x10000),  # i16 -0x6F15 is 0x90EB: bytes EB 90
    Pose(0x90EB, *(struct.unpack("<f", b"\xeb\x90\x01\x00")[0] for _ in range(6))),
    ServoConfig(0x90EB, 0x90EB, 0x90EB),
    inner_frame_message()[0],
    Heartbeat(0x90EB, BoardState.READY, 0x0001EB90, 0xEB90EB90, 0x90EB, 0xEB, 0x90),
]


def test_sync_words_inside_payloads_decode_fine() -> None:
    encoder = Encoder(src=0x10)
    frames = [encoder.encode(m, dst=0x01) for m in SYNC_PAYLOAD_MESSAGES]
    for raw in frames:
        assert raw.count(SYNC) >= 2  # the real sync word and at least one in the payload
    stream = b"".join(frames)
    expected = [Frame(0x10, 0x01, i, m) for i, m in enumerate(SYNC_PAYLOAD_MESSAGES)]
    for sizes in ([1], [2], [3], [7], [len(stream)]):
        decoder = Decoder()
        assert feed_in_chunks(decoder, stream, sizes, expected) == expected
        c = decoder.counters
        assert (c.frames_ok, c.bytes_discarded, c.crc_errors, c.bad_lengths, c.resyncs) == (len(frames), 0, 0, 0, 0)


def test_frame_hidden_in_a_payload_appears_only_when_its_carrier_is_broken() -> None:
    carrier_msg, inner = inner_frame_message()
    carrier = encode_frame(carrier_msg, src=0x10, dst=0x01, seq=1)
    assert inner in carrier
    after_msg = DriveCmd(9, 1, -1)
    after = encode_frame(after_msg, src=0x01, dst=0x20, seq=0x0103)

    decoder = Decoder()
    assert decoder.feed(carrier + after) == [Frame(0x10, 0x01, 1, carrier_msg), Frame(0x01, 0x20, 0x0103, after_msg)]

    broken = b"\x00" + carrier[1:]  # the carrier's sync word is lost: the inner frame is real data now
    decoder = Decoder()
    got = decoder.feed(broken + after + FLUSH)
    assert got == [Frame(0x01, 0x20, 0x0102, DriveDisable(AxisMask.BOTH)), Frame(0x01, 0x20, 0x0103, after_msg)]
    assert decoder.counters.seq_gaps == {}


SYNC_RUNS = [
    pytest.param(b"\xeb" * 1000, id="EB*1000"),
    pytest.param(SYNC * 500, id="EB90*500"),
    pytest.param(b"\x90" * 500, id="90*500"),
    pytest.param((SYNC + b"\x01") * 300, id="EB9001*300"),
    pytest.param(header(0x7F, MAX_PAYLOAD) * 60, id="plausible-header*60"),
    pytest.param(header(0x10, 28) * 60, id="GYRO_SAMPLE-header*60"),
]


@pytest.mark.parametrize("run", SYNC_RUNS)
@pytest.mark.parametrize("sizes", [[1], [7], [1 << 20]], ids=["1", "7", "all"])
def test_runs_of_sync_bytes_lose_no_frame(run: bytes, sizes: list[int]) -> None:
    encoder = Encoder(src=0x20)
    messages = [DriveStatus(1, AxisMask.AZ, 0, 1.5, -1.5, 28.0, 0), TrackCmd(TrackMode.TRACK, 0x90EB), Ack(1, 2)]
    stream = run
    spans = []
    for m in messages:
        raw = encoder.encode(m, dst=0x01)
        spans.append((len(stream), len(stream) + len(raw)))
        stream += raw + run
    stream += FLUSH
    expected = [Frame(0x20, 0x01, i, m) for i, m in enumerate(messages)]
    assert stray_frames(stream, spans) == []  # the runs hold no valid frame of their own
    decoder = Decoder()
    assert feed_in_chunks(decoder, stream, sizes, expected) == expected
    c = decoder.counters
    assert c.frames_ok == 3
    assert c.bytes_discarded == len(stream) - c.bytes_in_frames
    assert decoder.pending == 0


# --- loses none -----------------------------------------------------------------------------------------


def clean_stream() -> tuple[list[bytes], list[Frame]]:
    """Twelve frames, no sync word anywhere but at frame starts, so error counts are exact."""
    encoder = Encoder(src=0x10)
    messages = [
        GyroSample(2000 + i, i, i / 1000, -0.5, 0.25, 10.0 + i, -5.0) if i % 2 else DriveCmd(i, i, -i)
        for i in range(12)
    ]
    raws = [encoder.encode(m, dst=0x01) for m in messages]
    assert all(raw.count(SYNC) == 1 and raw.find(SYNC) == 0 and raw.count(b"\xeb") == 1 for raw in raws)
    return raws, [Frame(0x10, 0x01, i, m) for i, m in enumerate(messages)]


def _set(at: int, value: int) -> Any:
    def edit(raw: bytes) -> bytes:
        b = bytearray(raw)
        b[at] = value
        return bytes(b)

    return edit


def _xor(at: int) -> Any:
    def edit(raw: bytes) -> bytes:
        b = bytearray(raw)
        b[at] ^= 0x01
        return bytes(b)

    return edit


# (edit of frame 3, expected crc_errors, bad_lengths, unknown_ids)
CORRUPTIONS = [
    pytest.param(_set(8, MAX_PAYLOAD + 1), 0, 1, 0, id="length>MAX_PAYLOAD"),
    pytest.param(_set(8, 0xFF), 0, 1, 0, id="length=255"),
    pytest.param(_set(8, 29), 0, 1, 0, id="length off by one"),
    pytest.param(lambda r: _set(8, MAX_PAYLOAD)(_set(5, 0x7F)(r)), 0, 0, 1, id="unknown id, length 240"),
    pytest.param(lambda r: _set(8, 2)(_set(5, 0x7F)(r)), 0, 0, 1, id="unknown id, length 2"),
    pytest.param(_set(5, 0x7F), 0, 0, 1, id="unknown id"),
    pytest.param(_xor(12), 1, 0, 0, id="payload bit"),
    pytest.param(_xor(-1), 1, 0, 0, id="CRC bit"),
    pytest.param(_xor(6), 1, 0, 0, id="seq bit"),
    pytest.param(_set(2, 2), 0, 0, 0, id="version"),
    pytest.param(_set(0, 0x00), 0, 0, 0, id="sync lost"),
    pytest.param(lambda r: r[:-1], 1, 0, 0, id="last byte lost"),
    pytest.param(lambda r: r[:20], 1, 0, 0, id="cut after 20 bytes"),
    pytest.param(lambda r: r[:5], 0, 0, 1, id="cut inside the header"),  # EB 90 01 10 01 + next frame: id 0xEB
]


@pytest.mark.parametrize(("edit", "crc_errors", "bad_lengths", "unknown_ids"), CORRUPTIONS)
def test_a_broken_frame_loses_no_other_frame(edit: Any, crc_errors: int, bad_lengths: int, unknown_ids: int) -> None:
    """Contrast: a parser that skips a bad frame's claimed span (pymavlink) loses the frames after it."""
    raws, frames = clean_stream()
    broken = edit(raws[3])
    assert broken != raws[3]
    stream = b"".join(raws[:3]) + broken + b"".join(raws[4:])
    expected = frames[:3] + frames[4:]
    for sizes in ([1], [5], [1 << 20]):
        decoder = Decoder()
        out = feed_in_chunks(decoder, stream + FLUSH, sizes, expected)
        assert out == expected
        c = decoder.counters
        assert (c.frames_ok, c.crc_errors, c.bad_lengths, c.unknown_ids) == (11, crc_errors, bad_lengths, unknown_ids)
        assert c.bytes_discarded == len(broken) + len(FLUSH)
        assert c.seq_gaps == {0x10: 1} and c.frames_lost == {0x10: 1}


@pytest.mark.parametrize(
    ("msg_id", "crc_errors", "unknown_ids"), [(0x7F, 0, 1), (0x13, 1, 0)], ids=["unknown", "known"]
)
def test_a_false_header_does_not_swallow_the_frames_it_claims(msg_id: int, crc_errors: int, unknown_ids: int) -> None:
    """A false header spanning the next frames: every one of them comes out.

    With an unknown id it is rejected at the header; with a known id (LOOP_TIMING, 32 bytes) the
    receiver waits for the claimed bytes, the CRC fails, and it rescans from the next byte.
    """
    raws, frames = clean_stream()
    false_header = header(msg_id, 32 if msg_id == 0x13 else MAX_PAYLOAD)
    stream = raws[0] + false_header + b"".join(raws[1:]) + FLUSH
    decoder = Decoder()
    assert decoder.feed(stream) == frames
    c = decoder.counters
    assert (c.crc_errors, c.unknown_ids, c.frames_ok) == (crc_errors, unknown_ids, 12)


def unknown_frame(payload: bytes, *, msg_id: int = 0x7F, src: int = 0x10, seq: int = 0) -> bytes:
    """A well-formed frame (good CRC) of an id the catalogue does not define."""
    assert msg_id not in CATALOGUE.by_id
    body = bytes([PROTOCOL_VERSION, src, 0x01, msg_id]) + seq.to_bytes(2, "little") + bytes([len(payload)]) + payload
    return SYNC + body + crc_hqx(body, 0xFFFF).to_bytes(2, "little")


@pytest.mark.parametrize("length", [0, 1, 28, MAX_PAYLOAD])
def test_unknown_id_is_rejected_at_its_header_and_its_bytes_rescanned(length: int) -> None:
    """A frame of an id the catalogue lacks is garbage to this receiver: rescanned, not skipped whole.

    That bounds how long a false sync can hold the link (to the longest known frame), and it means a
    real frame inside the unknown frame's payload comes out.
    """
    raws, frames = clean_stream()
    hidden_msg = Ack(1, 2)
    hidden = encode_frame(hidden_msg, src=0x20, dst=0x01, seq=0)
    payload = (bytes(5) + hidden + bytes(length))[:length]  # the hidden frame fits only when length >= 19
    unknown = unknown_frame(payload, src=0x55, seq=0x1234)
    stream = raws[0] + raws[1] + unknown + b"".join(raws[2:])
    hidden_out = [Frame(0x20, 0x01, 0, hidden_msg)] if length >= 5 + len(hidden) else []
    expected = frames[:2] + hidden_out + frames[2:]
    for sizes in ([1], [3], [1 << 20]):
        decoder = Decoder()
        assert feed_in_chunks(decoder, stream, sizes, expected) == expected
        c = decoder.counters
        assert (c.unknown_ids, c.frames_ok, c.crc_errors, c.bad_lengths) == (1, 12 + len(hidden_out), 0, 0)
        assert c.bytes_discarded == len(unknown) - len(hidden) * len(hidden_out)
        assert c.seq_gaps == {} and decoder.pending == 0


def test_unknown_id_header_releases_the_next_frame_at_once() -> None:
    """Nine header bytes of an unknown id claiming 240 bytes, then a real frame, in one feed: it comes out."""
    good = encode_frame(Ack(1, 2), src=0x10, dst=0x01, seq=0)
    decoder = Decoder()
    assert decoder.feed(header(0x77, MAX_PAYLOAD) + good) == [Frame(0x10, 0x01, 0, Ack(1, 2))]
    assert decoder.counters.unknown_ids == 1 and decoder.pending == 0


def test_frame_of_an_unknown_id_shows_as_a_sequence_gap() -> None:
    """The sender used up a sequence number on a frame this receiver cannot read: one lost frame."""
    encoder = Encoder(src=0x10)
    known = [encoder.encode(DriveCmd(i, 0, 0), dst=0x01) for i in range(2)]
    unknown = unknown_frame(b"\x01\x02", src=0x10, seq=2)
    encoder.next_seq = 3
    after = encoder.encode(DriveCmd(3, 0, 0), dst=0x01)
    decoder = Decoder()
    frames = decoder.feed(known[0] + known[1] + unknown + after)
    assert [f.seq for f in frames] == [0, 1, 3]
    c = decoder.counters
    assert c.unknown_ids == 1 and c.seq_gaps == {0x10: 1} and c.frames_lost == {0x10: 1}


# --- memory and sequence gaps ----------------------------------------------------------------------------


def feed_randomly(decoder: Decoder, stream: bytes, rng: random.Random, *, max_chunk: int) -> int:
    """Feed ``stream`` in random chunks, checking the counters after each; return the most ever pending."""
    pos = worst = 0
    while pos < len(stream):
        n = rng.randint(1, max_chunk)
        decoder.feed(stream[pos : pos + n])
        pos += n
        worst = max(worst, decoder.pending)
        check_counters(decoder, min(pos, len(stream)))
    return worst


def test_memory_stays_bounded_on_a_megabyte_of_garbage() -> None:
    rng = random.Random(20240601)
    stream = rng.randbytes(1 << 20)
    decoder = Decoder()
    worst = feed_randomly(decoder, stream, rng, max_chunk=4096)
    assert worst < decoder.max_frame
    c = decoder.counters
    assert c.bytes == 1 << 20 and c.frames_ok == 0
    # the link still works afterwards
    msg = Ack(1, 2)
    assert decoder.feed(FLUSH + encode_frame(msg, src=3, dst=4, seq=5)) == [Frame(3, 4, 5, msg)]


def test_memory_stays_bounded_on_sync_rich_garbage() -> None:
    """Bytes drawn from EB 90 01 7F F0 00: thousands of plausible headers claiming long payloads."""
    rng = random.Random(7)
    stream = bytes(rng.choice(b"\xeb\x90\x01\x7f\xf0\x00") for _ in range(200_000))
    decoder = Decoder()
    worst = feed_randomly(decoder, stream, rng, max_chunk=512)
    # unknown ids (7F, F0, 90, EB, 00) are refused at the header; only IDENT_REQ (id 01, length 0) is known
    assert worst < decoder.max_frame == 43
    assert decoder.counters.unknown_ids > 500  # ~200000 / 6**3 headers with version 1, nearly all unknown


def _gaps(start: int, dropped: Sequence[bool]) -> tuple[int, int, int]:
    """(gaps, frames lost, restarts) a receiver can see: dropped runs between the first and last kept
    frame, except that a kept seq 0 after a run that ended before 65535 reads as a restart (no loss)."""
    kept = [(start + i) & 0xFFFF for i, d in enumerate(dropped) if not d]
    gaps = lost = restarts = 0
    for last, seq in itertools.pairwise(kept):
        skipped = (seq - last - 1) & 0xFFFF
        if skipped and seq == 0:
            restarts += 1
        elif skipped:
            gaps, lost = gaps + 1, lost + skipped
    return gaps, lost, restarts


@given(
    starts=st.tuples(st.sampled_from([0, 65530, 65535]) | st.integers(0, 65535), st.integers(0, 65535)),
    drops=st.tuples(st.lists(st.booleans(), max_size=40), st.lists(st.booleans(), max_size=40)),
    sizes=chunk_sizes,
)
def test_sequence_gaps_are_counted_per_source(
    starts: tuple[int, int], drops: tuple[list[bool], list[bool]], sizes: list[int]
) -> None:
    sources = (0x10, 0x20)
    encoders = [Encoder(src=s) for s in sources]
    for e, start in zip(encoders, starts, strict=True):
        e.next_seq = start
    stream = b""
    expected = []
    for i in range(max(len(d) for d in drops)):
        for e, dropped in zip(encoders, drops, strict=True):  # interleave the two senders
            if i < len(dropped):
                msg = DriveCmd(i, e.src, -1)
                seq = e.next_seq
                raw = e.encode(msg, dst=0x01)
                if not dropped[i]:
                    stream += raw
                    expected.append(Frame(e.src, 0x01, seq, msg))
    decoder = Decoder()
    assert feed_in_chunks(decoder, stream, sizes, expected) == expected
    c = decoder.counters
    seen = [_gaps(start, dropped) for start, dropped in zip(starts, drops, strict=True)]
    for src, (gaps, lost, restarts) in zip(sources, seen, strict=True):
        assert c.seq_gaps.get(src, 0) == gaps
        assert c.frames_lost.get(src, 0) == lost
        assert c.restarts.get(src, 0) == restarts
    assert c.errors() == sum(gaps for gaps, _, _ in seen)


def test_sequence_gaps_across_the_wrap() -> None:
    encoder = Encoder(src=0x30)
    encoder.next_seq = 65532
    raws = [encoder.encode(Ack(1, i), dst=0x01) for i in range(10)]  # seqs 65532..65535, 0..5
    keep = [0, 1, 5, 6, 9]  # drops 65534, 65535, 0 (one gap of 3) and 2, 3, 4 (one gap of 3)
    decoder = Decoder()
    frames = decoder.feed(b"".join(raws[i] for i in keep))
    assert [f.seq for f in frames] == [65532, 65533, 1, 2, 5]
    assert decoder.counters.seq_gaps == {0x30: 2}
    assert decoder.counters.frames_lost == {0x30: 5}


# --- never raises ----------------------------------------------------------------------------------------

byte_soup = st.one_of(
    st.binary(max_size=300),
    st.lists(st.sampled_from([0xEB, 0x90, 0x01, 0x00, 0x10, 0x13, 0x7F, 0xF0, 0xFF]), max_size=300).map(bytes),
)


@settings(max_examples=500)
@given(
    chunks=st.lists(byte_soup, max_size=20),
    kind=st.sampled_from([bytes, bytearray, memoryview]),
)
def test_feed_never_raises(chunks: list[bytes], kind: type) -> None:
    decoder = Decoder()
    fed = 0
    for chunk in chunks:
        frames = decoder.feed(kind(chunk))
        fed += len(chunk)
        for frame in frames:
            assert isinstance(frame, Frame)
            assert type(frame.message) in CATALOGUE.by_type
        check_counters(decoder, fed)
