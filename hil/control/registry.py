"""Controllers by name: what a session config's ``controller: {name: ..., params: {...}}`` builds.

Each name has a pydantic parameter model (units in the field names, defaults for the default plant
k_m = 0.023 deg/s^2 per count) and builds one :class:`RateController` per axis. An unknown name or
parameter raises :class:`ControllerConfigError` with one line that names it and lists what exists.
:func:`effective_params` gives the full parameter set a config runs with (a session log records it).

:data:`REGISTRY` holds the controllers that run from what a lab measures (gyro, encoders, their own drive): the
bench, replays and benchmarks run every one of them. :data:`SIM_ONLY` holds the ``oracle``
(hil.control.oracle), which needs the plant's true state and so runs only on the ``sim`` clock; names are looked
up in both (:func:`needs_truth` tells them apart).

Every parameter has a valid range (its Field bounds; NaN and infinities refused) and the derived
quantities are checked too (docs/reliability.md has the table, tested against these models):
a controller that validates cannot overflow, divide by zero or leave its discretisation's stable
range inside the 1 kHz loop.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from hil.control.controller import FilteredFeedback, ImbalanceCompensation, RateController, RateEstimator
from hil.control.eso import LinearESO, NonlinearESO
from hil.control.filters import LowPass1, LowPass2
from hil.control.kalman import EsoKalman
from hil.control.loops import DAC_MAX_COUNTS, RateLoop
from hil.control.oracle import TruthFeedback, truth_refusal
from hil.control.ukf_imbalance import ImbalanceFeedForward, ImbalanceUKF

K_M_DEFAULT = 0.023  # deg/s^2 per DAC count, seed 000 eq 38
GYRO_NOISE_VAR_DPS2 = 0.034**2  # seed 000 Fig. 12a: +-0.102 deg/s peak ~ 3 sigma


class ControllerConfigError(ValueError):
    """A controller name or parameter in a config is not valid (one line, names the field)."""


KP_MAX_COUNTS_PER_DPS = 1e5  # kp k_m h = 2.3 on the default plant at 1 kHz: past the sampled P loop's limit of 2
KI_MAX_COUNTS_PER_DEG = 1e7
DT_MIN_S, DT_MAX_S = 1e-4, 1e-2  # 10 kHz .. 100 Hz loops (the bench's is 1 kHz)
BENCH_TICK_S = 1e-3  # the session's loop period (GYRO_SAMPLE at 1 kHz)
OMEGA_O_H_MAX = math.pi  # observer bandwidth up to the Nyquist rate pi/h: its poles exp(-omega_o h) >= 0.043
VARIANCE_MAX_DPS2 = 1e4  # (100 deg/s)^2 per sample


class RateLoopParams(BaseModel):
    """Parameters every controller shares: the PI rate loop and the sample time."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    kp_counts_per_dps: float = Field(8000.0, ge=0, le=KP_MAX_COUNTS_PER_DPS,
                                     description="P gain; bandwidth = kp * k_m rad/s")
    ki_counts_per_deg: float = Field(0.0, ge=0, le=KI_MAX_COUNTS_PER_DEG,
                                     description="I gain (counts per deg/s per s)")
    u_max_counts: int = Field(DAC_MAX_COUNTS, gt=0, le=DAC_MAX_COUNTS, description="drive saturation")
    dt_s: float = Field(1e-3, ge=DT_MIN_S, le=DT_MAX_S, description="sample time of the rate loop")

    @model_validator(mode="after")
    def _integral_below_sample_rate(self) -> RateLoopParams:
        """The PI zero ki/kp lies below the sample rate 1/dt_s (with kp = 0 there is no PI: ki must be 0)."""
        if self.ki_counts_per_deg * self.dt_s > self.kp_counts_per_dps:
            raise ValueError(f"ki_counts_per_deg: {self.ki_counts_per_deg:g} puts the PI zero ki/kp above the sample "
                             f"rate 1/dt_s; need ki * dt_s <= kp ({self.kp_counts_per_dps:g})")
        return self

    def loop(self) -> RateLoop:
        return RateLoop(
            kp_counts_per_dps=self.kp_counts_per_dps,
            ki_counts_per_deg=self.ki_counts_per_deg,
            u_max_counts=self.u_max_counts,
            dt_s=self.dt_s,
        )


