"""`hil check`: validate any config file of the bench or the emulator without running anything.

A file's kind comes from the caller, else from its folder (``profiles/KIND/``), else from its keys (the model
whose fields cover most of them). The file is then loaded by that kind's own loader, so the check is exactly
what `hil run`, `hil campaign` or the emulator would say."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from firmware_stub.config import EmulatorConfig, load_emulator_config
from firmware_stub.plant import PlantConfig, load_plant_config
from hil.campaign import load_campaign
from hil.campaign.model import CampaignConfig
from hil.config import (
    ConfigError,
    ControllerConfig,
    HexapodLimits,
    SessionConfig,
    SwingProfile,
    load_model,
    load_session,
    read_yaml_mapping,
    require_regular_file,
)
from hil.control.registry import controller_params
from hil.fit.targets import TargetsConfig, load_targets

KINDS: tuple[str, ...] = ("session", "campaign", "controller", "swing", "hexapod", "emulator", "plant", "targets")
FOLDERS = {"sessions": "session", "campaigns": "campaign", "controllers": "controller", "swing": "swing",
           "hexapod": "hexapod", "emulator": "emulator", "plant": "plant", "targets": "targets"}


def _models() -> dict[str, type]:

    return {"session": SessionConfig, "campaign": CampaignConfig, "controller": ControllerConfig,
            "swing": SwingProfile, "hexapod": HexapodLimits, "emulator": EmulatorConfig, "plant": PlantConfig,
            "targets": TargetsConfig}


def guess_kind(path: Path) -> str:
    """The kind of config ``path`` holds: its folder's, else the model whose fields cover most of its keys."""
    for part in reversed(path.resolve().parent.parts[-2:]):
        if part in FOLDERS:
            return FOLDERS[part]
    try:
        keys = set(read_yaml_mapping(path))
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    if not keys:
        raise ConfigError(f"{path}: empty; cannot tell which kind of config it is (pass kind=)")
    scores = {}
    for kind, model in _models().items():
        fields = set(model.model_fields)  # type: ignore[attr-defined]
        scores[kind] = (len(keys & fields) / len(keys), len(keys & fields) / len(fields))
    best = max(scores, key=lambda k: scores[k])
    if scores[best][0] < 0.5:
        raise ConfigError(f"{path}: its keys ({', '.join(sorted(keys)[:6])}) match no config kind; pass kind= "
                          f"({', '.join(KINDS)})")
    return best


def _summary_session(config: Any) -> str:
    where = "the lab's ports" if config.ports is not None else "loopback only (no ports)"
    return (f"session {config.name}: {config.duration_s:g} s, controller {config.controller.name}, "
            f"{len(config.profile.segments)} swing segment(s), tracking {'on' if config.tracking.enabled else 'off'}, "
            f"{where}")


def _summary_campaign(config: Any) -> str:
    n = len(config.profiles) * len(config.controllers) * len(config.seeds)
    return (f"campaign {config.name}: {n} cells ({len(config.profiles)} profiles x {len(config.controllers)} "
            f"controllers x {len(config.seeds)} seeds), {len(config.acceptance)} acceptance rule(s)")


def _summary_controller(config: Any) -> str:

    params = controller_params(config.name, config.params)
    return (f"controller {config.name}: {len(type(params).model_fields)} parameters "
            f"({len(config.params)} set in the file)")


def _summary_swing(config: Any) -> str:
    axes = sorted({s.axis for s in config.segments})
    end = max((s.start_s + s.duration_s for s in config.segments), default=0.0)
    return (f"swing profile {config.name or '(unnamed)'}: {len(config.segments)} segment(s) on "
            f"{', '.join(axes) or '-'}, {end:g} s")


def _summary_hexapod(config: Any) -> str:
    return (f"hexapod envelope: x/y/z +-{config.x.position:g}/{config.y.position:g}/{config.z.position:g} mm, "
            f"roll/pitch/yaw +-{config.roll.position:g}/{config.pitch.position:g}/{config.yaw.position:g} deg")


def _summary_emulator(config: Any) -> str:
    return f"emulator: {config.clock} clock, seed {config.seed}, plant {config.plant}, " \
           f"{len(config.faults)} scheduled fault(s)"


def _summary_plant(config: Any) -> str:
    return f"plant: internal step {config.internal_step_s * 1e6:g} us"


def _summary_targets(config: Any) -> str:
    return (f"targets {config.name}: {len(config.targets)} figures, {len(config.measurements)} extra measurement(s), "
            f"{len(config.search.plant_ranges())} plant parameters searched")


def _loaders() -> dict[str, tuple[Callable[[Path], Any], Callable[[Any], str]]]:

    return {"session": (load_session, _summary_session), "campaign": (load_campaign, _summary_campaign),
            "targets": (load_targets, _summary_targets),
            "controller": (lambda p: load_model(ControllerConfig, p), _summary_controller),
            "swing": (lambda p: load_model(SwingProfile, p), _summary_swing),
            "hexapod": (lambda p: load_model(HexapodLimits, p), _summary_hexapod),
            "emulator": (load_emulator_config, _summary_emulator),
            "plant": (load_plant_config, _summary_plant)}


def check_config_file(path: Path, kind: str | None = None) -> dict[str, Any]:
    """{"file", "kind", "summary"} if ``path`` is a valid config of ``kind`` (guessed when None); ConfigError
    (one line naming the file and the field) otherwise."""

    if kind is not None and kind not in KINDS:
        raise ConfigError(f"kind={kind!r}: not one of {', '.join(KINDS)}")
    try:
        require_regular_file(path)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    kind = kind or guess_kind(path)
    load, summarize = _loaders()[kind]
    try:
        config = load(path)
    except ValueError as exc:  # every loader's error is a ValueError with its one line
        message = str(exc)
        raise ConfigError(message if str(path) in message else f"{path}: {message}") from None
    return {"file": str(path), "kind": kind, "summary": summarize(config)}
