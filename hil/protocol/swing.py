"""What a PROFILE_LOAD profile means: the hexapod pose as a function of time, and its envelope check.

This is part of the protocol's definition (docs/protocol.md, PROFILE_LOAD): the hexapod controller
(or its emulator) moves along it and the bench checks a profile with it before uploading, so both
sides agree on every pose, rate and acceleration. Units per axis (HexAxis order): mm for X, Y, Z;
deg for ROLL, PITCH, YAW; rates per s, accelerations per s^2.

One segment on one axis::

    p(t) = A r(t) sin(phi(t)),  phi(t) = 2 pi f (t - start) + phase,  start <= t < start + duration

where the ramp r(t) rises linearly 0 -> 1 over ``ramp_s`` after the start and falls 1 -> 0 over
``ramp_s`` before the end (r = 1 throughout when ``ramp_s`` = 0). The pose is the sum of the segments
on each axis. Its derivatives are analytic (r is piecewise linear, so r'' = 0 between its corners):
p' = A (r' sin + r w cos), p'' = A (2 r' w cos - r w^2 sin), w = 2 pi f.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Sequence
from typing import NamedTuple

import numpy as np

from hil.protocol.messages import ErrorCode, HexAxis, ProfileLoad

N_AXES = 6
AXIS_UNITS = ("mm", "mm", "mm", "deg", "deg", "deg")
Vec6 = tuple[float, float, float, float, float, float]
ZERO6: Vec6 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


class Segment(NamedTuple):
    """One sinusoid on one axis (the payload of PROFILE_LOAD without its index/count)."""

    axis: HexAxis
    start_s: float
    duration_s: float
    amplitude: float
    frequency_hz: float
    phase_deg: float = 0.0
    ramp_s: float = 0.0

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    def to_messages(self, index: int, count: int) -> ProfileLoad:
        return ProfileLoad(index, count, self.axis, *self[1:])


def segments_to_messages(segments: Sequence[Segment]) -> list[ProfileLoad]:
    return [seg.to_messages(i, len(segments)) for i, seg in enumerate(segments)]


def segment_from_message(msg: ProfileLoad) -> Segment:
    return Segment(HexAxis(msg.axis), msg.start_s, msg.duration_s, msg.amplitude, msg.frequency_hz, msg.phase_deg,
                   msg.ramp_s)


def profile_end_s(segments: Iterable[Segment]) -> float:
    return max((seg.end_s for seg in segments), default=0.0)


RESUME_RAMP_S = 1.0  # a resumed profile ramps in over at least this long: the table starts from rest at home


def resume_segments(segments: Sequence[Segment], t_s: float, ramp_s: float = RESUME_RAMP_S) -> list[Segment]:
    """The rest of a profile from its time ``t_s`` on, as a profile of its own (its t = 0 is ``t_s``): what a
    hexapod that parked mid-profile runs to go on where the swing would be now. A segment under way keeps its
    phase (its sine continues where it would be) and ramps in again over at least ``ramp_s`` (the table is at rest
    at home: it must not jump to the sine's value), as it ramps out; segments ended by ``t_s`` are left out."""
    out = []
    for seg in segments:
        if seg.end_s <= t_s:
            continue
        if seg.start_s >= t_s:
            out.append(seg._replace(start_s=seg.start_s - t_s))
            continue
        done_s = t_s - seg.start_s
        left_s = seg.duration_s - done_s
        phase_deg = (seg.phase_deg + 360.0 * seg.frequency_hz * done_s) % 360.0
        out.append(seg._replace(start_s=0.0, duration_s=left_s, phase_deg=phase_deg,
                                ramp_s=min(max(seg.ramp_s, ramp_s), left_s / 2)))
    return out


class Profile:
    """A profile ready to evaluate at 1 kHz: each segment's constants computed once (the emulated hexapod and
    the imbalance feed-forward call it every tick). ``Profile(segments)(t_s)`` is :func:`evaluate`."""

    def __init__(self, segments: Iterable[Segment]) -> None:
        self.segments = tuple(segments)
        self._terms = tuple(
            (int(seg.axis), seg.start_s, seg.end_s, min(seg.ramp_s, seg.duration_s / 2), 2 * math.pi * seg.frequency_hz,
             math.radians(seg.phase_deg), seg.amplitude)
            for seg in self.segments)

    def __call__(self, t_s: float) -> tuple[Vec6, Vec6, Vec6]:
        """Pose, rate and acceleration at t_s (profile clock), per HexAxis. Each segment is
        ``a r(t) sin(w (t - t0) + phase)`` with the linear ramp ``r`` over ``ramp_s`` at both ends."""
        pos = [0.0] * N_AXES
        vel = [0.0] * N_AXES
        acc = [0.0] * N_AXES
        for axis, start, end, ramp, w, phase, a in self._terms:
            if not start <= t_s < end:
                continue
            r, dr = 1.0, 0.0
            if ramp > 0:
                since, until = t_s - start, end - t_s
                if since < ramp:
                    r, dr = since / ramp, 1.0 / ramp
                elif until < ramp:
                    r, dr = until / ramp, -1.0 / ramp
            phi = w * (t_s - start) + phase
            s, c = math.sin(phi), math.cos(phi)
            pos[axis] += a * r * s
            vel[axis] += a * (dr * s + r * w * c)
            acc[axis] += a * (2 * dr * w * c - r * w * w * s)
        return tuple(pos), tuple(vel), tuple(acc)  # type: ignore[return-value]


def evaluate(segments: Iterable[Segment], t_s: float) -> tuple[Vec6, Vec6, Vec6]:
    """Pose, rate and acceleration of the profile at t_s (profile clock), per HexAxis (see :class:`Profile`)."""
    return Profile(segments)(t_s)


def evaluate_batch(segments: Iterable[Segment], t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`evaluate` on an array of times: three arrays of shape (6, len(t_s))."""
    t = np.asarray(t_s, dtype=float)
    pos, vel, acc = (np.zeros((N_AXES, t.size)) for _ in range(3))
    for seg in segments:
        inside = (t >= seg.start_s) & (t < seg.end_s)
        if not inside.any():
            continue
        ramp = min(seg.ramp_s, seg.duration_s / 2)
        since, until = t - seg.start_s, seg.end_s - t
        if ramp > 0:
            r = np.clip(np.minimum(since, until) / ramp, 0.0, 1.0)
            dr = np.where(since < ramp, 1.0 / ramp, np.where(until < ramp, -1.0 / ramp, 0.0))
        else:
            r, dr = np.ones_like(t), np.zeros_like(t)
        w = 2 * math.pi * seg.frequency_hz
        phi = w * since + math.radians(seg.phase_deg)
        s, c = np.sin(phi), np.cos(phi)
        a = seg.amplitude * inside
        pos[seg.axis] += a * r * s
        vel[seg.axis] += a * (dr * s + r * w * c)
        acc[seg.axis] += a * (2 * dr * w * c - r * w * w * s)
    return pos, vel, acc


class Envelope(NamedTuple):
    """Per-axis limits of a hexapod (HexAxis order): |pose|, |rate| and |acceleration|."""

    position: Vec6
    rate: Vec6
    accel: Vec6


class EnvelopeViolation(NamedTuple):
    """The first limit a profile breaks: the NACK's error, axis, value and limit."""

    error: ErrorCode
    axis: HexAxis
    value: float
    limit: float
    t_s: float

    def describe(self) -> str:
        kind = {ErrorCode.ENVELOPE_POSITION: "position", ErrorCode.ENVELOPE_RATE: "rate",
                ErrorCode.ENVELOPE_ACCEL: "acceleration"}[self.error]
        unit = AXIS_UNITS[self.axis] + {"position": "", "rate": "/s", "acceleration": "/s^2"}[kind]
        return (f"{HexAxis(self.axis).name.lower()} {kind} reaches {self.value:.4g} {unit} at t = {self.t_s:.3f} s, "
                f"beyond the hexapod's limit of {self.limit:.4g} {unit}")


CHECK_STEP_S = 1e-3  # envelope sampling step: a 50 Hz sine's peak is under-read by < 0.5 %


def check_envelope(segments: Sequence[Segment], envelope: Envelope, step_s: float = CHECK_STEP_S
                   ) -> EnvelopeViolation | None:
    """The worst violation of the envelope over the whole profile (position first, then rate, then
    acceleration), or None. The profile is sampled every ``step_s`` and at every segment boundary
    and ramp corner, where the ramp's rate and acceleration terms peak.

    A pure function of its arguments, so its last 64 answers are remembered: the bench checks a session's profile
    when it loads the session file, and the hexapod checks it again when it is uploaded, for every campaign cell."""
    return _check_envelope(tuple(Segment(*seg) for seg in segments), Envelope(*envelope), float(step_s))


@functools.lru_cache(maxsize=64)
def _check_envelope(segments: tuple[Segment, ...], envelope: Envelope, step_s: float) -> EnvelopeViolation | None:
    if not segments:
        return None
    end = profile_end_s(segments)
    corners = []
    for seg in segments:
        ramp = min(seg.ramp_s, seg.duration_s / 2)
        corners += [seg.start_s, seg.start_s + ramp, seg.end_s - ramp, seg.end_s - 1e-9]
    grid = np.arange(0.0, end + step_s, step_s)
    corner_t = np.array(corners)
    limits = [np.asarray(lim, dtype=float)[:, None] for lim in (envelope.position, envelope.rate, envelope.accel)]
    errors = (ErrorCode.ENVELOPE_POSITION, ErrorCode.ENVELOPE_RATE, ErrorCode.ENVELOPE_ACCEL)
    worst: list[tuple[float, EnvelopeViolation] | None] = [None, None, None]
    chunk = 20_000  # samples per evaluation: bounded memory for hour-long profiles
    for i in range(0, grid.size, chunk):
        t = grid[i : i + chunk]
        t = np.unique(np.concatenate([t, corner_t[(corner_t >= t[0]) & (corner_t <= t[-1] + step_s)]]))
        for k, series in enumerate(evaluate_batch(segments, t)):
            excess = np.abs(series) / limits[k]
            axis, at = np.unravel_index(int(np.argmax(excess)), excess.shape)
            ratio = float(excess[axis, at])
            if ratio > 1.0 and (worst[k] is None or ratio > worst[k][0]):  # type: ignore[index]
                worst[k] = (ratio, EnvelopeViolation(errors[k], HexAxis(int(axis)), float(series[axis, at]),
                                                     float(limits[k][axis, 0]), float(t[at])))
    for found in worst:
        if found is not None:
            return found[1]
    return None


__all__ = [
    "AXIS_UNITS",
    "CHECK_STEP_S",
    "N_AXES",
    "RESUME_RAMP_S",
    "ZERO6",
    "Envelope",
    "EnvelopeViolation",
    "Segment",
    "Vec6",
    "check_envelope",
    "evaluate",
    "evaluate_batch",
    "profile_end_s",
    "resume_segments",
    "segment_from_message",
    "segments_to_messages",
]
