"""Physics model ("plant") of the emulated gimbal: two DC torque-motor axes on a hexapod, gyro, encoders, camera.

Model (docs/emulator.md, "The plant"; seed 000 = Wang et al. 2023, seed 001 = Zhang & Shi, seed 004 = Zhang et al.):

* each axis (az, el): armature ``L di/dt = V - R i - K_e w_rel`` (seed 000 eq 35), torque ``K_t i`` (eq 36), rigid
  load ``J dw/dt = K_t i - T_f(w_rel) + T_imb`` (eqs 33-34 with ``theta_m = theta_L``); ``w`` is the axis' inertial
  rate about its own axis, ``w_rel = w - c`` its rate relative to the carrier (``c`` = carrier rate projected on the
  axis; seed 004 eqs 4-9 style), what friction, back-EMF and the encoder see. ``k_m = K_t V_count / (J R)`` (eq 38);
* friction ``T_f = T_c tanh(w_rel / w_s) + D w_rel``; mass imbalance ``T = -m rho x f`` (seed 001 eq 4), ``f`` the
  carrier's specific force in the elevation frame;
* gyro (seed 000 eq 3): ``k_a w_c / (s + w_c) e^{-T_d s}`` on the elevation-frame inertial rates, + white noise,
  bias, quantisation, sampled each 1 ms tick; encoders quantised; camera miss distance in pixels.

Optional mechanisms ("plant v2"), each off unless its YAML key is present (docs/emulator.md, "Mechanisms"):

* ``structure.<axis>``: two-mass compliance (seed 000 eqs 33-34 with a finite shaft stiffness). The axis' inertia J
  is split into a motor side ``J_m = f J`` and a load side ``J_l = (1 - f) J`` joined by a torsion spring ``k`` and
  damper ``c_s``; from the free-free mode ``w_r = 2 pi mode_hz = sqrt(k / mu)``, ``mu = J_m J_l / J``:
  ``k = w_r^2 mu``, ``c_s = 2 zeta w_r mu``::

      J_m dw_m/dt = K_t i (1 + ripple) - T_f(w_m - c) - k_c theta_m - c_c (w_m - c) - k (theta_m - theta_l)
                    - c_s (w_m - w_l)
      J_l dw_l/dt = k (theta_m - theta_l) + c_s (w_m - w_l) + T_imb
      d theta_m/dt = w_m - c,   d theta_l/dt = w_l - c

  Motor side (collocated with the motor): motor torque and its ripple, back-EMF (``K_e (w_m - c)``), bearing
  friction (tanh or LuGre), the cable harness and the **encoder**. Load side: the mass imbalance, the **gyro** and
  the **camera** (the LOS is the load's). Without ``structure`` both sides are one rigid body (``theta_m = theta_l``).
* ``friction.<axis>.model: lugre``: LuGre friction (Canudas de Wit et al., IEEE TAC 40(3), 1995) on the motor-side
  relative rate ``v``: ``dz/dt = v - sigma_0 |v| z / g(v)``, ``g(v) = T_c + (T_s - T_c) exp(-(v / v_s)^2)``,
  ``T_f = sigma_0 z + sigma_1 dz/dt + D v``; z is updated implicitly (``z' = (z + h v) / (1 + h sigma_0 |v| / g)``),
  stable for any step: true stiction (no creep below breakaway), bounded presliding.
* ``drive.<axis>.current_limit_a``: the driver's current limit, ``|i| <= I_max`` (torque authority ``K_t I_max``).
* ``cable.<axis>``: harness spring and damper on the motor-side relative angle, ``-k_c theta_m - c_c (w_m - c)``
  (neutral at encoder zero).
* ``mount.pivot_offset_m``: the gimbal's pivot at ``r`` (body frame) from the hexapod's rotation centre; the
  imbalance feels ``f_pivot = f_centre + alpha x r + omega x (omega x r)`` (seed 001 eqs 2-4).
* ``gyro.noise_psd``: coloured gyro noise, each ``{centre_hz, bandwidth_hz, std_dps}`` a second-order digital
  band-pass (the bilinear peak filter of ``scipy.signal.iirpeak``) of its own white noise, per axis;
  ``gyro.random_walk``: rate random walk of the bias (deg/s per sqrt(s)).
* ``ripple.<axis>``: motor torque ripple ``K_t i (1 + a sin(N theta_m))`` (current-proportional ripple at N periods
  per revolution of the motor-side relative angle; cogging proper, a torque independent of the current, is not
  modelled).

Frames: carrier body x forward, y right, z down; gimbal at ``az = el = 0`` aligned with the body; ``az`` about
``z_b``, ``el`` about ``y_o``; the LOS is ``x_e``. Positive az turns the LOS right, positive el raises it.

Integration: exact zero-order-hold discretisation of the linear part (current, motor and load rates and angles,
back-EMF, viscous friction, shaft, cable) at the internal step, by the matrix exponential at construction; drive,
carrier rate and imbalance torque held over the tick (the carrier is given at mid-tick), friction (tanh or LuGre) and
ripple over each sub-step; the current limit as a fast current loop (a sub-step whose update would exceed the limit
is redone with the voltage that holds ``di/dt = 0`` at the limit). The gyro filter is discretised exactly at the tick
for an input linear between tick ends (first-order hold), the delay evaluated exactly inside the tick plus whole
ticks from a ring.

The hot path is a numba kernel (``@numba.njit(cache=True)``: compiled once, cached in ``firmware_stub/__pycache__``)
over float64 arrays of parameters and state; :class:`Plant` is the readable API around it. ``Plant.step_tick`` makes
one compiled call per tick; :meth:`Plant.run` loops many ticks inside one compiled call (offline use: fitting,
benchmarks).

Randomness (reproducible across platforms): the bytes of ``random.Random(seed).randbytes``, drawn in blocks of 1000
ticks (by numpy's MT19937 put in that generator's state: the same 32-bit words, ~10x faster); each Gaussian is one of
2^16 normal quantiles picked by 16 little-endian random bits. The white gyro and camera noise sequence is the one of
the pure-Python plant before the kernel. The coloured noise and random walk draw from a second stream,
``random.Random(f"{seed}/gyro-extra")``, so switching them on leaves the white noise unchanged.

This module imports nothing from ``hil`` (``firmware_stub`` may only use ``hil.protocol``).
"""

from __future__ import annotations

import math
import random
from array import array
from collections.abc import Iterable
from pathlib import Path
from statistics import NormalDist
from typing import Any, Generic, Literal, NamedTuple, TypeVar

import llvmlite.ir as llvm_ir
import numba
import numpy as np
from numba import types as nbt
from numba.extending import intrinsic
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from firmware_stub.config import ConfigError, read_yaml_mapping

__all__ = [
    "DEFAULT_PLANT_CONFIG",
    "RIGID_PLANT_CONFIG",
    "CableAxisConfig",
    "CableConfig",
    "CameraConfig",
    "CarrierMotion",
    "DriveAxisConfig",
    "DriveConfig",
    "EncoderConfig",
    "FrictionAxisConfig",
    "FrictionConfig",
    "GyroConfig",
    "GyroNoiseBand",
    "HexapodConfig",
    "ImbalanceConfig",
    "MotorConfig",
    "MountConfig",
    "Plant",
    "PlantConfig",
    "PlantConfigError",
    "RippleAxisConfig",
    "RippleConfig",
    "StructureAxisConfig",
    "StructureConfig",
    "attitude_at_tick_end",
    "carrier_state",
    "imbalance_torques",
    "load_plant_config",
]

DEFAULT_PLANT_CONFIG = Path(__file__).parents[1] / "profiles/plant/default.yaml"
RIGID_PLANT_CONFIG = Path(__file__).parents[1] / "profiles/plant/rigid.yaml"

G0_M_S2 = 9.80665  # standard gravity; lab z is down, so gravity in the lab is (0, 0, +G0)
D2R = math.pi / 180.0
R2D = 180.0 / math.pi
TICK_S = 1e-3
GYRO_NYQUIST_HZ = 0.5 / TICK_S

Vec3f = tuple[float, float, float]
Axis = Literal["az", "el"]


class PlantConfigError(ValueError):
    """A plant config file is not valid: one line naming the file, the field path and the reason."""


# --- configuration -------------------------------------------------------------------------------------------------


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
            j_m = self.motor_side_inertia(axis)  # type: ignore[arg-type]
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


# --- carrier input -------------------------------------------------------------------------------------------------


class CarrierMotion(NamedTuple):
    """Hexapod pose (lab -> platform) at mid-tick and its first and second time derivatives.

    ``pose = (x_mm, y_mm, z_mm, roll_deg, pitch_deg, yaw_deg)`` (ZYX Euler angles), ``rate`` in mm/s and deg/s,
    ``accel`` in mm/s^2 and deg/s^2, same order.
    """

    pose: tuple[float, float, float, float, float, float]
    rate: tuple[float, float, float, float, float, float]
    accel: tuple[float, float, float, float, float, float]

    @classmethod
    def at_rest(cls) -> CarrierMotion:
        z = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        return cls(z, z, z)


_AT_REST = CarrierMotion.at_rest()


class _CarrierState(NamedTuple):
    """What the plant derives from one CarrierMotion (all SI, body frame)."""

    pqr: Vec3f  # body rate at mid-tick, rad/s
    pqr_dot: Vec3f  # its derivative, rad/s^2
    f_body: Vec3f  # specific force (inertial acceleration minus gravity), m/s^2
    dcm_lab_to_body: tuple[Vec3f, Vec3f, Vec3f]  # at the end of the tick (camera)


