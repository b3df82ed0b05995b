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

Frames: carrier body x forward, y right, z down; gimbal at ``az = el = 0`` aligned with the body; ``az`` about
``z_b``, ``el`` about ``y_o``; the LOS is ``x_e``. Positive az turns the LOS right, positive el raises it.

Integration: exact zero-order-hold discretisation of the linear part (current, rate, viscous friction, back-EMF) at
the internal step; drive, carrier rate and imbalance torque held over the tick (the carrier is given at mid-tick),
the Coulomb torque over each sub-step; trapezoidal rule for the angle. The gyro filter is discretised exactly at the
tick for an input linear between tick ends (first-order hold), the delay evaluated exactly inside the tick plus whole
ticks from a ring. The hot path (:meth:`Plant.step_tick`) runs on plain floats and ``math``; it is a closure whose
constants are positional defaults, then specialised by :func:`specialise` (numeric constants folded into the code,
the sub-step loop unrolled): the same source, about 3 % faster (docs/performance.md).

This module imports nothing from ``hil`` (``firmware_stub`` may only use ``hil.protocol``).
"""

from __future__ import annotations

import ast
import inspect
import math
import random
import sys
import textwrap
import types
from array import array
from collections.abc import Callable
from pathlib import Path
from statistics import NormalDist
from typing import Any, Literal, NamedTuple

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from firmware_stub.config import ConfigError, read_yaml_mapping

__all__ = [
    "DEFAULT_PLANT_CONFIG",
    "CameraConfig",
    "CarrierMotion",
    "EncoderConfig",
    "FrictionAxisConfig",
    "FrictionConfig",
    "GyroConfig",
    "HexapodConfig",
    "ImbalanceConfig",
    "MotorConfig",
    "Plant",
    "PlantConfig",
    "PlantConfigError",
    "attitude_at_tick_end",
    "carrier_state",
    "imbalance_torques",
    "load_plant_config",
]

DEFAULT_PLANT_CONFIG = Path(__file__).parents[1] / "profiles/plant/default.yaml"

G0_M_S2 = 9.80665  # standard gravity; lab z is down, so gravity in the lab is (0, 0, +G0)
D2R = math.pi / 180.0
R2D = 180.0 / math.pi
TICK_S = 1e-3

Vec3f = tuple[float, float, float]


class PlantConfigError(ValueError):
    """A plant config file is not valid: one line naming the file, the field path and the reason."""


# --- configuration -------------------------------------------------------------------------------------------------


class _Section(BaseModel):
    """Base of the plant's config sections: unknown fields refused, immutable, NaN and infinities refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class MotorConfig(_Section):
    """One brush DC torque motor, its driver and the load it turns (seed 000 eqs 33-37, rigid coupling)."""

    resistance_ohm: float = Field(gt=0, description="armature resistance R_a")
    inductance_h: float = Field(gt=0, description="armature inductance L_a")
    torque_constant_n_m_per_a: float = Field(gt=0, description="K_t")
    back_emf_v_s_per_rad: float = Field(ge=0, description="K_e (= K_t in SI units for an ideal motor)")
    inertia_kg_m2: float = Field(gt=0, description="J_sigma: motor + load about the axis")
    volts_per_count: float = Field(gt=0, description="driver gain: armature volts per signed 16-bit DAC count")
    bus_voltage_v: float = Field(gt=0, description="|V| is clamped to this")


class FrictionAxisConfig(_Section):
    """Bearing friction on the rate relative to the carrier: T_c tanh(w_rel / w_s) + D w_rel."""

    coulomb_n_m: float = Field(ge=0, description="Coulomb level T_c")
    viscous_n_m_s_per_rad: float = Field(ge=0, description="viscous coefficient D")
    smoothing_rate_dps: float = Field(gt=0, description="w_s of the tanh smoothing (stability: see validator)")


class FrictionConfig(_Section):
    az: FrictionAxisConfig
    el: FrictionAxisConfig


class ImbalanceConfig(_Section):
    """Mass imbalance of the elevation assembly (seed 001 eqs 2-4)."""

    mass_kg: float = Field(ge=0, description="mass of the elevation assembly")
    eccentricity_mm: tuple[float, float, float] = Field(
        description="centre of mass relative to the pivot (axes' intersection), elevation-frame components"
    )


class GyroConfig(_Section):
    """Three-axis rate gyro on the elevation frame (seed 000 eq 3 plus noise, bias, quantisation)."""

    scale_factor: float = Field(gt=0, description="k_a")
    bandwidth_hz: float = Field(gt=0, description="omega_c / (2 pi)")
    delay_s: float = Field(ge=0, le=0.05, description="T_d (any value; the input is linear between ticks)")
    noise_std_dps: tuple[float, float, float] = Field(description="white-noise std per axis (x, y, z)")
    bias_dps: tuple[float, float, float] = Field(description="constant bias per axis (x, y, z)")
    quantisation_lsb_dps: float = Field(ge=0, description="output LSB; 0 = not quantised")

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


