"""Replays (docs/capture.md): a logged session through another controller offline, and a capture back at a board.

**Controller replay** (:func:`replay_log`, ``hil replay LOG --controller NAME``): the session's 1 kHz cycle
(hil.session.ControlLoop.on_sample) run again, open loop, on what the log recorded: each logged gyro sample, the
rate command the session computed (its tracking loop re-run on the logged camera frames, its excitation), the
hexapod poses for a controller with imbalance feed-forward, and the drive that was actually applied. The other
controller steps as the session's would have, with the same drive limits and slew; its estimator is then told the
logged drive (what the plant really got), so its estimates follow the logged run. Out come its estimates and the
drive it would have sent, compared with the logged controller's: estimate noise, estimate lag behind the gyro,
drive ripple, and the difference from the logged drive. Only logged channels are used, so a log from the real lab
replays as one from the emulator. Replaying the logged controller itself reproduces the logged drive exactly: the
inputs are rebuilt bit for bit (the log's float32 gyro and miss-distance values hold the protocol's integers
exactly up to 16 deg/s and 16 000 px; the command is recomputed in float64 and checked against its float32 copy).

**Capture playback** (:func:`replay_capture`, ``hil replay CAPTURE --to-emulator``; :func:`play_capture` to given
ports): the frames the bench sent in a capture (hil.link), written again, byte for byte, to a board's or an
emulator's ports with their original timing, by one thread that sleeps in select() (reading what comes in), then
spins, to each write's time. What comes back is decoded and counted: commands answered (ACK, NACK, IDENT), samples,
the board's timing reports. The stream starts only when the replayed SERVO_MODE STREAM asks for it; a write that
followed a sample in the capture goes out as long after the replayed stream's sample of the same tick
(``timing="samples"``), so DRIVE_CMD k answers sample k however the board is paced (a lockstep emulator waits for
each), or at its original time from the first write (``timing="clock"``). The board's rules apply as to the bench,
in either timing: the replay stops sending when the board stops streaming (a watchdog on the samples' arrival) or
latches a driver fault, and whatever it left enabled, streaming or swinging it then disables, stops and idles, and
sends nothing else. A capture that ends with a sample after its last write (a session killed mid-run) is played to
that sample: the safe end waits for it, so it cannot reach the board before the step that answers the last write.

:func:`replay_log` and :func:`replay_capture` are what ``hil replay`` calls (through hil.api): everything but the
parsing and printing, bad input refused with a ReplayError or CaptureError (ValueErrors) naming the option.
"""

from __future__ import annotations

import contextlib
import math
import os
import select
import threading
import time
import zlib
from array import array
from collections import Counter, deque
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil.analysis import drive_ripple, json_safe
from hil.link import (
    LINKS,
    Capture,
    CaptureReader,
    PortClaims,
    PortUnavailable,
    claim_ports,
    link_decoder,
    set_exclusive,
    time_ordered,
)
from hil.protocol import (
    CATALOGUE,
    NO_LATENCY_US,
    Ack,
    AxisMask,
    Board,
    DriveDisable,
    DriveEnable,
    DriveStatus,
    Encoder,
    GyroSample,
    HexapodStart,
    HexapodStop,
    Ident,
    IdentRequest,
    LockstepAck,
    LoopTiming,
    Nack,
    ServoMode,
    StreamMode,
)

AXES = ("el", "az")
GYRO = {"el": "gyro_y_dps", "az": "gyro_z_dps"}  # the rate each axis's controller feeds back
DT_S = 1e-3
MAX_LAG_S = 0.05  # cross-correlation lags searched, each way
LAG_BAND_HZ = 50.0  # the lag is read below this (zero-phase low-pass on both): the motion, not the gyro's noise
PLOT_WINDOW_S = 0.5


class ReplayError(ValueError):
    """A log or capture that cannot be replayed (one line naming why)."""


# --- controller replay ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ControllerSpec:
    name: str
    params: dict[str, Any]


@dataclass
class AxisReplay:
    """One axis's comparison, over the metric window. Noise: std of the estimate minus its 20 ms moving mean (the
    session report's drive-ripple definition, :func:`hil.analysis.drive_ripple`, applied to the rate). Lag: where the
    cross-correlation of the estimate with the logged gyro peaks (positive: the estimate lags), both low-passed
    below LAG_BAND_HZ with zero phase, parabola-interpolated between 1 ms lags (:func:`xcorr_lag`)."""

    noise_gyro_dps: float
    noise_logged_dps: float
    noise_replayed_dps: float
    lag_logged_ms: float
    lag_replayed_ms: float
    ripple_logged_counts: float
    ripple_replayed_counts: float
    drive_diff_rms_counts: float
    drive_diff_max_counts: float
    drive_equal_fraction: float
    estimate_diff_rms_dps: float


