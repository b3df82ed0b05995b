"""The plant's fittable parameters, their plausible ranges, and plants drawn inside them.

One vocabulary for the three users of a plant's parameters: ``hil fit`` (logs -> plant YAML), the paper-targets
search (:func:`hil.fit.fit_targets`) and the tests that draw hidden plants. A parameter is a flat name such as
``friction.el.coulomb_n_m``; most are a path into the plant YAML (``firmware_stub.plant.PlantConfig``), a few are
derived and set through others:

- ``motor_<axis>.k_m_dps2_per_count``: seed 000 eq 38, ``k_m = K_t V_count / (J R) * 180/pi``; set through the
  inertia (the motor's K_t, R and the driver's volts per count are datasheet values the fit keeps);
- ``friction.<axis>.stiction_ratio``: ``T_s / T_c`` (LuGre); the bristle damping follows ``sqrt(sigma_0 J)``;
- ``gyro.noise_std_dps``: the white noise std of all three gyro axes; ``gyro.noise_std_dps.<x|y|z>`` one axis;
- ``imbalance.m_rho_<x|z>_kg_mm``: mass times the centre-of-mass offset (what a torque balance sees).

``PLAUSIBLE`` documents each range and its source class (docs/fit.md has the table). ``draw_lo``/``draw_hi`` narrow
a range where the shipped controllers cannot run at its end (the measured reason is in ``note``): a hidden plant is
drawn inside those, so that a campaign on it compares controllers rather than limit cycles.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from firmware_stub.plant import PlantConfig
from hil.config import read_yaml_mapping

AXES = ("az", "el")
GYRO_AXES = ("x", "y", "z")
R2D = 180.0 / math.pi


@dataclass(frozen=True)
class ParamRange:
    """A fittable parameter: plausible ``lo..hi`` (unit); drawn uniformly (``log``: in log) in ``draw_lo..draw_hi``."""

    name: str
    lo: float
    hi: float
    unit: str
    source: str
    log: bool = False
    draw_lo: float | None = None
    draw_hi: float | None = None
    note: str = ""
    target_rel: float | None = None  # the accuracy a fit aims at, relative (docs/fit.md, "What the logs determine")
    target_abs: float | None = None  # ... or absolute, in ``unit``
    resolved_by: str = ""  # the recording that determines it (what `hil fit` asks for when it cannot)

    def tolerance(self, value: float) -> float | None:
        """The target accuracy at ``value`` (in ``unit``), None without a target."""
        if self.target_abs is not None:
            return self.target_abs
        return None if self.target_rel is None else abs(value) * self.target_rel

    @property
    def draw_range(self) -> tuple[float, float]:
        return (self.lo if self.draw_lo is None else self.draw_lo, self.hi if self.draw_hi is None else self.draw_hi)

    def draw(self, rng: np.random.Generator) -> float:
        a, b = self.draw_range
        if self.log:
            return float(math.exp(rng.uniform(math.log(a), math.log(b))))
        return float(rng.uniform(a, b))

    def contains(self, value: float) -> bool:
        return self.lo <= value <= self.hi


def _axis_ranges(axis: str) -> list[ParamRange]:
    heavy = axis == "az"  # the azimuth axis carries both frames: more inertia, friction and current
    return [
        ParamRange(f"motor_{axis}.k_m_dps2_per_count", 0.0115, 0.046, "deg/s^2 per count",
                   "paper (seed 000 eq 38: 0.023), x0.5..x2 for other payloads", log=True, target_rel=0.05,
                   resolved_by=f"`hil ident SESSION` with axis={axis}"),
        ParamRange(f"friction.{axis}.coulomb_n_m", 0.10 if heavy else 0.06, 0.60 if heavy else 0.40, "N m",
                   "literature (sealed bearings + cables of airborne gimbals; T_c / J 1-10 rad/s^2)", log=True,
                   target_rel=0.10, resolved_by=f"a swing session (`hil run` with a swing profile) and `hil ident "
                   f"SESSION` with axis={axis} (motion both ways)"),
        ParamRange(f"friction.{axis}.stiction_ratio", 1.0, 1.5, "1",
                   "literature (T_s / T_c of ball bearings and seals; Canudas de Wit 1995)"),
        ParamRange(f"friction.{axis}.stribeck_rate_dps", 0.1, 1.0, "deg/s", "literature (Canudas de Wit 1995)",
                   log=True),
        ParamRange(f"friction.{axis}.viscous_n_m_s_per_rad", 0.005, 0.1, "N m s/rad", "datasheet-typical", log=True),
        ParamRange(f"structure.{axis}.mode_hz", 50.0, 300.0, "Hz",
                   "literature (first torsion mode of gimbal structures; Hilkert 2008, Masten 2008)",
                   draw_lo=180.0, target_rel=0.10,
                   resolved_by=f"`hil ident SESSION` with axis={axis}, coherent up to the mode",
                   note="below ~160 Hz the shipped eso_kf_high_gain loop limit-cycles "
                   "(docs/emulator.md, Mechanisms)"),
        ParamRange(f"structure.{axis}.damping_ratio", 0.02, 0.1, "1", "literature (bolted aluminium frames)"),
        ParamRange(f"drive.{axis}.current_limit_a", 1.5 if heavy else 1.0, 5.0 if heavy else 4.0, "A",
                   "datasheet-typical (PWM servo amplifiers, continuous rating)"),
        ParamRange(f"cable.{axis}.stiffness_n_m_per_rad", 0.1, 5.0, "N m/rad",
                   "literature (harness restraint of slip-ring-free gimbals)", log=True, draw_hi=1.0,
                   target_rel=0.10, resolved_by="swing sessions (travel over degrees)",
                   note="a stiffer harness with a weak driver holds the axis within a few degrees: "
                   "(K_t I_max - T_c) / k_c = 10 deg at 1.7 N m/rad and 2 A, less than an ident sweep's travel"),
    ]


PLAUSIBLE: tuple[ParamRange, ...] = (
    *_axis_ranges("az"),
    *_axis_ranges("el"),
    ParamRange("gyro.bandwidth_hz", 100.0, 500.0, "Hz", "datasheet-typical MEMS rate gyro", draw_lo=150.0,
               draw_hi=400.0, target_rel=0.10,
               resolved_by="`hil ident SESSION` whose coherent band reaches ~1.25 x the bandwidth",
               note="a 100 Hz gyro puts the shipped eso_kf_high_gain loop into a limit cycle "
               "(docs/emulator.md, Calibration)"),
    ParamRange("gyro.delay_s", 0.1e-3, 1.0e-3, "s", "datasheet-typical (MEMS output filter + interface)",
               draw_lo=0.2e-3, draw_hi=0.8e-3, target_abs=0.1e-3,
               resolved_by="`hil ident SESSION` (a coherent band to a few hundred Hz)",
               note="1 ms of gyro delay puts eso_kf_high_gain into a limit cycle "
               "(docs/emulator.md, Calibration)"),
    ParamRange("gyro.noise_std_dps", 0.01, 0.06, "deg/s", "datasheet-typical MEMS noise density at 1 kHz "
               "(paper Fig 12a: 0.0315)", log=True, target_rel=0.05,
               resolved_by="a static session (`hil run` with profiles/swing/static.yaml, 30 s; each further one "
               "adds to it, the 1-sigma falling as 1/sqrt(their total duration))"),
    ParamRange("gyro.noise_psd.std_dps", 0.0, 0.03, "deg/s",
               "FACTS (MEMS noise shaped near its sense band; one 2nd-order component)"),
    ParamRange("gyro.noise_psd.centre_hz", 300.0, 480.0, "Hz", "FACTS (sense-mode band below Nyquist)"),
    ParamRange("imbalance.m_rho_x_kg_mm", -20.0, 20.0, "kg mm", "datasheet-typical residual after balancing "
               "(10 kg at +-2 mm)", target_abs=1.0, resolved_by="swing sessions (the pitch swing's accelerations)"),
    ParamRange("imbalance.m_rho_z_kg_mm", -20.0, 20.0, "kg mm", "datasheet-typical residual after balancing"),
)

BY_NAME: dict[str, ParamRange] = {p.name: p for p in PLAUSIBLE}


def param_range(name: str) -> ParamRange | None:
    """The range of a parameter, per-axis gyro noise (``gyro.noise_std_dps.x``) by its family's."""
    return BY_NAME.get(name) or BY_NAME.get(name.rsplit(".", 1)[0])


