"""The plant's YAML as pydantic models (docs/emulator.md, "The plant" and "Mechanisms"): one section per mechanism,
each off unless its key is present; ``load_plant_config`` with one-line errors naming the file and field."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Generic, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from firmware_stub.config import ConfigError, read_yaml_mapping

DEFAULT_PLANT_CONFIG = Path(__file__).parents[2] / "profiles/plant/default.yaml"
RIGID_PLANT_CONFIG = Path(__file__).parents[2] / "profiles/plant/rigid.yaml"

G0_M_S2 = 9.80665  # standard gravity; lab z is down, so gravity in the lab is (0, 0, +G0)
D2R = math.pi / 180.0
R2D = 180.0 / math.pi
TICK_S = 1e-3
GYRO_NYQUIST_HZ = 0.5 / TICK_S

Vec3f = tuple[float, float, float]
Axis = Literal["az", "el"]


class PlantConfigError(ValueError):
    """A plant config file is not valid: one line naming the file, the field path and the reason."""


class _Section(BaseModel):
    """Base of the plant's config sections: unknown fields refused, immutable, NaN and infinities refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


AxisSection = TypeVar("AxisSection", bound=_Section)


class MotorConfig(_Section):
    """One brush DC torque motor, its driver and the load it turns (seed 000 eqs 33-37)."""

    resistance_ohm: float = Field(gt=0, description="armature resistance R_a")
    inductance_h: float = Field(gt=0, description="armature inductance L_a")
    torque_constant_n_m_per_a: float = Field(gt=0, description="K_t")
    back_emf_v_s_per_rad: float = Field(ge=0, description="K_e (= K_t in SI units for an ideal motor)")
    inertia_kg_m2: float = Field(gt=0, description="J_sigma: motor + load about the axis (split by `structure`)")
    volts_per_count: float = Field(gt=0, description="driver gain: armature volts per signed 16-bit DAC count")
    bus_voltage_v: float = Field(gt=0, description="|V| is clamped to this")


class FrictionAxisConfig(_Section):
    """Bearing friction on the (motor-side) rate relative to the carrier.

    ``model: tanh`` (default): ``T_c tanh(w_rel / w_s) + D w_rel``. ``model: lugre`` (Canudas de Wit et al. 1995):
    ``T_f = sigma_0 z + sigma_1 dz/dt + D v``, ``dz/dt = v - sigma_0 |v| z / g(v)``,
    ``g(v) = T_c + (T_s - T_c) exp(-(v / v_s)^2)``; the four LuGre parameters are required with ``lugre`` and
    ignored with ``tanh`` (so one line switches the model); ``smoothing_rate_dps`` is used by ``tanh`` only.
    """

    coulomb_n_m: float = Field(ge=0, description="Coulomb level T_c")
    viscous_n_m_s_per_rad: float = Field(ge=0, description="viscous coefficient D")
    smoothing_rate_dps: float = Field(gt=0, description="w_s of the tanh smoothing (stability: see validator)")
    model: Literal["tanh", "lugre"] = Field("tanh", description="tanh (smoothed Coulomb) or lugre")
    stiction_n_m: float | None = Field(None, gt=0, description="LuGre: breakaway (static) level T_s >= T_c")
    stribeck_rate_dps: float | None = Field(None, gt=0, description="LuGre: Stribeck rate v_s")
    bristle_stiffness_n_m_per_rad: float | None = Field(None, gt=0, description="LuGre: sigma_0")
    bristle_damping_n_m_s_per_rad: float | None = Field(None, ge=0, description="LuGre: sigma_1")

    @model_validator(mode="after")
    def _lugre_complete(self) -> FrictionAxisConfig:
        if self.model == "lugre":
            for name in ("stiction_n_m", "stribeck_rate_dps", "bristle_stiffness_n_m_per_rad",
                         "bristle_damping_n_m_s_per_rad"):
                if getattr(self, name) is None:
                    raise ValueError(f"{name}: required with model lugre")
            assert self.stiction_n_m is not None
            if self.stiction_n_m < self.coulomb_n_m:
                raise ValueError(f"stiction_n_m: {self.stiction_n_m!r} is below coulomb_n_m {self.coulomb_n_m!r}")
        return self


