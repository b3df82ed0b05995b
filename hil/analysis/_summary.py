"""Session metrics from a log: what `hil report LOG` prints and what the session summary shows.

The paper's figures of merit (seed 000 Tables 1-3): the rate error's range (+-, half the
peak-to-peak) and standard deviation, the miss distance's range and standard deviation in pixels,
and the drive ripple (standard deviation of the drive, counts). Plus the loop's own health: latency
p50/p99 (bench side and as the board measured it), late and missed cycles, link errors. The run
starts where the session's start pose phase ended (its ``phase`` event; the first sample in logs without
one), and its first ``settle_s`` seconds are left out of the control metrics (the swing ramps in, the
controllers converge), as is the start pose phase itself.

On the ``lockstep`` and ``sim`` clocks the emulator waits for the bench, so the board measures no latency:
``board_latency_us`` then holds ``None`` and an ``na_reason``. Empty figures are NaN; ``json_safe``
turns them into ``None`` for JSON. ``provenance`` is what the session recorded of its software, plant and
controller (hil.log.provenance). Spans in which the table did not swing (``swing_gap`` events: the hexapod parked
itself and a recovery resumed the profile) are left out of the control metrics and listed in ``swing_gaps``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from hil.log import LogData, read_log
from hil.log.schema import LATE_US
from hil.protocol import LINKS


def _spread(x: np.ndarray) -> dict[str, float]:
    if x.size == 0:
        return {"std": float("nan"), "range_pm": float("nan"), "mean": float("nan")}
    return {"std": float(np.std(x)), "range_pm": float((np.max(x) - np.min(x)) / 2), "mean": float(np.mean(x))}


RIPPLE_WINDOW = 20  # samples (20 ms): what varies faster than this is ripple, not the swing's compensation


def drive_ripple(drive: np.ndarray) -> float:
    """Std of the drive after removing its slow part (a 20 ms moving average), counts: the paper's
    "controller output ripple" without the 1 Hz effort that cancels the swing."""
    if drive.size <= RIPPLE_WINDOW:
        return float("nan")
    slow = np.convolve(drive, np.ones(RIPPLE_WINDOW) / RIPPLE_WINDOW, mode="valid")
    fast = drive[RIPPLE_WINDOW // 2 : RIPPLE_WINDOW // 2 + slow.size] - slow
    return float(np.std(fast))


def _pct(x: np.ndarray, q: float) -> float:
    x = x[np.isfinite(x)]
    return float(np.percentile(x, q)) if x.size else float("nan")


# the links columns (hil.log.schema.LINK_COUNTERS) a link's error figure sums: every frame lost, refused or
# out of order; not duplicates or restarts (a resend or a board reset loses nothing)
LINK_ERROR_COUNTERS = ("crc_errors", "bad_frames", "frames_lost", "reordered", "rejected")


def missed_cycles(loop: dict[str, np.ndarray]) -> int:
    """Samples that never arrived: the sum of ``tick_gap``. Logs that stored it as u1 (capped at 255)
    take a saturated row's gap from the ticks instead."""
    gap = loop.get("tick_gap", np.zeros(0, dtype="u4")).astype(np.int64)
    if loop.get("tick_gap", gap).dtype == np.uint8 and gap.size > 1:
        tick = loop["tick"].astype(np.int64)
        capped = np.flatnonzero(gap[1:] == 255) + 1
        gap[capped] = np.maximum(255, tick[capped] - tick[capped - 1] - 1)
    return int(gap.sum())


def swing_gap_mask(t_s: np.ndarray, gaps: list[dict[str, Any]]) -> np.ndarray:
    """Which of the board times ``t_s`` (the loop's ``t_s``, an image's ``t_exposure_s``) fall in a span the table
    did not swing: each ``swing_gap`` event's ``from_t_s`` up to its ``to_t_s`` (to the end when None: the profile
    was not resumed)."""
    mask = np.zeros(np.shape(t_s), dtype=bool)
    for gap in gaps:
        start, end = gap.get("from_t_s"), gap.get("to_t_s")
        if isinstance(start, int | float):
            mask |= (t_s >= start) & (t_s < (end if isinstance(end, int | float) else np.inf))
    return mask


def _relative(t_s: float | None, t0: float) -> float | None:
    return None if t_s is None else round(float(t_s) - float(t0), 3)