def _motor(cfg: Mapping[str, Any], axis: str) -> Mapping[str, Any]:
    return cfg[f"motor_{axis}"]


def k_m_of(cfg: Mapping[str, Any], axis: str) -> float:
    """Seed 000 eq 38 on a plant dict: ``K_t V_count / (J R)`` in deg/s^2 per count."""
    m = _motor(cfg, axis)
    return m["torque_constant_n_m_per_a"] * m["volts_per_count"] / (m["inertia_kg_m2"] * m["resistance_ohm"]) * R2D


def torque_per_count_n_m(cfg: Mapping[str, Any], axis: str) -> float:
    """Stall torque of one drive count, ``K_t V_count / R`` (N m per count)."""
    m = _motor(cfg, axis)
    return m["torque_constant_n_m_per_a"] * m["volts_per_count"] / m["resistance_ohm"]


def get_param(cfg: Mapping[str, Any], name: str) -> float | None:
    """The value of ``name`` in a plant dict; None where its mechanism is off."""
    parts = name.split(".")
    if name.endswith(".k_m_dps2_per_count"):
        return k_m_of(cfg, parts[0].removeprefix("motor_"))
    if name.endswith(".stiction_ratio"):
        fr = cfg.get("friction", {}).get(parts[1], {})
        if fr.get("model") != "lugre":
            return None
        return fr["stiction_n_m"] / fr["coulomb_n_m"]
    if parts[0] == "gyro" and parts[1] == "noise_std_dps":
        std = cfg["gyro"]["noise_std_dps"]
        return float(std[GYRO_AXES.index(parts[2])]) if len(parts) == 3 else float(np.mean(std))
    if parts[0] == "gyro" and parts[1] == "noise_psd":
        psd = cfg["gyro"].get("noise_psd") or []
        return float(psd[0][parts[2]]) if psd else None
    if parts[0] == "imbalance" and parts[1].startswith("m_rho_"):
        imb = cfg.get("imbalance")
        if not imb:
            return None
        return imb["mass_kg"] * imb["eccentricity_mm"]["xyz".index(parts[1][6])]
    node: Any = cfg
    for p in parts:
        if not isinstance(node, Mapping) or node.get(p) is None:
            return None
        node = node[p]
    return float(node)