class PlantConfig(_Section):
    """Every parameter of the plant. Units are in the field names; see profiles/plant/default.yaml."""

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

    @model_validator(mode="after")
    def _cross_checks(self) -> PlantConfig:
        h = self.internal_step_s
        n = round(TICK_S / h)
        if n < 1 or abs(n * h - TICK_S) > 1e-9 * TICK_S:
            raise ValueError(f"internal_step_s: {h!r} does not divide the 1 ms tick")
        for axis in ("az", "el"):
            fr: FrictionAxisConfig = getattr(self.friction, axis)
            motor: MotorConfig = getattr(self, f"motor_{axis}")
            # the Coulomb term is explicit (held over a step); its slope T_c / w_s must not overshoot
            gain = h * fr.coulomb_n_m / (motor.inertia_kg_m2 * fr.smoothing_rate_dps * D2R)
            if gain > 1.0:
                w_min = h * fr.coulomb_n_m / motor.inertia_kg_m2 * R2D
                raise ValueError(
                    f"friction.{axis}.smoothing_rate_dps: {fr.smoothing_rate_dps!r} is too small for "
                    f"internal_step_s {h!r} (explicit Coulomb term unstable); need >= {w_min:.3g}"
                )
        return self

    def k_m_dps2_per_count(self, axis: Literal["az", "el"]) -> float:
        """Seed 000 eq 38: ``k_m = K_t V_count / (J R)`` in deg/s^2 per DAC count (back-EMF, L, friction ignored)."""
        m: MotorConfig = getattr(self, f"motor_{axis}")
        return m.torque_constant_n_m_per_a * m.volts_per_count / (m.inertia_kg_m2 * m.resistance_ohm) * R2D

    def electrical_time_constant_s(self, axis: Literal["az", "el"]) -> float:
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


# --- exact ZOH discretisation ----------------------------------------------------------------------------------------


def _matmul(a: list[list[float]], b: list[list[float]]) -> list[list[float]]:
    n, m, k = len(a), len(b[0]), len(b)
    return [[sum(a[i][t] * b[t][j] for t in range(k)) for j in range(m)] for i in range(n)]


def expm(a: list[list[float]]) -> list[list[float]]:
    """Matrix exponential by scaling and squaring with a 20-term Taylor series (small matrices, construction only)."""
    n = len(a)
    norm = max(sum(abs(x) for x in row) for row in a)
    squarings = max(0, math.ceil(math.log2(norm / 0.25))) if norm > 0.25 else 0
    scale = 2.0**-squarings
    a = [[x * scale for x in row] for row in a]
    result = [[float(i == j) for j in range(n)] for i in range(n)]
    term = [row[:] for row in result]
    for k in range(1, 21):
        term = [[x / k for x in row] for row in _matmul(term, a)]
        result = [[r + t for r, t in zip(rr, tr, strict=True)] for rr, tr in zip(result, term, strict=True)]
    for _ in range(squarings):
        result = _matmul(result, result)
    return result


def axis_zoh(motor: MotorConfig, viscous_n_m_s_per_rad: float, h: float) -> tuple[list[list[float]], list[list[float]]]:
    """Exact ZOH of one axis over ``h``: state ``(i [A], w [rad/s])``, inputs ``(V [V], c [rad/s], tau [N m])``.

    ``L di/dt = V - R i - K_e (w - c)``;  ``J dw/dt = K_t i - D (w - c) + tau``  (viscous friction is linear, so it
    is in the exact part; ``tau`` = Coulomb friction + imbalance, held over the step). Returns ``(Phi, Gamma)``.
    """
    r, ll, kt = motor.resistance_ohm, motor.inductance_h, motor.torque_constant_n_m_per_a
    ke, j, d = motor.back_emf_v_s_per_rad, motor.inertia_kg_m2, viscous_n_m_s_per_rad
    a = [[-r / ll, -ke / ll], [kt / j, -d / j]]
    b = [[1.0 / ll, ke / ll, 0.0], [0.0, d / j, 1.0 / j]]
    aug = [[x * h for x in a[i] + b[i]] for i in range(2)] + [[0.0] * 5 for _ in range(3)]
    e = expm(aug)
    return [e[0][:2], e[1][:2]], [e[0][2:], e[1][2:]]


# --- Gaussian noise by table lookup --------------------------------------------------------------------------------

_NORMAL_BITS = 16
_NORMAL_TABLE = array("d")


def normal_table() -> array[float]:
    """2^16 standard-normal quantiles at ``(k + 1/2) / 2^16``: indexed by 16 random bits, a Gaussian draw that costs
    one table lookup (tails cut at +-4.17 sigma; std 0.9999). A contiguous array (512 kB, cache-friendlier than a
    list of float objects). Built once per process (~50 ms)."""
    if not _NORMAL_TABLE:
        inv = NormalDist().inv_cdf
        n = 1 << _NORMAL_BITS
        _NORMAL_TABLE.extend(inv((k + 0.5) / n) for k in range(n))
    return _NORMAL_TABLE


