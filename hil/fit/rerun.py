"""A log's session re-run on a fitted plant (``sim`` clock, the log's own configuration and seed; the emulator's plant
replaced), and the metrics a re-run is compared on: the fit report's twin checks use them, and so does the fit of
the friction's breakaway that the torque balance cannot resolve (:func:`match_breakaway`)."""

from __future__ import annotations

import copy
import math
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.config import SessionConfig
from hil.fit.logs import FitLog
from hil.fit.ranges import BY_NAME, apply_params, dump_plant, get_param
from hil.log import read_log
from hil.session import emulator_for_plant
from hil.session import run as run_session

SETTLE_S = 1.0


def session_metrics(loop: dict[str, np.ndarray], image: dict[str, np.ndarray], dt_s: float) -> dict[str, float]:
    """The rate errors' and drives' std per axis and, with a valid track, the miss distance's, after ``SETTLE_S``."""
    k0 = int(SETTLE_S / dt_s)
    out = {
        "rate_err_el_std_dps": float(np.std(loop["rate_err_el_dps"][k0:])),
        "rate_err_az_std_dps": float(np.std(loop["rate_err_az_dps"][k0:])),
        "drive_el_std_counts": float(np.std(loop["drive_el_counts"][k0:])),
        "drive_az_std_counts": float(np.std(loop["drive_az_counts"][k0:])),
    }
    valid = np.asarray(image.get("track_valid", []), dtype=bool)
    if valid.size and valid.sum() > 50:
        t = np.asarray(image["t_exposure_s"])
        sel = valid & (t >= t[0] + SETTLE_S)
        mx, my = np.asarray(image["miss_x_px"])[sel], np.asarray(image["miss_y_px"])[sel]
        out["miss_std_px"] = float(np.sqrt(np.var(mx) + np.var(my)))
    return out


UNITS = {"rate_err_el_std_dps": "deg/s", "rate_err_az_std_dps": "deg/s", "drive_el_std_counts": "counts",
         "drive_az_std_counts": "counts", "miss_std_px": "px"}


def rerun_log(lg: FitLog, plant_path: Path, work_dir: Path) -> Path | None:
    """``lg``'s session on the plant file ``plant_path`` (sim clock, its own config and seed, no ports): the new log's
    path (None when the session wrote none)."""
    data = dict(lg.config)
    emu = dict(data.get("emulator") or {})
    emulator = emulator_for_plant(plant_path, work_dir, seed=int(data.get("seed", 0)))
    emu.update(config=str(emulator), clock="sim")
    data.update(emulator=emu, logging={**(data.get("logging") or {}), "dir": str(work_dir / "runs")})
    data.pop("ports", None)
    return run_session(SessionConfig.model_validate(data), clock="sim").log_path


MATCH_FLAT = 0.03  # a breakaway is resolved only where the path moves the rate error std by more than 3 %


@dataclass
class Breakaway:
    """The friction's breakaway of one axis matched by re-running the swing logs (:func:`match_breakaway`)."""

    axis: str
    stiction_ratio: float
    stribeck_rate_dps: float
    moved: str  # "stribeck_rate_dps" or "stiction_ratio": the one the match set; the other stays where it was
    resolved: bool  # False: no point of the path moved the rate error std by MATCH_FLAT, the prior stays
    rms_log_ratio: float  # the rms over the logs of ln(twin / logged) at the chosen point
    logs: list[str]


def breakaway_path(ratio: float, axis: str) -> list[tuple[float, float]]:
    """The (stiction ratio, Stribeck rate) points :func:`match_breakaway` tries, ordered by the breakaway's excess
    torque impulse ``(T_s / T_c - 1) v_s``: the ratio held and the Stribeck rate over its plausible range, then below
    it the ratio lowered to 1 at the lowest rate, above it the ratio raised to its plausible top at the highest."""
    vs = BY_NAME[f"friction.{axis}.stribeck_rate_dps"].lo, BY_NAME[f"friction.{axis}.stribeck_rate_dps"].hi
    r_hi = BY_NAME[f"friction.{axis}.stiction_ratio"].hi
    ratio = min(max(ratio, 1.0), r_hi)
    low = [(1.0 + (ratio - 1.0) * k / 3.0, vs[0]) for k in range(3)]
    held = [(ratio, float(v)) for v in np.geomspace(vs[0], vs[1], 5)]
    high = [(r_hi, vs[1])] if r_hi > ratio + 1e-9 else []
    return low + held + high


