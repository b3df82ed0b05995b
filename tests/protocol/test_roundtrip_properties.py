"""Property tests of the message codec: every message of the catalogue, over every field's range.

- round trip: decode(encode(m)) == m for messages drawn over the whole wire range of every
  field (raw extremes, every float32 bit pattern that is finite, enum members and flag bits,
  ASCII text, arrays), with random src/dst/seq; the frame bytes are also checked against an
  independent packing of the raw values and a bitwise CRC, and re-encoding the decoded
  message must give the identical bytes;
- rejection: a value just outside each end of each field's range raises EncodeError naming
  ``MESSAGE.field``, and an Encoder does not use up a sequence number on a failed encode;
- sequence numbers wrap from 65535 to 0.
"""

from __future__ import annotations

import math
import re
import struct
import sys
from enum import IntFlag
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.protocol import (
    CATALOGUE,
    PROTOCOL_VERSION,
    SYNC,
    Ack,
    Decoder,
    EncodeError,
    Encoder,
    Frame,
    GyroSample,
    ServoMode,
    crc16,
    encode_frame,
)
from hil.protocol.wire import FieldSpec, MessageSpec, Wire
from tests.protocol.reference import crc16_bitwise

SPECS: list[MessageSpec] = list(CATALOGUE)
BY_NAME = {spec.name: spec for spec in SPECS}
NAMES = [spec.name for spec in SPECS]
F32_MAX = struct.unpack("<f", b"\xff\xff\x7f\x7f")[0]

nodes = st.one_of(st.sampled_from([0x00, 0x01, 0x90, 0xEB, 0xFF]), st.integers(0, 255))
seqs = st.one_of(st.sampled_from([0, 1, 0x90EB, 0xFFFE, 0xFFFF]), st.integers(0, 0xFFFF))


def expected_frame(spec: MessageSpec, payload: bytes, src: int, dst: int, seq: int) -> bytes:
    """The frame as docs/protocol.md section 3 lays it out, built by hand."""
    body = bytes([PROTOCOL_VERSION, src, dst, spec.msg_id]) + seq.to_bytes(2, "little") + bytes([len(payload)])
    body += payload
    return SYNC + body + crc16_bitwise(body).to_bytes(2, "little")


def assert_field_types(spec: MessageSpec, msg: Any) -> None:
    """Decoded values have the engineering types: enum members, bool, str, tuple, int, float."""
    for f, value in zip(spec.fields, msg, strict=True):
        w = f.wire
        if w.kind == "char":
            assert type(value) is str, f.name
            continue
        values = value if w.count > 1 else (value,)
        if w.count > 1:
            assert type(value) is tuple and len(value) == w.count, f.name
        for v in values:
            if w.kind == "bool":
                assert type(v) is bool, f.name
            elif w.enum is not None:
                assert isinstance(v, w.enum), f.name
            elif w.primitive.is_float or w.scale != 1:
                assert type(v) is float, f.name
            else:
                assert type(v) is int, f.name


def test_reference_crc_matches_the_documented_check_value() -> None:
    assert crc16_bitwise(b"123456789") == 0x29B1
    assert crc16(b"123456789") == 0x29B1


def test_every_catalogue_message_is_covered() -> None:
    assert len(NAMES) == len(CATALOGUE) == len(set(NAMES))
    assert {spec.msg_id for spec in SPECS} == set(CATALOGUE.by_id)


# --- round trip -------------------------------------------------------------------------------


def check_round_trip(spec: MessageSpec, payload: bytes | None, msg: Any, *, src: int, dst: int, seq: int) -> None:
    frame = encode_frame(msg, src=src, dst=dst, seq=seq)
    assert len(frame) == 11 + spec.payload_size
    if payload is not None:
        assert frame == expected_frame(spec, payload, src, dst, seq)
    decoder = Decoder()
    frames = decoder.feed(frame)
    assert len(frames) == 1
    (got,) = frames
    assert isinstance(got, Frame)
    assert (got.src, got.dst, got.seq) == (src, dst, seq)
    assert type(got.message) is spec.cls
    assert got.message == msg
    assert_field_types(spec, got.message)
    assert encode_frame(got.message, src=src, dst=dst, seq=seq) == frame
    c = decoder.counters
    assert (c.bytes, c.frames_ok, c.bytes_in_frames, c.bytes_discarded, decoder.pending) == (
        len(frame),
        1,
        len(frame),
        0,
        0,
    )
    assert c.errors() == 0


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=100)
@given(data=st.data(), header=st.tuples(nodes, nodes, seqs))
def test_round_trip_over_the_whole_range(name: str, wire_message: Any, data: Any, header: tuple[int, int, int]) -> None:
    spec = BY_NAME[name]
    payload, msg = data.draw(wire_message(spec), label="payload, message")
    src, dst, seq = header
    check_round_trip(spec, payload, msg, src=src, dst=dst, seq=seq)