# --- specialising the hot path ----------------------------------------------------------------------------------


def specialise(fn: Callable[..., Any], unroll: dict[str, int]) -> Callable[..., Any]:
    """``fn`` recompiled from its own source with its numeric defaults folded into the code as constants (no default
    copied per call, constant branches dropped by the compiler) and each ``for _ in NAME:`` loop with ``NAME`` in
    ``unroll`` written out that many times. The closure's free variables keep working (``nonlocal`` included):
    the recompiled function closes over the same cells. Returns ``fn`` itself if its source is unavailable.

    A partial evaluation, not a different algorithm: the result computes the same floats in the same order.
    """
    try:
        source = textwrap.dedent(inspect.getsource(fn))
    except (OSError, TypeError):  # pragma: no cover (no source, e.g. a frozen build)
        return fn
    fdef = ast.parse(source).body[0]
    assert isinstance(fdef, ast.FunctionDef)
    args = fdef.args.args
    defaults = fn.__defaults__ or ()
    names = [a.arg for a in args[len(args) - len(defaults):]]
    stored = {n.id for n in ast.walk(fdef) if isinstance(n, ast.Name) and not isinstance(n.ctx, ast.Load)}
    folded = {n: v for n, v in zip(names, defaults, strict=True)
              if type(v) in (int, float, bool) and n not in unroll and n not in stored}  # never reassigned
    kept = [(a, v) for a, v in zip(args[len(args) - len(defaults):], defaults, strict=True)
            if a.arg not in folded and a.arg not in unroll]
    fdef.args.args = args[: len(args) - len(defaults)] + [a for a, _ in kept]
    fdef.args.defaults = [ast.Constant(None) for _ in kept]  # the values are passed below, as objects

    class Fold(ast.NodeTransformer):
        def visit_Name(self, node: ast.Name) -> ast.AST:
            if isinstance(node.ctx, ast.Load) and node.id in folded:
                return ast.copy_location(ast.Constant(folded[node.id]), node)
            return node

        def visit_For(self, node: ast.For) -> Any:
            self.generic_visit(node)
            if isinstance(node.iter, ast.Name) and node.iter.id in unroll and not node.orelse:
                return [stmt for _ in range(unroll[node.iter.id]) for stmt in node.body]
            return node

    fdef = Fold().visit(fdef)
    fdef.decorator_list = []
    ast.increment_lineno(fdef, fn.__code__.co_firstlineno - 1)  # tracebacks name the lines of the real source
    free = fn.__code__.co_freevars
    # a factory whose locals are the closure's free variables, so that the inner function closes over cells
    factory = ast.FunctionDef(
        name="_factory", args=ast.arguments(posonlyargs=[], args=[], kwonlyargs=[], kw_defaults=[], defaults=[]),
        body=[*(ast.Assign(targets=[ast.Name(v, ast.Store())], value=ast.Constant(None)) for v in free), fdef,
              ast.Return(ast.Name(fdef.name, ast.Load()))],
        decorator_list=[], returns=None,
    )
    module = ast.fix_missing_locations(ast.Module(body=[factory], type_ignores=[]))
    namespace = dict(fn.__globals__)
    exec(compile(module, inspect.getsourcefile(fn) or "<specialised>", "exec"), namespace)
    code = namespace["_factory"]().__code__
    if code.co_freevars != fn.__code__.co_freevars:  # pragma: no cover (the compiler orders both alike)
        return fn
    # bound to the original cells: the specialised function shares the closure of ``fn``
    out = types.FunctionType(code, fn.__globals__, fn.__name__, tuple(v for _, v in kept), fn.__closure__)
    out.__doc__, out.__qualname__ = fn.__doc__, fn.__qualname__
    return out


# --- the plant -----------------------------------------------------------------------------------------------------


def _foh(wc: float, tau: float, gain: float) -> tuple[float, float, float]:
    """Exact discretisation of ``gain * wc / (s + wc)`` over ``tau`` for an input linear in time (first-order hold):
    ``y(tau) = e y(0) + c1 x(tau) + c0 x(0)``; returns ``(e, c1, c0)``."""
    e = math.exp(-wc * tau)
    one_minus_e = -math.expm1(-wc * tau)
    k = one_minus_e / (wc * tau)
    return e, gain * (1.0 - k), gain * (k - e)


_NOISE_PER_TICK = 5
_NOISE_BLOCK_TICKS = 1000
_ROUND = 6755399441055744.0  # 1.5 * 2^52: (x + _ROUND) - _ROUND is x rounded to the nearest integer (|x| < 2^51)

