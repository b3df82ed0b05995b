"""The PROFILE_LOAD profile semantics shared by the hexapod emulator and the bench."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.protocol import ErrorCode, HexAxis, ProfileLoad
from hil.protocol.swing import (
    Envelope,
    Segment,
    check_envelope,
    evaluate,
    evaluate_batch,
    profile_end_s,
    segment_from_message,
    segments_to_messages,
)

PITCH_1DEG_1HZ = Segment(HexAxis.PITCH, 0.0, 10.0, 1.0, 1.0, 0.0, 1.0)
WIDE = Envelope(position=(100, 100, 100, 15, 15, 15), rate=(200, 200, 200, 30, 30, 30),
                accel=(5000, 5000, 5000, 500, 500, 500))


def test_pose_is_the_sum_of_ramped_sines() -> None:
    segs = [PITCH_1DEG_1HZ, Segment(HexAxis.Z, 2.0, 3.0, 5.0, 2.0, 90.0, 0.0)]
    pos, _, _ = evaluate(segs, 0.25)  # inside the 1 s ramp: r = 0.25
    assert pos[HexAxis.PITCH] == pytest.approx(0.25 * math.sin(2 * math.pi * 0.25))
    assert pos[HexAxis.Z] == 0.0
    pos, _, _ = evaluate(segs, 2.1)
    assert pos[HexAxis.Z] == pytest.approx(5.0 * math.sin(2 * math.pi * 2.0 * 0.1 + math.pi / 2))
    assert pos[HexAxis.PITCH] == pytest.approx(math.sin(2 * math.pi * 2.1))
    assert evaluate(segs, 10.0)[0] == (0.0,) * 6  # past the end: home
    assert profile_end_s(segs) == 10.0


@pytest.mark.parametrize("t", [0.3, 0.77, 4.2, 9.4])
def test_rate_and_accel_are_the_derivatives(t: float) -> None:
    segs = [PITCH_1DEG_1HZ, Segment(HexAxis.PITCH, 0.0, 10.0, 0.3, 7.0, 30.0, 0.5)]
    h = 1e-5
    (_p0, v0, a0), (pm, vm, _), (pp, vp, _) = (evaluate(segs, x) for x in (t, t - h, t + h))
    ax = HexAxis.PITCH
    assert v0[ax] == pytest.approx((pp[ax] - pm[ax]) / (2 * h), rel=1e-5)
    assert a0[ax] == pytest.approx((vp[ax] - vm[ax]) / (2 * h), rel=1e-4)


def test_batch_matches_scalar() -> None:
    segs = [PITCH_1DEG_1HZ, Segment(HexAxis.YAW, 1.0, 4.0, 2.0, 3.0, 10.0, 0.7)]
    t = np.linspace(0, 11, 997)
    pos, vel, acc = evaluate_batch(segs, t)
    for i in range(0, t.size, 37):
        p, v, a = evaluate(segs, float(t[i]))
        np.testing.assert_allclose(pos[:, i], p, atol=1e-12)
        np.testing.assert_allclose(vel[:, i], v, atol=1e-9)
        np.testing.assert_allclose(acc[:, i], a, atol=1e-7)


def test_messages_round_trip() -> None:
    segs = [PITCH_1DEG_1HZ, Segment(HexAxis.X, 0.5, 2.0, 10.0, 0.5, 0.0, 0.25)]
    msgs = segments_to_messages(segs)
    assert [m.index for m in msgs] == [0, 1] and all(m.count == 2 for m in msgs)
    assert isinstance(msgs[0], ProfileLoad)
    assert [segment_from_message(m) for m in msgs] == segs


def test_envelope_accepts_the_papers_swings_and_names_the_broken_limit() -> None:
    assert check_envelope([PITCH_1DEG_1HZ], WIDE) is None
    assert check_envelope([PITCH_1DEG_1HZ._replace(amplitude=3.0)], WIDE) is None
    v = check_envelope([PITCH_1DEG_1HZ._replace(amplitude=20.0)], WIDE)
    assert v is not None and v.error == ErrorCode.ENVELOPE_POSITION and v.axis == HexAxis.PITCH
    assert v.value == pytest.approx(20.0, rel=1e-3) and v.limit == 15
    assert "pitch position reaches 20 deg" in v.describe() and "limit of 15 deg" in v.describe()
    # 2 deg at 3 Hz: rate 37.7 deg/s > 30 while the position is fine
    v = check_envelope([PITCH_1DEG_1HZ._replace(amplitude=2.0, frequency_hz=3.0)], WIDE)
    assert v is not None and v.error == ErrorCode.ENVELOPE_RATE
    assert abs(v.value) == pytest.approx(2 * 2 * math.pi * 3, rel=1e-3)
    # 0.5 deg at 6 Hz: rate 18.8 deg/s fine, accel 711 deg/s^2 > 500
    v = check_envelope([PITCH_1DEG_1HZ._replace(amplitude=0.5, frequency_hz=6.0)], WIDE)
    assert v is not None and v.error == ErrorCode.ENVELOPE_ACCEL and v.limit == 500


def test_envelope_sees_superposed_segments() -> None:
    half = Segment(HexAxis.ROLL, 0.0, 5.0, 8.0, 0.5, 0.0, 0.0)
    assert check_envelope([half], WIDE) is None
    v = check_envelope([half, half], WIDE)  # 16 deg together
    assert v is not None and v.axis == HexAxis.ROLL and v.value == pytest.approx(16.0, rel=1e-3)
