"""Record the logs a lab would give ``hil fit``, on an emulated plant (sim clock): the hidden-plant acceptance
tests and ``benchmarks/fit_hidden_plants.py`` use it, and so can a lab that wants to see what a fit needs.

The set: a static session (ESO+KF holding the gimbal, no swing), an ``hil ident`` sweep on each axis, and swing
sessions at 1 deg and 3 deg / 1 Hz with the plain ESO and at 3 deg with the high-gain ESO+KF (the hardest the
shipped controllers drive the axes: where a current limit shows, if anything does). Every session is a shipped
profile with the emulator pointed at the given plant file; nothing is re-implemented here.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from hil.analysis import SweptSine
from hil.campaign import load_campaign, run_campaign
from hil.config import PROFILES, SessionConfig, load_session
from hil.session import emulator_for_plant, run

SWING_SESSION = PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml"


def session_on_plant(plant: str | Path, work_dir: str | Path, *, name: str, swing: str | None,
                     controller: str = "eso", seconds: float = 20.0, seed: int = 1,
                     tracking: bool = False) -> SessionConfig:
    """The shipped swing session with another swing (``None``: static), controller, duration and the given plant."""
    base = load_session(SWING_SESSION)
    data = base.model_dump(mode="json", exclude_none=True)
    data.update(
        name=name, duration_s=seconds, seed=seed,
        controller=str(PROFILES / "controllers" / f"{controller}.yaml"),
        profile=str(PROFILES / "swing" / f"{swing or 'static'}.yaml"),
        tracking={**data.get("tracking", {}), "enabled": tracking},
        emulator={**data["emulator"], "config": str(emulator_for_plant(plant, work_dir, seed=seed)), "clock": "sim"},
        logging={**data.get("logging", {}), "dir": str(Path(work_dir) / "runs")},
        mqtt=base.mqtt, hexapod=base.hexapod,
    )
    return SessionConfig.model_validate(data)


def record_platform_logs(plant: str | Path, out_dir: str | Path, *, seed: int = 1, static_s: float = 10.0,
                         swing_s: float = 20.0, sweep_s: float = 6.0, f_start_hz: float = 1.0,
                         f_stop_hz: float = 450.0, amplitude_dps: float = 1.5, offset_dps: float = 3.0,
                         swings: tuple[tuple[str, str], ...] = (("swing-1deg-1hz", "eso"), ("swing-3deg-1hz", "eso"),
                                                                ("swing-3deg-1hz", "eso_kf_high_gain")),
                         axes: tuple[str, ...] = ("el", "az"),
                         progress: Callable[[str], Any] | None = None) -> list[Path]:
    """Record a fit's logs on ``plant`` (sim clock, ``seed``): static, ident per axis, each swing. Their paths.

    The sweep is the session ``hil ident`` runs (docs/ident.md) around a rate offset (no friction reversal), kept
    short (``offset_dps * (sweep_s + 1 s)`` = 21 deg by default) because a cable harness restrains the travel."""
    out = Path(out_dir)
    logs: list[Path] = []

    def say(text: str) -> None:
        if progress is not None:
            progress(text)

    say("static session")
    static = session_on_plant(plant, out, name="fit-static", swing=None, controller="eso_kf", seconds=static_s,
                              seed=seed)
    logs.append(run(static, clock="sim").log_path)
    for axis in axes:
        say(f"ident sweep, {axis}")
        sweep = SweptSine(f_start_hz=f_start_hz, f_stop_hz=f_stop_hz, duration_s=sweep_s, amplitude_dps=amplitude_dps,
                          axis=axis, offset_dps=offset_dps)  # type: ignore[arg-type]
        cfg = session_on_plant(plant, out, name=f"fit-ident-{axis}", swing=None, controller="eso",
                               seconds=sweep.total_s + 0.5, seed=seed)
        logs.append(run(cfg.model_copy(update={"excitation": sweep}), clock="sim").log_path)
    for swing, controller in swings:
        say(f"swing session, {swing}, {controller}")
        cfg = session_on_plant(plant, out, name=f"fit-{swing}-{controller.replace('_', '-')}", swing=swing,
                               controller=controller, seconds=swing_s, seed=seed, tracking=True)
        logs.append(run(cfg, clock="sim").log_path)
    return logs


ACCEPTANCE_CAMPAIGN = PROFILES / "campaigns" / "swing-miss-distance.yaml"


def campaign_on_plant(plant: str | Path, out_dir: str | Path, *, seeds: tuple[int, ...] = (1,),
                      duration_s: float = 10.0, jobs: int = 1) -> dict[tuple[str, str, str], float]:
    """The fit's acceptance campaign (ESO, ESO+KF, high-gain ESO+KF at 1 and 3 deg / 1 Hz, tracking on: the shipped
    swing-miss-distance campaign) on ``plant``: (profile, controller, metric) -> the mean over ``seeds``."""
    out = Path(out_dir)
    base = load_campaign(ACCEPTANCE_CAMPAIGN)
    overrides = {**base.overrides, "emulator": {"config": str(emulator_for_plant(plant, out))}}
    cfg = base.model_copy(update={"overrides": overrides, "seeds": list(seeds), "duration_s": duration_s,
                                  "name": f"fit-check-{Path(plant).stem}"})
    result = run_campaign(cfg, out / "campaign", jobs=jobs)
    means: dict[tuple[str, str, str], float] = {}
    for p in cfg.profiles:
        for c in cfg.controllers:
            for m in cfg.metrics:
                means[(p.label, c.label, m)] = result.mean(p.label, c.label, m)
    return means