# indices into the state tuple Plant._box[0], shared by the hot path and the output methods
_I_A, _W_A, _TH_A, _I_E, _W_E, _TH_E = range(6)
_GX, _GY, _GZ, _XO, _YO, _ZO, _RING_J, _TICK = range(6, 14)
_MX, _MY, _MZ, _NOISE_K, _V_A, _V_E = range(14, 20)
_SIN_A, _COS_A, _SIN_E, _COS_E = range(20, 24)  # of the angles at the tick end (the next tick rotates them)
_STATE_LEN = 24


class Plant:
    """The emulated gimbal on its hexapod. See the module docstring and docs/emulator.md.

    ``step_tick(u_az_counts, u_el_counts, carrier)`` advances 1 ms; the outputs (``gyro_dps``, ``encoders_deg``,
    ``currents_a``, ``miss_px``, ``truth``) describe the instant ``t_s`` reached. All randomness comes from
    ``random.Random(seed)``: every tick uses five 16-bit random numbers (3 gyro, 2 camera), each an index into a table
    of normal quantiles, drawn in blocks of 1000 ticks; the sequence does not depend on which outputs are read.
    """

    TICK_S = TICK_S

    def __init__(self, config: PlantConfig, seed: int) -> None:
        self.config = config
        self.seed = seed
        self.n_sub = round(TICK_S / config.internal_step_s)
        self._table = normal_table()
        self._zoh = {
            "az": axis_zoh(config.motor_az, config.friction.az.viscous_n_m_s_per_rad, config.internal_step_s),
            "el": axis_zoh(config.motor_el, config.friction.el.viscous_n_m_s_per_rad, config.internal_step_s),
        }
        g = config.gyro
        self._delay_ticks = int(g.delay_s / TICK_S + 1e-9)
        self._ring: list[Vec3f] = []
        self._cache: list[Any] = [None]  # the last CarrierMotion step_tick derived (kept by reset(): still valid)
        self._noise: list[float] = []  # gyro bias + noise and camera noise, _NOISE_PER_TICK per tick
        self._box: list[tuple[Any, ...]] = [()]  # the state, one tuple (indices _I_A ...), replaced every tick
        self._cs_memo: list[Any] = [None, None]  # (CarrierMotion, its _CarrierState at t_s) for truth()
        self._att_memo: list[Any] = [None, None]  # (CarrierMotion, attitude at t_s) for the camera
        self._encoder_lsb_deg = 360.0 / config.encoder.counts_per_rev
        cam = config.camera
        taz, tel = cam.target_az_deg * D2R, cam.target_el_deg * D2R
        self._target_lab = (math.cos(tel) * math.cos(taz), math.cos(tel) * math.sin(taz), -math.sin(tel))
        self.step_tick = self._build()  # type: ignore[method-assign]
        self.reset()

    def reset(self) -> None:
        """Back to the initial state: angles from the config, at rest, the random sequence restarted."""
        cfg = self.config
        self._rng = random.Random(self.seed)
        self._refill_noise()
        self._ring[:] = [(0.0, 0.0, 0.0)] * self._delay_ticks
        bias = [self._quantise(b) for b in cfg.gyro.bias_dps]
        s = [0.0] * _STATE_LEN
        s[_TH_A], s[_TH_E] = cfg.initial_az_deg * D2R, cfg.initial_el_deg * D2R
        s[_RING_J] = s[_TICK] = 0
        s[_NOISE_K] = -_NOISE_PER_TICK  # no noise drawn before the first tick
        s[_MX], s[_MY], s[_MZ] = bias
        s[_SIN_A], s[_COS_A] = math.sin(s[_TH_A]), math.cos(s[_TH_A])
        s[_SIN_E], s[_COS_E] = math.sin(s[_TH_E]), math.cos(s[_TH_E])
        self._box[0] = tuple(s)

    @property
    def t_s(self) -> float:
        """Simulated time reached, s."""
        return self._box[0][_TICK] * TICK_S

    def _refill_noise(self) -> None:
        """The next block of noise, five values per tick: gyro x, y, z (bias + std * N(0, 1), deg/s) and camera x, y
        (std * N(0, 1), px). Each N(0, 1) is a normal quantile picked by 16 random bits (little-endian pairs of
        bytes, so any platform draws the same)."""
        raw = array("H")
        raw.frombytes(self._rng.randbytes(2 * _NOISE_PER_TICK * _NOISE_BLOCK_TICKS))
        if sys.byteorder == "big":  # pragma: no cover
            raw.byteswap()
        z = list(map(self._table.__getitem__, raw))
        g = self.config.gyro
        sn = self.config.camera.centroid_noise_std_px
        unit = g.quantisation_lsb_dps or 1.0  # the hot path works in gyro LSBs (see _build)
        offsets = (*(b / unit for b in g.bias_dps), 0.0, 0.0)
        scales = (*(x / unit for x in g.noise_std_dps), sn, sn)
        block = self._noise
        block[:] = z
        for k in range(_NOISE_PER_TICK):
            block[k::_NOISE_PER_TICK] = [offsets[k] + scales[k] * v for v in z[k::_NOISE_PER_TICK]]

    def _quantise(self, x: float) -> float:
        lsb = self.config.gyro.quantisation_lsb_dps
        return round(x / lsb) * lsb if lsb > 0 else x

    def step_tick(self, u_az_counts: float, u_el_counts: float, carrier: CarrierMotion) -> None:
        """Advance one 1 ms tick with the drive (DAC counts) held; ``carrier`` is evaluated at mid-tick.

        (Each instance replaces this with the closure built by ``_build``, which has the same signature.)
        """
        raise NotImplementedError  # pragma: no cover

    # -- the hot path --

    def _build(self) -> Any:
        cfg = self.config
        h = cfg.internal_step_s
        n_sub = (None,) * self.n_sub  # iterated by the sub-step loop (cheaper than a new range each tick)
        half_tick = 0.5 * TICK_S
        sin, cos, tanh = math.sin, math.cos, math.tanh

        (pa11, pa12), (pa21, pa22) = self._zoh["az"][0]
        (ga1v, ga1c, ga1t), (ga2v, ga2c, ga2t) = self._zoh["az"][1]
        (pe11, pe12), (pe21, pe22) = self._zoh["el"][0]
        (ge1v, ge1c, ge1t), (ge2v, ge2c, ge2t) = self._zoh["el"][1]
        vpc_a, vmax_a = cfg.motor_az.volts_per_count, cfg.motor_az.bus_voltage_v
        vpc_e, vmax_e = cfg.motor_el.volts_per_count, cfg.motor_el.bus_voltage_v
        tc_a, iws_a = cfg.friction.az.coulomb_n_m, 1.0 / (cfg.friction.az.smoothing_rate_dps * D2R)
        tc_e, iws_e = cfg.friction.el.coulomb_n_m, 1.0 / (cfg.friction.el.smoothing_rate_dps * D2R)
        ka1, ka2 = ga1t * tc_a, ga2t * tc_a  # Coulomb torque's effect per unit tanh
        ke1, ke2 = ge1t * tc_e, ge2t * tc_e
        mass = cfg.imbalance.mass_kg
        mrx, mry, mrz = (mass * x * 1e-3 for x in cfg.imbalance.eccentricity_mm)
        has_imbalance = mass > 0.0 and (mrx or mry or mrz)

        g = cfg.gyro
        wc = 2.0 * math.pi * g.bandwidth_hz
        ef, c1, c0 = _foh(wc, TICK_S, g.scale_factor)  # filter state, tick end to tick end
        delay_ticks = self._delay_ticks
        tau_r = g.delay_s - delay_ticks * TICK_S  # the rest of the delay, within one tick
        alpha = TICK_S - tau_r if tau_r > 1e-12 else TICK_S
        ea, c1a, c0a = _foh(wc, alpha, g.scale_factor)
        fa = alpha / TICK_S  # the input at t0 + alpha, linearly interpolated
        d1, d0 = c1a * fa, c1a * (1.0 - fa) + c0a  # y(alpha) = ea y0 + d1 x1 + d0 x0
        # the filter, the delay ring and the noise work in the output's unit: gyro LSBs (deg/s if not quantised)
        lsb = g.quantisation_lsb_dps
        inv_lsb = 1.0 / lsb if lsb > 0 else 0.0
        per_rad_s = R2D * inv_lsb if lsb > 0 else R2D
        c1, c0, d1, d0 = c1 * per_rad_s, c0 * per_rad_s, d1 * per_rad_s, d0 * per_rad_s
        rnd = _ROUND
        ring = self._ring
        noise = self._noise
        noise_len = len(noise) if noise else _NOISE_PER_TICK * _NOISE_BLOCK_TICKS
        refill = self._refill_noise
        cache = self._cache
        box = self._box

        # carrier, derived once per distinct CarrierMotion (nonlocal cache)
        last_carrier: Any = None
        p = q = r = pe = qe = fbx = fby = 0.0
        fbz = -G0_M_S2

        def step_tick(  # noqa: PLR0917 (the constants ride as defaults)
            u_az_counts: float,
            u_el_counts: float,
            carrier: CarrierMotion,
            # constants as positional defaults; specialise() then folds the numeric ones into the code
            sin=sin, cos=cos, tanh=tanh, n_sub=n_sub, half_tick=half_tick, hd=D2R * half_tick, h=h, pa11=pa11,
            pa12=pa12, pa21=pa21,
            pa22=pa22, ga1v=ga1v, ga1c=ga1c, ga1t=ga1t, ga2v=ga2v, ga2c=ga2c, ga2t=ga2t, pe11=pe11, pe12=pe12,
            pe21=pe21, pe22=pe22, ge1v=ge1v, ge1c=ge1c, ge1t=ge1t, ge2v=ge2v, ge2c=ge2c, ge2t=ge2t, vpc_a=vpc_a,
            vmax_a=vmax_a, vpc_e=vpc_e, vmax_e=vmax_e, iws_a=iws_a, iws_e=iws_e, ka1=ka1, ka2=ka2, ke1=ke1, ke2=ke2,
            mrx=mrx, mry=mry, mrz=mrz, has_imbalance=has_imbalance, ef=ef, c1=c1, c0=c0, ea=ea, d1=d1, d0=d0,
            delay_ticks=delay_ticks, lsb=lsb, inv_lsb=inv_lsb,
            rnd=rnd, ring=ring, noise=noise, noise_len=noise_len, refill=refill, cache=cache, box=box,
            D2R=D2R, R2D=R2D, TICK_S=TICK_S, G0_M_S2=G0_M_S2
        ) -> None:
            nonlocal last_carrier, p, q, r, pe, qe, fbx, fby, fbz
            if carrier is not last_carrier:
                last_carrier = cache[0] = carrier
                pose, rate, acc = carrier
                _, _, _, ph, th, ps = pose
                _, _, _, phd, thd, psd = rate
                axx, ayy, azz, phdd, thdd, psdd = acc
                ph *= D2R
                th *= D2R
                phd *= D2R
                thd *= D2R
                psd *= D2R
                sf, cf, s_t, ct = sin(ph), cos(ph), sin(th), cos(th)
                # body rates from the ZYX Euler rates (exact), and their time derivative
                pc = psd * ct
                p = phd - psd * s_t
                q = thd * cf + pc * sf
                r = pc * cf - thd * sf
                # p and q at the tick end, by their time derivatives (rearranged): dp/dt = phdd - psdd st - thd pc,
                # dq/dt = thdd cf + psdd ct sf + phd r - psd thd st sf (the gyro needs no r: the azimuth axis's own
                # rate w_a carries it); accelerations in deg/s^2, hence hd = D2R half_tick
                pe = p + (phdd - psdd * s_t) * hd - thd * pc * half_tick
                qe = q + (thdd * cf + psdd * ct * sf) * hd + (phd * r - psd * thd * s_t * sf) * half_tick
                # specific force (a - g) in the body frame: C_lab^body (a_lab - (0, 0, g))
                fz = azz * 1e-3 - G0_M_S2
                if axx or ayy:
                    ps *= D2R
                    sp, cp = sin(ps), cos(ps)
                    fx, fy = axx * 1e-3, ayy * 1e-3
                    fbx = ct * cp * fx + ct * sp * fy - s_t * fz
                    fby = (sf * s_t * cp - cf * sp) * fx + (sf * s_t * sp + cf * cp) * fy + sf * ct * fz
                    fbz = (cf * s_t * cp + sf * sp) * fx + (cf * s_t * sp - sf * cp) * fy + cf * ct * fz
                else:
                    fbx, fby, fbz = -s_t * fz, sf * ct * fz, cf * ct * fz
            (i_a, w_a, th_a, i_e, w_e, th_e, gx, gy, gz, xo, yo, zo, ring_j, tick, _, _, _, nk, _, _,
             sa, ca, se, ce) = box[0]
            # gimbal angles predicted at mid-tick: the kinematics are held over the tick (midpoint rule); their sin
            # and cos by rotating the tick end's through the half-tick angle d (first order: error d^2/2 < 2e-6)
            d = (w_a - r) * half_tick
            sa, ca = sa + ca * d, ca - sa * d
            c_a = r  # carrier rate on the azimuth axis (z_o = z_b)
            c_e = ca * q - sa * p  # carrier rate on the elevation axis (y_o)
            d = (w_e - c_e) * half_tick
            se, ce = se + ce * d, ce - se * d
            if has_imbalance:  # -m rho x f, f in the elevation frame (seed 001 eqs 3-4)
                hxy = ca * fbx + sa * fby
                fx = hxy * ce - fbz * se
                fy = ca * fby - sa * fbx
                fz = hxy * se + fbz * ce
                tix = mrz * fy - mry * fz
                tim_e = mrx * fz - mrz * fx  # about y_e = y_o
                tim_a = ce * (mry * fx - mrx * fy) - se * tix  # about z_o
            else:
                tim_a = tim_e = 0.0
            v_a = u_az_counts * vpc_a  # volts, clamped to the bus
            if v_a > vmax_a:
                v_a = vmax_a
            elif v_a < -vmax_a:
                v_a = -vmax_a
            v_e = u_el_counts * vpc_e
            if v_e > vmax_e:
                v_e = vmax_e
            elif v_e < -vmax_e:
                v_e = -vmax_e
            # exact ZOH sub-steps: drive, carrier rate and imbalance held over the tick, Coulomb over a sub-step
            ea1 = ga1v * v_a + ga1c * c_a + ga1t * tim_a
            ea2 = ga2v * v_a + ga2c * c_a + ga2t * tim_a
            ee1 = ge1v * v_e + ge1c * c_e + ge1t * tim_e
            ee2 = ge2v * v_e + ge2c * c_e + ge2t * tim_e
            ca_w = c_a * iws_a
            ce_w = c_e * iws_e
            w_a0, w_e0 = w_a, w_e
            sum_a = sum_e = 0.0
            for _ in n_sub:
                t = tanh(w_a * iws_a - ca_w)
                i_a, w_a = pa11 * i_a + pa12 * w_a + ea1 - ka1 * t, pa21 * i_a + pa22 * w_a + ea2 - ka2 * t
                t = tanh(w_e * iws_e - ce_w)
                i_e, w_e = pe11 * i_e + pe12 * w_e + ee1 - ke1 * t, pe21 * i_e + pe22 * w_e + ee2 - ke2 * t
                sum_a += w_a
                sum_e += w_e
            # angles: trapezoidal rule on the relative rate over the sub-steps
            th_a += h * (sum_a + 0.5 * (w_a0 - w_a)) - c_a * TICK_S
            th_e += h * (sum_e + 0.5 * (w_e0 - w_e)) - c_e * TICK_S
            # gyro: true elevation-frame inertial rates at the tick end (seed 001 eq 1)
            sa, ca = sin(th_a), cos(th_a)
            se, ce = sin(th_e), cos(th_e)
            ox = ca * pe + sa * qe
            xn = ox * ce - w_a * se
            zn = ox * se + w_a * ce
            # filter k_a w_c / (s + w_c), input linear between tick ends; the delay's fraction of a tick evaluated
            # exactly inside this tick, whole ticks from the ring
            mx = ea * gx + d1 * xn + d0 * xo
            my = ea * gy + d1 * w_e + d0 * yo
            mz = ea * gz + d1 * zn + d0 * zo
            gx = ef * gx + c1 * xn + c0 * xo
            gy = ef * gy + c1 * w_e + c0 * yo
            gz = ef * gz + c1 * zn + c0 * zo
            if delay_ticks:
                old = ring[ring_j]
                ring[ring_j] = (mx, my, mz)
                mx, my, mz = old
                ring_j += 1
                if ring_j == delay_ticks:
                    ring_j = 0
            nk += 5  # this tick's five noise indices: gyro x, y, z, camera x, y (miss_px)
            if nk == noise_len:
                refill()
                nk = 0
            mx += noise[nk]  # bias + noise, precomputed per block
            my += noise[nk + 1]
            mz += noise[nk + 2]
            if inv_lsb:  # LSBs to deg/s, rounded: adding and removing 1.5 * 2^52 rounds a float to an integer
                mx = ((mx + rnd) - rnd) * lsb
                my = ((my + rnd) - rnd) * lsb
                mz = ((mz + rnd) - rnd) * lsb
            tick += 1
            box[0] = (i_a, w_a, th_a, i_e, w_e, th_e, gx, gy, gz, xn, w_e, zn, ring_j, tick,
                     mx, my, mz, nk, v_a, v_e, sa, ca, se, ce)

        return specialise(step_tick, unroll={"n_sub": self.n_sub})

    # -- outputs --

    def gyro_dps(self) -> tuple[float, float, float]:
        """Measured rates (x about the LOS, y elevation axis, z cross-elevation) at ``t_s``: filtered, delayed,
        noisy, biased, quantised. The noise is drawn once per tick."""
        s = self._box[0]
        return (s[_MX], s[_MY], s[_MZ])

    def encoders_deg(self) -> tuple[float, float]:
        """Azimuth (wrapped to [-180, 180)) and elevation angles relative to the carrier, quantised to the encoder."""
        s = self._box[0]
        lsb = self._encoder_lsb_deg
        az = (s[_TH_A] * R2D + 180.0) % 360.0 - 180.0
        return (round(az / lsb) * lsb, round(s[_TH_E] * R2D / lsb) * lsb)

    def currents_a(self) -> tuple[float, float]:
        """Armature currents (A), azimuth and elevation."""
        s = self._box[0]
        return (s[_I_A], s[_I_E])

    def _carrier_now(self) -> _CarrierState:
        """The carrier's derived state at ``t_s`` (rates at the tick end; at rest before the first tick); memoised
        on the CarrierMotion object, so the outputs read in one tick derive it once."""
        carrier = self._cache[0] if self._box[0][_TICK] else _AT_REST
        memo = self._cs_memo
        if memo[0] is carrier:
            return memo[1]
        cs = carrier_state(carrier)
        if carrier is not _AT_REST:
            dt = 0.5 * TICK_S
            pqr = tuple(x + xd * dt for x, xd in zip(cs.pqr, cs.pqr_dot, strict=True))
            cs = cs._replace(pqr=pqr)  # type: ignore[arg-type]
        memo[0], memo[1] = carrier, cs
        return cs

    def _attitude_now(self) -> tuple[Vec3f, Vec3f, Vec3f]:
        """DCM lab -> platform at ``t_s`` (the camera's path: only the attitude, memoised per CarrierMotion)."""
        carrier = self._cache[0] if self._box[0][_TICK] else _AT_REST
        memo = self._att_memo
        if memo[0] is not carrier:
            memo[0], memo[1] = carrier, attitude_at_tick_end(carrier)
        return memo[1]

    def los_error_deg(self) -> tuple[float, float, float]:
        """Exact LOS error ``(x, y, in_front)`` at ``t_s``: the angles (deg) the LOS must turn about z_e (+ = target
        right) and about y_e (sign flipped, so + = target up) to reach the target, and the target direction's
        x_e component (> 0: in front of the camera)."""
        s = self._box[0]
        t0, t1, t2 = self._target_lab
        (c00, c01, c02), (c10, c11, c12), (c20, c21, c22) = self._attitude_now()
        tb0 = c00 * t0 + c01 * t1 + c02 * t2
        tb1 = c10 * t0 + c11 * t1 + c12 * t2
        tb2 = c20 * t0 + c21 * t1 + c22 * t2
        ca, sa = math.cos(s[_TH_A]), math.sin(s[_TH_A])
        ce, se = math.cos(s[_TH_E]), math.sin(s[_TH_E])
        hxy = ca * tb0 + sa * tb1
        tex = hxy * ce - tb2 * se
        tey = ca * tb1 - sa * tb0
        tez = hxy * se + tb2 * ce
        return (math.atan2(tey, tex) * R2D, math.atan2(-tez, math.hypot(tex, tey)) * R2D, tex)

    def miss_px(self) -> tuple[float, float, bool]:
        """Miss distance (px, + = target right / up) with centroid noise, and track_valid, at ``t_s``."""
        cam = self.config.camera
        ex, ey, front = self.los_error_deg()
        k = self._box[0][_NOISE_K]
        nx, ny = (self._noise[k + 3], self._noise[k + 4]) if k >= 0 else (0.0, 0.0)
        x = ex / cam.ifov_deg_per_px + nx
        y = ey / cam.ifov_deg_per_px + ny
        valid = front > 0.0 and abs(x) <= cam.half_width_px and abs(y) <= cam.half_height_px
        return (x, y, valid)

    def truth(self) -> dict[str, float]:
        """True (noise-free) values at ``t_s``. Torques (N m) are those acting on the axis; rates in deg/s."""
        cfg = self.config
        s = self._box[0]
        cs = self._carrier_now()
        p, q, r = cs.pqr
        w_a, w_e, az, el = s[_W_A], s[_W_E], s[_TH_A], s[_TH_E]
        ca, sa = math.cos(az), math.sin(az)
        ce, se = math.cos(el), math.sin(el)
        ox = ca * p + sa * q
        wr_a, wr_e = w_a - r, w_e - (ca * q - sa * p)
        fr_a, fr_e = cfg.friction.az, cfg.friction.el
        friction_a = -(fr_a.coulomb_n_m * math.tanh(wr_a / (fr_a.smoothing_rate_dps * D2R))
                       + fr_a.viscous_n_m_s_per_rad * wr_a)
        friction_e = -(fr_e.coulomb_n_m * math.tanh(wr_e / (fr_e.smoothing_rate_dps * D2R))
                       + fr_e.viscous_n_m_s_per_rad * wr_e)
        imb_a, imb_e = imbalance_torques(cfg.imbalance, cs.f_body, az, el)
        ex, ey, _ = self.los_error_deg()
        return {
            "t_s": self.t_s,
            "los_rate_x_dps": (ox * ce - w_a * se) * R2D,
            "los_rate_y_dps": w_e * R2D,
            "los_rate_z_dps": (ox * se + w_a * ce) * R2D,
            "az_rate_dps": w_a * R2D,
            "el_rate_dps": w_e * R2D,
            "az_rel_rate_dps": wr_a * R2D,
            "el_rel_rate_dps": wr_e * R2D,
            "az_deg": az * R2D,
            "el_deg": el * R2D,
            "current_az_a": s[_I_A],
            "current_el_a": s[_I_E],
            "voltage_az_v": s[_V_A],
            "voltage_el_v": s[_V_E],
            "friction_az_n_m": friction_a,
            "friction_el_n_m": friction_e,
            "imbalance_az_n_m": imb_a,
            "imbalance_el_n_m": imb_e,
            "carrier_p_dps": p * R2D,
            "carrier_q_dps": q * R2D,
            "carrier_r_dps": r * R2D,
            "los_error_x_deg": ex,
            "los_error_y_deg": ey,
        }


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