class PiLpfParams(RateLoopParams):
    """PI on the low-pass-filtered gyro (the baseline without disturbance rejection)."""

    ki_counts_per_deg: float = Field(80000.0, ge=0, le=KI_MAX_COUNTS_PER_DEG)
    cutoff_hz: float = Field(150.0, gt=0, le=0.5 / DT_MIN_S, description="gyro low-pass cut-off (seed 000: 150 Hz)")
    order: Literal[1, 2] = Field(1, description="1: first-order (ZOH); 2: Butterworth (bilinear)")

    @model_validator(mode="after")
    def _below_nyquist(self) -> PiLpfParams:
        if self.cutoff_hz >= 0.5 / self.dt_s:
            raise ValueError(f"cutoff_hz: {self.cutoff_hz:g} Hz is not below the Nyquist frequency "
                             f"{0.5 / self.dt_s:g} Hz of dt_s {self.dt_s:g} s")
        return self


class EsoParams(RateLoopParams):
    """Linear ESO disturbance compensation, raw gyro fed back (seed 000 eqs 39-43)."""

    omega_o_rad_s: float = Field(300.0, gt=0, le=OMEGA_O_H_MAX / DT_MIN_S, description="observer bandwidth")
    b0_dps2_per_count: float = Field(K_M_DEFAULT, ge=1e-5, le=10.0, description="plant gain k_m")

    @model_validator(mode="after")
    def _discretisation(self) -> EsoParams:
        """omega_o h up to pi (the ZOH current observer is stable for any omega_o h, but past the Nyquist rate
        it is already deadbeat to 4 %: a larger value only passes more gyro noise); kp b0 h < 1 (the sampled
        P loop's pole 1 - kp b0 h stays in (0, 1): no oscillation at the Nyquist rate)."""
        if self.omega_o_rad_s * self.dt_s > OMEGA_O_H_MAX:
            raise ValueError(f"omega_o_rad_s: omega_o * dt_s = {self.omega_o_rad_s * self.dt_s:.3g} is above pi: "
                             f"the observer's bandwidth would exceed the Nyquist rate "
                             f"{OMEGA_O_H_MAX / self.dt_s:.0f} rad/s")
        if self.kp_counts_per_dps * self.b0_dps2_per_count * self.dt_s >= 1.0:
            product = self.kp_counts_per_dps * self.b0_dps2_per_count * self.dt_s
            raise ValueError(f"kp_counts_per_dps: kp * b0 * dt_s = {product:.3g}, need < 1 (a rate-loop bandwidth "
                             "kp * b0 below the sample rate 1/dt_s)")
        return self


class EsoNonlinearParams(EsoParams):
    """Han's fal ESO (eqs 41-42), linear-zone gains equal to the linear ESO's."""

    alpha: float = Field(0.5, gt=0, le=1)
    delta_dps: float = Field(0.05, ge=1e-6, le=100.0, description="fal linear zone, in the rate error's units")


class EsoKfParams(EsoParams):
    """ESO + Kalman filter (eqs 44-45, Fig. 5 and 10): the KF rate is fed back and feeds the ESO."""

    # q + s = 1e-3 (K ~ 0.59): the measured variance per sample of the model's one-step prediction error
    # x + h (b0 u + z2) on the default plant under the 1 deg / 1 Hz swing (9e-4; docs/control.md)
    q_dps2: float = Field(5e-4, gt=0, le=VARIANCE_MAX_DPS2, description="KF process noise variance per sample")
    s_dps2: float = Field(5e-4, ge=0, le=VARIANCE_MAX_DPS2, description="the paper's S, added to Q")
    r_dps2: float = Field(GYRO_NOISE_VAR_DPS2, gt=0, le=VARIANCE_MAX_DPS2, description="gyro noise variance")
    steady_state: bool = Field(True, description="constant gain from the discrete Riccati equation")


class EsoKfHighGainParams(EsoKfParams):
    """High-gain ESO + KF: the same method with a faster observer (seed 000 Table 1, third column)."""

    omega_o_rad_s: float = Field(1000.0, gt=0, le=OMEGA_O_H_MAX / DT_MIN_S)


