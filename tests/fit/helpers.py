"""Shared by the fit tests: a plant drawn inside the plausible ranges, and a log recorded on it (sim clock)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from firmware_stub.plant import DEFAULT_PLANT_CONFIG
from hil.config import SessionConfig
from hil.fit.logs import FitLog, load_fit_log
from hil.fit.ranges import draw_plant, dump_plant, load_plant_dict
from hil.session import run


def drawn_plant(seed: int, work: Path) -> tuple[dict[str, Any], Path]:
    """``draw_plant(seed)`` from the default plant, and its YAML in ``work``."""
    hidden, _ = draw_plant(seed, load_plant_dict(DEFAULT_PLANT_CONFIG))
    return hidden, dump_plant(hidden, work / "hidden.yaml", f"draw_plant({seed})")


def recorded(config: SessionConfig) -> FitLog:
    """``config`` run on the sim clock, its log loaded as the fit loads it."""
    log = run(config, clock="sim").log_path
    assert log is not None
    return load_fit_log(log)

SLOW_WIRE_BAUD = 921_600  # the slow-wire lab's line rate (profiles/emulator/slow-wire.yaml)