def summarize_log(path: str | Path, settle_s: float = 1.0, *, data: LogData | None = None) -> dict[str, Any]:
    """The session's summary from its log at ``path`` (``data``: that log already read with :func:`read_log`)."""
    data = read_log(path) if data is None else data
    loop, image, timing, links = (data.groups.get(g, {}) for g in ("loop", "image", "timing", "links"))
    out: dict[str, Any] = {"log": str(path), "session": data.attrs.get("session_name", ""),
                           "controller": data.attrs.get("controller", ""), "settle_s": settle_s}
    t = loop.get("t_s", np.zeros(0))
    config = data.attrs.get("config") or {}
    run_s = float(config.get("duration_s", np.inf)) if isinstance(config, dict) else np.inf
    events = data.groups.get("events", {})
    kinds = [k.decode() if isinstance(k, bytes) else str(k) for k in events.get("kind", [])]
    details = list(events.get("detail", []))
    phases = [_detail(d) for k, d in zip(kinds, details, strict=True) if k == "phase"]
    pose = next((p for p in phases if p.get("phase") == "start_pose"), None)
    if pose is not None:
        out["start_pose"] = {key: pose.get(key) for key in ("outcome", "took_s", "from_az_deg", "from_el_deg",
                                                            "error_deg")}
    # the run starts where the start pose phase ended (the first loop row without one)
    t0 = float(pose["to_t_s"]) if pose is not None and isinstance(pose.get("to_t_s"), int | float) else (
        float(t[0]) if t.size else 0.0)
    keep = ((t - t0) >= settle_s) & ((t - t0) < run_s)  # the run itself, not the start pose or the wind-down
    out["run_from_t_s"] = t0  # board time of the run's first sample
    gaps = [_detail(d) for k, d in zip(kinds, details, strict=True) if k == "swing_gap"]
    in_gap = swing_gap_mask(t, gaps)
    keep &= ~in_gap  # spans where the table did not swing (the hexapod had parked itself) are not the swing's
    if gaps:
        out["swing_gaps"] = [{"from_s": _relative(g.get("from_t_s"), t0), "to_s": _relative(g.get("to_t_s"), t0),
                              "reason": g.get("reason")} for g in gaps]
        out["swing_gap_s"] = float(np.count_nonzero(in_gap) / 1000.0)
    out["cycles"] = int(t.size)
    out["duration_s"] = float(t[-1] - t[0]) if t.size else 0.0
    for axis in ("el", "az"):
        err = loop.get(f"rate_err_{axis}_dps", np.zeros(0))[keep]
        out[f"rate_error_{axis}_dps"] = _spread(err)
        drive = loop.get(f"drive_{axis}_counts", np.zeros(0))[keep].astype(float)
        out[f"drive_ripple_{axis}_counts"] = drive_ripple(drive)
    drive_status = data.groups.get("drive", {})
    if drive_status.get("loop_tick") is not None and drive_status["loop_tick"].size and t.size:
        rows = np.clip(np.searchsorted(loop["tick"], drive_status["loop_tick"]), 0, t.size - 1)
        run = keep[rows] & (drive_status["enabled"] > 0)
        for axis in ("el", "az"):
            amps = np.abs(drive_status[f"{axis}_current_a"][run].astype(float))
            out[f"motor_current_{axis}_a"] = {"rms": float(np.sqrt(np.mean(amps**2))) if amps.size else float("nan"),
                                              "peak": float(np.max(amps)) if amps.size else float("nan")}
    if image:
        ti = image["t_exposure_s"]
        valid = (image["track_valid"] > 0) & ((ti - t0) >= settle_s) & ((ti - t0) < run_s)
        valid &= ~swing_gap_mask(ti, gaps)
        out["frames"] = int(ti.size)
        out["frames_valid"] = int(valid.sum())
        out["miss_x_px"] = _spread(image["miss_x_px"][valid])
        out["miss_y_px"] = _spread(image["miss_y_px"][valid])
        radial = np.hypot(image["miss_x_px"][valid], image["miss_y_px"][valid])
        out["miss_radial_px_rms"] = float(np.sqrt(np.mean(radial**2))) if radial.size else float("nan")
    lat = loop.get("latency_us", np.zeros(0))
    out["latency_us"] = {"p50": _pct(lat, 50), "p99": _pct(lat, 99), "max": float(np.max(lat)) if lat.size else 0.0}
    out["late_cycles"] = int(np.sum(lat > LATE_US))
    out["missed_cycles"] = missed_cycles(loop)
    out["board_latency_us"] = board_latency(timing.get("board_latency_us", np.zeros(0)), data.attrs.get("clock"))
    errors = {}
    for name in LINKS:
        cols = [f"{name}_{c}" for c in LINK_ERROR_COUNTERS]
        errors[name] = int(sum(int(links[c][-1]) for c in cols if c in links and links[c].size))
    out["link_errors"] = errors
    out["faults"] = kinds.count("fault")
    out["fault_reasons"] = [_reason(d) for k, d in zip(kinds, details, strict=True) if k == "fault"]
    stalls = [_detail(d) for k, d in zip(kinds, details, strict=True) if k == "host_stall"]
    out["host_stalls"] = len(stalls)
    out["host_stall_max_ms"] = max((float(d.get("silent_ms", 0.0)) for d in stalls), default=0.0)
    # who was late: the bench's own watchdog look, or (emulated boards, with the grace) the emulator's clock (its
    # CLOCK_LATE) or the bytes on their way through the shared host; older logs: the bench
    out["host_stalls_emulator"] = sum(d.get("late_by") in ("emulator", "host") for d in stalls)
    # a session writes its summary event last, on every exit path it controls: without one, the bench died
    out["complete"] = "summary" in kinds
    if not out["complete"]:
        out["incomplete"] = INCOMPLETE
    provenance = data.attrs.get("provenance")
    out["provenance"] = provenance if isinstance(provenance, dict) else {}  # {} in logs written before it existed
    return out


