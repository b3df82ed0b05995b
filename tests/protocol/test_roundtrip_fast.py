"""MessageSpec.roundtrip (the sim clock's message path): the generated fast path gives exactly what encoding then
decoding gives (values, types), and every value the encoder refuses is refused with the encoder's own error."""

from __future__ import annotations

import enum
import math
import random
from typing import Any

import pytest

from hil.protocol import CATALOGUE, EncodeError, MessageSpec
from hil.protocol.wire import Wire

FAST = [spec for spec in CATALOGUE if getattr(spec.roundtrip, "__source__", None)]  # the generated ones


def value(w: Wire, rng: random.Random) -> Any:
    """A value for a field of wire ``w``: mostly valid, sometimes at or past the edges, sometimes the wrong type."""
    lo, hi = w.eng_range
    pick = rng.random()
    if pick < 0.05:
        return rng.choice([math.nan, math.inf, -math.inf, "x", None, True, 1.5, 10**12, -(10**12)])
    if w.kind == "bool":
        return rng.choice([True, False, 0, 1])
    if w.enum is not None:
        members = list(w.enum)
        return rng.choice([*members, *members, int(members[0]), 255, w.enum(0) if 0 in w.enum._value2member_map_
                           or issubclass(w.enum, enum.IntFlag) else members[0]])
    if w.count > 1:
        n = w.count if rng.random() < 0.9 else w.count + 1
        return tuple(rng.randint(int(lo), int(hi)) if rng.random() < 0.97 else int(hi) + 1 for _ in range(n))
    if w.primitive.is_float:
        return rng.choice([rng.uniform(-1e6, 1e6), rng.uniform(-1e-3, 1e-3), hi * 1.0001, lo, 0.0])
    if w.scale == 1:
        return rng.choice([rng.randint(int(lo), int(hi)), int(lo), int(hi), int(hi) + 1, int(lo) - 1, float(lo)])
    return rng.choice([rng.uniform(lo, hi), lo, hi, hi + 2 * abs(w.scale), rng.uniform(-1, 1), rng.randint(-5, 5)])


def outcome(fn: Any, msg: Any) -> Any:
    try:
        out = fn(msg)
    except EncodeError as exc:
        return ("refused", str(exc))
    return (out, [type(x) for x in out])


def test_the_hot_messages_have_a_fast_path() -> None:
    assert {spec.name for spec in FAST} >= {"GYRO_SAMPLE", "DRIVE_CMD", "LOOP_TIMING", "MISS_DISTANCE", "POSE",
                                            "DRIVE_STATUS", "HEXAPOD_STATUS", "ACK", "NACK"}


@pytest.mark.parametrize("spec", FAST, ids=lambda s: s.name)
def test_fast_roundtrip_equals_encode_then_decode(spec: MessageSpec) -> None:
    rng = random.Random(spec.msg_id)
    refused = 0
    for _ in range(3000):
        msg = spec.cls(*(value(f.wire, rng) for f in spec.fields))
        fast, slow = outcome(spec.roundtrip, msg), outcome(spec.roundtrip_slow, msg)
        assert fast == slow, msg
        refused += fast[0] == "refused"
    assert 0 < refused < 3000  # both kinds of input were exercised