def match_breakaway(logs: list[FitLog], plant: Mapping[str, Any], axes: list[str], *,
                    progress: Callable[[str], Any] | None = None) -> dict[str, Breakaway]:
    """The breakaway of each axis in ``axes`` (LuGre's ``T_s / T_c`` and Stribeck rate ``v_s``) chosen so that the
    swing logs, re-run on ``plant`` (their own controller, swing and seed), show the rate error std they logged:
    the point of :func:`breakaway_path` with the least ``sum ln(twin / logged)^2``, then the midpoint towards its
    better neighbour. For an axis whose breakaway lies inside the torque balance's stick band (docs/fit.md, "Limits"),
    where the rate error at the reversals is all that shows it. The path's two ends run first; a log whose rate
    error moves by less than ``MATCH_FLAT`` between them does not see the breakaway and is left out of the rest.
    The axes share each re-run (each moves along its own path); only the impulse is determined, so the ratio is
    held where it was unless the rate reaches its bound."""
    swings = [lg for lg in logs if lg.kind == "swing"]
    if not swings or not axes:
        return {}
    logged_metrics = [session_metrics(read_log(lg.path).groups["loop"], {}, lg.dt_s) for lg in swings]
    logged = {ax: np.array([m[f"rate_err_{ax}_std_dps"] for m in logged_metrics]) for ax in axes}
    paths = {ax: breakaway_path(float(get_param(plant, f"friction.{ax}.stiction_ratio") or 1.0), ax) for ax in axes}
    n = max(len(p) for p in paths.values())
    done = 0

    def point(ax: str, k: int) -> tuple[float, float]:
        return paths[ax][min(k, len(paths[ax]) - 1)]

    with tempfile.TemporaryDirectory(prefix="hil-fit-breakaway-") as tmp:
        work = Path(tmp)

        def rerun(points: Mapping[str, tuple[float, float]], use: list[int]) -> dict[str, np.ndarray]:
            """ln(twin / logged) of each log in ``use`` (NaN for the others) with each axis at its point."""
            nonlocal done
            done += 1
            if progress is not None:
                progress(f"friction breakaway ({', '.join(axes)}): the swing logs re-run on the twin, {done} of "
                         f"{n + 1}")
            values: dict[str, float] = {}
            for ax, (r, v) in points.items():
                values |= {f"friction.{ax}.stiction_ratio": r, f"friction.{ax}.stribeck_rate_dps": v}
            path = dump_plant(apply_params(copy.deepcopy(dict(plant)), values), work / "plant.yaml", "breakaway")
            out = {ax: np.full(len(swings), np.nan) for ax in points}
            for i in use:
                lg = swings[i]
                try:
                    new = rerun_log(lg, path, work)
                except Exception:  # a log that cannot be re-run tells nothing: NaN, left out
                    continue
                if new is None:
                    continue
                got = session_metrics(read_log(new).groups["loop"], {}, lg.dt_s)
                for ax in points:
                    out[ax][i] = math.log(got[f"rate_err_{ax}_std_dps"] / logged[ax][i])
            return out

        everything = list(range(len(swings)))
        ends = {k: rerun({ax: point(ax, k) for ax in axes}, everything) for k in (0, n - 1)}
        seen = [i for i in everything if any(abs(ends[n - 1][ax][i] - ends[0][ax][i]) > MATCH_FLAT for ax in axes)]
        use = seen or everything
        dev = {k: ends[k] for k in ends}
        for k in range(1, n - 1):
            dev[k] = rerun({ax: point(ax, k) for ax in axes}, use)

        def cost(d: np.ndarray) -> float:
            c = float(np.sum(d[use] ** 2))
            return c if math.isfinite(c) else math.inf  # a point whose re-run failed is never chosen

        def cost_at(ax: str) -> Callable[[int], float]:
            return lambda k: cost(dev[k][ax])

        best = {ax: min(range(len(paths[ax])), key=cost_at(ax)) for ax in axes}
        mids = {}
        for ax in axes:
            i, last = best[ax], len(paths[ax]) - 1
            j = i - 1 if i == last or (i > 0 and cost(dev[i - 1][ax]) < cost(dev[i + 1][ax])) else i + 1
            (r0, v0), (r1, v1) = paths[ax][i], paths[ax][j]
            mids[ax] = (0.5 * (r0 + r1), math.sqrt(v0 * v1))
        dev_mid = rerun(mids, use)
    out: dict[str, Breakaway] = {}
    for ax in axes:
        (r, v), c_best = paths[ax][best[ax]], cost(dev[best[ax]][ax])
        if cost(dev_mid[ax]) < c_best:
            (r, v), c_best = mids[ax], cost(dev_mid[ax])
        resolved = any(abs(ends[n - 1][ax][i] - ends[0][ax][i]) > MATCH_FLAT for i in everything)
        held = paths[ax][3][0]  # the ratio the path holds while the rate moves
        moved = "stribeck_rate_dps" if abs(r - held) < 1e-9 else "stiction_ratio"
        resolved = resolved and math.isfinite(c_best)
        out[ax] = Breakaway(ax, r, v, moved, resolved, math.sqrt(c_best / len(use)), [swings[i].name for i in use])
    return out


__all__ = ["MATCH_FLAT", "SETTLE_S", "UNITS", "Breakaway", "breakaway_path", "match_breakaway", "rerun_log",
           "session_metrics"]