@pytest.mark.parametrize("name", NAMES)
def test_round_trip_at_the_range_ends(name: str, boundary_messages: dict[str, list[Any]]) -> None:
    """Every field at its lowest, then its highest representable value (deterministic)."""
    spec = BY_NAME[name]
    low, high = boundary_messages[name]
    for msg in (low, high):
        check_round_trip(spec, None, msg, src=0xEB, dst=0x90, seq=0xFFFF)
    if spec.fields:
        assert encode_frame(low, src=1, dst=2, seq=3) != encode_frame(high, src=1, dst=2, seq=3)


def test_scaled_fields_decode_as_exact_decimals() -> None:
    """raw / (1/scale): 0.5 deg/s reads back as 0.5, not 0.49999999999999994."""
    msg = GyroSample(1, 2, 0.5, -0.25, 12.0, 30.000001, -2147.483648)
    (frame,) = Decoder().feed(encode_frame(msg, src=0x10, dst=0x01, seq=7))
    assert frame.message == msg
    assert frame.message.el_deg == -2147.483648
    assert encode_frame(msg, src=0x10, dst=0x01, seq=7)[9 + 8 : 9 + 12] == (500_000).to_bytes(4, "little")


# --- out-of-range rejection -------------------------------------------------------------------


def bad_scalars(w: Wire) -> list[tuple[str, Any]]:
    """Values one element of a field cannot carry: just past each end, wrong types, non-members."""
    p = w.primitive
    lo, hi = int(p.lo), int(p.hi)
    common: list[tuple[str, Any]] = [("None", None), ("text", "1")]
    if w.kind == "bool":
        return [("2", 2), ("-1", -1), ("0.5", 0.5), *common]
    if w.enum is not None:
        out = [("hi+1", hi + 1), ("lo-1", lo - 1), ("0.5", 0.5), ("member name", next(iter(w.enum)).name), *common]
        if not issubclass(w.enum, IntFlag):
            known = {int(m) for m in w.enum}
            out.append(("non-member", min(v for v in range(lo, hi + 1) if v not in known)))
            out.append(("largest non-member", max(v for v in range(lo, hi + 1) if v not in known)))
        return out
    if p.is_float:
        above = math.nextafter(F32_MAX, math.inf)
        return [
            ("max+1ulp", above),
            ("-max-1ulp", -above),
            ("3.4028235e38", 3.4028235e38),
            ("-3.4028235e38", -3.4028235e38),
            ("1e39", 1e39),
            ("inf", math.inf),
            ("-inf", -math.inf),
            ("nan", math.nan),
            ("bool", True),
            *common,
        ]
    if w.scale == 1:
        return [
            ("hi+1", hi + 1),
            ("lo-1", lo - 1),
            ("hi+2**40", hi + 2**40),
            ("float 1.0", 1.0),
            ("float lo", float(lo)),
            ("float hi", float(hi)),
            ("bool", True),
            ("nan", math.nan),
            *common,
        ]
    return [
        ("hi+1 raw", w.to_eng(hi + 1)),
        ("lo-1 raw", w.to_eng(lo - 1)),
        ("hi+1000 raw", w.to_eng(hi + 1000)),
        ("nan", math.nan),
        ("inf", math.inf),
        ("-inf", -math.inf),
        ("bool", True),
        *common,
    ]


def bad_values(f: FieldSpec, valid: Any) -> list[tuple[str, Any]]:
    """Whole-field values that must be rejected; ``valid`` is a good value of the field."""
    w = f.wire
    if w.kind == "char":
        return [
            ("too long", "x" * (w.count + 1)),
            ("much too long", "x" * 300),
            ("non-ASCII", "é"),
            ("non-ASCII at the end", "x" * (w.count - 1) + "\x80"),
            ("NUL", "a\0b"),
            ("bytes", b"abc"),
            ("int", 5),
            ("None", None),
        ]
    if w.count == 1:
        return bad_scalars(w)
    out: list[tuple[str, Any]] = [
        ("one short", valid[:-1]),
        ("one long", (*valid, valid[0])),
        ("scalar", valid[0]),
        ("None", None),
        ("text", "x" * w.count),
    ]
    for why, element in bad_scalars(w):
        for index in (0, w.count - 1):
            changed = list(valid)
            changed[index] = element
            out.append((f"[{index}] {why}", tuple(changed)))
    return out