def carrier_state(carrier: CarrierMotion) -> _CarrierState:
    """Body rates (exact ZYX Euler-rate formula) and their derivative, specific force in the body frame, attitude."""
    _, _, _, roll, pitch, yaw = carrier.pose
    _, _, _, rolld, pitchd, yawd = carrier.rate
    xdd, ydd, zdd, rolldd, pitchdd, yawdd = carrier.accel
    phi, th, psi = roll * D2R, pitch * D2R, yaw * D2R
    phid, thd, psid = rolld * D2R, pitchd * D2R, yawd * D2R
    phidd, thdd, psidd = rolldd * D2R, pitchdd * D2R, yawdd * D2R
    sf, cf = math.sin(phi), math.cos(phi)
    st, ct = math.sin(th), math.cos(th)
    sp, cp = math.sin(psi), math.cos(psi)
    p = phid - psid * st
    q = thd * cf + psid * sf * ct
    r = -thd * sf + psid * cf * ct
    pd = phidd - psidd * st - psid * thd * ct
    qd = thdd * cf - thd * phid * sf + psidd * sf * ct + psid * (phid * cf * ct - thd * sf * st)
    rd = -thdd * sf - thd * phid * cf + psidd * cf * ct - psid * (phid * sf * ct + thd * cf * st)
    c = _dcm_zyx((sf, cf), (st, ct), (sp, cp))
    fx, fy, fz = xdd * 1e-3, ydd * 1e-3, zdd * 1e-3 - G0_M_S2
    f_body = (
        c[0][0] * fx + c[0][1] * fy + c[0][2] * fz,
        c[1][0] * fx + c[1][1] * fy + c[1][2] * fz,
        c[2][0] * fx + c[2][1] * fy + c[2][2] * fz,
    )
    return _CarrierState((p, q, r), (pd, qd, rd), f_body, attitude_at_tick_end(carrier))


def attitude_at_tick_end(carrier: CarrierMotion) -> tuple[Vec3f, Vec3f, Vec3f]:
    """DCM lab -> platform at the end of the tick: the pose is given at mid-tick, extrapolated by half a tick with
    its rate and acceleration (second order)."""
    dt = 0.5 * TICK_S
    k2 = 0.5 * dt * dt
    _, _, _, roll, pitch, yaw = carrier.pose
    _, _, _, rolld, pitchd, yawd = carrier.rate
    _, _, _, rolldd, pitchdd, yawdd = carrier.accel
    phi = (roll + rolld * dt + rolldd * k2) * D2R
    th = (pitch + pitchd * dt + pitchdd * k2) * D2R
    psi = (yaw + yawd * dt + yawdd * k2) * D2R
    return _dcm_zyx((math.sin(phi), math.cos(phi)), (math.sin(th), math.cos(th)), (math.sin(psi), math.cos(psi)))


def _dcm_zyx(
    roll_sc: tuple[float, float], pitch_sc: tuple[float, float], yaw_sc: tuple[float, float]
) -> tuple[Vec3f, Vec3f, Vec3f]:
    """Passive DCM lab -> body for ZYX Euler angles, given (sin, cos) of each: ``R_x(roll) R_y(pitch) R_z(yaw)``."""
    (sf, cf), (st, ct), (sp, cp) = roll_sc, pitch_sc, yaw_sc
    return (
        (ct * cp, ct * sp, -st),
        (sf * st * cp - cf * sp, sf * st * sp + cf * cp, sf * ct),
        (cf * st * cp + sf * sp, cf * st * sp - sf * cp, cf * ct),
    )


# --- discretisation (construction only) ----------------------------------------------------------------------------


def _expm(a: np.ndarray) -> np.ndarray:
    """Matrix exponential (construction only): ``scipy.linalg.expm`` of the balanced matrix. The augmented
    ``[[A, B], [0, 0]] h`` of an axis with a structural mode has entries ten decades apart; balancing (a diagonal
    scaling by powers of two, exact) keeps every entry of the result to ~1e-13 relative, where plain ``expm`` leaves
    ~1e-9 on the smallest ones (current and voltage into the load rate and the angles). The tests check every
    entry against a 50-digit series, and the plant against analytic solutions."""
    from scipy.linalg import expm, matrix_balance

    balanced, (scale, _) = matrix_balance(a, permute=False, separate=True)
    return expm(balanced) * scale[:, None] / scale[None, :]


def axis_matrices(cfg: PlantConfig, axis: Axis) -> tuple[np.ndarray, np.ndarray]:
    """Continuous ``(A, B)`` of one axis: state ``(i, w_m, theta_m, w_l, theta_l)`` [A, rad/s, rad, rad/s, rad],
    inputs ``(V, c, T_m, T_l)`` [V, rad/s, N m, N m]: ``T_m`` the nonlinear torque on the motor side (friction,
    ripple), ``T_l`` on the load (imbalance). Without ``structure`` the load rows repeat the motor rows (one rigid
    body, ``T_l`` on the same inertia)."""
    m: MotorConfig = getattr(cfg, f"motor_{axis}")
    r, ll, kt, ke, j = (m.resistance_ohm, m.inductance_h, m.torque_constant_n_m_per_a, m.back_emf_v_s_per_rad,
                        m.inertia_kg_m2)
    d = getattr(cfg.friction, axis).viscous_n_m_s_per_rad
    cab = cfg.cable_of(axis)
    kc, cc = (0.0, 0.0) if cab is None else (cab.stiffness_n_m_per_rad, cab.damping_n_m_s_per_rad)
    st = cfg.structure_of(axis)
    a = np.zeros((5, 5))
    b = np.zeros((5, 4))
    a[0, 0], a[0, 1] = -r / ll, -ke / ll
    b[0, 0], b[0, 1] = 1.0 / ll, ke / ll
    a[2, 1], b[2, 1] = 1.0, -1.0
    if st is None:
        a[1, 0], a[1, 1], a[1, 2] = kt / j, -(d + cc) / j, -kc / j
        b[1, 1], b[1, 2], b[1, 3] = (d + cc) / j, 1.0 / j, 1.0 / j
        a[3:5], b[3:5] = a[1:3], b[1:3]  # the load is the motor
        a[:, 3:5] = 0.0
        return a, b
    f = st.motor_inertia_fraction
    jm, jl = f * j, (1.0 - f) * j
    mu = jm * jl / j
    wr = 2.0 * math.pi * st.mode_hz
    ks, cs = wr * wr * mu, 2.0 * st.damping_ratio * wr * mu
    a[1, 0], a[1, 1], a[1, 2], a[1, 3], a[1, 4] = kt / jm, -(d + cc + cs) / jm, -(ks + kc) / jm, cs / jm, ks / jm
    b[1, 1], b[1, 2] = (d + cc) / jm, 1.0 / jm
    a[3, 1], a[3, 2], a[3, 3], a[3, 4] = cs / jl, ks / jl, -cs / jl, -ks / jl
    b[3, 3] = 1.0 / jl
    a[4, 3], b[4, 1] = 1.0, -1.0
    return a, b


