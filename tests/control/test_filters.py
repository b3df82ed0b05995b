"""Low-pass filters against their exact discrete-time responses."""

from __future__ import annotations

import cmath
import math

import pytest

from hil.control.filters import LowPass1, LowPass2

H = 1e-3


def steady_gain(filt, freq_hz: float, seconds: float = 1.0) -> float:
    """Amplitude ratio of a sine after the transient, by projection on sin/cos over whole cycles."""
    n = int(seconds / H)
    out = [filt.step(math.sin(2 * math.pi * freq_hz * k * H)) for k in range(2 * n)][n:]
    s = sum(y * math.sin(2 * math.pi * freq_hz * (n + i) * H) for i, y in enumerate(out)) * 2 / n
    c = sum(y * math.cos(2 * math.pi * freq_hz * (n + i) * H) for i, y in enumerate(out)) * 2 / n
    return math.hypot(s, c)


def test_first_order_step_response_is_the_exact_zoh_exponential():
    lp = LowPass1(cutoff_hz=150.0, dt_s=H)
    a = math.exp(-2 * math.pi * 150.0 * H)
    for k in range(1, 20):
        assert lp.step(1.0) == pytest.approx(1 - a**k, rel=1e-12)


@pytest.mark.parametrize("freq_hz", [5.0, 15.0, 150.0, 400.0])
def test_first_order_gain_matches_its_transfer_function(freq_hz):
    a = math.exp(-2 * math.pi * 150.0 * H)
    z = cmath.exp(1j * 2 * math.pi * freq_hz * H)
    expected = abs((1 - a) / (1 - a / z))
    assert steady_gain(LowPass1(cutoff_hz=150.0, dt_s=H), freq_hz) == pytest.approx(expected, rel=2e-3)


def test_second_order_butterworth_is_3db_down_at_cutoff_and_unity_at_dc():
    assert steady_gain(LowPass2(cutoff_hz=150.0, dt_s=H), 150.0) == pytest.approx(math.sqrt(0.5), rel=2e-3)
    lp = LowPass2(cutoff_hz=150.0, dt_s=H)
    for _ in range(200):
        y = lp.step(2.5)
    assert y == pytest.approx(2.5, rel=1e-9)
    # 40 dB/decade beyond cut-off, up to the bilinear warping: at 400 Hz well under the 1st order's gain
    assert steady_gain(LowPass2(cutoff_hz=150.0, dt_s=H), 400.0) < 0.5 * steady_gain(LowPass1(dt_s=H), 400.0)


def test_second_order_reset_starts_in_steady_state():
    lp = LowPass2(cutoff_hz=50.0, dt_s=H)
    lp.reset(3.0)
    assert [lp.step(3.0) for _ in range(5)] == pytest.approx([3.0] * 5, rel=1e-12)


@pytest.mark.parametrize("kwargs", [{"cutoff_hz": 0.0}, {"cutoff_hz": 600.0}, {"damping": 0.0}])
def test_second_order_rejects_impossible_parameters(kwargs):
    with pytest.raises(ValueError):
        LowPass2(dt_s=H, **kwargs)