def set_param(cfg: dict[str, Any], name: str, value: float) -> None:
    """Set ``name`` in a plant dict (in place), switching its mechanism on with the other values it needs."""
    parts = name.split(".")
    if name.endswith(".k_m_dps2_per_count"):
        axis = parts[0].removeprefix("motor_")
        m = cfg[f"motor_{axis}"]
        m["inertia_kg_m2"] = m["torque_constant_n_m_per_a"] * m["volts_per_count"] / (value * m["resistance_ohm"]) * R2D
        _follow_inertia(cfg, axis)
        return
    if name.endswith(".stiction_ratio"):
        fr = cfg["friction"][parts[1]]
        fr.setdefault("model", "lugre")
        fr["model"] = "lugre"
        fr.setdefault("stribeck_rate_dps", 0.5)
        fr.setdefault("bristle_stiffness_n_m_per_rad", 2.0e4)
        fr["stiction_n_m"] = float(value) * fr["coulomb_n_m"]
        _follow_inertia(cfg, parts[1])
        return
    if parts[0] == "gyro" and parts[1] == "noise_std_dps":
        std = list(cfg["gyro"]["noise_std_dps"])
        for i, ax in enumerate(GYRO_AXES):
            if len(parts) == 2 or parts[2] == ax:
                std[i] = float(value)
        cfg["gyro"]["noise_std_dps"] = std
        return
    if parts[0] == "gyro" and parts[1] == "noise_psd":
        psd = cfg["gyro"].get("noise_psd") or [{"centre_hz": 450.0, "bandwidth_hz": 100.0, "std_dps": 0.0}]
        psd = [dict(c) for c in psd]
        psd[0][parts[2]] = float(value)
        cfg["gyro"]["noise_psd"] = psd
        return
    if parts[0] == "imbalance" and parts[1].startswith("m_rho_"):
        imb = cfg.setdefault("imbalance", {"mass_kg": 10.0, "eccentricity_mm": [0.0, 0.0, 0.0]})
        ecc = list(imb["eccentricity_mm"])
        ecc["xyz".index(parts[1][6])] = float(value) / imb["mass_kg"]
        imb["eccentricity_mm"] = ecc
        return
    if parts[0] == "friction" and parts[2] == "coulomb_n_m":
        fr = cfg["friction"][parts[1]]
        ratio = fr["stiction_n_m"] / fr["coulomb_n_m"] if fr.get("model") == "lugre" else None
        fr["coulomb_n_m"] = float(value)
        if ratio is not None:
            fr["stiction_n_m"] = ratio * float(value)
        return
    node = cfg
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = float(value)
    if parts[0] == "structure":
        node.setdefault("mode_hz", 250.0)
        node.setdefault("damping_ratio", 0.05)
        node.setdefault("motor_inertia_fraction", 0.3)
        _follow_inertia(cfg, parts[1])


