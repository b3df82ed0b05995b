"""Controllers by name: what a session config's ``controller: {name: ..., params: {...}}`` builds.

Each name has a pydantic parameter model (units in the field names, defaults for the default plant
k_m = 0.023 deg/s^2 per count) and builds one :class:`RateController` per axis. An unknown name or
parameter raises :class:`ControllerConfigError` with one line that names it and lists what exists.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hil.control.controller import FilteredFeedback, ImbalanceCompensation, RateController, RateEstimator
from hil.control.eso import LinearESO, NonlinearESO
from hil.control.filters import LowPass1, LowPass2
from hil.control.kalman import EsoKalman
from hil.control.loops import DAC_MAX_COUNTS, RateLoop
from hil.control.ukf_imbalance import ImbalanceFeedForward, ImbalanceUKF

K_M_DEFAULT = 0.023  # deg/s^2 per DAC count, seed 000 eq 38
GYRO_NOISE_VAR_DPS2 = 0.034**2  # seed 000 Fig. 12a: +-0.102 deg/s peak ~ 3 sigma


class ControllerConfigError(ValueError):
    """A controller name or parameter in a config is not valid (one line, names the field)."""


class RateLoopParams(BaseModel):
    """Parameters every controller shares: the PI rate loop and the sample time."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kp_counts_per_dps: float = Field(8000.0, ge=0, description="P gain; bandwidth = kp * k_m rad/s")
    ki_counts_per_deg: float = Field(0.0, ge=0, description="I gain (counts per deg/s per s)")
    u_max_counts: int = Field(DAC_MAX_COUNTS, gt=0, le=DAC_MAX_COUNTS, description="drive saturation")
    dt_s: float = Field(1e-3, gt=0, description="sample time of the rate loop")

    def loop(self) -> RateLoop:
        return RateLoop(
            kp_counts_per_dps=self.kp_counts_per_dps,
            ki_counts_per_deg=self.ki_counts_per_deg,
            u_max_counts=self.u_max_counts,
            dt_s=self.dt_s,
        )


class PiLpfParams(RateLoopParams):
    """PI on the low-pass-filtered gyro (the baseline without disturbance rejection)."""

    ki_counts_per_deg: float = Field(80000.0, ge=0)
    cutoff_hz: float = Field(150.0, gt=0, description="gyro low-pass cut-off (seed 000: 150 Hz)")
    order: Literal[1, 2] = Field(1, description="1: first-order (ZOH); 2: Butterworth (bilinear)")


class EsoParams(RateLoopParams):
    """Linear ESO disturbance compensation, raw gyro fed back (seed 000 eqs 39-43)."""

    omega_o_rad_s: float = Field(300.0, gt=0, description="observer bandwidth")
    b0_dps2_per_count: float = Field(K_M_DEFAULT, gt=0, description="plant gain k_m")


class EsoNonlinearParams(EsoParams):
    """Han's fal ESO (eqs 41-42), linear-zone gains equal to the linear ESO's."""

    alpha: float = Field(0.5, gt=0, le=1)
    delta_dps: float = Field(0.05, gt=0, description="fal linear zone, in the rate error's units")


class EsoKfParams(EsoParams):
    """ESO + Kalman filter (eqs 44-45, Fig. 5 and 10): the KF rate is fed back and feeds the ESO."""

    # q + s = 1e-3 (K ~ 0.59): the measured variance per sample of the model's one-step prediction error
    # x + h (b0 u + z2) on the default plant under the 1 deg / 1 Hz swing (9e-4; docs/control.md)
    q_dps2: float = Field(5e-4, gt=0, description="KF process noise variance per sample")
    s_dps2: float = Field(5e-4, ge=0, description="the paper's S, added to Q")
    r_dps2: float = Field(GYRO_NOISE_VAR_DPS2, gt=0, description="gyro noise variance")
    steady_state: bool = Field(True, description="constant gain from the discrete Riccati equation")


class EsoKfHighGainParams(EsoKfParams):
    """High-gain ESO + KF: the same method with a faster observer (seed 000 Table 1, third column)."""

    omega_o_rad_s: float = Field(1000.0, gt=0)


class EsoKfUkfFfParams(EsoKfParams):
    """ESO + KF with UKF-identified mass-imbalance feed-forward (seed 001)."""

    mass_kg: float = Field(10.0, gt=0, description="mass of the imbalanced (inner) frame")
    inertia_kg_m2: float = Field(0.05, gt=0, description="its inertia about the axis")
    counts_per_n_m: float = Field(
        49830.0, gt=0, description="DAC counts per N*m: 1 / (J k_m), k_m in rad/s^2 per count (0.023 deg/s^2)"
    )
    ukf_dt_s: float = Field(0.01, gt=0, description="UKF step (seed 001: 0.01 s); the session decimates to it")
    ff_limit_counts: float = Field(8000.0, gt=0, description="clamp of the feed-forward drive")


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


def _describe(exc: ValidationError, name: str) -> str:
    err = exc.errors()[0]
    field = ".".join(str(part) for part in err["loc"])
    if err["type"] == "extra_forbidden":
        known = ", ".join(REGISTRY[name].params.model_fields)
        return f"controller {name!r}: unknown parameter {field!r} (parameters: {known})"
    return f"controller {name!r}: parameter {field!r}: {err['msg']} (got {err.get('input')!r})"


def controller_params(name: str, params: dict[str, Any] | None = None) -> RateLoopParams:
    """Validate ``params`` for controller ``name``; ControllerConfigError (one line) if either is wrong."""
    kind = REGISTRY.get(name)
    if kind is None:
        raise ControllerConfigError(f"unknown controller {name!r} (controllers: {', '.join(sorted(REGISTRY))})")
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
    return RateController(estimator=REGISTRY[name].estimator(p), loop=p.loop(), imbalance=imbalance)