@dataclass
class ReplayResult:
    """What :func:`replay_log` found. ``series`` holds the per-tick arrays over the replayed rows (``t_s`` from the
    first sample; ``{axis}_gyro``, ``{axis}_fb_logged``, ``{axis}_fb_replayed``, ``{axis}_drive_logged``,
    ``{axis}_drive_replayed``, ``{axis}_dist_replayed``) and ``xcorr`` the correlation curves behind the lags."""

    log: Path
    logged: ControllerSpec
    replayed: ControllerSpec
    ticks: int  # rows replayed
    rows: int  # rows in the log
    window_s: tuple[float, float]  # the metric window, from the first sample
    window_ticks: int
    ended: str  # why the replay stopped where it did
    axes: dict[str, AxisReplay]
    inputs: dict[str, int]
    series: dict[str, np.ndarray] = field(repr=False)
    xcorr: dict[str, np.ndarray] = field(repr=False)

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON types (NaN stays a float: the JSON writer turns it into null)."""
        return {
            "log": str(self.log),
            "controller": {"logged": {"name": self.logged.name, "params": self.logged.params},
                           "replayed": {"name": self.replayed.name, "params": self.replayed.params}},
            "rows": self.rows, "ticks_replayed": self.ticks, "ended": self.ended,
            "window_s": list(self.window_s), "window_ticks": self.window_ticks,
            "inputs": dict(self.inputs),
            "axes": {axis: dict(vars(a)) for axis, a in self.axes.items()},
        }

    def table(self) -> list[tuple[str, str, str, float, float]]:
        """(metric, axis, unit, logged, replayed) rows: what `hil replay` prints."""
        out: list[tuple[str, str, str, float, float]] = []
        for axis, a in self.axes.items():
            out += [
                ("estimate noise (std)", axis, "deg/s", a.noise_logged_dps, a.noise_replayed_dps),
                ("estimate lag behind gyro", axis, "ms", a.lag_logged_ms, a.lag_replayed_ms),
                ("drive ripple (std)", axis, "counts", a.ripple_logged_counts, a.ripple_replayed_counts),
                ("drive minus logged (rms)", axis, "counts", 0.0, a.drive_diff_rms_counts),
                ("drive minus logged (max)", axis, "counts", 0.0, a.drive_diff_max_counts),
            ]
        return out


@dataclass
class _Inputs:
    """The logged run, as the replay needs it."""

    path: Path
    n: int  # rows replayed (the armed stretch)
    rows: int
    ended: str
    t_s: np.ndarray
    t_us: list[int]  # unwrapped board time of each sample, us (what the session compares frame times with)
    gyro: dict[str, list[float]]  # "x", "y", "z": the decoded values
    az_deg: list[float]
    el_deg: list[float]
    cmd_logged: dict[str, np.ndarray]  # float32, as logged
    drive: dict[str, list[int]]
    ff_logged: np.ndarray
    frames: list[tuple[int, int, int, float, float, float, bool]]  # row, apply_us, frame, t_exp_s, miss_x, miss_y, ok
    poses: list[tuple[int, float]]  # row before which it arrived, t_profile_s
    tracking: Any
    safety: Any
    excitation: Any
    segments: list[Any]
    duration_s: float
    logged: ControllerSpec
    gyro_inexact: int


def _section(model: Any, data: Any, notes: list[str], what: str) -> Any:
    try:
        return model.model_validate(data if data is not None else {})
    except Exception as exc:  # a log from another version: its defaults, and say so
        notes.append(f"{what}: {type(exc).__name__}; defaults used")
        return model()


def _decoded(values: np.ndarray, divisor: int) -> tuple[list[float], int]:
    """Logged float32 values of a protocol field with scale 1/``divisor`` -> the float64 values the decoder gave
    (raw / divisor), and how many could not be recovered exactly (beyond float32's resolution of the field)."""
    v32 = np.asarray(values, dtype=np.float32)
    raw = np.round(v32.astype(np.float64) * divisor)
    out = raw / divisor
    inexact = int(np.count_nonzero(out.astype(np.float32) != v32)) + int(
        np.count_nonzero(np.abs(v32) >= 2.0**24 / divisor))  # past this, two raw values share a float32
    return out.tolist(), inexact


def _stretch(loop: dict[str, np.ndarray], events: dict[str, np.ndarray]) -> tuple[int, str]:
    """Rows the controller ran on: from the first row to the last one with a drive, and not past the first fault
    or signal (a recovery restarts the stream and the controllers: it is not replayed)."""
    n = len(loop["tick"])
    driven = np.flatnonzero((loop["drive_az_counts"] != 0) | (loop["drive_el_counts"] != 0))
    end = int(driven[-1]) + 1 if driven.size else 0
    ended = "the last driven sample"
    kinds = [str(k) for k in events.get("kind", [])]
    for kind, tick in zip(kinds, events.get("tick", []), strict=False):
        if kind in ("fault", "signal"):
            ticks = loop["tick"].astype(np.int64)
            at = int(np.searchsorted(ticks[: max(end, 1)], int(tick), side="right"))
            if at <= end:
                end, ended = at, f"a {kind} at tick {int(tick)}"
            break
    return min(end, n), ended


def _frame_rows(image: dict[str, np.ndarray], ticks: np.ndarray, t_host: np.ndarray) -> np.ndarray:
    """For each camera frame, the row before which the session's loop had it: the first sample after
    ``loop_tick``, the loop's last tick when the frame arrived (read by the session as it queued the frame, so it
    holds when the loop thread had a sample in hand but had not yet run it). ``loop_tick`` 0 is also "no sample
    yet": the host times tell the two apart. Without ``loop_tick`` (an older log), the host times alone."""
    t_frame = np.asarray(image["t_host_ns"], dtype=np.int64)
    by_time = np.searchsorted(t_host, t_frame, side="right")
    if "loop_tick" not in image:
        return by_time
    loop_tick = np.asarray(image["loop_tick"], dtype=np.int64)
    rows = np.searchsorted(np.asarray(ticks, dtype=np.int64), loop_tick, side="right")
    before_first = (loop_tick == 0) & (t_frame < t_host[0])
    return np.where(before_first, 0, rows)


def _load(path: Path) -> _Inputs:
    from hil.config import SafetyConfig, SwingProfile, TrackingConfig
    from hil.log import read_log

    try:
        data = read_log(path)
    except Exception as exc:
        raise ReplayError(f"{path}: cannot read the log: {exc}") from None
    loop = data.groups.get("loop") or {}
    if not loop or not len(loop.get("tick", ())):
        raise ReplayError(f"{path}: the log has no loop samples to replay")
    config = data.attrs.get("config") if isinstance(data.attrs.get("config"), dict) else {}
    notes: list[str] = []
    tracking = _section(TrackingConfig, config.get("tracking"), notes, "tracking")
    safety = _section(SafetyConfig, config.get("safety"), notes, "safety")
    profile = _section(SwingProfile, config.get("profile"), notes, "profile")
    excitation = None
    if config.get("excitation"):
        from pydantic import TypeAdapter

        from hil.config import Excitation

        try:
            excitation = TypeAdapter(Excitation).validate_python(config["excitation"])
        except Exception as exc:
            raise ReplayError(f"{path}: the logged excitation cannot be rebuilt ({type(exc).__name__})") from None
    ctrl = config.get("controller") or {}
    provenance = data.attrs.get("provenance")
    resolved = provenance.get("controller") if isinstance(provenance, dict) else None
    name = str(ctrl.get("name") or data.attrs.get("controller") or "")
    if not name:
        raise ReplayError(f"{path}: the log does not say which controller ran")
    params = dict(ctrl.get("params") or {})
    if isinstance(resolved, dict) and resolved.get("name") == name and isinstance(resolved.get("params"), dict):
        params = dict(resolved["params"])  # every parameter as it ran, defaults included
    n, ended = _stretch(loop, data.groups.get("events") or {})
    if n == 0:
        raise ReplayError(f"{path}: the controller never drove (no sample with a drive): nothing to replay")
    t_s = np.asarray(loop["t_s"], dtype=np.float64)[:n]
    gyro, inexact = {}, 0
    for axis in "xyz":
        gyro[axis], bad = _decoded(loop[f"gyro_{axis}_dps"][:n], 1_000_000)
        inexact += bad
    t_host = np.asarray(loop["t_host_ns"], dtype=np.int64)[:n]
    frames = []
    image = data.groups.get("image") or {}
    if image and len(image.get("frame", ())):
        mx, _ = _decoded(image["miss_x_px"], 1000)
        my, _ = _decoded(image["miss_y_px"], 1000)
        rows = _frame_rows(image, loop["tick"][:n], t_host)
        apply_after_us = round(tracking.apply_after_ms * 1000)
        for i in range(len(image["frame"])):
            t_exp_s = float(image["t_exposure_s"][i])
            frames.append((int(rows[i]), round(t_exp_s * 1e6) + apply_after_us, int(image["frame"][i]), t_exp_s,
                           mx[i], my[i], bool(image["track_valid"][i])))
        frames.sort(key=lambda f: f[0])
    poses = []
    hexa = data.groups.get("hexapod") or {}
    if hexa and len(hexa.get("t_profile_s", ())):
        rows = np.searchsorted(t_host, np.asarray(hexa["t_host_ns"], dtype=np.int64), side="right")
        poses = sorted(((int(r), float(t)) for r, t in zip(rows, hexa["t_profile_s"], strict=True)),
                       key=lambda p: p[0])
    return _Inputs(
        path=Path(path), n=n, rows=len(loop["tick"]), ended=ended, t_s=t_s,
        t_us=[round(t * 1e6) for t in t_s.tolist()], gyro=gyro,
        az_deg=np.asarray(loop["az_deg"], dtype=np.float64)[:n].tolist(),
        el_deg=np.asarray(loop["el_deg"], dtype=np.float64)[:n].tolist(),
        cmd_logged={"az": np.asarray(loop["rate_cmd_az_dps"][:n], dtype=np.float32),
                    "el": np.asarray(loop["rate_cmd_el_dps"][:n], dtype=np.float32)},
        drive={axis: [int(v) for v in loop[f"drive_{axis}_counts"][:n]] for axis in ("az", "el")},
        ff_logged=np.asarray(loop["ff_el_counts"][:n], dtype=np.float32),
        frames=frames, poses=poses, tracking=tracking, safety=safety, excitation=excitation,
        segments=profile.protocol_segments(), duration_s=float(config.get("duration_s") or math.inf),
        logged=ControllerSpec(name, params), gyro_inexact=inexact)


def _run(inp: _Inputs, spec: ControllerSpec) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """The session's cycle (ControlLoop.on_sample, armed) over the logged rows, open loop. Returns the per-tick
    arrays and the input checks."""
    from hil.control.imbalance_feed import ImbalanceFeed, ProfileClock
    from hil.control.loops import TrackingLoop
    from hil.control.registry import build_controller

    ctrl_az, ctrl_el = build_controller(spec.name, spec.params), build_controller(spec.name, spec.params)
    tr = inp.tracking
    kw = {"kp_per_s": tr.kp_per_s, "ki_per_s2": tr.ki_per_s2, "ifov_deg_per_px": tr.ifov_deg_per_px,
          "max_rate_dps": tr.max_rate_dps, "stale_s": tr.stale_s}
    track_az, track_el = TrackingLoop(**kw), TrackingLoop(**kw)
    tracking = tr.enabled
    imbalance = ctrl_el.imbalance
    feed = None if imbalance is None else ImbalanceFeed(imbalance, inp.segments, dt_s=1e-3)
    clock = ProfileClock()
    exc = inp.excitation
    excite_el = exc is None or exc.axis == "el"
    lim, slew = inp.safety.max_drive_counts, inp.safety.max_slew_counts
    n = inp.n
    out = {key: np.zeros(n) for key in ("az_fb", "el_fb", "az_dist", "el_dist", "ff_el", "az_cmd", "el_cmd")}
    drive_az, drive_el = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    pending: deque[tuple[int, int]] = deque()  # (board time to use it, us; index into inp.frames)
    frames, poses = inp.frames, inp.poses
    fi = pi = 0
    t_list = inp.t_s.tolist()
    t0 = t_list[0]
    t_rel = 0.0
    gy, gz = inp.gyro["y"], inp.gyro["z"]
    logged_az, logged_el = inp.drive["az"], inp.drive["el"]
    cmd32_az, cmd32_el = inp.cmd_logged["az"].tolist(), inp.cmd_logged["el"].tolist()
    f32 = np.float32
    u_az_prev = u_el_prev = 0
    ff_el = 0.0
    checks = Counter()
    for k in range(n):
        while fi < len(frames) and frames[fi][0] <= k:  # camera frames that arrived before this sample
            pending.append((frames[fi][1], fi))
            fi += 1
        while pi < len(poses) and poses[pi][0] <= k:  # poses: the profile clock, at the last sample's time
            clock.on_pose(poses[pi][1], t_rel)
            pi += 1
        t_abs = t_list[k]
        t_rel = t_abs - t0
        now_us = inp.t_us[k]
        while pending and pending[0][0] < now_us:
            _, j = pending.popleft()
            _, _, frame, t_exp, mx, my, ok = frames[j]
            checks["frames_used"] += 1
            if tracking:
                now_s = t_rel + t0
                track_az.on_frame(frame=frame, miss_px=mx, track_valid=ok, t_exposure_s=t_exp, now_s=now_s)
                track_el.on_frame(frame=frame, miss_px=my, track_valid=ok, t_exposure_s=t_exp, now_s=now_s)
        cmd_az = track_az.rate_cmd_dps(t_abs) if tracking else 0.0
        cmd_el = track_el.rate_cmd_dps(t_abs) if tracking else 0.0
        if exc is not None:
            if excite_el:
                cmd_el += exc.rate_dps(t_rel)
            else:
                cmd_az += exc.rate_dps(t_rel)
        if f32(cmd_az) != cmd32_az[k]:  # the rebuilt command is not the one the session used: take the logged one
            checks["command_mismatches_az"] += 1
            cmd_az = cmd32_az[k]
        if f32(cmd_el) != cmd32_el[k]:
            checks["command_mismatches_el"] += 1
            cmd_el = cmd32_el[k]
        u_az = ctrl_az.step(cmd_az, gz[k])
        if feed is not None:
            ff_el = feed.tick(clock.at(t_rel), gy[k], inp.az_deg[k], inp.el_deg[k], u_el_prev)
        u_el = ctrl_el.step(cmd_el, gy[k], ff_el)
        u_az = max(-lim, min(lim, max(u_az_prev - slew, min(u_az_prev + slew, u_az))))
        u_el = max(-lim, min(lim, max(u_el_prev - slew, min(u_el_prev + slew, u_el))))
        drive_az[k], drive_el[k] = u_az, u_el
        out["az_fb"][k], out["el_fb"][k] = ctrl_az.rate_fb_dps, ctrl_el.rate_fb_dps
        out["az_dist"][k], out["el_dist"][k] = ctrl_az.disturbance_counts, ctrl_el.disturbance_counts
        out["ff_el"][k], out["az_cmd"][k], out["el_cmd"][k] = ff_el, cmd_az, cmd_el
        # open loop: what the plant really got is what the estimators are told was applied
        u_az_prev, u_el_prev = logged_az[k], logged_el[k]
        ctrl_az.hold(u_az_prev)
        ctrl_el.hold(u_el_prev)
    out["az_drive"], out["el_drive"] = drive_az, drive_el
    checks["gyro_inexact"] = inp.gyro_inexact
    checks["poses_used"] = pi
    return out, dict(checks)


def xcorr_lag(reference: np.ndarray, signal: np.ndarray, dt_s: float = DT_S, max_lag_s: float = MAX_LAG_S,
              band_hz: float | None = LAG_BAND_HZ) -> tuple[float, np.ndarray, np.ndarray]:
    """How far ``signal`` lags ``reference`` (s; positive: it comes later), from the peak of their normalised
    cross-correlation over lags up to ``max_lag_s`` each way, interpolated by a parabola through the peak and its
    neighbours. Both are first low-passed below ``band_hz`` (4th-order Butterworth, forward and backward: no phase
    of its own), so the peak is the delay of the motion rather than of the gyro's white noise, whose
    correlation through any causal filter peaks at lag 0. Returns (lag_s, lags_s, correlation)."""
    x = np.asarray(reference, dtype=float)
    y = np.asarray(signal, dtype=float)
    n = min(x.size, y.size)
    if n < 3:
        return math.nan, np.zeros(0), np.zeros(0)
    x, y = x[:n] - x[:n].mean(), y[:n] - y[:n].mean()
    if band_hz is not None and band_hz < 0.5 / dt_s and n > 30:
        from scipy.signal import butter, sosfiltfilt

        sos = butter(4, band_hz * 2 * dt_s, output="sos")
        x, y = sosfiltfilt(sos, x), sosfiltfilt(sos, y)
    norm = math.sqrt(float(np.dot(x, x)) * float(np.dot(y, y)))
    if norm == 0.0:
        return math.nan, np.zeros(0), np.zeros(0)
    max_lag = max(1, min(round(max_lag_s / dt_s), n - 1))
    nfft = 1 << (2 * n - 1).bit_length()
    c = np.fft.irfft(np.conj(np.fft.rfft(x, nfft)) * np.fft.rfft(y, nfft), nfft)  # c[l] = sum x[i] y[i + l]
    corr = np.concatenate((c[-max_lag:], c[: max_lag + 1])) / norm
    lags = np.arange(-max_lag, max_lag + 1)
    k = int(np.argmax(corr))
    shift = 0.0
    if 0 < k < corr.size - 1:
        a, b, d = corr[k - 1], corr[k], corr[k + 1]
        denom = a - 2 * b + d
        if denom < 0:
            shift = 0.5 * (a - d) / denom
    return float((lags[k] + shift) * dt_s), lags * dt_s, corr


def parse_params(text: str) -> dict[str, Any]:
    """``"k=v,k=v"`` as a dict, each value a number where it is one (``500`` an int, ``1e-3`` a float), else read
    as YAML (``true``, ``[1, 2]``...). ReplayError naming ``--params`` for an item that is not ``k=v``."""
    out: dict[str, Any] = {}
    for item in (p.strip() for p in text.split(",")):
        if not item:
            continue
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise ReplayError(f"--params: {item!r} is not k=v")
        out[key.strip()] = _param_value(key.strip(), value.strip())
    return out


def _param_value(key: str, text: str) -> Any:
    """A number as a number (``1e-3`` too, which YAML 1.1 reads as a string), anything else as YAML reads it."""
    from hil.config import parse_yaml

    if not text:
        return ""
    for kind in (int, float):
        try:
            value = kind(text)
        except ValueError:
            continue
        if math.isfinite(value):
            return value
    try:
        return parse_yaml(text)
    except Exception as exc:  # YAML's errors, or its size limit
        raise ReplayError(f"--params: {key}: not a value ({type(exc).__name__})") from None


def controller_choice(controller: str | None, params: Mapping[str, Any] | str | Path | None
                      ) -> tuple[str | None, dict[str, Any] | None]:
    """The controller name and parameters ``controller`` and ``params`` ask for: ``params`` a dict, a ``"k=v,..."``
    string (:func:`parse_params`) or a controller YAML (a ``Path``, a name ending in .yaml/.yml, or an existing
    file: its name and params; ``controller``, if given, must be that name). ReplayError (one line) otherwise."""
    if params is None:
        return controller, None
    if isinstance(params, Mapping):
        return controller, dict(params)
    text = str(params)
    path = Path(text)
    if isinstance(params, Path) or text.endswith((".yaml", ".yml")) or path.is_file():
        from hil.config import ConfigError, ControllerConfig, load_model

        try:
            cfg = load_model(ControllerConfig, path)
        except (ConfigError, ValueError, OSError) as exc:
            raise ReplayError(f"--params {text}: {' '.join(str(exc).split())}") from None
        if controller is not None and controller != cfg.name:
            raise ReplayError(f"--controller {controller} but {text} is a {cfg.name} controller")
        return cfg.name, dict(cfg.params)
    return controller, parse_params(text)


def replay_log(log: Path | str, controller: str | None = None,
               params: Mapping[str, Any] | str | Path | None = None, *, settle_s: float = 1.0) -> ReplayResult:
    """Replay the session log ``log`` through ``controller`` (default: the logged one, or the YAML's) with
    ``params``: a dict over the registry defaults, a ``"k=v,k=v"`` string, or a controller YAML (name and params)
    (:func:`controller_choice`); None with the logged controller: the logged parameters, with another: the registry
    defaults. Metrics over [``settle_s``, the session's duration) from the first sample. ReplayError (one line) for
    input that cannot be replayed; ControllerConfigError (also a ValueError) for an unknown controller or
    parameter. :func:`write_outputs` writes the plot and JSON."""
    from hil.config import require_regular_file
    from hil.control.registry import controller_params

    if not isinstance(settle_s, int | float) or not math.isfinite(settle_s) or settle_s < 0:
        raise ReplayError(f"--settle: {settle_s!r} is not a finite number of seconds >= 0")
    try:
        require_regular_file(Path(log))
    except ValueError as exc:
        raise ReplayError(str(exc)) from None
    controller, params = controller_choice(controller, params)
    inp = _load(Path(log))
    name = controller or inp.logged.name
    if params is None:
        params = dict(inp.logged.params) if name == inp.logged.name else {}
    controller_params(name, params)  # ControllerConfigError, one line, before anything runs
    spec = ControllerSpec(name, dict(params))
    out, checks = _run(inp, spec)
    t = inp.t_s - inp.t_s[0]
    keep = (t >= settle_s) & (t < inp.duration_s)
    if not keep.any():  # a run shorter than the settling time: the whole of it
        keep = np.ones(inp.n, dtype=bool)
    window = (float(t[keep][0]), float(t[keep][-1]))
    from hil.log import read_log

    loop = read_log(inp.path, groups=["loop"]).groups["loop"]
    axes: dict[str, AxisReplay] = {}
    series: dict[str, np.ndarray] = {"t_s": t}
    xcorr: dict[str, np.ndarray] = {}
    for axis in AXES:
        gyro = np.asarray(inp.gyro["y" if axis == "el" else "z"])
        fb_logged = np.asarray(loop[f"rate_fb_{axis}_dps"][: inp.n], dtype=float)
        fb = out[f"{axis}_fb"].astype(np.float32).astype(float)  # as a log would hold it: like for like
        drive_logged = np.asarray(inp.drive[axis], dtype=np.int64)
        drive = out[f"{axis}_drive"]
        lag_l, lags, corr_l = xcorr_lag(gyro[keep], fb_logged[keep])
        lag_r, _, corr_r = xcorr_lag(gyro[keep], fb[keep])
        diff = (drive - drive_logged)[keep].astype(float)
        axes[axis] = AxisReplay(
            noise_gyro_dps=drive_ripple(gyro[keep]),
            noise_logged_dps=drive_ripple(fb_logged[keep]),
            noise_replayed_dps=drive_ripple(fb[keep]),
            lag_logged_ms=lag_l * 1e3, lag_replayed_ms=lag_r * 1e3,
            ripple_logged_counts=drive_ripple(drive_logged[keep]),
            ripple_replayed_counts=drive_ripple(drive[keep]),
            drive_diff_rms_counts=float(np.sqrt(np.mean(diff**2))),
            drive_diff_max_counts=float(np.max(np.abs(diff))),
            drive_equal_fraction=float(np.mean(diff == 0)),
            estimate_diff_rms_dps=float(np.sqrt(np.mean((fb - fb_logged)[keep] ** 2))))
        series.update({f"{axis}_gyro": gyro, f"{axis}_fb_logged": fb_logged, f"{axis}_fb_replayed": fb,
                       f"{axis}_drive_logged": drive_logged, f"{axis}_drive_replayed": drive,
                       f"{axis}_dist_replayed": out[f"{axis}_dist"], f"{axis}_cmd": out[f"{axis}_cmd"]})
        xcorr.update({"lags_s": lags, f"{axis}_logged": corr_l, f"{axis}_replayed": corr_r})
    series["ff_el_replayed"] = out["ff_el"]
    return ReplayResult(log=inp.path, logged=inp.logged, replayed=spec, ticks=inp.n, rows=inp.rows,
                        window_s=window, window_ticks=int(keep.sum()), ended=inp.ended, axes=axes,
                        inputs=checks, series=series, xcorr=xcorr)


def write_plot(result: ReplayResult, path: Path, window_s: float = PLOT_WINDOW_S) -> Path:
    """A PNG (matplotlib, Agg): per axis, the gyro with both estimates and both drives over ``window_s`` from the
    start of the metric window, and the cross-correlations behind the lags."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s, lo = result.series, result.window_s[0]
    t = s["t_s"]
    sel = (t >= lo) & (t < lo + window_s)
    names = (f"logged {result.logged.name}", f"replayed {result.replayed.name}")
    fig, axs = plt.subplots(3, 2, figsize=(12, 9), constrained_layout=True)
    for col, axis in enumerate(AXES):
        a = axs[0, col]
        a.plot(t[sel], s[f"{axis}_gyro"][sel], color="0.7", lw=0.8, label="gyro (logged)")
        a.plot(t[sel], s[f"{axis}_fb_logged"][sel], lw=1.0, label=f"estimate, {names[0]}")
        a.plot(t[sel], s[f"{axis}_fb_replayed"][sel], lw=1.0, ls="--", label=f"estimate, {names[1]}")
        a.set(title=f"{axis.upper()} rate", xlabel="t (s)", ylabel="deg/s")
        a.legend(fontsize=7)
        a = axs[1, col]
        a.plot(t[sel], s[f"{axis}_drive_logged"][sel], lw=1.0, label=f"drive, {names[0]}")
        a.plot(t[sel], s[f"{axis}_drive_replayed"][sel], lw=1.0, ls="--", label=f"would-be drive, {names[1]}")
        a.set(title=f"{axis.upper()} drive", xlabel="t (s)", ylabel="counts")
        a.legend(fontsize=7)
        a = axs[2, col]
        ax_r = result.axes[axis]
        lags_ms = result.xcorr["lags_s"] * 1e3
        if lags_ms.size:
            a.plot(lags_ms, result.xcorr[f"{axis}_logged"], label=f"{names[0]}: {ax_r.lag_logged_ms:.2f} ms")
            a.plot(lags_ms, result.xcorr[f"{axis}_replayed"], ls="--",
                   label=f"{names[1]}: {ax_r.lag_replayed_ms:.2f} ms")
        a.set(title=f"{axis.upper()} estimate vs gyro: cross-correlation", xlabel="lag (ms)", ylabel="normalised")
        a.legend(fontsize=7)
    fig.suptitle(f"{result.log.name}: {names[0]} vs {names[1]}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def write_outputs(result: ReplayResult, out_dir: Path) -> tuple[Path, Path]:
    """``<log stem>-replay-<controller>.png`` and ``.json`` in ``out_dir``; returns both paths."""
    import json

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = f"{result.log.stem}-replay-{result.replayed.name}"
    png = write_plot(result, out_dir / f"{stem}.png")
    js = out_dir / f"{stem}.json"
    js.write_text(json.dumps(json_safe(result.as_dict()), indent=1) + "\n")
    return png, js


# --- capture playback -------------------------------------------------------------------------------------------

SPIN_S = 200e-6  # the last part of each wait is a spin that keeps polling the ports, the rest a select() sleep
FIRST_SAMPLE_WAIT_S = 2.0  # how long the replay waits for the stream the replayed SERVO_MODE STREAM starts
WATCHDOG_S = 0.1  # no awaited sample this long (beyond the capture's own gap): the board stopped; so does the replay
LINGER_S = 0.5  # after the last frame, replies are awaited this long
SAMPLE_TIMES_KEPT = 4096  # arrival times of the latest samples kept (4 s of stream), whatever the replay's length
TIMINGS = ("samples", "clock")
EMULATOR_CLOCKS = ("lockstep", "realtime")
_REPLY_ACK = {spec.msg_id for spec in CATALOGUE if spec.reply in ("ACK", "ACK/NACK")}
_NAMES = {spec.msg_id: spec.name for spec in CATALOGUE}
_ID = {spec.cls: spec.msg_id for spec in CATALOGUE}
Timing = str  # "samples" | "clock"


class Quantiles:
    """Quantiles of non-negative integers (here: ns) in fixed memory, however many are added: a log-linear
    histogram (HDR-like) exact below 128 and with buckets 1/64 of their value wide above (a quantile is its bucket's
    middle: within 0.8 %); count and maximum exact."""

    SUB = 64  # buckets per power of two, above 2 * SUB
    SIZE = 2 * SUB + 57 * SUB  # values up to 2**63

    __slots__ = ("buckets", "count", "max")

    def __init__(self) -> None:
        self.buckets = array("q", bytes(8 * self.SIZE))
        self.count = 0
        self.max = 0

    def add(self, value: int) -> None:
        v = max(0, int(value))
        if v < 2 * self.SUB:
            i = v
        else:
            shift = v.bit_length() - self.SUB.bit_length()  # v >> shift in [SUB, 2 * SUB)
            i = 2 * self.SUB + (shift - 1) * self.SUB + (v >> shift) - self.SUB
        self.buckets[i] += 1
        self.count += 1
        self.max = max(self.max, v)

    def _bounds(self, i: int) -> tuple[int, int]:
        if i < 2 * self.SUB:
            return i, i
        shift, top = divmod(i - 2 * self.SUB, self.SUB)
        shift += 1
        lo = (top + self.SUB) << shift
        return lo, lo + (1 << shift) - 1

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (0..1, nearest rank), NaN when empty."""
        if not self.count:
            return math.nan
        rank = max(1, math.ceil(q * self.count))
        seen = 0
        for i, n in enumerate(self.buckets):
            seen += n
            if seen >= rank:
                lo, hi = self._bounds(i)
                return float(min((lo + hi) / 2, self.max))
        return float(self.max)


@dataclass
class _Tx:
    """One write of the capture: when, on which link, the bytes and their frames; ``anchor`` the sample (stream
    number, tick) it followed and ``offset_ns`` how long after that sample's arrival it went out (``anchor`` None:
    before the first sample, ``offset_ns`` from the first write); ``gap_ns`` the capture's wait for that sample
    after the one before it. ``end``: no write, but the sample the capture received after its last write."""

    t_ns: int
    link: str
    data: bytes
    frames: list[tuple[int, int, Any]]  # (msg_id, seq, message) of the frames the write holds
    anchor: tuple[int, int] | None = None
    offset_ns: int = 0
    gap_ns: int = 0
    end: bool = False


@dataclass
class LinkPlayback:
    """One link's side of a playback: what went out, what came back, what the capture itself had."""

    sent: Counter = field(default_factory=Counter)  # message name -> frames written
    received: Counter = field(default_factory=Counter)  # message name -> frames decoded
    captured_rx: Counter = field(default_factory=Counter)  # message name -> frames the bench received in the capture
    acked: int = 0
    nacked: int = 0
    unanswered: int = 0
    nacks: Counter = field(default_factory=Counter)  # "MESSAGE: ERROR" -> count
    write_stalls: int = 0  # writes the port did not take whole within 50 ms
    decoder_errors: int = 0


@dataclass
class PlaybackResult:
    """What :func:`play_capture` sent and got back. ``commands``: frames expecting an ACK/NACK or IDENT, counted
    once however often the capture resent them; ``samples_*``: the replayed stream's GYRO_SAMPLEs compared, tick by
    tick, with the capture's first stream (equal in lockstep with the same seed and config; near in real time)."""

    capture: Path
    ports: dict[str, str]
    timing: str
    links: dict[str, LinkPlayback]
    frames_sent: int
    frames_in_capture: int
    commands: int
    answered: int
    stream_started: bool
    samples: int
    samples_compared: int
    samples_equal: int
    samples_lost: int  # samples a write was timed from that the replay never received
    first_differing_tick: int  # the first tick of the first stream whose sample differs from the capture's, -1: none
    loop_timing: dict[str, int]  # ticks reported, missing (0xFFFF), late_total and missing_total of the last report
    drive_enabled_seen: bool  # a DRIVE_STATUS said an axis was enabled
    drive_last_tick: int  # DRIVE_STATUS last_tick: the last DRIVE_CMD the driver applied
    stopped: str  # "" when the capture played to its end, else why the replay stopped early
    safe_end: list[str]  # what the replay sent at the end to leave the boards safe
    duration_s: float
    lateness_us: dict[str, float]  # how late the writes went out against their schedule: p50, p99, max
    record: Path | None = None  # the replay's own capture (what it sent and received), if asked for
    emulator: dict[str, Any] | None = None  # the fresh emulator replay_capture started: config, clock, seed

    def as_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in vars(self).items() if k != "links"}
        out["capture"], out["record"] = str(self.capture), str(self.record) if self.record else None
        out["links"] = {name: {"sent": dict(lp.sent), "received": dict(lp.received),
                               "captured_rx": dict(lp.captured_rx), "acked": lp.acked, "nacked": lp.nacked,
                               "unanswered": lp.unanswered, "nacks": dict(lp.nacks), "write_stalls": lp.write_stalls,
                               "decoder_errors": lp.decoder_errors} for name, lp in self.links.items()}
        return out