def _follow_inertia(cfg: dict[str, Any], axis: str) -> None:
    """LuGre's bristle damping follows ``sqrt(sigma_0 J)`` (Canudas de Wit 1995's choice), as the presets do."""
    fr = cfg.get("friction", {}).get(axis)
    if fr and fr.get("model") == "lugre" and fr.get("bristle_stiffness_n_m_per_rad"):
        fr["bristle_damping_n_m_s_per_rad"] = math.sqrt(
            fr["bristle_stiffness_n_m_per_rad"] * cfg[f"motor_{axis}"]["inertia_kg_m2"])


def apply_params(cfg: Mapping[str, Any], values: Mapping[str, float]) -> dict[str, Any]:
    """A copy of the plant dict with ``values`` set (in the order given: k_m before friction is safe either way)."""
    out = copy.deepcopy(dict(cfg))
    for name, value in values.items():
        set_param(out, name, value)
    return out


def validate_plant(cfg: Mapping[str, Any]) -> PlantConfig:
    """``PlantConfig`` of a plant dict (ValueError with the field on a bad one)."""

    return PlantConfig.model_validate(dict(cfg))


def load_plant_dict(path: str | Path) -> dict[str, Any]:
    """A plant YAML as a dict, validated."""

    # the bench's bounded reader, then the validated model's plain dump (YAML 1.1 reads ``2.0e4`` as text; pydantic
    # reads it as the number it is): every value typed, mechanisms that are off left out
    return validate_plant(read_yaml_mapping(path)).model_dump(mode="json", exclude_none=True)


AUTHORITY_MARGIN = 2.0


def check_authority(cfg: Mapping[str, Any]) -> None:
    """ValueError unless each axis' torque authority (``K_t I_max``, or the bus' stall torque) is at least
    ``AUTHORITY_MARGIN`` times its breakaway torque plus the cable at 10 deg: a driver is sized so, and below it
    the axis cannot follow the carrier (it sticks to it), which no controller comparison can use."""
    for axis in AXES:
        m = cfg[f"motor_{axis}"]
        limit = ((cfg.get("drive") or {}).get(axis) or {}).get("current_limit_a")
        authority = m["torque_constant_n_m_per_a"] * min(limit or math.inf, m["bus_voltage_v"] / m["resistance_ohm"])
        fr = cfg["friction"][axis]
        breakaway = fr.get("stiction_n_m") or fr["coulomb_n_m"]
        cable = ((cfg.get("cable") or {}).get(axis) or {}).get("stiffness_n_m_per_rad") or 0.0
        need = AUTHORITY_MARGIN * (breakaway + cable * math.radians(10.0))
        if authority < need:
            raise ValueError(f"{axis}: torque authority {authority:.3g} N m < {need:.3g} N m "
                             f"({AUTHORITY_MARGIN:g} x breakaway + cable at 10 deg)")


def draw_plant(seed: int, base: Mapping[str, Any], names: Iterable[str] | None = None,
               attempts: int = 50) -> tuple[dict[str, Any], dict[str, float]]:
    """A hidden plant: ``base`` with each of ``names`` (default: every ``PLAUSIBLE`` parameter) drawn inside its
    draw range with ``numpy.random.default_rng(seed)``; redrawn (same stream) until ``PlantConfig`` accepts it and
    :func:`check_authority` holds."""
    rng = np.random.default_rng(seed)
    chosen = [BY_NAME[n] for n in names] if names is not None else list(PLAUSIBLE)
    last: Exception | None = None
    for _ in range(attempts):
        values = {p.name: p.draw(rng) for p in chosen}
        cfg = apply_params(base, values)
        try:
            validate_plant(cfg)
            check_authority(cfg)
        except ValueError as exc:
            last = exc
            continue
        return cfg, values
    raise ValueError(f"no valid plant in {attempts} draws (seed {seed}): {last}")


def dump_plant(cfg: Mapping[str, Any], path: str | Path, header: str = "") -> Path:
    """Write a plant dict as YAML (validated first), with ``header`` as a comment block."""
    validate_plant(cfg)
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    text = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines())
    p.write_text(text + yaml.safe_dump(_plain(cfg), sort_keys=False, default_flow_style=None, width=118),
                 encoding="utf-8")
    return p


def _plain(node: Any) -> Any:
    if isinstance(node, Mapping):
        return {str(k): _plain(v) for k, v in node.items()}
    if isinstance(node, list | tuple):
        return [_plain(v) for v in node]
    if isinstance(node, np.generic):
        return node.item()
    return node
