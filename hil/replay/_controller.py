"""Controller replay (docs/capture.md): a logged session through another controller offline.

**Controller replay** (:func:`replay_log`, ``hil replay LOG``): the session's 1 kHz cycle
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

:func:`replay_log` is what ``hil replay LOG`` calls (through hil.api): everything but the parsing and printing,
bad input refused with a ReplayError (a ValueError) naming the parameter.
"""

from __future__ import annotations

import json
import math
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import TypeAdapter

from hil.analysis import drive_ripple, json_safe
from hil.config import (
    ConfigError,
    ControllerConfig,
    Excitation,
    SafetyConfig,
    StartPoseConfig,
    SwingProfile,
    TrackingConfig,
    load_model,
    parse_yaml,
    require_regular_file,
)
from hil.control.cycle import DriveStep
from hil.control.imbalance_feed import ImbalanceFeed, ProfileClock
from hil.control.loops import TrackingLoop
from hil.control.registry import build_controller, controller_params
from hil.control.start_pose import REACHED, StartPose
from hil.log import read_log

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
    start_pose: Any
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

    try:
        data = read_log(path)
    except Exception as exc:
        raise ReplayError(f"{path}: cannot read the log: {exc}") from None
    loop = data.groups.get("loop") or {}
    if not loop or not len(loop.get("tick", ())):
        raise ReplayError(f"{path}: the log has no loop samples to replay")
    config = data.attrs.get("config")
    if not isinstance(config, dict):
        config = {}
    notes: list[str] = []
    tracking = _section(TrackingConfig, config.get("tracking"), notes, "tracking")
    # a log written before sessions had a start pose phase had none
    start_pose = _section(StartPoseConfig, config.get("start_pose", {"enabled": False}), notes, "start_pose")
    safety = _section(SafetyConfig, config.get("safety"), notes, "safety")
    profile = _section(SwingProfile, config.get("profile"), notes, "profile")
    excitation = None
    if config.get("excitation"):


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
        frames=frames, poses=poses, tracking=tracking, start_pose=start_pose, safety=safety, excitation=excitation,
        segments=profile.protocol_segments(), duration_s=float(config.get("duration_s") or math.inf),
        logged=ControllerSpec(name, params), gyro_inexact=inexact)