class FrictionConfig(_Section):
    az: FrictionAxisConfig
    el: FrictionAxisConfig


class ImbalanceConfig(_Section):
    """Mass imbalance of the elevation assembly (seed 001 eqs 2-4)."""

    mass_kg: float = Field(ge=0, description="mass of the elevation assembly")
    eccentricity_mm: tuple[float, float, float] = Field(
        description="centre of mass relative to the pivot (axes' intersection), elevation-frame components"
    )


class GyroNoiseBand(_Section):
    """One coloured component of the gyro noise: white noise through a second-order band-pass."""

    centre_hz: float = Field(gt=0, lt=GYRO_NYQUIST_HZ, description="centre of the band (below the 500 Hz Nyquist)")
    bandwidth_hz: float = Field(gt=0, lt=GYRO_NYQUIST_HZ, description="-3 dB width of the band")
    std_dps: float = Field(ge=0, description="std of this component on each axis, deg/s")


class GyroConfig(_Section):
    """Three-axis rate gyro on the elevation frame (seed 000 eq 3 plus noise, bias, quantisation)."""

    scale_factor: float = Field(gt=0, description="k_a")
    bandwidth_hz: float = Field(gt=0, description="omega_c / (2 pi)")
    delay_s: float = Field(ge=0, le=0.05, description="T_d (any value; the input is linear between ticks)")
    noise_std_dps: tuple[float, float, float] = Field(description="white-noise std per axis (x, y, z)")
    bias_dps: tuple[float, float, float] = Field(description="constant bias per axis (x, y, z)")
    quantisation_lsb_dps: float = Field(ge=0, description="output LSB; 0 = not quantised")
    noise_psd: tuple[GyroNoiseBand, ...] = Field((), max_length=8, description="coloured noise components")
    random_walk: float = Field(0.0, ge=0, le=1.0, description="rate random walk of the bias, deg/s per sqrt(s)")

    @model_validator(mode="after")
    def _noise_non_negative(self) -> GyroConfig:
        if min(self.noise_std_dps) < 0:
            raise ValueError("noise_std_dps: every std must be >= 0")
        return self


class EncoderConfig(_Section):
    counts_per_rev: int = Field(gt=0, le=1 << 30, description="resolution of both axis encoders")


class CameraConfig(_Section):
    """Camera on the LOS looking at a collimated target fixed in the lab."""

    ifov_deg_per_px: float = Field(gt=0, description="instantaneous field of view of one pixel")
    half_width_px: float = Field(gt=0, description="track_valid needs |x_px| <= this")
    half_height_px: float = Field(gt=0, description="track_valid needs |y_px| <= this")
    centroid_noise_std_px: float = Field(ge=0, description="white noise on each miss component")
    target_az_deg: float = Field(ge=-180, le=180, description="target direction in the lab: azimuth (right +)")
    target_el_deg: float = Field(ge=-90, le=90, description="target direction in the lab: elevation (up +)")
    frame_rate_hz: float = Field(ge=0.1, le=1000, description="used by the image-processing board (at most one "
                                 "frame per 1 ms tick), not by the plant")
    latency_frames: int = Field(ge=0, le=100, description="used by the image-processing board, not by the plant")


class LinearAxisLimits(_Section):
    position_mm: float = Field(gt=0)
    rate_mm_s: float = Field(gt=0)
    accel_mm_s2: float = Field(gt=0)


class AngularAxisLimits(_Section):
    angle_deg: float = Field(gt=0)
    rate_dps: float = Field(gt=0)
    accel_dps2: float = Field(gt=0)


class HexapodConfig(_Section):
    """Envelope of the swing table, symmetric +- limits (used by the hexapod board, not by the plant)."""

    x: LinearAxisLimits
    y: LinearAxisLimits
    z: LinearAxisLimits
    roll: AngularAxisLimits
    pitch: AngularAxisLimits
    yaw: AngularAxisLimits


class PerAxis(_Section, Generic[AxisSection]):
    """A mechanism given per axis (``az``, ``el``); an absent axis has it off."""

    az: AxisSection | None = None
    el: AxisSection | None = None