class _Port:
    """One link's port: pyserial opens it (baud rate, raw mode), the fd does the rest."""

    def __init__(self, name: str, path: str, baudrate: int) -> None:
        import serial

        self.name = name
        self.path = path
        try:
            self.ser = serial.Serial(path, baudrate=baudrate, timeout=0, exclusive=True)
            set_exclusive(self.ser.fd, True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise ReplayError(f"{name}: cannot open {path}: {exc}") from None
        self.ser.reset_input_buffer()
        self.fd: int = self.ser.fd
        os.set_blocking(self.fd, False)

    def write(self, data: bytes, give_up_s: float = 0.05) -> int:
        """Write all of ``data`` unless the port stays full ``give_up_s``; returns the bytes written."""
        view, done = memoryview(data), 0
        deadline = time.monotonic() + give_up_s
        while done < len(data):
            try:
                done += os.write(self.fd, view[done:])
            except BlockingIOError:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                select.select((), (self.fd,), (), left)
            except OSError:
                break
        return done

    def close(self) -> None:
        with contextlib.suppress(OSError):
            set_exclusive(self.fd, False)
        with contextlib.suppress(Exception):
            self.ser.close()


@dataclass
class _Captured:
    """What a playback needs to know of a capture before it starts (one streamed pass): the links the bench sent
    on and how many frames, the frames it received by link and name, a CRC-32 of each sample of the first stream
    by tick, and the header. The writes themselves are streamed again while playing (:func:`_writes`)."""

    tx_frames: Counter  # link -> frames the bench sent on it (its LOCKSTEP_ACKs aside)
    acknowledged: set[str]  # links the bench acknowledged in lockstep: the replay acknowledges on them too
    rx_counts: dict[str, Counter]
    samples: array
    meta: dict[str, Any]


class _Streams:
    """Numbers the streams of GYRO_SAMPLE (a stream that starts again at tick 0 is the next one), so a sample is
    known by (stream, tick) in the capture and in the replay alike."""

    def __init__(self) -> None:
        self.stream = -1
        self.last_tick: int | None = None

    def key(self, tick: int) -> tuple[int, int]:
        if self.last_tick is None or tick < self.last_tick or (tick == 0 and self.last_tick != 0):
            self.stream += 1
        self.last_tick = tick
        return self.stream, tick


def _scan_capture(path: Path) -> _Captured:
    reader = CaptureReader(path)
    tx_dec = {name: link_decoder(name, "tx") for name in reader.links}
    rx_dec = {name: link_decoder(name, "rx") for name in reader.links}
    tx_frames: Counter = Counter()
    acknowledged: set[str] = set()
    rx_counts: dict[str, Counter] = {name: Counter() for name in reader.links}
    samples = array("q")
    streams = _Streams()
    for rec in time_ordered(reader):
        if rec.direction == "tx":
            for f in tx_dec[rec.link].feed(rec.data):
                if type(f.message) is LockstepAck:
                    acknowledged.add(rec.link)
                else:
                    tx_frames[rec.link] += 1
        elif rec.direction == "rx":
            for f in rx_dec[rec.link].feed(rec.data):
                msg = f.message
                rx_counts[rec.link][_NAMES[_ID[type(msg)]]] += 1
                if type(msg) is GyroSample:
                    key = streams.key(msg.tick)
                    if key[0] == 0 and msg.tick == len(samples):
                        samples.append(_sample_key(msg))
    if reader.end == "corrupt":
        raise ReplayError(f"{path}: {reader.problem}")
    return _Captured(+tx_frames, acknowledged, rx_counts, samples, reader.meta)


def _writes(path: Path, links: set[str]) -> Iterator[_Tx]:
    """The capture's writes on ``links`` in time order, each timed from the last sample the bench had received
    before it (streamed: memory stays bounded whatever the capture's length). When a sample came after the last
    write (a capture cut mid-run), a last ``_Tx`` with ``end`` set names it: the board's answer to that write."""
    reader = CaptureReader(path)
    tx_dec = {name: link_decoder(name, "tx") for name in links}
    servo = link_decoder("servo", "rx")
    streams = _Streams()
    last: tuple[int, int] | None = None
    last_t = prev_t = 0
    first: int | None = None
    tail: _Tx | None = None  # the first sample after the latest write
    for rec in time_ordered(reader):
        if rec.direction == "rx" and rec.link == "servo":
            for f in servo.feed(rec.data):
                if type(f.message) is GyroSample:
                    last, prev_t, last_t = streams.key(f.message.tick), last_t, rec.t_ns
                    if tail is None and first is not None:
                        tail = _Tx(rec.t_ns, "", b"", [], last, 0, last_t - prev_t if prev_t else 0, end=True)
        elif rec.direction == "tx" and rec.link in links:
            # the bench's LOCKSTEP_ACKs answered the captured boards' frames: the player acknowledges its own
            frames = [(_ID[type(f.message)], f.seq, f.message) for f in tx_dec[rec.link].feed(rec.data)
                      if type(f.message) is not LockstepAck]
            if not frames:  # the bench writes each frame on its own: a write of acknowledgements only
                continue
            tail = None
            if first is None:
                first = rec.t_ns
            if last is None:
                yield _Tx(rec.t_ns, rec.link, rec.data, frames, None, rec.t_ns - first, 0)
            else:
                gap = last_t - prev_t if prev_t else 0
                yield _Tx(rec.t_ns, rec.link, rec.data, frames, last, rec.t_ns - last_t, gap)
    if tail is not None:
        yield tail


def _sample_key(g: GyroSample) -> int:
    return zlib.crc32(repr(tuple(g)).encode())


class CapturePlayer:
    """Plays one capture's host-side frames to ``ports`` (link name -> device path); see :func:`play_capture`."""

    def __init__(self, capture: Path, ports: Mapping[str, str], *, baudrate: int = 921_600,
                 timing: Timing = "samples", watchdog_s: float = WATCHDOG_S, linger_s: float = LINGER_S,
                 record_dir: Path | None = None, links: set[str] | None = None) -> None:
        from hil.link import find_capture

        if timing not in ("samples", "clock"):
            raise ReplayError(f"timing {timing!r}: samples or clock")
        self.capture = find_capture(Path(capture))
        cap = _scan_capture(self.capture)
        self.meta = cap.meta
        used = set(cap.tx_frames)
        self.link_names = sorted(used if links is None else used & set(links))
        missing = [name for name in self.link_names if name not in ports]
        if missing:
            raise ReplayError(f"no port for link(s) {', '.join(missing)} (the capture sent on "
                              f"{', '.join(self.link_names)})")
        self.frames_in_capture = sum(cap.tx_frames[name] for name in self.link_names)
        if not self.frames_in_capture:
            raise ReplayError(f"{self.capture}: the capture holds nothing the bench sent")
        self.ports = {name: str(ports[name]) for name in self.link_names}
        self.baudrate = baudrate
        self.timing = timing
        self.watchdog_s = watchdog_s
        self.linger_s = linger_s
        self.record_dir = record_dir
        self.captured_samples = cap.samples
        # the bench acknowledged on these links (a lockstep world waits for it): the player does as it did
        self._acknowledge = {name: Encoder(Board.HOST) for name in cap.acknowledged & set(self.link_names)}
        self.links = {name: LinkPlayback(captured_rx=cap.rx_counts.get(name, Counter())) for name in self.link_names}
        self._stop = threading.Event()
        self._wake_r = self._wake_w = -1
        self._sample_rx: dict[tuple[int, int], int] = {}  # (stream, tick) -> when the replay received it
        self._sample_order: deque[tuple[int, int]] = deque()  # its keys, oldest first: SAMPLE_TIMES_KEPT at most
        self._forgotten: tuple[tuple[int, int], int] | None = None  # the newest sample whose time was let go
        self._latest: tuple[int, int] | None = None
        self._streams = _Streams()
        self._first_wait: int | None = None
        self.stopped = ""
        self.first_sample_rx: int | None = None
        self.last_sample_rx = 0
        self.samples = self.samples_compared = self.samples_equal = self.samples_lost = 0
        self.first_differing_tick = -1
        self.timing_report = {"ticks_reported": 0, "missing": 0, "late_total": 0, "missing_total": 0}
        self.drive_enabled_seen = False
        self.drive_last_tick = -1
        self._expect: set[tuple[str, int, int]] = set()  # (link, msg_id, seq): frames that expect a reply
        self._answered: set[tuple[str, int, int]] = set()
        self._last_seq: dict[str, int] = {}
        self._state = {"enabled": False, "streaming": False, "swinging": False}
        self.lateness = Quantiles()  # how late each write went out against its schedule, ns
        self.safe_end: list[str] = []
        self.record: Capture | None = None

    # --- control ---------------------------------------------------------------------------------------------

    def stop(self, reason: str = "stopped") -> None:
        """Stop sending captured frames (any thread); the replay then leaves the boards safe."""
        if not self.stopped:
            self.stopped = reason
        self._stop.set()
        if self._wake_w >= 0:
            with contextlib.suppress(OSError):
                os.write(self._wake_w, b"x")

    def run(self) -> PlaybackResult:
        """Open the ports, play in a thread of its own, return what came of it. Ctrl-C stops it safely."""
        ports: dict[str, _Port] = {}
        t0 = time.monotonic()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        claims: PortClaims | None = None
        try:
            try:  # owned, as a session owns its ports: a port another bench holds is refused by name
                claims = claim_ports({name: self.ports[name] for name in self.link_names}, f"replay {self.capture}")
            except PortUnavailable as exc:
                raise ReplayError(str(exc)) from None
            for name in self.link_names:
                ports[name] = _Port(name, self.ports[name], self.baudrate)
            if self.record_dir is not None:
                self.record = Capture.create(self.record_dir, f"replay-{self.capture.stem}",
                                             links=self.link_names, meta={"replay_of": str(self.capture)})
            player = threading.Thread(target=self._main, args=(ports,), name="hil-replay", daemon=True)
            player.start()
            try:
                while player.is_alive():
                    player.join(0.1)
            except KeyboardInterrupt:
                self.stop("interrupted")
                player.join(5.0)
        finally:
            for port in ports.values():
                port.close()
            if claims is not None:
                claims.release()
            if self.record is not None:
                self.record.close()
            for fd in (self._wake_r, self._wake_w):
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._wake_r = self._wake_w = -1
        for key in self._expect - self._answered:
            self.links[key[0]].unanswered += 1
        lat = self.lateness
        return PlaybackResult(
            capture=self.capture, ports=dict(self.ports), timing=self.timing, links=self.links,
            frames_sent=sum(sum(lp.sent.values()) for lp in self.links.values()),
            frames_in_capture=self.frames_in_capture,
            commands=len(self._expect), answered=len(self._answered),
            stream_started=self.first_sample_rx is not None, samples=self.samples,
            samples_compared=self.samples_compared, samples_equal=self.samples_equal, samples_lost=self.samples_lost,
            first_differing_tick=self.first_differing_tick,
            loop_timing=dict(self.timing_report), drive_enabled_seen=self.drive_enabled_seen,
            drive_last_tick=self.drive_last_tick, stopped=self.stopped, safe_end=self.safe_end,
            duration_s=round(time.monotonic() - t0, 3),
            lateness_us={"p50": lat.quantile(0.5) / 1e3, "p99": lat.quantile(0.99) / 1e3,
                         "max": lat.max / 1e3 if lat.count else math.nan},
            record=None if self.record is None else self.record.path)

    # --- the player thread: pacing and reading in one loop -------------------------------------------------------

    def _main(self, ports: dict[str, _Port]) -> None:
        self._ports = ports
        self._decoders = {name: link_decoder(name, "rx") for name in ports}
        self._by_fd = {port.fd: name for name, port in ports.items()}
        self._fds = [*self._by_fd, self._wake_r]
        try:
            self._play(ports)
        except Exception as exc:  # whatever happened, the boards are left safe
            self.stop(f"replay failed: {type(exc).__name__}: {exc}")
        finally:
            self._safe_end(ports)
            give_up = time.monotonic_ns() + int(self.linger_s * 1e9)  # the replies still due
            self._serve(give_up, lambda: self._expect <= self._answered, stoppable=False)
            for name, dec in self._decoders.items():
                self.links[name].decoder_errors = dec.counters.errors()

    def _serve(self, until_ns: int, done: Any = None, *, stoppable: bool = True) -> bool:
        """Read and handle what the boards send until ``time.monotonic_ns() >= until_ns`` or ``done()`` holds (True
        then). Sleeps in select() (which wakes for incoming bytes, read and stamped as they come) to SPIN_S before
        ``until_ns``, then spins, still polling the ports: a write is timed to tens of microseconds."""
        spin_ns = int(SPIN_S * 1e9)
        fds, wake, by_fd = self._fds, self._wake_r, self._by_fd
        while True:
            if done is not None and done():
                return True
            left = until_ns - time.monotonic_ns()
            if left <= 0 or (stoppable and self._stop.is_set()):
                return False
            timeout = min((left - spin_ns) / 1e9, 0.05) if left > spin_ns else 0.0
            try:
                ready = select.select(fds, (), (), timeout)[0]
            except (OSError, ValueError):
                return False
            for fd in ready:
                if fd == wake:
                    with contextlib.suppress(OSError):
                        os.read(wake, 64)
                    continue
                try:
                    data = os.read(fd, 65536)
                except BlockingIOError:
                    continue
                except OSError:
                    fds.remove(fd)
                    continue
                t_ns = time.monotonic_ns()
                name = by_fd[fd]
                if self.record is not None:
                    self.record.link(name).rx(data, t_ns)
                last = None
                for frame in self._decoders[name].feed(data):
                    self._on_frame(name, frame.message, t_ns)
                    last = frame
                if last is not None and name in self._acknowledge:
                    self._ack(name, last.seq)

    def _ack(self, link: str, seq: int) -> None:
        """LOCKSTEP_ACK of what the player has handled on ``link`` up to ``seq`` (docs/protocol.md, "Host liveness"),
        numbered apart from the captured frames it plays."""
        data = self._acknowledge[link].encode(LockstepAck(seq), Board[link.upper()])
        port = self._ports[link]
        if port.write(data) and self.record is not None:
            self.record.link(link).tx(data)

    def _play(self, ports: dict[str, _Port]) -> None:
        first: int | None = None
        start = time.monotonic_ns()
        for tx in _writes(self.capture, set(self.link_names)):
            if first is None:
                first = tx.t_ns
            if self._stop.is_set():
                return
            if tx.end:  # the capture's end: the sample that answered its last write, before the safe end
                if tx.anchor is not None and self._state["streaming"]:
                    self._await_tail(tx.anchor, tx.gap_ns)
                return
            if self.timing == "samples" and tx.anchor is not None:
                t_anchor = self._await_sample(tx.anchor, tx.gap_ns)
                if t_anchor is None:
                    return
                due = t_anchor + tx.offset_ns
                self._serve(due)
            else:
                due = start + (tx.t_ns - first)
                self._serve(due)
                if tx.anchor is not None and self.first_sample_rx is None:  # clock timing: the stream must start
                    if not self._await_first():
                        return
                    waited = max(0, time.monotonic_ns() - due)  # the schedule moves by the wait
                    start += waited
                    due += waited
                if tx.anchor is not None and not self._stream_alive(tx):
                    return
            if self._stop.is_set():
                return
            self.lateness.add(time.monotonic_ns() - due)
            self._send(ports[tx.link], tx.link, tx.data, tx.frames)

    def _await_tail(self, key: tuple[int, int], gap_ns: int) -> None:
        """After the last write: wait for the sample ``key`` the capture received after it (or a later one), so the
        safe end cannot reach the board before the step that answers that write and change or suppress the sample.
        Gives up quietly after the capture's gap before it plus ``watchdog_s``: the capture is played either way."""
        give_up = self.last_sample_rx + gap_ns + int(self.watchdog_s * 1e9)
        self._serve(give_up, lambda: self._latest is not None and self._latest >= key)

    def _await_first(self) -> bool:
        """Clock timing: wait up to FIRST_SAMPLE_WAIT_S for the stream's first sample; False (stopped) if none."""
        give_up = time.monotonic_ns() + int(FIRST_SAMPLE_WAIT_S * 1e9)
        if self._serve(give_up, lambda: self.first_sample_rx is not None):
            return True
        if not self._stop.is_set():
            self.stop("no GYRO_SAMPLE: the servo board did not start its stream")
        return False

    def _stream_alive(self, tx: _Tx) -> bool:
        """Clock timing's watchdog, before a write the capture made ``tx.offset_ns`` after a sample: False (and the
        replay stops) when the replay's stream has been silent longer than the capture's was at this write, plus
        the capture's gap before that sample, plus ``watchdog_s``. Not while the replay itself has idled the
        stream (a replayed SERVO_MODE IDLE)."""
        if not self._state["streaming"] or self.first_sample_rx is None:
            return True
        silence = time.monotonic_ns() - self.last_sample_rx
        if silence <= tx.offset_ns + tx.gap_ns + int(self.watchdog_s * 1e9):
            return True
        self.stop(f"watchdog: no GYRO_SAMPLE for {silence / 1e6:.0f} ms (the capture's last sample was "
                  f"{tx.offset_ns / 1e6:.0f} ms old at this write)")
        return False

    def _await_sample(self, key: tuple[int, int], gap_ns: int) -> int | None:
        """When the replay received the sample ``key``. If a later one came instead, it was lost: the latest
        arrival stands in. None (and the replay stops) when none came in time: the first within
        FIRST_SAMPLE_WAIT_S, later ones within the capture's own gap before it plus ``watchdog_s``."""
        while True:
            t = self._sample_rx.get(key)
            if t is not None:
                while self._sample_order and self._sample_order[0] < key:  # older ones are never awaited again
                    self._sample_rx.pop(self._sample_order.popleft(), None)
                return t
            if self._forgotten is not None and key <= self._forgotten[0]:  # came so long ago its time was let go
                return self._forgotten[1]  # a later sample's time: the write is overdue either way
            if self._stop.is_set():
                return None
            if self._latest is not None and self._latest > key:
                self.samples_lost += 1
                return self.last_sample_rx
            now = time.monotonic_ns()
            if self.first_sample_rx is None:
                if self._first_wait is None:
                    self._first_wait = now + int(FIRST_SAMPLE_WAIT_S * 1e9)
                give_up = self._first_wait
                why = "no GYRO_SAMPLE: the servo board did not start its stream"
            else:
                give_up = self.last_sample_rx + gap_ns + int(self.watchdog_s * 1e9)
                why = f"watchdog: no GYRO_SAMPLE for {(now - self.last_sample_rx) / 1e6:.0f} ms (stream " \
                      f"{key[0]}, tick {key[1]} awaited)"
            if now >= give_up:
                self.stop(why)
                return None
            self._serve(give_up, lambda: key in self._sample_rx or (self._latest is not None and self._latest > key))

    def _send(self, port: _Port, link: str, data: bytes, frames: list[tuple[int, int, Any]]) -> None:
        lp = self.links[link]
        for msg_id, seq, msg in frames:  # registered before the write: a reply may come at once
            if msg_id in _REPLY_ACK or msg_id == _ID[IdentRequest]:
                self._expect.add((link, msg_id, seq))
            self._last_seq[link] = seq
            self._track_state(msg)
        n = port.write(data)
        if self.record is not None and n:
            self.record.link(link).tx(data[:n])
        if n < len(data):
            lp.write_stalls += 1
            return
        for msg_id, _, _ in frames:
            lp.sent[_NAMES[msg_id]] += 1

    def _track_state(self, msg: Any) -> None:
        kind, st = type(msg), self._state
        if kind is DriveEnable:
            st["enabled"] = True
        elif kind is DriveDisable:
            st["enabled"] = False
        elif kind is ServoMode:
            st["streaming"] = msg.mode == StreamMode.STREAM
        elif kind is HexapodStart:
            st["swinging"] = True
        elif kind is HexapodStop:
            st["swinging"] = False

    def _safe_end(self, ports: dict[str, _Port]) -> None:
        """Disable, stop and idle whatever the replay left on: new frames, numbered after the link's last."""
        plan = (("enabled", "driver", DriveDisable(AxisMask.BOTH), Board.DRIVER),
                ("swinging", "hexapod", HexapodStop(), Board.HEXAPOD),
                ("streaming", "servo", ServoMode(StreamMode.IDLE), Board.SERVO))
        for flag, link, msg, dst in plan:
            if not self._state[flag] or link not in ports:
                continue
            enc = Encoder(Board.HOST)
            enc.next_seq = self._last_seq.get(link, -1) + 1
            seq = enc.next_seq
            data = enc.encode(msg, dst)
            self.safe_end.append(_NAMES[_ID[type(msg)]])
            with contextlib.suppress(OSError):
                self._send(ports[link], link, data, [(_ID[type(msg)], seq, msg)])

    def _on_frame(self, link: str, msg: Any, t_ns: int) -> None:
        lp = self.links[link]
        kind = type(msg)
        lp.received[_NAMES[_ID[kind]]] += 1
        if kind is GyroSample:
            key = self._streams.key(msg.tick)
            self.samples += 1
            if key[0] == 0 and msg.tick < len(self.captured_samples):
                self.samples_compared += 1
                if _sample_key(msg) == self.captured_samples[msg.tick]:
                    self.samples_equal += 1
                elif self.first_differing_tick < 0:
                    self.first_differing_tick = msg.tick
            self.last_sample_rx = t_ns
            if self.first_sample_rx is None:
                self.first_sample_rx = t_ns
            self._sample_rx[key] = t_ns
            self._sample_order.append(key)
            self._latest = key
            while len(self._sample_order) > SAMPLE_TIMES_KEPT:  # bounded, whether or not writes await them
                old = self._sample_order.popleft()
                t_old = self._sample_rx.pop(old, None)
                if t_old is not None:
                    self._forgotten = (old, t_old)
        elif kind is Ack or kind is Nack:
            key = (link, msg.msg_id, msg.seq)
            err = "" if kind is Ack else f"{_NAMES.get(msg.msg_id, hex(msg.msg_id))}: " \
                                         f"{getattr(msg.error, 'name', msg.error)}"
            if key in self._expect and key not in self._answered:
                self._answered.add(key)
                if kind is Ack:
                    lp.acked += 1
                else:
                    lp.nacked += 1
            if err:  # also a NACK to a frame that expects none (DRIVE_CMD while the driver is disabled)
                lp.nacks[err] += 1
        elif kind is Ident:
            waiting = sorted(k for k in self._expect - self._answered if k[0] == link and k[1] == _ID[IdentRequest])
            if waiting:
                self._answered.add(waiting[0])
                lp.acked += 1
        elif kind is LoopTiming:
            t = self.timing_report
            t["ticks_reported"] += len(msg.latency_us)
            t["missing"] += sum(1 for v in msg.latency_us if v == NO_LATENCY_US)
            t["late_total"], t["missing_total"] = msg.late_total, msg.missing_total
        elif kind is DriveStatus:
            self.drive_last_tick = msg.last_tick
            if msg.enabled:
                self.drive_enabled_seen = True
            if msg.faults & 0x03:
                self.stop(f"driver fault {msg.faults:#04x}: overcurrent latched")


def play_capture(capture: Path, ports: Mapping[str, str], **kwargs: Any) -> PlaybackResult:
    """Play ``capture``'s host-side frames to ``ports`` (link name -> serial device or emulator pty) and count what
    comes back (see the module docstring). ``timing="samples"`` (default): a write that followed a GYRO_SAMPLE in the
    capture goes out as long after the replayed stream's sample of the same tick, so the board sees the same
    answers to the same samples even where it runs at another pace (lockstep); ``"clock"``: every write at its
    original time from the first (the stream's start awaited, as in samples timing, the schedule moving by that
    wait). Either way the replay stops when the stream does (``watchdog_s`` beyond the capture's own silence) and
    leaves the boards safe. Other keywords: ``baudrate``, ``watchdog_s``, ``linger_s``, ``record_dir`` (write
    the replay's own capture there), ``links`` (only these links). Blocks until done; Ctrl-C stops it, leaving the
    boards safe."""
    return CapturePlayer(capture, ports, **kwargs).run()


def ports_from_file(path: Path) -> dict[str, str]:
    """A ports file (the emulator's ``--ports-file``: JSON ``{"servo": path, ...}``) as link -> path (its
    ``control`` socket left out). ReplayError naming ``--ports-file`` and the file otherwise."""
    import json

    from hil.config import read_text_file

    try:
        text = read_text_file(path, 1 << 20)
    except ValueError as exc:  # names the file
        raise ReplayError(f"--ports-file {exc}") from None
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise ReplayError(f"--ports-file {path}: not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ReplayError(f"--ports-file {path}: not a ports file (a JSON object of link: path)")
    return {str(k): str(v) for k, v in data.items() if k != "control"}


def resolve_ports(ports: Mapping[str, str] | Iterable[str] | None = None,
                  ports_file: Path | str | None = None) -> dict[str, str]:
    """The boards' ports (link name -> device path): ``ports_file``'s (:func:`ports_from_file`), then ``ports`` over
    them, a mapping or ``"LINK=PATH"`` strings (the command's ``--port``). ReplayError naming the option otherwise."""
    out: dict[str, str] = {}
    if ports_file is not None:
        out.update(ports_from_file(Path(ports_file)))
    if ports is None:
        return out
    if isinstance(ports, str):
        raise ReplayError(f"--port: {ports!r}: give a list of LINK=PATH, or a dict of link: path")
    items = [f"{k}={v}" for k, v in ports.items()] if isinstance(ports, Mapping) else [str(p) for p in ports]
    for item in items:
        name, eq, path = item.partition("=")
        if not eq or name not in LINKS or not path:
            raise ReplayError(f"--port: {item!r} is not LINK=PATH with LINK servo, driver, image or hexapod")
        out[name] = path
    return out


@dataclass(frozen=True)
class EmulatorSettings:
    """What a fresh emulator for a playback is started with (:func:`emulator_settings`)."""

    config: Path | None  # None: the emulator's default config
    clock: str  # lockstep | realtime
    seed: int

    def as_dict(self) -> dict[str, Any]:
        return {"config": None if self.config is None else str(self.config), "clock": self.clock, "seed": self.seed}


def emulator_settings(meta: Mapping[str, Any], *, clock: str | None = None, seed: int | None = None,
                      config: Path | str | None = None) -> EmulatorSettings:
    """The fresh emulator a capture with header ``meta`` is played to: ``clock``, ``seed`` and ``config`` where given,
    else what the header recorded (``emulator_clock`` or ``session_clock``, ``emulator_seed`` or ``seed``,
    ``emulator_config``; lockstep, 0 and the default config for a capture that says nothing). ReplayError naming the
    option for a clock or seed that is not one, or a config file that does not exist here."""
    if clock is None:
        clock = str(meta.get("emulator_clock") or meta.get("session_clock") or "lockstep")
        if clock not in EMULATOR_CLOCKS:
            raise ReplayError(f"the capture's session clock {clock!r} is not one the emulator runs: give --clock "
                              f"{' or '.join(EMULATOR_CLOCKS)}")
    elif clock not in EMULATOR_CLOCKS:
        raise ReplayError(f"--clock: {clock!r} is not {' or '.join(EMULATOR_CLOCKS)}")
    if seed is None:
        recorded = meta.get("emulator_seed", meta.get("seed"))
        try:
            seed = int(recorded or 0)
        except (TypeError, ValueError):
            raise ReplayError(f"the capture's seed {recorded!r} is not an integer: give --seed") from None
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ReplayError(f"--seed: {seed!r} is not an integer >= 0")
    path: Path | None = None
    if config is not None:
        path = Path(config)
        if not path.is_file():
            raise ReplayError(f"emulator config {path}: no such file")
    elif meta.get("emulator_config"):
        path = Path(str(meta["emulator_config"]))
        if not path.is_file():
            raise ReplayError(f"the captured emulator config {path} is not a file here: start an emulator with it "
                              f"and give its ports (--ports-file)")
    return EmulatorSettings(path, clock, seed)


def replay_capture(capture: Path | str, *, ports: Mapping[str, str] | Iterable[str] | None = None,
                   ports_file: Path | str | None = None, clock: str | None = None, seed: int | None = None,
                   timing: Timing = "samples", record_dir: Path | str | None = None, links: Iterable[str] | None = None,
                   emulator_config: Path | str | None = None, **kwargs: Any) -> PlaybackResult:
    """Play ``capture`` (a ``.hilcap`` file, or the directory holding one) back at the boards, as ``hil replay
    CAPTURE --to-emulator`` does. The boards: ``ports`` (a mapping link -> path, or ``"LINK=PATH"`` strings) over
    ``ports_file``'s (the emulator's ``--ports-file``); with neither, a fresh emulator is started for the playback
    and stopped after it, with ``clock``, ``seed`` and ``emulator_config`` where given, else the capture's
    (:func:`emulator_settings`; the result's ``emulator`` says which). ``timing``, ``record_dir`` (where the replay's
    own capture goes), ``links`` (only these) and the other keywords as :func:`play_capture`. Bad input raises
    ReplayError or CaptureError (ValueErrors, one line naming the option) before anything is sent."""
    from hil.link import find_capture

    if timing not in TIMINGS:
        raise ReplayError(f"--timing: {timing!r} is not {' or '.join(TIMINGS)}")
    path = find_capture(Path(capture))
    named = resolve_ports(ports, ports_file)
    if record_dir is not None:
        from hil.config import require_writable_dir

        try:
            require_writable_dir(Path(record_dir), "--out")
        except ValueError as exc:
            raise ReplayError(str(exc)) from None
    options = {"timing": timing, "record_dir": None if record_dir is None else Path(record_dir),
               "links": None if links is None else set(links), **kwargs}
    if named:
        if clock is not None or seed is not None or emulator_config is not None:
            raise ReplayError("--clock and --seed start a fresh emulator: not with --port or --ports-file")
        return play_capture(path, named, **options)
    settings = emulator_settings(CaptureReader(path).meta, clock=clock, seed=seed, config=emulator_config)
    from hil.link import LinkError
    from hil.session import EmulatorProcess

    emulator = EmulatorProcess(settings.config, clock=settings.clock, seed=settings.seed)
    try:
        try:
            started = emulator.start()
        except LinkError as exc:
            raise ReplayError(str(exc)) from None
        result = play_capture(path, {k: v for k, v in started.items() if k != "control"}, **options)
    finally:
        emulator.stop()
    result.emulator = settings.as_dict()
    return result


def write_playback_json(result: PlaybackResult, out_dir: Path | str) -> Path:
    """``replay-<capture stem>.json`` in ``out_dir``: ``result.as_dict()`` as strict JSON; returns its path."""
    import json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"replay-{result.capture.stem}.json"
    path.write_text(json.dumps(json_safe(result.as_dict()), indent=1) + "\n")
    return path