def _run(inp: _Inputs, spec: ControllerSpec) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """The session's cycle (ControlLoop.on_sample, armed; its drive step is the shared hil.control.cycle.DriveStep)
    over the logged rows, open loop. Returns the per-tick arrays and the input checks."""

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
    step = DriveStep(ctrl_az, ctrl_el, feed, clock, max_drive_counts=inp.safety.max_drive_counts,
                     max_slew_counts=inp.safety.max_slew_counts)
    n = inp.n
    out: dict[str, np.ndarray] = {key: np.zeros(n) for key in
                                  ("az_fb", "el_fb", "az_dist", "el_dist", "ff_el", "az_cmd", "el_cmd")}
    drive_az, drive_el = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    pending: deque[tuple[int, int]] = deque()  # (board time to use it, us; index into inp.frames)
    frames, poses = inp.frames, inp.poses
    fi = pi = 0
    t_list = inp.t_s.tolist()
    t0 = t_list[0]
    t_rel = 0.0
    pose = StartPose(inp.start_pose) if inp.start_pose.enabled else None
    run_t0 = 0.0
    gy, gz = inp.gyro["y"], inp.gyro["z"]
    logged_az, logged_el = inp.drive["az"], inp.drive["el"]
    cmd32_az, cmd32_el = inp.cmd_logged["az"].tolist(), inp.cmd_logged["el"].tolist()
    f32 = np.float32
    checks: Counter[str] = Counter()
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
        if pose is not None and pose.judge(t_abs, inp.az_deg[k], inp.el_deg[k]) == REACHED:
            pose, run_t0 = None, t_rel  # the run starts at this sample, its tracking from fresh loops
            checks["start_pose_rows"] = k
            track_az.reset()
            track_el.reset()
        if pose is not None:  # the start pose phase's position hold
            cmd_az, cmd_el = pose.rate_cmds_dps(inp.az_deg[k], inp.el_deg[k])
        else:
            cmd_az = track_az.rate_cmd_dps(t_abs) if tracking else 0.0
            cmd_el = track_el.rate_cmd_dps(t_abs) if tracking else 0.0
            if exc is not None:
                if excite_el:
                    cmd_el += exc.rate_dps(t_rel - run_t0)
                else:
                    cmd_az += exc.rate_dps(t_rel - run_t0)
        if f32(cmd_az) != cmd32_az[k]:  # the rebuilt command is not the one the session used: take the logged one
            checks["command_mismatches_az"] += 1
            cmd_az = cmd32_az[k]
        if f32(cmd_el) != cmd32_el[k]:
            checks["command_mismatches_el"] += 1
            cmd_el = cmd32_el[k]
        drive_az[k], drive_el[k] = step.step(cmd_az, cmd_el, gy[k], gz[k], az_deg=inp.az_deg[k],
                                             el_deg=inp.el_deg[k], t_s=t_rel)
        out["az_fb"][k], out["el_fb"][k] = ctrl_az.rate_fb_dps, ctrl_el.rate_fb_dps
        out["az_dist"][k], out["el_dist"][k] = ctrl_az.disturbance_counts, ctrl_el.disturbance_counts
        out["ff_el"][k], out["az_cmd"][k], out["el_cmd"][k] = step.ff_el, cmd_az, cmd_el
        step.applied(int(logged_az[k]), int(logged_el[k]))  # open loop: what the plant really got
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
        from scipy.signal import butter, sosfiltfilt  # noqa: PLC0415  (heavy: loaded only when this computation runs)

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
    as YAML (``true``, ``[1, 2]``...). ReplayError naming ``params`` for an item that is not ``k=v``."""
    out: dict[str, Any] = {}
    for item in (p.strip() for p in text.split(",")):
        if not item:
            continue
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise ReplayError(f"params={text!r}: {item!r} is not k=v")
        out[key.strip()] = _param_value(key.strip(), value.strip())
    return out


def _param_value(key: str, text: str) -> Any:
    """A number as a number (``1e-3`` too, which YAML 1.1 reads as a string), anything else as YAML reads it."""

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
        raise ReplayError(f"params: {key!r}: not a value ({type(exc).__name__})") from None


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

        try:
            cfg = load_model(ControllerConfig, path)
        except (ConfigError, ValueError, OSError) as exc:
            raise ReplayError(f"params={text!r}: {' '.join(str(exc).split())}") from None
        if controller is not None and controller != cfg.name:
            raise ReplayError(f"controller={controller!r} but {text} is a {cfg.name} controller")
        return cfg.name, dict(cfg.params)
    return controller, parse_params(text)


def replay_log(log: Path | str, controller: str | None = None,
               params: Mapping[str, Any] | str | Path | None = None, *, settle_s: float = 1.0) -> ReplayResult:
    """Replay the session log ``log`` through ``controller`` (default: the logged one, or the YAML's) with
    ``params``: a dict over the registry defaults, a ``"k=v,k=v"`` string, or a controller YAML (name and params)
    (:func:`controller_choice`); None with the logged controller: the logged parameters, with another: the registry
    defaults. Metrics over [``settle_s``, the session's duration) from the run's first sample (the first after the
    start pose phase). ReplayError (one line) for
    input that cannot be replayed; ControllerConfigError (also a ValueError) for an unknown controller or
    parameter. :func:`write_outputs` writes the plot and JSON."""

    if not isinstance(settle_s, int | float) or not math.isfinite(settle_s) or settle_s < 0:
        raise ReplayError(f"settle_s={settle_s!r}: not a finite number of seconds >= 0")
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
    t_run = t - t[checks.get("start_pose_rows", 0)]  # the run starts where the start pose phase ended
    keep = (t_run >= settle_s) & (t_run < inp.duration_s)
    if not keep.any():  # a run shorter than the settling time: the whole of it
        keep = np.ones(inp.n, dtype=bool)
    window = (float(t[keep][0]), float(t[keep][-1]))

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
    import matplotlib  # noqa: PLC0415  (heavy: loaded only when a figure is drawn)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415  (heavy: loaded only when a figure is drawn)

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

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = f"{result.log.stem}-replay-{result.replayed.name}"
    png = write_plot(result, out_dir / f"{stem}.png")
    js = out_dir / f"{stem}.json"
    js.write_text(json.dumps(json_safe(result.as_dict()), indent=1) + "\n")
    return png, js


# --- capture playback -------------------------------------------------------------------------------------------