class EsoKfUkfFfParams(EsoKfParams):
    """ESO + KF with UKF-identified mass-imbalance feed-forward (seed 001)."""

    mass_kg: float = Field(10.0, ge=1e-3, le=1000.0, description="mass of the imbalanced (inner) frame")
    inertia_kg_m2: float = Field(0.05, ge=1e-6, le=1000.0, description="its inertia about the axis")
    counts_per_n_m: float = Field(
        49830.0, gt=0, le=1e8, description="DAC counts per N*m: 1 / (J k_m), k_m in rad/s^2 per count (0.023 deg/s^2)"
    )
    ukf_dt_s: float = Field(0.01, ge=DT_MIN_S, le=1.0,
                            description="UKF step (seed 001: 0.01 s); the session decimates to it")
    ff_limit_counts: float = Field(8000.0, gt=0, le=DAC_MAX_COUNTS, description="clamp of the feed-forward drive")

    @model_validator(mode="after")
    def _ukf_step_is_whole_ticks(self) -> EsoKfUkfFfParams:
        """The bench decimates its 1 ms tick (and the controller its dt_s) to the UKF step: whole numbers of both."""
        for tick_s, what in ((self.dt_s, "dt_s"), (BENCH_TICK_S, "the bench's 1 ms tick")):
            n = round(self.ukf_dt_s / tick_s)
            if n < 1 or abs(n * tick_s - self.ukf_dt_s) > 1e-6 * self.ukf_dt_s:
                raise ValueError(f"ukf_dt_s: {self.ukf_dt_s:g} s is not a whole number of {what} ({tick_s:g} s)")
        return self


class OracleParams(RateLoopParams):
    """The oracle (sim clock only): the rate loop on the plant's true LOS rate, the true disturbance cancelled."""

    @model_validator(mode="after")
    def _sampled_p_loop(self) -> OracleParams:
        """kp k_m h < 1 on the default plant (k_m 0.023): the sampled P loop's pole stays in (0, 1), as for the
        ESO controllers."""
        product = self.kp_counts_per_dps * K_M_DEFAULT * self.dt_s
        if product >= 1.0:
            raise ValueError(f"kp_counts_per_dps: kp * k_m * dt_s = {product:.3g} with the default plant's k_m "
                             f"{K_M_DEFAULT:g}, need < 1 (a rate-loop bandwidth below the sample rate 1/dt_s)")
        return self


def _eso_kf(p: EsoKfParams) -> RateEstimator:
    return EsoKalman(
        omega_o_rad_s=p.omega_o_rad_s,
        b0_dps2_per_count=p.b0_dps2_per_count,
        dt_s=p.dt_s,
        q_dps2=p.q_dps2,
        r_dps2=p.r_dps2,
        s_dps2=p.s_dps2,
        steady_state=p.steady_state,
    )


@dataclass(frozen=True)
class ControllerKind:
    params: type[RateLoopParams]
    estimator: Callable[[Any], RateEstimator]
    summary: str


REGISTRY: dict[str, ControllerKind] = {
    "pi_lpf": ControllerKind(
        PiLpfParams,
        lambda p: FilteredFeedback((LowPass1 if p.order == 1 else LowPass2)(cutoff_hz=p.cutoff_hz, dt_s=p.dt_s)),
        "PI on the 150 Hz low-pass-filtered gyro",
    ),
    "eso": ControllerKind(
        EsoParams,
        lambda p: LinearESO(omega_o_rad_s=p.omega_o_rad_s, b0_dps2_per_count=p.b0_dps2_per_count, dt_s=p.dt_s),
        "linear ESO (ZOH current observer) compensation",
    ),
    "eso_nonlinear": ControllerKind(
        EsoNonlinearParams,
        lambda p: NonlinearESO(
            omega_o_rad_s=p.omega_o_rad_s,
            b0_dps2_per_count=p.b0_dps2_per_count,
            dt_s=p.dt_s,
            alpha=p.alpha,
            delta_dps=p.delta_dps,
        ),
        "Han's fal ESO compensation",
    ),
    "eso_kf": ControllerKind(EsoKfParams, _eso_kf, "ESO + Kalman filter"),
    "eso_kf_high_gain": ControllerKind(EsoKfHighGainParams, _eso_kf, "ESO + Kalman filter, high-gain observer"),
    "eso_kf_ukf_ff": ControllerKind(EsoKfUkfFfParams, _eso_kf, "ESO + Kalman filter + UKF imbalance feed-forward"),
}

# controllers that need the plant's true state (hil.control.oracle): sim clock only
SIM_ONLY: dict[str, ControllerKind] = {
    "oracle": ControllerKind(OracleParams, lambda p: TruthFeedback(),
                             "oracle: true LOS rate fed back, true disturbance cancelled (sim clock only)"),
}


