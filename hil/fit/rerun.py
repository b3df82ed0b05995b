"""A log's session re-run on a fitted plant (``sim`` clock, the log's own configuration and seed; the emulator's plant
replaced), and the metrics a re-run is compared on: the fit report's twin checks use them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hil.config import SessionConfig
from hil.fit.logs import FitLog
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


__all__ = ["SETTLE_S", "UNITS", "rerun_log", "session_metrics"]