FIELD_CASES = [pytest.param(spec.name, f.name, id=f"{spec.name}.{f.name}") for spec in SPECS for f in spec.fields]


@pytest.mark.parametrize(("name", "field_name"), FIELD_CASES)
def test_out_of_range_values_raise_encode_error_naming_the_field(
    name: str, field_name: str, boundary_messages: dict[str, list[Any]]
) -> None:
    spec = BY_NAME[name]
    f = next(f for f in spec.fields if f.name == field_name)
    label = f"{name}.{field_name}"
    low, high = boundary_messages[name]
    encoder = Encoder(src=0x10)
    encoder.next_seq = 0xFFFF
    cases = bad_values(f, getattr(low, field_name))
    assert len(cases) >= 5
    failures = []
    for base in (low, high):
        for why, value in cases:
            bad = base._replace(**{field_name: value})
            for encode in (lambda m: encode_frame(m, src=1, dst=2, seq=3), lambda m: encoder.encode(m, dst=2)):
                try:
                    encode(bad)
                except EncodeError as e:
                    if label not in str(e):
                        failures.append(f"{why} ({value!r}): message {e} does not name {label}")
                except Exception as e:
                    failures.append(f"{why} ({value!r}): {type(e).__name__}: {e}")
                else:
                    failures.append(f"{why} ({value!r}): accepted")
    assert failures == []
    assert issubclass(EncodeError, ValueError)
    # the failed encodes used no sequence number: the next good frame still gets 65535
    assert encoder.next_seq == 0xFFFF
    good = encoder.encode(high, dst=2)
    assert encoder.next_seq == 0
    (frame,) = Decoder().feed(good)
    assert (frame.src, frame.dst, frame.seq, frame.message) == (0x10, 2, 0xFFFF, high)


SCALED_FIELDS = [(spec, f) for spec in SPECS for f in spec.fields if f.wire.scale != 1]


def test_huge_finite_value_of_a_scaled_field_raises_encode_error(boundary_messages: dict[str, list[Any]]) -> None:
    assert len(SCALED_FIELDS) == 10
    for spec, f in SCALED_FIELDS:
        low = boundary_messages[spec.name][0]
        for value in (sys.float_info.max, -sys.float_info.max, 1e303):
            with pytest.raises(EncodeError, match=re.escape(f"{spec.name}.{f.name}")):
                encode_frame(low._replace(**{f.name: value}), src=1, dst=2, seq=3)


@pytest.mark.parametrize(("src", "dst"), [(256, 1), (1, -1), (1, 1.0), (None, 1)])
def test_node_ids_outside_a_byte_raise_encode_error(src: Any, dst: Any) -> None:
    with pytest.raises(EncodeError, match=r"^ACK frame (src|dst) = .*: a node id is a byte, 0..255$"):
        encode_frame(Ack(1, 2), src=src, dst=dst, seq=0)


@pytest.mark.parametrize("value", [1.0, True])
def test_enum_fields_refuse_numbers_that_merely_equal_a_member(value: Any) -> None:
    with pytest.raises(EncodeError, match=r"^SERVO_MODE\.mode = .*: expected a StreamMode member$"):
        encode_frame(ServoMode(value), src=1, dst=0x10, seq=0)


# --- sequence numbers -------------------------------------------------------------------------


def test_encoder_sequence_wraps_from_65535_to_0() -> None:
    encoder = Encoder(src=0x10)
    encoder.next_seq = 65534
    msg = GyroSample(0x90EB, 1, 0.0, 0.0, 0.0, 0.0, 0.0)
    stream = b"".join(encoder.encode(msg, dst=0x01) for _ in range(4))
    assert encoder.next_seq == 2
    decoder = Decoder()
    frames = decoder.feed(stream)
    assert [f.seq for f in frames] == [65534, 65535, 0, 1]
    assert {f.src for f in frames} == {0x10}
    assert decoder.counters.seq_gaps == {} and decoder.counters.frames_lost == {}
    assert decoder.counters.frames_ok == 4


@given(src=nodes, dst=nodes, start=seqs, count=st.integers(1, 5))
def test_encoder_numbers_frames_consecutively(src: int, dst: int, start: int, count: int) -> None:
    encoder = Encoder(src=src)
    encoder.next_seq = start
    msg = GyroSample(1, 2, 0.0, 0.0, 0.0, 0.0, 0.0)
    frames = Decoder().feed(b"".join(encoder.encode(msg, dst=dst) for _ in range(count)))
    assert [(f.src, f.dst, f.seq) for f in frames] == [(src, dst, (start + i) % 65536) for i in range(count)]
    assert encoder.next_seq == (start + count) % 65536