class StructureAxisConfig(_Section):
    """Two-mass compliance of one axis: the free-free torsion mode between motor and load."""

    mode_hz: float = Field(ge=1.0, le=5000.0, description="free-free mode sqrt(k (1/J_m + 1/J_l)) / 2 pi")
    damping_ratio: float = Field(ge=0.0, le=2.0, description="modal damping ratio zeta of that mode")
    motor_inertia_fraction: float = Field(gt=0.0, lt=1.0, description="f: J_m = f J, J_l = (1 - f) J")


StructureConfig = PerAxis[StructureAxisConfig]


class DriveAxisConfig(_Section):
    current_limit_a: float | None = Field(None, gt=0, description="|armature current| <= this; null = no limit")


DriveConfig = PerAxis[DriveAxisConfig]


class CableAxisConfig(_Section):
    """Cable harness across the axis: a spring and damper on the motor-side angle relative to the carrier."""

    stiffness_n_m_per_rad: float = Field(ge=0, le=1e4, description="k_c (neutral at encoder zero)")
    damping_n_m_s_per_rad: float = Field(ge=0, le=1e3, description="c_c")


CableConfig = PerAxis[CableAxisConfig]


class MountConfig(_Section):
    pivot_offset_m: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="gimbal pivot from the hexapod's rotation centre, platform (body) frame, m"
    )

    @model_validator(mode="after")
    def _bounded(self) -> MountConfig:
        if max(abs(x) for x in self.pivot_offset_m) > 10.0:
            raise ValueError("pivot_offset_m: each component must be within +-10 m")
        return self


class RippleAxisConfig(_Section):
    """Motor torque ripple: ``K_t i (1 + a sin(N theta_m))``."""

    amplitude_fraction: float = Field(ge=0.0, le=0.5, description="a: peak ripple as a fraction of K_t i")
    periods_per_rev: int = Field(gt=0, le=100000, description="N: ripple periods per motor revolution")


RippleConfig = PerAxis[RippleAxisConfig]


