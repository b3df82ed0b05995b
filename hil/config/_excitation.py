"""The swept-sine excitation of a session (``excitation:``), which ``hil ident`` runs (seed 000 Figs 8-9).

The bench adds a swept sine ``r(t)`` (:class:`SweptSine`) to the rate command of the closed 1 kHz rate loop and logs,
per tick, the command ``r`` (deg/s), the drive ``u`` (signed DAC counts) and the measured gyro rate ``y`` (deg/s).

Docs: docs/ident.md.
"""

from __future__ import annotations

import contextlib
import itertools
import math
from bisect import bisect_right
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, model_validator

TWO_PI = 2.0 * math.pi


class SweptSine(BaseModel):
    """A swept sine added to one axis' rate command, ``t_s`` from the start of the excitation.

    ``[0, settle_s)``: zero (plus the ``offset_dps`` ramp, if any); ``[settle_s, settle_s + duration_s)``: the
    sweep ``amplitude_dps * taper * sin(phase)``, phase continuous and zero at the start, frequency ``f_start_hz ->
    f_stop_hz`` exponentially (``log``) or linearly; a raised-cosine taper of ``taper_s`` at each end; then zero.

    ``offset_dps`` (default 0) adds a constant rate during the sweep, ramped in over ``settle_s`` and out over the
    ``settle_s`` after it (``total_s`` covers both): if it exceeds the rate swing, the axis never reverses, so the
    Coulomb friction stays constant instead of switching at every zero crossing (the relay it makes otherwise looks
    like a pole near ``4 T_c k_m / (pi A)``, A the rate amplitude, and biases the identified ``k_m``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    f_start_hz: float = Field(0.5, gt=0, le=450, description="frequency at the start of the sweep")
    f_stop_hz: float = Field(300.0, gt=0, le=450, description="frequency at the end of the sweep (< 500 Hz Nyquist)")
    duration_s: float = Field(20.0, gt=0, le=3600, description="length of the sweep itself")
    amplitude_dps: float = Field(2.0, gt=0, le=200, description="peak of the sweep")
    kind: Literal["log", "linear"] = Field("log", description="log: exponential chirp; linear: linear chirp")
    axis: Literal["el", "az"] = Field("el", description="the axis whose rate command gets the sweep")
    settle_s: float = Field(0.5, ge=0, le=60, description="zero before the sweep starts (offset ramp, if any)")
    taper_s: float = Field(0.1, ge=0, le=60, description="raised-cosine fade in and out of the sweep amplitude")
    offset_dps: float = Field(0.0, ge=-200, le=200,
                              description="constant rate during the sweep (keeps friction on one side)")
    levels: tuple[tuple[float, float], ...] = Field(
        (), description="[frequency_hz, amplitude_dps] pairs, frequencies rising: the amplitude at the chirp's "
        "frequency, interpolated on log frequency and held beyond the ends (a levelled sweep); empty: amplitude_dps "
        "throughout")

    _c: tuple[float, ...] = PrivateAttr(default=())
    _lv: tuple[tuple[float, ...], tuple[float, ...]] = PrivateAttr(default=((), ()))

    @model_validator(mode="before")
    @classmethod
    def _peak_of_levels(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("levels"):
            with contextlib.suppress(TypeError, ValueError):  # the field's own validation names what is wrong
                data = {**data, "amplitude_dps": max(float(a) for _, a in data["levels"])}
        return data

    @model_validator(mode="after")
    def _check(self) -> SweptSine:
        if self.f_stop_hz == self.f_start_hz:
            raise ValueError("f_stop_hz must differ from f_start_hz")
        if 2.0 * self.taper_s > self.duration_s:
            raise ValueError("taper_s: the two tapers are longer than duration_s")
        freqs = [f for f, _ in self.levels]
        if any(not 0 < f <= 500 for f in freqs) or any(b <= a for a, b in itertools.pairwise(freqs)):
            raise ValueError("levels: frequencies must rise and lie in (0, 500] Hz")
        if any(not 0 < a <= 200 for _, a in self.levels):
            raise ValueError("levels: amplitudes must lie in (0, 200] deg/s")
        return self

    def model_post_init(self, __context: Any) -> None:
        f0, f1, dur = self.f_start_hz, self.f_stop_hz, self.duration_s
        if f0 == f1:
            return  # refused by _check, which runs after this
        if self.kind == "log":
            rate = math.log(f1 / f0) / dur  # f(tau) = f0 exp(rate tau)
            c1, c2 = TWO_PI * f0 / rate, rate
        else:
            c1, c2 = TWO_PI * f0, math.pi * (f1 - f0) / dur  # phase = c1 tau + c2 tau^2
        self._c = (c1, c2)
        if self.levels:
            self._lv = (tuple(math.log(f) for f, _ in self.levels), tuple(a for _, a in self.levels))

    def amplitude_at_dps(self, f_hz: float) -> float:
        """The sweep's amplitude at frequency ``f_hz``: ``levels`` interpolated on log frequency, else
        ``amplitude_dps``."""
        lf, amp = self._lv
        if not lf:
            return self.amplitude_dps
        x = math.log(f_hz)
        if x <= lf[0]:
            return amp[0]
        i = bisect_right(lf, x)
        if i >= len(lf):
            return amp[-1]
        w = (x - lf[i - 1]) / (lf[i] - lf[i - 1])
        return amp[i - 1] + w * (amp[i] - amp[i - 1])

    @property
    def total_s(self) -> float:
        """Length of the whole excitation: settle, sweep, and a settle after it."""
        return 2.0 * self.settle_s + self.duration_s

    @property
    def window_s(self) -> tuple[float, float]:
        """Where the sweep is active, relative to the start of the excitation."""
        return (self.settle_s, self.settle_s + self.duration_s)

    def frequency_hz(self, t_s: float) -> float:
        """Instantaneous frequency at ``t_s`` (clamped to the sweep)."""
        tau = min(max(t_s - self.settle_s, 0.0), self.duration_s)
        if self.kind == "log":
            return self.f_start_hz * math.exp(self._c[1] * tau)
        return self.f_start_hz + (self.f_stop_hz - self.f_start_hz) * tau / self.duration_s

    def rate_dps(self, t_s: float) -> float:
        """The rate command to add at ``t_s`` (plain float math: a few microseconds, for the 1 kHz loop)."""
        settle, dur = self.settle_s, self.duration_s
        tau = t_s - settle
        out = 0.0
        if 0.0 < tau < dur:
            c1, c2 = self._c
            phase = c1 * math.expm1(c2 * tau) if self.kind == "log" else tau * (c1 + c2 * tau)
            a = self.amplitude_dps if not self.levels else self.amplitude_at_dps(self.frequency_hz(t_s))
            tp = self.taper_s
            if tau < tp:
                a *= 0.5 - 0.5 * math.cos(math.pi * tau / tp)
            elif dur - tau < tp:
                a *= 0.5 - 0.5 * math.cos(math.pi * (dur - tau) / tp)
            out = a * math.sin(phase)
        off = self.offset_dps
        if off != 0.0 and 0.0 < t_s < dur + 2.0 * settle:
            if t_s < settle:
                off *= 0.5 - 0.5 * math.cos(math.pi * t_s / settle)
            elif tau > dur:
                off *= 0.5 + 0.5 * math.cos(math.pi * (tau - dur) / settle)
            out += off
        return out

    __call__ = rate_dps


IDENT_SWEEP = SweptSine(f_start_hz=1.0, f_stop_hz=450.0, duration_s=8.0, amplitude_dps=1.5, offset_dps=3.0)
"""Where ``hil ident``'s sweep starts (its levelling goes on from here): 1-450 Hz in 8 s, 1.5 deg/s around 3 deg/s
(the axis turns 27 deg)."""
