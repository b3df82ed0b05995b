"""Hypothesis strategies for catalogue messages, shared by the protocol tests through fixtures.

The strategies draw *raw wire values* over each field's whole range (extremes included) and
convert them to engineering values exactly the way the decoder does, so every drawn message
is representable on the wire: encoding then decoding it must give it back unchanged. Each
draw also carries the payload bytes packed independently from those raw values (field by
field, little-endian), which pins the byte layout without trusting the codec's own struct.

Fixtures (all session-scoped, so they are safe to combine with ``@given``):

- ``wire_message(spec)`` -> strategy of ``(payload_bytes, message)`` for one MessageSpec;
- ``any_message`` -> strategy of messages of every catalogue type;
- ``any_frame`` -> strategy of ``(frame_bytes, Frame)`` with random src, dst and seq;
- ``boundary_messages`` -> ``{spec name: [all-low message, all-high message]}``.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from enum import IntFlag
from typing import Any

import pytest
from hypothesis import strategies as st

from hil.protocol import CATALOGUE, Frame, MessageSpec, encode_frame
from hil.protocol.wire import FieldSpec, Wire

F32_MAX = struct.unpack("<f", b"\xff\xff\x7f\x7f")[0]  # 3.4028234663852886e38, the largest finite float32
F32_SPECIALS = (
    0.0,
    -0.0,
    1.0,
    -1.0,
    F32_MAX,
    -F32_MAX,
    struct.unpack("<f", b"\x01\x00\x00\x00")[0],  # smallest subnormal, 1.4e-45
    -struct.unpack("<f", b"\x01\x00\x00\x00")[0],
    struct.unpack("<f", b"\x00\x00\x80\x00")[0],  # smallest normal, 1.1754943508222875e-38
    struct.unpack("<f", b"\xeb\x90\x01\x00")[0],  # a subnormal whose bytes are a sync word + version
)

WireValue = tuple[bytes, Any]  # (bytes on the wire, engineering value)


def _f32_from_bits(bits: int) -> float:
    return struct.unpack("<f", struct.pack("<I", bits))[0]


def f32_values() -> st.SearchStrategy[float]:
    """Finite floats that are exactly representable as float32 (struct round trip holds)."""
    return st.one_of(
        st.sampled_from(F32_SPECIALS),
        st.integers(0, 2**32 - 1).map(_f32_from_bits).filter(math.isfinite),  # every bit pattern
        st.floats(width=32, allow_nan=False, allow_infinity=False),
    )


def raw_ints(w: Wire) -> st.SearchStrategy[int]:
    """The full raw range of an integer primitive, with both ends and their neighbours favoured."""
    p = w.primitive
    lo, hi = int(p.lo), int(p.hi)
    edges = sorted({lo, lo + 1, hi - 1, hi, max(lo, 0)})
    return st.one_of(st.sampled_from(edges), st.integers(lo, hi))


def _pack(w: Wire, raw: int | float) -> bytes:
    return struct.pack("<" + w.primitive.code, raw)


def scalar_wire_value(w: Wire) -> st.SearchStrategy[WireValue]:
    """One element of a field (the whole field unless it is an array)."""
    if w.kind == "bool":
        return st.booleans().map(lambda b: (bytes([b]), b))
    if w.enum is not None:
        enum = w.enum
        members: st.SearchStrategy[Any] = st.sampled_from(list(enum.__members__.values()))
        if issubclass(enum, IntFlag):  # any bit combination is a valid flag value
            members = st.one_of(members, raw_ints(w).map(enum))
        return members.map(lambda m: (_pack(w, int(m)), m))
    if w.primitive.is_float:
        return f32_values().map(lambda x: (_pack(w, x), x))
    if w.scale == 1:
        return raw_ints(w).map(lambda r: (_pack(w, r), r))
    return raw_ints(w).map(lambda r: (_pack(w, r), w.to_eng(r)))


def field_wire_value(f: FieldSpec) -> st.SearchStrategy[WireValue]:
    w = f.wire
    if w.kind == "char":
        text = st.text(st.characters(min_codepoint=1, max_codepoint=127), max_size=w.count)
        return text.map(lambda s: (s.encode("ascii").ljust(w.count, b"\0"), s))
    if w.count == 1:
        return scalar_wire_value(w)
    element = scalar_wire_value(w)
    return st.tuples(*[element] * w.count).map(
        lambda items: (b"".join(b for b, _ in items), tuple(v for _, v in items))
    )


def wire_message_strategy(spec: MessageSpec) -> st.SearchStrategy[tuple[bytes, Any]]:
    """``(payload, message)`` pairs for one message type, over the whole range of every field."""

    def assemble(items: tuple[WireValue, ...]) -> tuple[bytes, Any]:
        payload = b"".join(b for b, _ in items)
        assert len(payload) == spec.payload_size
        return payload, spec.cls._make(v for _, v in items)  # type: ignore[attr-defined]

    return st.tuples(*[field_wire_value(f) for f in spec.fields]).map(assemble)


def _extreme(f: FieldSpec, high: bool) -> Any:
    w = f.wire
    if w.kind == "char":
        return "\x7f" * w.count if high else ""
    if w.kind == "bool":
        return high
    p = w.primitive
    if w.enum is not None:
        if issubclass(w.enum, IntFlag):
            value: Any = w.enum(int(p.hi) if high else 0)
        else:
            value = (max if high else min)(w.enum.__members__.values())
    elif p.is_float:
        value = F32_MAX if high else -F32_MAX
    else:
        value = w.to_eng(int(p.hi if high else p.lo))
        value = int(value) if w.scale == 1 else value
    return value if w.count == 1 else (value,) * w.count


_WIRE_MESSAGE = {spec.name: wire_message_strategy(spec) for spec in CATALOGUE}


@pytest.fixture(scope="session")
def wire_message() -> Callable[[MessageSpec], st.SearchStrategy[tuple[bytes, Any]]]:
    return lambda spec: _WIRE_MESSAGE[spec.name]


@pytest.fixture(scope="session")
def any_message() -> st.SearchStrategy[Any]:
    return st.sampled_from(list(CATALOGUE)).flatmap(lambda spec: _WIRE_MESSAGE[spec.name]).map(lambda pm: pm[1])


@pytest.fixture(scope="session")
def any_frame(any_message: st.SearchStrategy[Any]) -> st.SearchStrategy[tuple[bytes, Frame]]:
    node = st.one_of(st.sampled_from([0x00, 0x01, 0x10, 0x90, 0xEB, 0xFF]), st.integers(0, 255))
    seq = st.one_of(st.sampled_from([0, 0x90EB, 0xEB90, 0xFFFF]), st.integers(0, 0xFFFF))

    def make(t: tuple[Any, int, int, int]) -> tuple[bytes, Frame]:
        msg, src, dst, sq = t
        return encode_frame(msg, src=src, dst=dst, seq=sq), Frame(src, dst, sq, msg)

    return st.tuples(any_message, node, node, seq).map(make)


@pytest.fixture(scope="session")
def boundary_messages() -> dict[str, list[Any]]:
    return {
        spec.name: [spec.cls._make(_extreme(f, high) for f in spec.fields) for high in (False, True)]  # type: ignore[attr-defined]
        for spec in CATALOGUE
    }