class PlantConfig(_Section):
    """Every parameter of the plant. Units are in the field names; see profiles/plant/rigid.yaml (every mechanism
    off) and profiles/plant/default.yaml (every mechanism on). The mechanism sections are optional: absent = off."""

    internal_step_s: float = Field(gt=0, le=2e-4, description="fixed integration step; must divide 1 ms")
    initial_az_deg: float = Field(0.0, description="gimbal angles at construction and reset()")
    initial_el_deg: float = Field(0.0, ge=-90, le=90)
    motor_az: MotorConfig
    motor_el: MotorConfig
    friction: FrictionConfig
    imbalance: ImbalanceConfig
    gyro: GyroConfig
    encoder: EncoderConfig
    camera: CameraConfig
    hexapod: HexapodConfig
    structure: StructureConfig | None = None
    drive: DriveConfig | None = None
    cable: CableConfig | None = None
    mount: MountConfig | None = None
    ripple: RippleConfig | None = None

    def structure_of(self, axis: Axis) -> StructureAxisConfig | None:
        return None if self.structure is None else getattr(self.structure, axis)

    def current_limit_a(self, axis: Axis) -> float | None:
        d = None if self.drive is None else getattr(self.drive, axis)
        return None if d is None else d.current_limit_a

    def cable_of(self, axis: Axis) -> CableAxisConfig | None:
        return None if self.cable is None else getattr(self.cable, axis)

    def ripple_of(self, axis: Axis) -> RippleAxisConfig | None:
        return None if self.ripple is None else getattr(self.ripple, axis)

    def pivot_offset_m(self) -> Vec3f:
        return (0.0, 0.0, 0.0) if self.mount is None else self.mount.pivot_offset_m

    def motor_side_inertia(self, axis: Axis) -> float:
        """J_m: the inertia friction, cable and ripple act on (J without ``structure``)."""
        j = getattr(self, f"motor_{axis}").inertia_kg_m2
        st = self.structure_of(axis)
        return j if st is None else st.motor_inertia_fraction * j

    @model_validator(mode="after")
    def _cross_checks(self) -> PlantConfig:
        h = self.internal_step_s
        n = round(TICK_S / h)
        if n < 1 or abs(n * h - TICK_S) > 1e-9 * TICK_S:
            raise ValueError(f"internal_step_s: {h!r} does not divide the 1 ms tick")
        for axis in ("az", "el"):
            fr: FrictionAxisConfig = getattr(self.friction, axis)
            j_m = self.motor_side_inertia(axis)
            if fr.model == "tanh":
                # the Coulomb term is explicit (held over a step); its slope T_c / w_s must not overshoot
                gain = h * fr.coulomb_n_m / (j_m * fr.smoothing_rate_dps * D2R)
                if gain > 1.0:
                    w_min = h * fr.coulomb_n_m / j_m * R2D
                    raise ValueError(
                        f"friction.{axis}.smoothing_rate_dps: {fr.smoothing_rate_dps!r} is too small for "
                        f"internal_step_s {h!r} and motor-side inertia {j_m:.3g} kg m^2 (explicit Coulomb term "
                        f"unstable); need >= {w_min:.3g}"
                    )
            else:
                # bristle spring and damper held over a sub-step while sticking: the discrete oscillator
                # z+ = z + h v, v+ = v - h (sigma_0 z+ + sigma_1 v) / J_m is stable for a + 2 b < 4 (a = h^2 sigma_0
                # / J_m, b = h sigma_1 / J_m); required with a 2x margin
                s0, s1 = fr.bristle_stiffness_n_m_per_rad, fr.bristle_damping_n_m_s_per_rad
                assert s0 is not None and s1 is not None
                a, b = h * h * s0 / j_m, h * s1 / j_m
                if a + 2.0 * b > 2.0:
                    raise ValueError(
                        f"friction.{axis}.bristle_stiffness_n_m_per_rad: with bristle_damping_n_m_s_per_rad {s1!r} "
                        f"too stiff for internal_step_s {h!r} and motor-side inertia {j_m:.3g} kg m^2 "
                        f"(h^2 sigma_0 / J_m + 2 h sigma_1 / J_m = {a + 2 * b:.3g} > 2)"
                    )
        return self

    def k_m_dps2_per_count(self, axis: Axis) -> float:
        """Seed 000 eq 38: ``k_m = K_t V_count / (J R)`` in deg/s^2 per DAC count (back-EMF, L, friction ignored)."""
        m: MotorConfig = getattr(self, f"motor_{axis}")
        return m.torque_constant_n_m_per_a * m.volts_per_count / (m.inertia_kg_m2 * m.resistance_ohm) * R2D

    def electrical_time_constant_s(self, axis: Axis) -> float:
        m: MotorConfig = getattr(self, f"motor_{axis}")
        return m.inductance_h / m.resistance_ohm


def _describe(exc: ValidationError) -> str:
    err = exc.errors()[0]
    loc = ".".join(str(part) for part in err["loc"])
    msg = str(err["msg"])
    if err["type"] == "extra_forbidden":
        return f"{loc}: unknown field"
    if err["type"] == "value_error":
        msg = msg.removeprefix("Value error, ")
        if not loc:  # a model-level check: the message starts with the field path
            return msg
        if msg.split(":", 1)[0].replace("_", "").isalnum() and ":" in msg:
            return f"{loc}.{msg}"
        return f"{loc}: {msg}"
    got = err.get("input")
    got_s = "" if isinstance(got, dict) else f" (got {got!r})"
    return f"{loc or '<root>'}: {msg}{got_s}"


def load_plant_config(path: str | Path) -> PlantConfig:
    """Read and validate a plant YAML file; :class:`PlantConfigError` (one line: file, field path, reason) if bad."""
    p = Path(path)
    try:
        data: Any = read_yaml_mapping(p)  # the emulator's bounded reader: regular file, size, UTF-8, YAML
    except ConfigError as exc:
        raise PlantConfigError(str(exc)) from None
    try:
        return PlantConfig.model_validate(data)
    except ValidationError as exc:
        raise PlantConfigError(f"{p}: {_describe(exc)}".replace("\n", " ")) from None