def _kind(name: str) -> ControllerKind | None:
    return REGISTRY.get(name) or SIM_ONLY.get(name)


def needs_truth(name: str) -> bool:
    """Whether controller ``name`` needs the plant's true state (runs only on the sim clock)."""
    return name in SIM_ONLY


def require_sim_clock(name: str, clock: str) -> None:
    """ControllerConfigError (one line naming controller.name) if controller ``name`` cannot run on ``clock``
    (``sim``, ``lockstep``, ``realtime`` or ``hardware``): the oracle needs the sim clock. Call it before anything
    starts."""
    if clock != "sim" and needs_truth(name):
        raise ControllerConfigError(truth_refusal(name, clock))


def _describe(exc: ValidationError, name: str) -> str:
    err = exc.errors()[0]
    field = ".".join(str(part) for part in err["loc"])
    if err["type"] == "extra_forbidden":
        kind = _kind(name)
        assert kind is not None
        known = ", ".join(kind.params.model_fields)
        return f"controller {name!r}: unknown parameter {field!r} (parameters: {known})"
    if not field:  # a check across parameters: the message starts with the parameter it blames
        return f"controller {name!r}: parameter {str(err['msg']).removeprefix('Value error, ')}"
    got = repr(err.get("input"))
    return f"controller {name!r}: parameter {field!r}: {err['msg']} (got {got[:77] + '...' if len(got) > 80 else got})"


def controller_params(name: str, params: dict[str, Any] | None = None) -> RateLoopParams:
    """Validate ``params`` for controller ``name``; ControllerConfigError (one line) if either is wrong."""
    kind = _kind(name)
    if kind is None:
        names = ", ".join(sorted({**REGISTRY, **SIM_ONLY}))
        raise ControllerConfigError(f"unknown controller {name!r} (controllers: {names})")
    try:
        return kind.params.model_validate(params or {})
    except ValidationError as exc:
        raise ControllerConfigError(_describe(exc, name)) from None


def _imbalance(p: EsoKfUkfFfParams) -> ImbalanceCompensation:
    return ImbalanceCompensation(
        ukf=ImbalanceUKF(mass_kg=p.mass_kg, inertia_kg_m2=p.inertia_kg_m2, dt_s=p.ukf_dt_s),
        feedforward=ImbalanceFeedForward(
            mass_kg=p.mass_kg, drive_per_n_m=p.counts_per_n_m, drive_limit=p.ff_limit_counts
        ),
    )


def build_controller(name: str, params: dict[str, Any] | RateLoopParams | None = None) -> RateController:
    """A fresh controller for one axis. Build one per axis: they hold state."""
    if isinstance(params, RateLoopParams):
        params = params.model_dump(exclude_unset=True)
    p = controller_params(name, params)
    imbalance = _imbalance(p) if isinstance(p, EsoKfUkfFfParams) else None
    kind = _kind(name)
    assert kind is not None  # controller_params checked the name
    return RateController(estimator=kind.estimator(p), loop=p.loop(), imbalance=imbalance)


def effective_params(controller_config: Any) -> dict[str, Any]:
    """Every parameter controller ``name`` runs with: the config's overrides over the registry's defaults.

    ``controller_config``: a ``hil.config.ControllerConfig``, a mapping ``{"name": ..., "params": {...}}`` (as a
    session log's ``config["controller"]`` holds it) or a controller name alone. The name's own defaults count:
    ``eso_kf_high_gain`` gives ``omega_o_rad_s`` 1000, not the 300 of ``eso_kf``. Returns plain JSON types, in
    the parameter model's field order. Raises :class:`ControllerConfigError` for an unknown name or parameter.
    """
    name: object  # checked below: a str
    if isinstance(controller_config, str):
        name, params = controller_config, None
    elif isinstance(controller_config, Mapping):
        name, params = controller_config.get("name"), controller_config.get("params")
    else:
        name, params = getattr(controller_config, "name", None), getattr(controller_config, "params", None)
    if not isinstance(name, str):
        raise ControllerConfigError(f"controller name missing or not a string (got {name!r})")
    if isinstance(params, RateLoopParams):
        params = params.model_dump(exclude_unset=True)
    return controller_params(name, dict(params or {})).model_dump(mode="json")