def axis_zoh(cfg: PlantConfig, axis: Axis, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact ZOH of :func:`axis_matrices` over ``h``: ``(Phi, Gamma)`` from ``expm([[A, B], [0, 0]] h)``. Without
    ``structure`` the rigid 3-state system is discretised and its rate and angle rows copied to the load rows (so
    the load equals the motor bit for bit)."""
    a, b = axis_matrices(cfg, axis)
    n = 3 if cfg.structure_of(axis) is None else 5
    aug = np.zeros((n + 4, n + 4))
    aug[:n, :n], aug[:n, n:] = a[:n, :n] * h, b[:n] * h
    e = _expm(aug)
    phi, gam = np.zeros((5, 5)), np.zeros((5, 4))
    phi[:n, :n], gam[:n] = e[:n, :n], e[:n, n:]
    if n == 3:
        phi[3:5], gam[3:5] = phi[1:3], gam[1:3]
    return phi, gam


def _foh(wc: float, tau: float, gain: float) -> tuple[float, float, float]:
    """Exact discretisation of ``gain * wc / (s + wc)`` over ``tau`` for an input linear in time (first-order hold):
    ``y(tau) = e y(0) + c1 x(tau) + c0 x(0)``; returns ``(e, c1, c0)``."""
    e = math.exp(-wc * tau)
    one_minus_e = -math.expm1(-wc * tau)
    k = one_minus_e / (wc * tau)
    return e, gain * (1.0 - k), gain * (k - e)


def band_pass(centre_hz: float, bandwidth_hz: float, fs_hz: float = 1.0 / TICK_S) -> tuple[float, float, float, float]:
    """Second-order digital band-pass ``H(z) = b0 (1 - z^-2) / (1 + a1 z^-1 + a2 z^-2)``, unit gain at the centre,
    -3 dB width ``bandwidth_hz`` (the bilinear peak filter of ``scipy.signal.iirpeak(centre, centre / bandwidth,
    fs)``). Returns ``(b0, a1, a2, var_gain)``, ``var_gain`` the output variance for unit white input
    (``2 b0^2 (gamma_0 - gamma_2)`` from the AR(2) autocovariances)."""
    w0 = 2.0 * math.pi * centre_hz / fs_hz
    bw = 2.0 * math.pi * bandwidth_hz / fs_hz
    gain = 1.0 / (1.0 + math.tan(bw / 2.0))
    b0 = 1.0 - gain
    a1, a2 = -2.0 * gain * math.cos(w0), 2.0 * gain - 1.0
    f1, f2 = -a1, -a2  # x_t = f1 x_{t-1} + f2 x_{t-2} + e_t
    g0 = (1.0 - f2) / ((1.0 + f2) * ((1.0 - f2) ** 2 - f1 * f1))
    g1 = f1 * g0 / (1.0 - f2)
    g2 = f1 * g1 + f2 * g0
    return b0, a1, a2, 2.0 * b0 * b0 * (g0 - g2)


# --- Gaussian noise by table lookup --------------------------------------------------------------------------------

_NORMAL_BITS = 16
_NORMAL_TABLE = array("d")


def normal_table() -> array[float]:
    """2^16 standard-normal quantiles at ``(k + 1/2) / 2^16``: indexed by 16 random bits, a Gaussian draw that costs
    one table lookup (tails cut at +-4.17 sigma; std 0.9999). Built once per process (~50 ms)."""
    if not _NORMAL_TABLE:
        inv = NormalDist().inv_cdf
        n = 1 << _NORMAL_BITS
        _NORMAL_TABLE.extend(inv((k + 0.5) / n) for k in range(n))
    return _NORMAL_TABLE


_NOISE_WHITE = 5  # per tick: gyro x, y, z (bias + noise, output units), camera x, y (px)
_NOISE_BLOCK_TICKS = 1000
_ROUND = 6755399441055744.0  # 1.5 * 2^52: (x + _ROUND) - _ROUND is x rounded to the nearest integer (|x| < 2^51)
_MAX_BANDS = 8

# --- layout of the parameter array p (float64) ----------------------------------------------------------------------
# per axis (az at 0, el at PA_LEN):
PA_PHI = 0  # 25: Phi, row-major 5 x 5
PA_GAM = 25  # 20: Gamma, row-major 5 x 4 (inputs V, c, T_m, T_l)
(PA_VPC, PA_VMAX, PA_FMODEL, PA_TC, PA_IWS, PA_TS, PA_IVS, PA_S0, PA_S1, PA_ILIM, PA_R, PA_KE, PA_RIPA, PA_RIPN,
 PA_D, PA_KC, PA_CC, PA_KS, PA_CS, PA_S1H) = range(45, 65)
PA_LEN = 65
# global
(P_NSUB, P_H, P_MRX, P_MRY, P_MRZ, P_HAS_IMB, P_PVX, P_PVY, P_PVZ, P_HAS_PIV, P_EF, P_C1, P_C0, P_EA, P_D1, P_D0,
 P_DELAY, P_LSB, P_INV_LSB, P_ENC_LSB, P_NCOL, P_RW, P_STRIDE, P_TGX, P_TGY, P_TGZ, P_IFOV, P_HW, P_HH) = range(
    2 * PA_LEN, 2 * PA_LEN + 29)
P_COL = 2 * PA_LEN + 29  # _MAX_BANDS x (b0 in output units per unit normal, a1, a2)
P_LEN = P_COL + 3 * _MAX_BANDS

# --- layout of the state array s (float64) --------------------------------------------------------------------------
S_X = 0  # 10: per axis (i, w_m, theta_m, w_l, theta_l); az at 0, el at 5
S_Z = 10  # 2: LuGre bristle deflection z (rad)
S_V = 12  # 2: armature voltage applied over the last sub-step
S_TF = 14  # 2: friction torque held over the last sub-step (opposing motion)
S_SC = 16  # 4: sin, cos of the load's az, sin, cos of the load's el, at the tick end
S_G = 20  # 3: gyro filter state (output units)
S_XO = 23  # 3: the filter's input at the previous tick end (rad/s)
S_M = 26  # 3: gyro outputs (deg/s)
S_TICK, S_NK, S_RINGJ, S_REFILL = 29, 30, 31, 32
S_CAMN = 33  # 2: this tick's camera noise (px)
S_CARR = 35  # 18: the last tick's carrier (pose, rate, accel)
S_HASC = 53  # 1 once a tick ran
S_RW = 54  # 3: random-walk part of the gyro bias (output units)
S_IMB = 57  # 2: imbalance torque held over the last tick (az, el)
S_LOS = 59  # 3: true elevation-frame inertial rates at the tick end (rad/s)
S_ATT = 62  # 4: sin, cos of the carrier's roll and pitch at the last mid-tick
S_RIP = 66  # 4: sin, cos of N theta_m (ripple phase), az then el
S_COL = 70  # _MAX_BANDS x 3 axes x (e1, e2, y1, y2) of the coloured-noise filters
S_RING = S_COL + 4 * 3 * _MAX_BANDS  # 3 x delay_ticks: the gyro's whole-tick delay line

OUT_LEN = 8  # step_tick's tuple: gyro x, y, z (deg/s), encoders az, el (deg), currents az, el (A), refill flag


def _params(cfg: PlantConfig) -> np.ndarray:
    """Every constant of the kernel, in the layout above."""
    p = np.zeros(P_LEN)
    h = cfg.internal_step_s
    for ax, axis in enumerate(("az", "el")):
        b = ax * PA_LEN
        phi, gam = axis_zoh(cfg, axis, h)  # type: ignore[arg-type]
        p[b + PA_PHI: b + PA_PHI + 25] = phi.ravel()
        p[b + PA_GAM: b + PA_GAM + 20] = gam.ravel()
        m: MotorConfig = getattr(cfg, f"motor_{axis}")
        fr: FrictionAxisConfig = getattr(cfg.friction, axis)
        p[b + PA_VPC], p[b + PA_VMAX] = m.volts_per_count, m.bus_voltage_v
        p[b + PA_TC], p[b + PA_IWS] = fr.coulomb_n_m, 1.0 / (fr.smoothing_rate_dps * D2R)
        p[b + PA_D] = fr.viscous_n_m_s_per_rad
        if fr.model == "lugre":
            assert fr.stiction_n_m is not None and fr.stribeck_rate_dps is not None
            p[b + PA_FMODEL] = 1.0
            p[b + PA_TS], p[b + PA_IVS] = fr.stiction_n_m, 1.0 / (fr.stribeck_rate_dps * D2R)
            p[b + PA_S0] = fr.bristle_stiffness_n_m_per_rad or 0.0
            p[b + PA_S1] = fr.bristle_damping_n_m_s_per_rad or 0.0
            p[b + PA_S1H] = p[b + PA_S1] / h
        p[b + PA_ILIM] = cfg.current_limit_a(axis) or 0.0  # type: ignore[arg-type]
        p[b + PA_R], p[b + PA_KE] = m.resistance_ohm, m.back_emf_v_s_per_rad
        rip = cfg.ripple_of(axis)  # type: ignore[arg-type]
        if rip is not None:
            p[b + PA_RIPA], p[b + PA_RIPN] = rip.amplitude_fraction * m.torque_constant_n_m_per_a, rip.periods_per_rev
        cab = cfg.cable_of(axis)  # type: ignore[arg-type]
        if cab is not None:
            p[b + PA_KC], p[b + PA_CC] = cab.stiffness_n_m_per_rad, cab.damping_n_m_s_per_rad
        st = cfg.structure_of(axis)  # type: ignore[arg-type]
        if st is not None:
            j = m.inertia_kg_m2
            mu = st.motor_inertia_fraction * (1.0 - st.motor_inertia_fraction) * j
            wr = 2.0 * math.pi * st.mode_hz
            p[b + PA_KS], p[b + PA_CS] = wr * wr * mu, 2.0 * st.damping_ratio * wr * mu
    p[P_NSUB], p[P_H] = round(TICK_S / h), h
    mass = cfg.imbalance.mass_kg
    mr = [mass * x * 1e-3 for x in cfg.imbalance.eccentricity_mm]
    p[P_MRX], p[P_MRY], p[P_MRZ] = mr
    p[P_HAS_IMB] = 1.0 if mass > 0.0 and any(mr) else 0.0
    piv = cfg.pivot_offset_m()
    p[P_PVX], p[P_PVY], p[P_PVZ] = piv
    p[P_HAS_PIV] = 1.0 if any(piv) else 0.0
    g = cfg.gyro
    wc = 2.0 * math.pi * g.bandwidth_hz
    ef, c1, c0 = _foh(wc, TICK_S, g.scale_factor)  # filter state, tick end to tick end
    delay_ticks = int(g.delay_s / TICK_S + 1e-9)
    tau_r = g.delay_s - delay_ticks * TICK_S  # the rest of the delay, within one tick
    alpha = TICK_S - tau_r if tau_r > 1e-12 else TICK_S
    ea, c1a, c0a = _foh(wc, alpha, g.scale_factor)
    fa = alpha / TICK_S  # the input at t0 + alpha, linearly interpolated
    d1, d0 = c1a * fa, c1a * (1.0 - fa) + c0a  # y(alpha) = ea y0 + d1 x1 + d0 x0
    # the filter, the delay ring and the noise work in the output's unit: gyro LSBs (deg/s if not quantised)
    lsb = g.quantisation_lsb_dps
    inv_lsb = 1.0 / lsb if lsb > 0 else 0.0
    per_rad_s = R2D * inv_lsb if lsb > 0 else R2D
    unit = lsb or 1.0
    p[P_EF], p[P_C1], p[P_C0] = ef, c1 * per_rad_s, c0 * per_rad_s
    p[P_EA], p[P_D1], p[P_D0] = ea, d1 * per_rad_s, d0 * per_rad_s
    p[P_DELAY], p[P_LSB], p[P_INV_LSB] = delay_ticks, lsb, inv_lsb
    p[P_ENC_LSB] = 360.0 / cfg.encoder.counts_per_rev
    bands = [b for b in g.noise_psd if b.std_dps > 0.0]
    p[P_NCOL] = len(bands)
    for k, band in enumerate(bands):
        b0, a1, a2, var = band_pass(band.centre_hz, band.bandwidth_hz)
        p[P_COL + 3 * k: P_COL + 3 * k + 3] = (b0 * band.std_dps / math.sqrt(var) / unit, a1, a2)
    p[P_RW] = g.random_walk * math.sqrt(TICK_S) / unit
    p[P_STRIDE] = _NOISE_WHITE + 3 * len(bands) + (3 if g.random_walk > 0 else 0)
    cam = cfg.camera
    taz, tel = cam.target_az_deg * D2R, cam.target_el_deg * D2R
    p[P_TGX], p[P_TGY], p[P_TGZ] = math.cos(tel) * math.cos(taz), math.cos(tel) * math.sin(taz), -math.sin(tel)
    p[P_IFOV], p[P_HW], p[P_HH] = cam.ifov_deg_per_px, cam.half_width_px, cam.half_height_px
    return p


# --- the compiled kernel ---------------------------------------------------------------------------------------------
# Plain functions over float64 arrays (p: parameters, s: state, nz: the current noise block); numba compiles them on
# first use and caches the machine code (cache=True) next to this file. No Python objects inside.

_HALF = 0.5 * TICK_S
_JIT = {"cache": True, "error_model": "numpy"}  # (no nogil: releasing the GIL costs ~0.2 us per call)
_INLINE = {**_JIT, "inline": "always"}  # small helpers, inlined into their callers at numba's IR level


@numba.njit(**_INLINE)
def _carrier(p, pose, rate, acc):
    """Body rates (p, q, r) and derivatives at the carrier's instant, and the specific force at the gimbal's pivot in
    the body frame: ``f_c + alpha x r + omega x (omega x r)`` (seed 001 eqs 2-4; r = mount.pivot_offset_m); and the
    sin and cos of roll and pitch."""
    ph, th, ps = pose[3] * D2R, pose[4] * D2R, pose[5] * D2R
    phd, thd, psd = rate[3] * D2R, rate[4] * D2R, rate[5] * D2R
    phdd, thdd, psdd = acc[3] * D2R, acc[4] * D2R, acc[5] * D2R
    sf, cf, st, ct = math.sin(ph), math.cos(ph), math.sin(th), math.cos(th)
    pc = psd * ct
    pr = phd - psd * st
    qr = thd * cf + pc * sf
    rr = pc * cf - thd * sf
    pd = phdd - psdd * st - thd * pc
    qd = thdd * cf - thd * phd * sf + psdd * sf * ct + psd * (phd * cf * ct - thd * sf * st)
    rd = -thdd * sf - thd * phd * cf + psdd * cf * ct - psd * (phd * sf * ct + thd * cf * st)
    fz = acc[2] * 1e-3 - G0_M_S2
    if acc[0] != 0.0 or acc[1] != 0.0:
        sp, cp = math.sin(ps), math.cos(ps)
        fx, fy = acc[0] * 1e-3, acc[1] * 1e-3
        fbx = ct * cp * fx + ct * sp * fy - st * fz
        fby = (sf * st * cp - cf * sp) * fx + (sf * st * sp + cf * cp) * fy + sf * ct * fz
        fbz = (cf * st * cp + sf * sp) * fx + (cf * st * sp - sf * cp) * fy + cf * ct * fz
    else:
        fbx, fby, fbz = -st * fz, sf * ct * fz, cf * ct * fz
    if p[P_HAS_PIV] != 0.0:
        rx, ry, rz = p[P_PVX], p[P_PVY], p[P_PVZ]
        wxr_x, wxr_y, wxr_z = qr * rz - rr * ry, rr * rx - pr * rz, pr * ry - qr * rx  # omega x r
        fbx += qd * rz - rd * ry + qr * wxr_z - rr * wxr_y
        fby += rd * rx - pd * rz + rr * wxr_x - pr * wxr_z
        fbz += pd * ry - qd * rx + pr * wxr_y - qr * wxr_x
    return pr, qr, rr, pd, qd, rd, fbx, fby, fbz, sf, cf, st, ct


@numba.njit(**_INLINE)
def _imbalance(p, fbx, fby, fbz, sa, ca, se, ce):  # noqa: PLR0917
    """``-m rho x f`` with f (body) in the elevation frame (seed 001 eqs 3-4): torques about z_o and y_e."""
    mrx, mry, mrz = p[P_MRX], p[P_MRY], p[P_MRZ]
    hxy = ca * fbx + sa * fby
    fx = hxy * ce - fbz * se
    fy = ca * fby - sa * fbx
    fz = hxy * se + fbz * ce
    tix = mrz * fy - mry * fz
    tim_e = mrx * fz - mrz * fx
    tim_a = ce * (mry * fx - mrx * fy) - se * tix
    return tim_a, tim_e


@intrinsic
def _vdiv(typingctx, num, den):
    """``num[j] / den[j]`` for two tuples of n float64 as one LLVM vector division: IEEE division in each lane (the
    same quotient as ``num[j] / den[j]``, bit for bit), but the CPU divides 2 or 4 lanes in about the time of one
    (division is the slowest arithmetic and the Taylor series below need six per angle)."""
    if not (isinstance(num, nbt.UniTuple) and isinstance(den, nbt.UniTuple) and num.count == den.count
            and num.dtype == nbt.float64 and den.dtype == nbt.float64):
        return None
    n = num.count

    def codegen(context, builder, signature, args):
        vec = llvm_ir.VectorType(llvm_ir.DoubleType(), n)
        lanes = [llvm_ir.Constant(llvm_ir.IntType(32), j) for j in range(n)]
        a = b = llvm_ir.Constant(vec, llvm_ir.Undefined)
        for j in range(n):
            a = builder.insert_element(a, builder.extract_value(args[0], j), lanes[j])
            b = builder.insert_element(b, builder.extract_value(args[1], j), lanes[j])
        q = builder.fdiv(a, b)  # no fast-math flags: IEEE, correctly rounded per lane
        return context.make_tuple(builder, signature.return_type, [builder.extract_element(q, x) for x in lanes])

    return num(num, den), codegen


_TAYLOR_DEN = (6.0, 20.0, 42.0, 12.0, 30.0, 56.0)  # the divisors of the sin / cos Taylor series in _rotated


@numba.njit(**_INLINE)
def _rotated(sa, ca, d, q):
    """sin and cos of ``a + d`` from those of ``a``, with ``q = d^2 / _TAYLOR_DEN`` (see :func:`_rotate`)."""
    if abs(d) < 0.1:
        d2 = d * d
        sd = d * (1.0 - q[0] * (1.0 - q[1] * (1.0 - q[2])))  # d (1 - d^2/6 (1 - d^2/20 (1 - d^2/42)))
        cd = 1.0 - d2 / 2.0 * (1.0 - q[3] * (1.0 - q[4] * (1.0 - q[5])))  # 1 - d^2/2 (1 - d^2/12 (...))
    else:
        sd, cd = math.sin(d), math.cos(d)
    return sa * cd + ca * sd, ca * cd - sa * sd


@numba.njit(**_INLINE)
def _rotate(sa, ca, d):
    """sin and cos of ``a + d`` from those of ``a``: Taylor series of sin d and cos d to 7th / 8th order for
    |d| < 0.1 (error < 3e-15), libm above."""
    d2 = d * d
    return _rotated(sa, ca, d, _vdiv((d2, d2, d2, d2, d2, d2), _TAYLOR_DEN))


@numba.njit(**_INLINE)
def _rotate2(sa, ca, da, sb, cb, db):  # noqa: PLR0917
    """:func:`_rotate` of two angles, their 12 divisions as one vector division."""
    a2, b2 = da * da, db * db
    q = _vdiv((a2, a2, a2, a2, a2, a2, b2, b2, b2, b2, b2, b2), _TAYLOR_DEN + _TAYLOR_DEN)
    sa, ca = _rotated(sa, ca, da, q[0:6])
    sb, cb = _rotated(sb, cb, db, q[6:12])
    return sa, ca, sb, cb


@numba.njit(**_INLINE)
def _renorm(sa, ca):
    """(sin, cos) pulled back onto the unit circle: one Newton step of 1 / sqrt(s^2 + c^2) (they drift by rounding
    only, ~1e-16 per rotation)."""
    k = 0.5 * (3.0 - (sa * sa + ca * ca))
    return sa * k, ca * k


@numba.njit(**_INLINE)
def _tanh(x):
    """tanh as ``1 - 2 / (e^{2x} + 1)``: absolute error < 3e-16, 2.5x faster than libm's tanh here."""
    return 1.0 - 2.0 / (math.exp(2.0 * x) + 1.0)


@numba.njit(**_INLINE)
def _held(p, b, v, c, tl):
    """The part of one sub-step's update that is held over the tick: ``Gamma (V, c, ., T_l)``."""
    g = b + PA_GAM
    return (p[g] * v + p[g + 1] * c + p[g + 3] * tl, p[g + 4] * v + p[g + 5] * c + p[g + 7] * tl,
            p[g + 8] * v + p[g + 9] * c + p[g + 11] * tl, p[g + 12] * v + p[g + 13] * c + p[g + 15] * tl,
            p[g + 16] * v + p[g + 17] * c + p[g + 19] * tl)


@numba.njit(**_INLINE)
def _lugre_z(p, b, vr, z, e):
    """LuGre's bristle deflection z over one sub-step, implicit (stable for any step; z -> g(v) / sigma_0 when
    sliding): ``z+ = (z + h v) / (1 + h sigma_0 |v| / g(v))``, ``g(v) = T_c + (T_s - T_c) exp(-(v / v_s)^2)``; ``e`` is
    that exponential. Returns the numerator and denominator of ``z+ = g (z + h v) / (g + h sigma_0 |v|)``."""
    tc = p[b + PA_TC]
    gv = tc + (p[b + PA_TS] - tc) * e
    return gv * (z + p[P_H] * vr), gv + p[P_H] * p[b + PA_S0] * abs(vr)


@numba.njit(**_INLINE)
def _lugre_torque(p, b, z, zn):
    """LuGre's friction torque over a sub-step: ``sigma_0 z+ + sigma_1 dz/dt``, ``dz/dt = (z+ - z) / h``."""
    return p[b + PA_S0] * zn + p[b + PA_S1H] * (zn - z)


@numba.njit(**_INLINE)
def _friction(p, b, vr, z):
    """Friction torque held over one sub-step (opposing the motor-side relative rate ``vr``) and LuGre's z at its
    end: LuGre, or ``T_c tanh(vr / w_s)`` (the viscous part is in the ZOH matrices)."""
    tc = p[b + PA_TC]
    if p[b + PA_FMODEL] != 0.0:
        u = vr * p[b + PA_IVS]
        num, den = _lugre_z(p, b, vr, z, math.exp(-u * u))
        zn = num / den
        return _lugre_torque(p, b, z, zn), zn
    if tc != 0.0:
        return tc * _tanh(vr * p[b + PA_IWS]), z
    return 0.0, z


@numba.njit(**_INLINE)
def _friction2(p, lugre2, vra, za, vre, ze):  # noqa: PLR0917
    """:func:`_friction` of both axes. With LuGre on both (``lugre2``) the two libm ``exp`` calls are made next to
    each other: a call clobbers every floating-point register, so the values live across it are spilled to the stack
    and reloaded, once per sub-step instead of twice. (Doing the same for tanh friction measured slower.)"""
    if lugre2:
        ua, ue = vra * p[PA_IVS], vre * p[PA_LEN + PA_IVS]
        ea = math.exp(-ua * ua)
        ee = math.exp(-ue * ue)
        na, da = _lugre_z(p, 0, vra, za, ea)
        ne, de = _lugre_z(p, PA_LEN, vre, ze, ee)
        zna, zne = na / da, ne / de
        return _lugre_torque(p, 0, za, zna), zna, _lugre_torque(p, PA_LEN, ze, zne), zne
    tfa, za = _friction(p, 0, vra, za)
    tfe, ze = _friction(p, PA_LEN, vre, ze)
    return tfa, za, tfe, ze


@numba.njit(**_INLINE)
def _zoh(p, b, x, k, tm, v, vr):  # noqa: PLR0917
    """One exact-ZOH sub-step of one axis (parameters at ``b``): ``x+ = Phi x + k + Gamma_m T_m`` with the motor-side
    torque ``T_m`` (friction, ripple) held over the sub-step and the current limit as a fast current loop. Returns
    ``(x+, applied voltage)``."""
    x0, x1, x2, x3, x4 = x
    f = b + PA_PHI
    g = b + PA_GAM
    # sums as trees (the compiler may not reassociate): the dependency chain between sub-steps is 4 adds deep, not 7
    n0 = ((p[f] * x0 + p[f + 1] * x1) + (p[f + 2] * x2 + p[f + 3] * x3)) + ((p[f + 4] * x4 + k[0]) + p[g + 2] * tm)
    n1 = ((p[f + 5] * x0 + p[f + 6] * x1) + (p[f + 7] * x2 + p[f + 8] * x3)) + ((p[f + 9] * x4 + k[1])
                                                                               + p[g + 6] * tm)
    n2 = ((p[f + 10] * x0 + p[f + 11] * x1) + (p[f + 12] * x2 + p[f + 13] * x3)) + ((p[f + 14] * x4 + k[2])
                                                                                 + p[g + 10] * tm)
    n3 = ((p[f + 15] * x0 + p[f + 16] * x1) + (p[f + 17] * x2 + p[f + 18] * x3)) + ((p[f + 19] * x4 + k[3])
                                                                                 + p[g + 14] * tm)
    n4 = ((p[f + 20] * x0 + p[f + 21] * x1) + (p[f + 22] * x2 + p[f + 23] * x3)) + ((p[f + 24] * x4 + k[4])
                                                                                 + p[g + 18] * tm)
    va = v
    ilim = p[b + PA_ILIM]
    if ilim > 0.0 and abs(n0) > ilim:
        # the driver's current loop: this sub-step again with the voltage that holds di/dt = 0 at the limit (within
        # the bus), the current clipped to the limit
        sg = 1.0 if n0 > 0.0 else -1.0
        vmax = p[b + PA_VMAX]
        va = min(max(sg * p[b + PA_R] * ilim + p[b + PA_KE] * vr, -vmax), vmax)  # V = R i + K_e v at i = +-I
        dv = va - v
        n0 += p[g] * dv
        n1 += p[g + 4] * dv
        n2 += p[g + 8] * dv
        n3 += p[g + 12] * dv
        n4 += p[g + 16] * dv
        if abs(n0) > ilim:
            n0 = sg * ilim
    return (n0, n1, n2, n3, n4), va


@numba.njit(**_JIT)
def _axes(p, s, v_a, c_a, tl_a, v_e, c_e, tl_e):  # noqa: PLR0917
    """Both axes over one tick: ``n_sub`` sub-steps with the drive ``v``, the carrier rate ``c`` and the load torque
    ``tl`` held over the tick. Each sub-step: the friction torques (:func:`_friction2`), the motor-side torques
    ``T_m = -T_f + a K_t i sin(N theta_m)`` (ripple; ``sin(N theta_m)`` at the sub-step's start), the exact-ZOH
    update (:func:`_zoh`), the ripple phase rotated. The axes are stepped in the same loop (their dependency chains
    overlap); the mechanism switches are read once per tick."""
    xa = (s[S_X], s[S_X + 1], s[S_X + 2], s[S_X + 3], s[S_X + 4])
    xe = (s[S_X + 5], s[S_X + 6], s[S_X + 7], s[S_X + 8], s[S_X + 9])
    ka = _held(p, 0, v_a, c_a, tl_a)
    ke = _held(p, PA_LEN, v_e, c_e, tl_e)
    za, ze = s[S_Z], s[S_Z + 1]
    tfa = tfe = 0.0
    vaa, vae = v_a, v_e
    lugre_a, lugre_e = p[PA_FMODEL] != 0.0, p[PA_LEN + PA_FMODEL] != 0.0
    lugre2 = lugre_a and lugre_e
    ripa_a, ripa_e = p[PA_RIPA], p[PA_LEN + PA_RIPA]
    # ripple phase sin / cos(N theta_m), carried in the state: rotated by N (change of theta_m) each sub-step
    na, ne = p[PA_RIPN], p[PA_LEN + PA_RIPN]
    sra, cra, sre, cre = s[S_RIP], s[S_RIP + 1], s[S_RIP + 2], s[S_RIP + 3]
    for _ in range(int(p[P_NSUB])):
        vra, vre = xa[1] - c_a, xe[1] - c_e
        tfa, za, tfe, ze = _friction2(p, lugre2, vra, za, vre, ze)
        tma, tme = -tfa, -tfe
        if ripa_a != 0.0:
            tma += ripa_a * xa[0] * sra
        if ripa_e != 0.0:
            tme += ripa_e * xe[0] * sre
        xa1, vaa = _zoh(p, 0, xa, ka, tma, v_a, vra)
        xe1, vae = _zoh(p, PA_LEN, xe, ke, tme, v_e, vre)
        if na != 0.0 and ne != 0.0:
            sra, cra, sre, cre = _rotate2(sra, cra, na * (xa1[2] - xa[2]), sre, cre, ne * (xe1[2] - xe[2]))
        elif na != 0.0:
            sra, cra = _rotate(sra, cra, na * (xa1[2] - xa[2]))
        elif ne != 0.0:
            sre, cre = _rotate(sre, cre, ne * (xe1[2] - xe[2]))
        xa, xe = xa1, xe1
    s[S_X], s[S_X + 1], s[S_X + 2], s[S_X + 3], s[S_X + 4] = xa
    s[S_X + 5], s[S_X + 6], s[S_X + 7], s[S_X + 8], s[S_X + 9] = xe
    if na != 0.0:
        s[S_RIP], s[S_RIP + 1] = _renorm(sra, cra)
    if ne != 0.0:
        s[S_RIP + 2], s[S_RIP + 3] = _renorm(sre, cre)
    s[S_Z], s[S_Z + 1] = za, ze
    s[S_TF], s[S_TF + 1] = tfa, tfe
    s[S_V], s[S_V + 1] = vaa, vae


@numba.njit(**_INLINE)
def _encoders(p, s):
    """Encoder readings (deg; az wrapped to [-180, 180), motor side), quantised to the encoder's LSB."""
    lsb = p[P_ENC_LSB]
    az = s[S_X + 2] * R2D
    if az < -180.0 or az >= 180.0:
        az = (az + 180.0) % 360.0 - 180.0
    el = s[S_X + 7] * R2D
    qa, qe = _vdiv((az, el), (lsb, lsb))
    return ((qa + _ROUND) - _ROUND) * lsb, ((qe + _ROUND) - _ROUND) * lsb


@numba.njit(**_INLINE)
def _outputs(p, s, flag):
    """step_tick's tuple: gyro (deg/s), encoders (deg), currents, flag."""
    az, el = _encoders(p, s)
    return s[S_M], s[S_M + 1], s[S_M + 2], az, el, s[S_X], s[S_X + 5], flag


@numba.njit(**_INLINE)
def _tick(p, s, nz, u_az, u_el, pose, rate, acc):  # noqa: PLR0917
    """One 1 ms tick (:func:`_advance`); returns :func:`_outputs` (step_tick's entry point)."""
    return _outputs(p, s, _advance(p, s, nz, u_az, u_el, pose, rate, acc))


@numba.njit(**_INLINE)
def _advance(p, s, nz, u_az, u_el, pose, rate, acc):  # noqa: PLR0917
    """One 1 ms tick; ``pose``, ``rate``, ``acc`` at mid-tick (tuples or array rows). Returns 1.0 if the tick used up
    the noise block (the caller refills it), else 0.0."""
    for j in range(6):
        s[S_CARR + j] = pose[j]
        s[S_CARR + 6 + j] = rate[j]
        s[S_CARR + 12 + j] = acc[j]
    s[S_HASC] = 1.0
    pr, qr, rr, pd, qd, _, fbx, fby, fbz, sf, cf, st, ct = _carrier(p, pose, rate, acc)
    s[S_ATT], s[S_ATT + 1], s[S_ATT + 2], s[S_ATT + 3] = sf, cf, st, ct  # for the camera (_los)
    # p and q at the tick end, for the gyro (the azimuth rate carries r)
    pe = pr + pd * _HALF
    qe = qr + qd * _HALF
    # load angles predicted at mid-tick (held over the tick: midpoint rule); sin and cos by rotating the tick end's
    # through the half-tick angle d (first order: error d^2/2 < 2e-6)
    sa, ca, se, ce = s[S_SC], s[S_SC + 1], s[S_SC + 2], s[S_SC + 3]
    d = (s[S_X + 3] - rr) * _HALF
    sa, ca = sa + ca * d, ca - sa * d
    c_a = rr  # carrier rate on the azimuth axis (z_o = z_b)
    c_e = ca * qr - sa * pr  # carrier rate on the elevation axis (y_o, carried by the azimuth load)
    d = (s[S_X + 8] - c_e) * _HALF
    se, ce = se + ce * d, ce - se * d
    tim_a = tim_e = 0.0
    if p[P_HAS_IMB] != 0.0:
        tim_a, tim_e = _imbalance(p, fbx, fby, fbz, sa, ca, se, ce)
    s[S_IMB], s[S_IMB + 1] = tim_a, tim_e
    vmax = p[PA_VMAX]
    v_a = min(max(u_az * p[PA_VPC], -vmax), vmax)
    vmax = p[PA_LEN + PA_VMAX]
    v_e = min(max(u_el * p[PA_LEN + PA_VPC], -vmax), vmax)
    th_a, th_e = s[S_X + 4], s[S_X + 9]
    _axes(p, s, v_a, c_a, tim_a, v_e, c_e, tim_e)
    # sin, cos of the load angles at the tick end: the tick start's rotated by the tick's change (exact up to
    # rounding, which _renorm keeps off the norm; reset() starts them exact)
    sa, ca, se, ce = _rotate2(s[S_SC], s[S_SC + 1], s[S_X + 4] - th_a, s[S_SC + 2], s[S_SC + 3], s[S_X + 9] - th_e)
    sa, ca = _renorm(sa, ca)
    se, ce = _renorm(se, ce)
    s[S_SC], s[S_SC + 1], s[S_SC + 2], s[S_SC + 3] = sa, ca, se, ce
    # gyro: true elevation-frame inertial rates of the load at the tick end (seed 001 eq 1)
    w_a, w_e = s[S_X + 3], s[S_X + 8]
    ox = ca * pe + sa * qe
    xn = ox * ce - w_a * se
    zn = ox * se + w_a * ce
    s[S_LOS], s[S_LOS + 1], s[S_LOS + 2] = xn, w_e, zn
    # filter k_a w_c / (s + w_c), input linear between tick ends; the delay's fraction of a tick evaluated exactly
    # inside this tick, whole ticks from the ring
    ef, c1, c0, ea, d1, d0 = p[P_EF], p[P_C1], p[P_C0], p[P_EA], p[P_D1], p[P_D0]
    gx, gy, gz = s[S_G], s[S_G + 1], s[S_G + 2]
    xo, yo, zo = s[S_XO], s[S_XO + 1], s[S_XO + 2]
    mx = ea * gx + d1 * xn + d0 * xo
    my = ea * gy + d1 * w_e + d0 * yo
    mz = ea * gz + d1 * zn + d0 * zo
    s[S_G] = ef * gx + c1 * xn + c0 * xo
    s[S_G + 1] = ef * gy + c1 * w_e + c0 * yo
    s[S_G + 2] = ef * gz + c1 * zn + c0 * zo
    s[S_XO], s[S_XO + 1], s[S_XO + 2] = xn, w_e, zn
    delay = int(p[P_DELAY])
    if delay:
        j = int(s[S_RINGJ])
        r = S_RING + 3 * j
        ox_, oy_, oz_ = s[r], s[r + 1], s[r + 2]
        s[r], s[r + 1], s[r + 2] = mx, my, mz
        mx, my, mz = ox_, oy_, oz_
        j += 1
        s[S_RINGJ] = 0.0 if j == delay else float(j)
    # noise: bias + white (precomputed per block, output units), camera; then coloured bands and random walk
    k = int(s[S_NK])
    mx += nz[k]
    my += nz[k + 1]
    mz += nz[k + 2]
    s[S_CAMN], s[S_CAMN + 1] = nz[k + 3], nz[k + 4]
    e = k + _NOISE_WHITE
    for c in range(int(p[P_NCOL])):
        b0, a1, a2 = p[P_COL + 3 * c], p[P_COL + 3 * c + 1], p[P_COL + 3 * c + 2]
        for j in range(3):
            o = S_COL + 4 * (3 * c + j)
            en = nz[e]
            e += 1
            y = b0 * (en - s[o + 1]) - a1 * s[o + 2] - a2 * s[o + 3]
            s[o + 1], s[o] = s[o], en
            s[o + 3], s[o + 2] = s[o + 2], y
            if j == 0:
                mx += y
            elif j == 1:
                my += y
            else:
                mz += y
    rw = p[P_RW]
    if rw != 0.0:
        s[S_RW] += rw * nz[e]
        s[S_RW + 1] += rw * nz[e + 1]
        s[S_RW + 2] += rw * nz[e + 2]
        mx += s[S_RW]
        my += s[S_RW + 1]
        mz += s[S_RW + 2]
    k += int(p[P_STRIDE])
    flag = 0.0
    if k >= nz.shape[0]:
        k = 0
        flag = 1.0
    s[S_NK] = k
    s[S_REFILL] = flag
    lsb = p[P_LSB]
    if p[P_INV_LSB] != 0.0:  # LSBs to deg/s, rounded: adding and removing 1.5 * 2^52 rounds a float to an integer
        mx = ((mx + _ROUND) - _ROUND) * lsb
        my = ((my + _ROUND) - _ROUND) * lsb
        mz = ((mz + _ROUND) - _ROUND) * lsb
    s[S_M], s[S_M + 1], s[S_M + 2] = mx, my, mz
    s[S_TICK] += 1.0
    return flag


@numba.njit(**_INLINE)
def _los(p, s):
    """Exact LOS error (deg about z_e, deg about -y_e, x_e component of the target) at the tick end."""
    t0, t1, t2 = p[P_TGX], p[P_TGY], p[P_TGZ]
    if s[S_HASC] != 0.0:  # attitude at the tick end: the mid-tick pose extrapolated by half a tick (2nd order)
        k2 = 0.5 * _HALF * _HALF
        c = S_CARR
        sf, cf, st, ct = _rotate2(s[S_ATT], s[S_ATT + 1], (s[c + 9] * _HALF + s[c + 15] * k2) * D2R,
                                  s[S_ATT + 2], s[S_ATT + 3], (s[c + 10] * _HALF + s[c + 16] * k2) * D2R)
        ps = (s[c + 5] + s[c + 11] * _HALF + s[c + 17] * k2) * D2R
        sp, cp = math.sin(ps), math.cos(ps)
        tb0 = ct * cp * t0 + ct * sp * t1 - st * t2
        tb1 = (sf * st * cp - cf * sp) * t0 + (sf * st * sp + cf * cp) * t1 + sf * ct * t2
        tb2 = (cf * st * cp + sf * sp) * t0 + (cf * st * sp - sf * cp) * t1 + cf * ct * t2
    else:
        tb0, tb1, tb2 = t0, t1, t2
    sa, ca, se, ce = s[S_SC], s[S_SC + 1], s[S_SC + 2], s[S_SC + 3]  # of the load's angles at the tick end
    hxy = ca * tb0 + sa * tb1
    tex = hxy * ce - tb2 * se
    tey = ca * tb1 - sa * tb0
    tez = hxy * se + tb2 * ce
    return math.atan2(tey, tex) * R2D, math.atan2(-tez, math.hypot(tex, tey)) * R2D, tex


@numba.njit(**_INLINE)
def _views(buf):
    """The parameter, state and noise arrays ``p``, ``s``, ``nz``: consecutive parts of the plant's one buffer (see
    :class:`Plant`), so that a per-tick call unboxes one array, not three (~50 ns each)."""
    ns = S_RING + 3 * int(buf[P_DELAY])
    return buf[:P_LEN], buf[P_LEN:P_LEN + ns], buf[P_LEN + ns:]


@numba.njit(**_JIT)
def _tick_entry(buf, u_az, u_el, pose, rate, acc):  # noqa: PLR0917
    """:func:`_tick` on the plant's buffer (step_tick's one compiled call per tick)."""
    p, s, nz = _views(buf)
    return _tick(p, s, nz, u_az, u_el, pose, rate, acc)


@numba.njit(**_JIT)
def _los_entry(buf):
    """:func:`_los` on the plant's buffer."""
    p, s, _ = _views(buf)
    return _los(p, s)


@numba.njit(**_JIT)
def _friction_now(p, s, ax, vr):
    """Friction torque acting on the axis (N m) at the current state, motor-side relative rate ``vr``."""
    b = ax * PA_LEN
    tc = p[b + PA_TC]
    if p[b + PA_FMODEL] != 0.0:
        z, s0, ts = s[S_Z + ax], p[b + PA_S0], p[b + PA_TS]
        u = vr * p[b + PA_IVS]
        gv = tc + (ts - tc) * math.exp(-u * u)
        zdot = vr - s0 * abs(vr) * z / gv
        return -(s0 * z + p[b + PA_S1] * zdot + p[b + PA_D] * vr)
    return -(tc * math.tanh(vr * p[b + PA_IWS]) + p[b + PA_D] * vr)


@numba.njit(**_JIT)
def _truth(p, s):
    """Noise-free values at the tick end, in the order of ``_TRUTH_KEYS`` (SI, rates in rad/s)."""
    pr = qr = rr = 0.0
    fbx, fby, fbz = 0.0, 0.0, -G0_M_S2
    if s[S_HASC] != 0.0:
        c = s[S_CARR: S_CARR + 18]
        pr, qr, rr, pd, qd, rd, fbx, fby, fbz, _, _, _, _ = _carrier(p, c[0:6], c[6:12], c[12:18])
        pr += pd * _HALF
        qr += qd * _HALF
        rr += rd * _HALF
    i_a, wm_a, thm_a, w_a, th_a = s[S_X], s[S_X + 1], s[S_X + 2], s[S_X + 3], s[S_X + 4]
    i_e, wm_e, thm_e, w_e, th_e = s[S_X + 5], s[S_X + 6], s[S_X + 7], s[S_X + 8], s[S_X + 9]
    ca, sa, ce, se = math.cos(th_a), math.sin(th_a), math.cos(th_e), math.sin(th_e)
    ox = ca * pr + sa * qr
    c_e = ca * qr - sa * pr
    tim_a = tim_e = 0.0
    if p[P_HAS_IMB] != 0.0:
        tim_a, tim_e = _imbalance(p, fbx, fby, fbz, sa, ca, se, ce)
    vr_a, vr_e = wm_a - rr, wm_e - c_e
    ex, ey, _ = _los(p, s)
    b = PA_LEN
    return (
        ox * ce - w_a * se, w_e, ox * se + w_a * ce,  # los rates x, y, z
        w_a, w_e, w_a - rr, w_e - c_e, th_a, th_e,  # load rates, relative rates, angles
        i_a, i_e, s[S_V], s[S_V + 1],
        _friction_now(p, s, 0, vr_a), _friction_now(p, s, 1, vr_e), tim_a, tim_e,
        pr, qr, rr, ex, ey,
        wm_a, wm_e, thm_a, thm_e,  # motor side
        -(p[PA_KC] * thm_a + p[PA_CC] * vr_a), -(p[b + PA_KC] * thm_e + p[b + PA_CC] * vr_e),  # cable
        p[PA_KS] * (thm_a - th_a) + p[PA_CS] * (wm_a - w_a),  # shaft torque on the load
        p[b + PA_KS] * (thm_e - th_e) + p[b + PA_CS] * (wm_e - w_e),
        s[S_Z], s[S_Z + 1],
    )


# what truth() returns, and the unit conversion of each kernel value
_TRUTH_KEYS: tuple[tuple[str, float], ...] = (
    ("los_rate_x_dps", R2D), ("los_rate_y_dps", R2D), ("los_rate_z_dps", R2D),
    ("az_rate_dps", R2D), ("el_rate_dps", R2D), ("az_rel_rate_dps", R2D), ("el_rel_rate_dps", R2D),
    ("az_deg", R2D), ("el_deg", R2D),
    ("current_az_a", 1.0), ("current_el_a", 1.0), ("voltage_az_v", 1.0), ("voltage_el_v", 1.0),
    ("friction_az_n_m", 1.0), ("friction_el_n_m", 1.0), ("imbalance_az_n_m", 1.0), ("imbalance_el_n_m", 1.0),
    ("carrier_p_dps", R2D), ("carrier_q_dps", R2D), ("carrier_r_dps", R2D),
    ("los_error_x_deg", 1.0), ("los_error_y_deg", 1.0),
    ("az_motor_rate_dps", R2D), ("el_motor_rate_dps", R2D), ("az_motor_deg", R2D), ("el_motor_deg", R2D),
    ("cable_az_n_m", 1.0), ("cable_el_n_m", 1.0), ("shaft_az_n_m", 1.0), ("shaft_el_n_m", 1.0),
    ("bristle_az_rad", 1.0), ("bristle_el_rad", 1.0),
)

# columns of Plant.run's output
RUN_COLUMNS = (
    "gyro_x_dps", "gyro_y_dps", "gyro_z_dps", "encoder_az_deg", "encoder_el_deg", "current_az_a", "current_el_a",
    "los_error_x_deg", "los_error_y_deg", "miss_x_px", "miss_y_px", "track_valid",
    "los_rate_x_dps", "los_rate_y_dps", "los_rate_z_dps", "az_deg", "el_deg", "voltage_az_v", "voltage_el_v",
)
_RUN_INDEX = {name: j for j, name in enumerate(RUN_COLUMNS)}


@numba.njit(**_JIT)
def _run(p, s, nz, u_az, u_el, carrier, out, rows, k0):  # noqa: PLR0917
    """Ticks ``k0 ..`` of a batch (one row of ``carrier`` = pose, rate, accel per tick); stops after the tick that
    used up the noise block (the caller refills it) or at the end. Column ``j`` of :data:`RUN_COLUMNS` goes to
    ``out[rows[j], tick]``, not computed if ``rows[j] < 0`` (the LOS error and camera columns cost 2 atan2, a
    hypot and a sin / cos per tick). Returns the next tick."""
    n = u_az.shape[0]
    ifov, hw, hh = p[P_IFOV], p[P_HW], p[P_HH]
    r_gx, r_gy, r_gz, r_ea, r_ee, r_ia, r_ie = rows[0], rows[1], rows[2], rows[3], rows[4], rows[5], rows[6]
    r_lx, r_ly, r_mx, r_my, r_tv = rows[7], rows[8], rows[9], rows[10], rows[11]
    r_wx, r_wy, r_wz, r_az, r_el, r_va, r_ve = rows[12], rows[13], rows[14], rows[15], rows[16], rows[17], rows[18]
    enc = r_ea >= 0 or r_ee >= 0
    cam = r_lx >= 0 or r_ly >= 0 or r_mx >= 0 or r_my >= 0 or r_tv >= 0
    k = k0
    while k < n:
        c = carrier
        flag = _advance(p, s, nz, u_az[k], u_el[k],
                        (c[k, 0], c[k, 1], c[k, 2], c[k, 3], c[k, 4], c[k, 5]),
                        (c[k, 6], c[k, 7], c[k, 8], c[k, 9], c[k, 10], c[k, 11]),
                        (c[k, 12], c[k, 13], c[k, 14], c[k, 15], c[k, 16], c[k, 17]))
        if r_gx >= 0:
            out[r_gx, k] = s[S_M]
        if r_gy >= 0:
            out[r_gy, k] = s[S_M + 1]
        if r_gz >= 0:
            out[r_gz, k] = s[S_M + 2]
        if enc:
            ea, ee = _encoders(p, s)
            if r_ea >= 0:
                out[r_ea, k] = ea
            if r_ee >= 0:
                out[r_ee, k] = ee
        if r_ia >= 0:
            out[r_ia, k] = s[S_X]
        if r_ie >= 0:
            out[r_ie, k] = s[S_X + 5]
        if cam:
            ex, ey, front = _los(p, s)
            qx, qy = _vdiv((ex, ey), (ifov, ifov))
            mx = qx + s[S_CAMN]
            my = qy + s[S_CAMN + 1]
            if r_lx >= 0:
                out[r_lx, k] = ex
            if r_ly >= 0:
                out[r_ly, k] = ey
            if r_mx >= 0:
                out[r_mx, k] = mx
            if r_my >= 0:
                out[r_my, k] = my
            if r_tv >= 0:
                out[r_tv, k] = 1.0 if front > 0.0 and abs(mx) <= hw and abs(my) <= hh else 0.0
        if r_wx >= 0:
            out[r_wx, k] = s[S_LOS] * R2D
        if r_wy >= 0:
            out[r_wy, k] = s[S_LOS + 1] * R2D
        if r_wz >= 0:
            out[r_wz, k] = s[S_LOS + 2] * R2D
        if r_az >= 0:
            out[r_az, k] = s[S_X + 4] * R2D
        if r_el >= 0:
            out[r_el, k] = s[S_X + 9] * R2D
        if r_va >= 0:
            out[r_va, k] = s[S_V]
        if r_ve >= 0:
            out[r_ve, k] = s[S_V + 1]
        k += 1
        if flag != 0.0:
            break
    return k


@numba.njit(**_JIT)
def _fill_noise(nz, stride, col0, ncols, raw, table, scales, offsets):  # noqa: PLR0917
    """Columns ``col0 .. col0 + ncols`` of the noise block: ``offsets[j] + scales[j] * table[raw]`` per tick."""
    ticks = nz.shape[0] // stride
    for t in range(ticks):
        for j in range(ncols):
            nz[t * stride + col0 + j] = offsets[j] + scales[j] * table[raw[t * ncols + j]]


_A1 = nbt.Array(nbt.float64, 1, "C")
_A2 = nbt.Array(nbt.float64, 2, "C")
_T6 = nbt.UniTuple(nbt.float64, 6)
_SIGNATURES: dict[str, tuple[Any, tuple[Any, ...]]] = {
    "tick": (_tick_entry, (_A1, nbt.float64, nbt.float64, _T6, _T6, _T6)),
    "run": (_run, (_A1, _A1, _A1, _A1, _A1, _A2, _A2, nbt.Array(nbt.int64, 1, "C"), nbt.int64)),
    "los": (_los_entry, (_A1,)),
    "truth": (_truth, (_A1, _A1)),
    "outputs": (_outputs, (_A1, _A1, nbt.float64)),
    "fill": (_fill_noise, (_A1, nbt.int64, nbt.int64, nbt.int64, nbt.Array(nbt.uint16, 1, "C"), _A1, _A1, _A1)),
}
_ENTRY: dict[str, Any] = {}


def kernel(name: str) -> Any:
    """The compiled entry point of one kernel function (compiled, or loaded from numba's cache, on first use in a
    process). Calling the entry point of the one compiled signature skips the dispatcher's type resolution (~0.4 us
    per call); its argument checks still refuse wrong types and tuple sizes (TypeError / ValueError)."""
    ep = _ENTRY.get(name)
    if ep is None:
        disp, sig = _SIGNATURES[name]
        ep = disp.compile(sig)  # returns the compiled entry point
        if not callable(ep):  # pragma: no cover (numba API change): the dispatcher is always correct
            ep = disp
        _ENTRY[name] = ep
    return ep


# --- the plant -----------------------------------------------------------------------------------------------------


def _python_mt(seed: int | str) -> np.random.MT19937:
    """numpy's MT19937 in the state of ``random.Random(seed)``: its 32-bit words are those ``random.Random(seed)``
    would give, so ``random_raw(n)`` as little-endian uint32 bytes is ``random.Random(seed).randbytes(4 n)`` (a test
    checks this), ~10x faster."""
    state = random.Random(seed).getstate()[1]
    bg = np.random.MT19937()
    bg.state = {"bit_generator": "MT19937", "state": {"key": np.array(state[:624], dtype=np.uint32),
                                                      "pos": state[624]}}
    return bg


def _random_u16(bg: np.random.MT19937, n: int) -> np.ndarray:
    """``n`` 16-bit numbers (n even): ``randbytes(2 n)`` read as little-endian uint16, on any platform."""
    return bg.random_raw(n // 2).astype("<u4").view("<u2").astype(np.uint16)


class Plant:
    """The emulated gimbal on its hexapod. See the module docstring and docs/emulator.md.

    ``step_tick(u_az_counts, u_el_counts, carrier)`` advances 1 ms (one compiled call); the outputs (``gyro_dps``,
    ``encoders_deg``, ``currents_a``, ``miss_px``, ``truth``) describe the instant ``t_s`` reached, as plain Python
    floats. :meth:`run` advances many ticks in one compiled call and returns arrays. All randomness comes from
    ``random.Random(seed)`` (and ``random.Random(f"{seed}/gyro-extra")`` for coloured noise and random walk): every
    tick uses five 16-bit random numbers (3 gyro, 2 camera), each an index into a table of normal quantiles, drawn in
    blocks of 1000 ticks; the sequence does not depend on which outputs are read.
    """

    TICK_S = TICK_S

    def __init__(self, config: PlantConfig, seed: int) -> None:
        self.config = config
        self.seed = seed
        self.n_sub = round(TICK_S / config.internal_step_s)
        p = _params(config)
        self._delay_ticks = int(p[P_DELAY])
        self._stride = int(p[P_STRIDE])
        # one buffer: parameters, state, noise block (views of it; the per-tick kernel call takes the buffer)
        ns = S_RING + 3 * self._delay_ticks
        self._buf = np.zeros(P_LEN + ns + _NOISE_BLOCK_TICKS * self._stride)
        self._p, self._s, self._nz = np.split(self._buf, [P_LEN, P_LEN + ns])
        self._p[:] = p
        self._table = np.frombuffer(normal_table(), dtype=np.float64)
        g = config.gyro
        unit = g.quantisation_lsb_dps or 1.0  # the kernel works in gyro LSBs (see _params)
        sn = config.camera.centroid_noise_std_px
        self._offsets = np.array([*(b / unit for b in g.bias_dps), 0.0, 0.0])
        self._scales = np.array([*(x / unit for x in g.noise_std_dps), sn, sn])
        self._ones, self._zeros = np.ones(3 * _MAX_BANDS + 3), np.zeros(3 * _MAX_BANDS + 3)
        self._tick = kernel("tick")
        self._out: tuple[float, ...] = ()
        self.reset()

    def reset(self) -> None:
        """Back to the initial state: angles from the config, at rest, the random sequences restarted."""
        cfg = self.config
        self._rng = _python_mt(self.seed)
        self._rng_extra = _python_mt(f"{self.seed}/gyro-extra")
        s = self._s
        s[:] = 0.0
        az, el = cfg.initial_az_deg * D2R, cfg.initial_el_deg * D2R
        s[S_X + 2] = s[S_X + 4] = az
        s[S_X + 7] = s[S_X + 9] = el
        s[S_SC], s[S_SC + 1], s[S_SC + 2], s[S_SC + 3] = math.sin(az), math.cos(az), math.sin(el), math.cos(el)
        na, ne = self._p[PA_RIPN], self._p[PA_LEN + PA_RIPN]
        s[S_RIP: S_RIP + 4] = (math.sin(na * az), math.cos(na * az), math.sin(ne * el), math.cos(ne * el))
        s[S_M: S_M + 3] = [self._quantise(b) for b in cfg.gyro.bias_dps]
        self._refill_noise()
        self._out = kernel("outputs")(self._p, s, 0.0)

    @property
    def t_s(self) -> float:
        """Simulated time reached, s."""
        return int(self._s[S_TICK]) * TICK_S

    def _refill_noise(self) -> None:
        """The next block of noise, per tick: gyro x, y, z (bias + std * N(0, 1), output units) and camera x, y
        (std * N(0, 1), px), then the unit normals of the coloured bands and the random walk. Each N(0, 1) is a
        normal quantile picked by 16 random bits (little-endian pairs of bytes, so any platform draws the same)."""
        n = _NOISE_BLOCK_TICKS
        fill = kernel("fill")
        fill(self._nz, self._stride, 0, _NOISE_WHITE, _random_u16(self._rng, _NOISE_WHITE * n), self._table,
             self._scales, self._offsets)
        extra = self._stride - _NOISE_WHITE
        if extra:
            fill(self._nz, self._stride, _NOISE_WHITE, extra, _random_u16(self._rng_extra, extra * n), self._table,
                 self._ones[:extra], self._zeros[:extra])
        self._s[S_REFILL] = 0.0

    def _quantise(self, x: float) -> float:
        lsb = self.config.gyro.quantisation_lsb_dps
        return round(x / lsb) * lsb if lsb > 0 else x

    def step_tick(self, u_az_counts: float, u_el_counts: float, carrier: CarrierMotion) -> None:
        """Advance one 1 ms tick with the drive (DAC counts) held; ``carrier`` is evaluated at mid-tick."""
        try:
            pose, rate, accel = carrier
            out = self._tick(self._buf, u_az_counts, u_el_counts, pose, rate, accel)
        except (TypeError, ValueError):  # not floats / tuples of 6 (nothing was stepped): convert, or say why
            out = self._tick(self._buf, float(u_az_counts), float(u_el_counts), *_carrier_tuples(carrier))
        self._out = out
        if out[7]:
            self._refill_noise()

    def run(self, u_az_counts: Any, u_el_counts: Any, carrier: Any,
            outputs: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        """Advance ``n`` ticks in one compiled loop (offline use: fitting, benchmarks): the same physics, noise and
        final state as ``n`` calls of :meth:`step_tick` (bit for bit; tested), so the two can be mixed.

        ``u_az_counts``, ``u_el_counts``: arrays ``(n,)`` of drive counts, held over each tick; ``carrier``: array
        ``(n, 18)``, per tick the CarrierMotion's ``pose + rate + accel`` at mid-tick (mm, deg, mm/s, deg/s, mm/s^2,
        deg/s^2). Returns arrays ``(n,)`` at each tick end: ``t_s`` and :data:`RUN_COLUMNS` (gyro x/y/z in deg/s,
        encoders in deg, currents in A, LOS error in deg, miss x/y in px with centroid noise, ``track_valid``
        (bool), true LOS rates in deg/s, load angles az/el in deg, armature voltages in V). ``outputs``: the names of
        the columns to compute and return (default: all); the physics, the noise and the state do not depend on it,
        only the time spent (without the LOS error and camera columns: no atan2, hypot, sin / cos of the yaw).
        """
        u_a = np.ascontiguousarray(u_az_counts, dtype=np.float64)
        u_e = np.ascontiguousarray(u_el_counts, dtype=np.float64)
        car = np.ascontiguousarray(carrier, dtype=np.float64)
        n = u_a.shape[0]
        if u_a.shape != (n,) or u_e.shape != (n,) or car.shape != (n, 18):
            raise ValueError(f"run: need u_az_counts (n,), u_el_counts (n,), carrier (n, 18); got {u_a.shape}, "
                             f"{u_e.shape}, {car.shape}")
        if not (np.all(np.isfinite(u_a)) and np.all(np.isfinite(u_e)) and np.all(np.isfinite(car))):
            raise ValueError("run: inputs must be finite")
        names = RUN_COLUMNS if outputs is None else tuple(dict.fromkeys(outputs))
        rows = np.full(len(RUN_COLUMNS), -1, dtype=np.int64)
        for i, name in enumerate(names):
            if name not in _RUN_INDEX:
                raise ValueError(f"run: unknown output {name!r}; the outputs are {', '.join(RUN_COLUMNS)}")
            rows[_RUN_INDEX[name]] = i
        out = np.empty((len(names), n))
        tick0 = int(self._s[S_TICK])
        step = kernel("run")
        k = 0
        while k < n:
            k = step(self._p, self._s, self._nz, u_a, u_e, car, out, rows, k)
            if self._s[S_REFILL]:
                self._refill_noise()
        self._out = kernel("outputs")(self._p, self._s, 0.0)
        res = {"t_s": (tick0 + np.arange(1, n + 1)) * TICK_S}
        for i, name in enumerate(names):
            res[name] = out[i] > 0.5 if name == "track_valid" else out[i]  # contiguous rows of one array
        return res

    # -- outputs --

    def gyro_dps(self) -> tuple[float, float, float]:
        """Measured rates (x about the LOS, y elevation axis, z cross-elevation) at ``t_s``: filtered, delayed,
        noisy, biased, quantised. The noise is drawn once per tick."""
        o = self._out
        return (o[0], o[1], o[2])

    def encoders_deg(self) -> tuple[float, float]:
        """Azimuth (wrapped to [-180, 180)) and elevation angles of the motor side relative to the carrier (the load
        side without ``structure``), quantised to the encoder."""
        o = self._out
        return (o[3], o[4])

    def currents_a(self) -> tuple[float, float]:
        """Armature currents (A), azimuth and elevation."""
        o = self._out
        return (o[5], o[6])

    def los_error_deg(self) -> tuple[float, float, float]:
        """Exact LOS error ``(x, y, in_front)`` at ``t_s``: the angles (deg) the LOS must turn about z_e (+ = target
        right) and about y_e (sign flipped, so + = target up) to reach the target, and the target direction's
        x_e component (> 0: in front of the camera)."""
        return kernel("los")(self._buf)

    def miss_px(self) -> tuple[float, float, bool]:
        """Miss distance (px, + = target right / up) with centroid noise, and track_valid, at ``t_s``."""
        cam = self.config.camera
        ex, ey, front = self.los_error_deg()
        x = ex / cam.ifov_deg_per_px + self._s.item(S_CAMN)
        y = ey / cam.ifov_deg_per_px + self._s.item(S_CAMN + 1)
        valid = front > 0.0 and abs(x) <= cam.half_width_px and abs(y) <= cam.half_height_px
        return (x, y, valid)

    def los_rate_dps(self) -> tuple[float, float, float]:
        """The true (noise-free, unfiltered, undelayed) LOS rates x, y, z (deg/s) at ``t_s``: :meth:`truth`'s first
        three values without building its dict (a per-tick recorder's cost)."""
        v = kernel("truth")(self._p, self._s)
        return (v[0] * R2D, v[1] * R2D, v[2] * R2D)

    def truth(self) -> dict[str, float]:
        """True (noise-free) values at ``t_s``. Torques (N m) are those acting on the axis; rates in deg/s. ``az_deg``,
        ``el_deg`` and the rates without ``motor`` are the load's (what the LOS, the gyro and the imbalance see);
        ``*_motor_*`` the motor side's (the encoder's); they are equal without ``structure``."""
        values = kernel("truth")(self._p, self._s)
        out = {"t_s": self.t_s}
        for (key, scale), v in zip(_TRUTH_KEYS, values, strict=True):
            out[key] = v * scale if scale != 1.0 else v
        return out


def _carrier_tuples(carrier: Any) -> tuple[tuple[float, ...], ...]:
    """The carrier as three tuples of 6 floats, or ValueError naming what is wrong."""
    try:
        parts = tuple(tuple(float(x) for x in part) for part in carrier)
    except (TypeError, ValueError):
        raise ValueError("carrier: need (pose, rate, accel), each 6 numbers") from None
    if len(parts) != 3 or any(len(part) != 6 for part in parts):
        raise ValueError("carrier: need (pose, rate, accel), each 6 numbers")
    return parts


def imbalance_torques(imb: ImbalanceConfig, f_body: Vec3f, az_rad: float, el_rad: float) -> tuple[float, float]:
    """Imbalance torques (N m) acting on the azimuth (about z_o) and elevation (about y_e) axes: ``-m rho x f`` with
    ``f`` the specific force (m/s^2, body frame) expressed in the elevation frame (seed 001 eqs 3-4)."""
    rx, ry, rz = (x * 1e-3 for x in imb.eccentricity_mm)
    m = imb.mass_kg
    ca, sa = math.cos(az_rad), math.sin(az_rad)
    ce, se = math.cos(el_rad), math.sin(el_rad)
    fbx, fby, fbz = f_body
    hxy = ca * fbx + sa * fby
    fx, fy, fz = hxy * ce - fbz * se, ca * fby - sa * fbx, hxy * se + fbz * ce
    tx, ty, tz = -m * (ry * fz - rz * fy), -m * (rz * fx - rx * fz), -m * (rx * fy - ry * fx)
    return ce * tz - se * tx, ty
