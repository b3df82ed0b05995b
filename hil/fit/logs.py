"""The logs ``hil fit`` reads: loaded, checked and sorted by what they can tell (docs/fit.md, "Inputs").

A log is ``static`` (no swing, no excitation: gyro noise, bias), ``ident`` (an ``hil ident`` sweep on one axis:
k_m, gyro bandwidth and delay, structural mode; its offset travel also shows the imbalance and the cable) or
``swing`` (a hexapod profile: friction at the rate reversals, current limit, cable, imbalance). Bad input is a
:class:`FitInputError` with one line naming the log and what is missing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from hil.analysis import GYRO_CHANNEL
from hil.log import LogError, read_log

Kind = Literal["static", "ident", "swing"]
AXES = ("az", "el")

#: loop-group channels every log must have, and what needs them
LOOP_CHANNELS = {
    "tick": "every parameter (the sample counter)",
    "t_s": "every parameter (the board's time)",
    "gyro_x_dps": "gyro noise (x)",
    "gyro_y_dps": "k_m, bandwidth, friction (elevation) and gyro noise (y)",
    "gyro_z_dps": "k_m, bandwidth, friction (azimuth) and gyro noise (z)",
    "az_deg": "friction, cable and bias (azimuth)",
    "el_deg": "friction, cable, imbalance and bias (elevation)",
    "drive_az_counts": "k_m and friction (azimuth)",
    "drive_el_counts": "k_m and friction (elevation)",
    "rate_cmd_az_dps": "the ident sweep (azimuth)",
    "rate_cmd_el_dps": "the ident sweep (elevation)",
    "t_host_ns": "aligning the hexapod's poses with the loop",
}
POSE_AXES = ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")
HEXAPOD_CHANNELS = ("t_host_ns", *POSE_AXES)


class FitInputError(ValueError):
    """A log ``hil fit`` cannot use; the message is one line naming the log and what is missing."""


@dataclass
class FitLog:
    """One loaded log: its arrays on the driven span (driver enabled), what kind it is, what it was recorded on."""

    path: Path
    kind: Kind
    axis: str | None  # the ident sweep's axis
    loop: dict[str, np.ndarray]  # the loop group's channels on the driven span, float64
    pose: dict[str, np.ndarray]  # hexapod pose, its rate and acceleration at each loop row (zeros without a swing)
    config: dict[str, Any]
    provenance: dict[str, Any]
    boards: dict[str, Any]
    dt_s: float
    controller: str
    excitation: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def duration_s(self) -> float:
        return self.loop["t_s"].size * self.dt_s

    def gyro(self, axis: str) -> np.ndarray:
        return self.loop[GYRO_CHANNEL[axis]]


def _driven_span(data: Any, n: int) -> tuple[int, int]:
    """Rows from the tick the driver was armed to the tick it was disarmed (the drive is applied only there)."""
    ev = data.groups.get("events") or {}
    ticks = np.asarray(ev.get("tick", []), dtype=np.int64)
    details = [str(d) for d in ev.get("detail", [])]
    tick0 = int(np.asarray(data.groups["loop"]["tick"])[0]) if n else 0
    start, stop = 0, n
    for t, d in zip(ticks, details, strict=False):
        if '"state":"armed"' in d.replace(" ", ""):
            start = max(start, int(t) - tick0)
        if '"state":"disarmed"' in d.replace(" ", ""):
            stop = min(stop, int(t) - tick0)
    return max(0, start), max(0, min(stop, n))


def load_fit_log(path: str | Path) -> FitLog:
    """Read and classify one log; :class:`FitInputError` (one line) if it cannot be used."""

    p = Path(path)
    try:
        data = read_log(p)
    except LogError as exc:
        raise FitInputError(str(exc)) from None  # names the file and what is wrong
    except OSError as exc:
        raise FitInputError(f"{p}: cannot read the log: {exc}") from None
    if not data.closed_cleanly or any(data.trimmed.values()):
        cut = ", ".join(f"{g} ({n} rows)" for g, n in data.trimmed.items() if n) or "its end"
        raise FitInputError(f"{p}: truncated log (the session did not close it; missing {cut}): "
                            "run `hil recover` on it, or leave it out")
    loop = data.groups.get("loop") or {}
    missing = [c for c in LOOP_CHANNELS if c not in loop]
    if missing:
        raise FitInputError(f"{p}: the loop group lacks {', '.join(missing)}, needed for "
                            f"{LOOP_CHANNELS[missing[0]]}")
    n = int(np.asarray(loop["tick"]).size)
    if n < 2000:
        raise FitInputError(f"{p}: {n} loop rows (2 s): too short to fit anything")
    config = data.attrs.get("config") or {}
    if not isinstance(config, dict):
        raise FitInputError(f"{p}: its 'config' attribute is not the session's configuration")
    a, b = _driven_span(data, n)
    if b - a < 2000:
        raise FitInputError(f"{p}: the driver was armed for {b - a} rows (< 2 s): nothing to fit")
    tick = np.asarray(loop["tick"], dtype=np.int64)
    gaps = int(np.count_nonzero(np.diff(tick[a:b]) != 1))
    arrays = {c: np.asarray(loop[c], dtype=np.float64)[a:b] for c in LOOP_CHANNELS}
    t = arrays["t_s"]
    dt = float(np.median(np.diff(t)))
    excitation = config.get("excitation")
    segments = (config.get("profile") or {}).get("segments") or []
    if excitation:
        kind: Kind = "ident"
        axis: str | None = str(excitation.get("axis", "el"))
    elif segments:
        kind, axis = "swing", None
    else:
        kind, axis = "static", None
    pose = {f"{k}{d}": np.zeros(b - a) for k in POSE_AXES for d in ("", "_rate", "_accel")}
    hexa = data.groups.get("hexapod") or {}
    if kind == "swing":
        lacking = [c for c in HEXAPOD_CHANNELS if c not in hexa]
        if lacking or np.asarray(hexa.get("t_host_ns", [])).size < 10:
            raise FitInputError(f"{p}: a swing log without the hexapod's poses ({', '.join(lacking) or 'no rows'}), "
                                "needed for the imbalance and the carrier's motion")
        pose = _pose_on_loop(hexa, arrays["t_host_ns"], arrays["t_s"])
    prov = data.attrs.get("provenance") or {}
    ident = data.attrs.get("ident")
    log = FitLog(path=p, kind=kind, axis=axis, loop=arrays, pose=pose, config=config,
                 provenance=prov if isinstance(prov, dict) else {},
                 boards=ident if isinstance(ident, dict) else {},
                 dt_s=dt, controller=str(data.attrs.get("controller", "")), excitation=excitation)
    if gaps:
        log.notes.append(f"{gaps} tick gaps (missed samples): rows around them are left out")
    return log


def _pose_on_loop(hexa: dict[str, np.ndarray], t_host_loop: np.ndarray, t_loop: np.ndarray) -> dict[str, np.ndarray]:
    """The hexapod's 100 Hz poses at every loop row, with rates and accelerations: each pose's host time is placed
    on the board's time through the loop rows' host times (valid on every clock), then a cubic spline."""
    from scipy.interpolate import make_interp_spline  # noqa: PLC0415  (heavy: loaded only when this computation runs)

    t_pose = np.interp(np.asarray(hexa["t_host_ns"], dtype=np.float64), t_host_loop, t_loop)
    keep = np.concatenate([[True], np.diff(t_pose) > 1e-6])  # one pose per board instant
    out: dict[str, np.ndarray] = {}
    for k in POSE_AXES:
        y = np.asarray(hexa[k], dtype=np.float64)[keep]
        spl = make_interp_spline(t_pose[keep], y, k=3)
        tt = np.clip(t_loop, t_pose[keep][0], t_pose[keep][-1])
        out[k] = spl(tt)
        out[f"{k}_rate"] = spl(tt, 1)
        out[f"{k}_accel"] = spl(tt, 2)
    return out


def platform_of(log: FitLog) -> dict[str, str]:
    """What identifies the platform a log was recorded on: the boards' serial numbers and, on the emulator, the
    plant file's sha256 (provenance)."""
    out: dict[str, str] = {}
    for board in ("servo", "driver"):
        info = log.boards.get(board) or {}
        if "serial_number" in info:
            out[f"{board} serial"] = str(info["serial_number"])
    plant = (log.provenance.get("plant") or {}) if isinstance(log.provenance.get("plant"), dict) else {}
    if plant.get("sha256"):
        out["plant sha256"] = str(plant["sha256"])[:12]
    return out


def load_fit_logs(paths: list[str | Path]) -> list[FitLog]:
    """Every log, checked to be of one platform; :class:`FitInputError` naming the two that differ."""
    if not paths:
        raise FitInputError("no logs given: pass the session logs of one platform (static, ident, swing)")
    logs = [load_fit_log(p) for p in paths]
    first = platform_of(logs[0])
    for other in logs[1:]:
        here = platform_of(other)
        for key in first.keys() & here.keys():
            if first[key] != here[key]:
                raise FitInputError(f"logs of two different platforms: {logs[0].name} has {key} {first[key]}, "
                                    f"{other.name} has {here[key]}; fit one platform at a time")
    return logs