# why a log's board-measured latency is no measurement: by the log's clock attribute, or by what the board sent
NO_BOARD_LATENCY = {
    "lockstep": "lockstep: the emulator waits for each command, so there is no board-measured latency (its boards "
                "report the modelled wire and host delay)",
    "sim": "sim: the emulated boards run in the bench's process and wait for each command, so there is no "
           "board-measured latency (they report the modelled wire and host delay)",
}
NO_BOARD_REPORT = "the servo board reported no loop timing"
NO_BOARD_COMMAND = "the servo board received no command on any tick it reported"
ZERO_BOARD_LATENCY = "the servo board reported 0 us on every tick (as an emulator in lockstep does): no measurement"


def board_latency(board: np.ndarray, clock: object = None) -> dict[str, Any]:
    """The board-measured latency's p50 / p99 / p99.9 (us) and the ticks without a command (``missing``).

    When there is no measurement, ``{"p50": None, "p99": None, "na_reason": ...}``: on the ``lockstep`` and
    ``sim`` clocks (the emulator waits for the bench, so the board measures nothing), or when the board reported
    nothing (no LOOP_TIMING rows, no tick with a command, or 0 on every tick)."""
    board = np.asarray(board)
    finite = board[np.isfinite(board)]
    reason = NO_BOARD_LATENCY.get(str(clock)) if clock is not None else None
    if reason is None and board.size == 0:
        reason = NO_BOARD_REPORT
    elif reason is None and finite.size == 0:
        reason = NO_BOARD_COMMAND
    elif reason is None and not np.any(finite):
        reason = ZERO_BOARD_LATENCY
    if reason is not None:
        return {"p50": None, "p99": None, "na_reason": reason}
    return {"p50": _pct(board, 50), "p99": _pct(board, 99), "p99.9": _pct(board, 99.9),
            "missing": int(board.size - finite.size)}


def json_safe(value: Any) -> Any:
    """``value`` (a summary) with NaN and infinities as None and numpy scalars as Python numbers, so that
    ``json.dumps`` writes valid JSON (``null``, never ``NaN``)."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


INCOMPLETE = "the bench stopped without a summary (killed or crashed): the figures cover what was logged"


def _text(detail: object) -> str:
    return detail.decode(errors="replace") if isinstance(detail, bytes) else str(detail)


def _detail(detail: object) -> dict[str, Any]:
    """An event's detail (JSON) as a dict; empty when it is not a JSON object."""
    try:
        parsed = json.loads(_text(detail))
    except ValueError:
        return {}
    return parsed if isinstance(parsed, dict) else {}


def _reason(detail: object) -> str:
    """A fault event's reason (its detail is JSON, ``{"reason": ...}``); the whole text otherwise."""
    d = _detail(detail)
    return str(d["reason"]) if "reason" in d else _text(detail)
