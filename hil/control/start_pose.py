"""The start pose phase of a session (hil.config.StartPoseConfig): before the swing and the tracking start, a position
hold on the encoders brings the gimbal to the pose the session starts from, with the platform at rest.

Per 1 kHz sample, each axis's rate command is a proportional position law, saturated:

    rate_cmd = sat( kp (angle_pose - angle_encoder), max_rate ),

which the rate loop (seed 000 eq 43) follows as it follows any command. The phase ends ``reached`` at the first sample
by which both axes have stayed within ``tolerance_deg`` of the pose for ``hold_ms`` of board time, or ``timeout``
once ``timeout_s`` has passed without that. The session's loop (hil.session.ControlLoop) and the controller replay
(hil.replay) both step it, so a replayed log rebuilds the phase's commands exactly.
"""

from __future__ import annotations

from typing import Protocol

REACHED = "reached"
TIMEOUT = "timeout"


class StartPoseSpec(Protocol):
    """What the phase reads of its configuration (hil.config.StartPoseConfig)."""

    @property
    def az_deg(self) -> float: ...
    @property
    def el_deg(self) -> float: ...
    @property
    def tolerance_deg(self) -> float: ...
    @property
    def hold_ms(self) -> float: ...
    @property
    def kp_per_s(self) -> float: ...
    @property
    def max_rate_dps(self) -> float: ...
    @property
    def timeout_s(self) -> float: ...


def wrap_deg(angle_deg: float) -> float:
    """An angle difference into [-180, 180)."""
    return (angle_deg + 180.0) % 360.0 - 180.0


class StartPose:
    """One session's start pose phase: :meth:`rate_cmds_dps` per sample until :attr:`outcome` is set."""

    def __init__(self, config: StartPoseSpec) -> None:
        self.config = config
        self.outcome: str | None = None  # REACHED or TIMEOUT, at the sample that decided it
        self.t0_s: float | None = None  # board time of the phase's first sample
        self.t_end_s: float | None = None  # ... and of the sample that decided it
        self.from_deg: tuple[float, float] = (0.0, 0.0)  # (az, el) encoder angles at its first sample
        self.at_deg: tuple[float, float] = (0.0, 0.0)  # ... at its last
        self.within_since_s: float | None = None

    def error_deg(self, az_deg: float, el_deg: float) -> tuple[float, float]:
        """The pose minus the encoders (az wrapped to the short way round), deg."""
        return wrap_deg(self.config.az_deg - az_deg), self.config.el_deg - el_deg

    def judge(self, t_s: float, az_deg: float, el_deg: float) -> str | None:
        """Whether this sample (board time ``t_s``, encoder angles) ends the phase: REACHED, TIMEOUT or None."""
        c = self.config
        if self.t0_s is None:
            self.t0_s, self.from_deg = t_s, (az_deg, el_deg)
        self.at_deg = (az_deg, el_deg)
        err_az, err_el = self.error_deg(az_deg, el_deg)
        if abs(err_az) <= c.tolerance_deg and abs(err_el) <= c.tolerance_deg:
            if self.within_since_s is None:
                self.within_since_s = t_s
            if (t_s - self.within_since_s) * 1000.0 >= c.hold_ms - 1e-6:
                self.outcome = REACHED
        else:
            self.within_since_s = None
        if self.outcome is None and t_s - self.t0_s > c.timeout_s:
            self.outcome = TIMEOUT
        if self.outcome is not None:
            self.t_end_s = t_s
        return self.outcome

    def rate_cmds_dps(self, az_deg: float, el_deg: float) -> tuple[float, float]:
        """The (az, el) rate commands of the position hold, deg/s."""
        c = self.config
        err_az, err_el = self.error_deg(az_deg, el_deg)
        lim = c.max_rate_dps
        return (max(-lim, min(lim, c.kp_per_s * err_az)), max(-lim, min(lim, c.kp_per_s * err_el)))

    def describe(self) -> dict[str, float | str | None]:
        """The phase as the log's ``phase`` event records it."""
        t0, t1 = self.t0_s or 0.0, self.t_end_s or 0.0
        err_az, err_el = self.error_deg(*self.at_deg)
        return {"phase": "start_pose", "outcome": self.outcome, "from_t_s": t0, "to_t_s": t1,
                "took_s": round(t1 - t0, 4), "from_az_deg": round(self.from_deg[0], 4),
                "from_el_deg": round(self.from_deg[1], 4), "az_deg": round(self.at_deg[0], 4),
                "el_deg": round(self.at_deg[1], 4), "error_deg": round(max(abs(err_az), abs(err_el)), 4),
                "pose_az_deg": self.config.az_deg, "pose_el_deg": self.config.el_deg}

    def failure(self) -> str:
        """Why a TIMEOUT ends the session, in one line."""
        c = self.config
        az, el = self.at_deg
        return (f"start pose not reached within {c.timeout_s:g} s (start_pose.timeout_s): az {az:.2f} deg, el "
                f"{el:.2f} deg against the pose az {c.az_deg:g}, el {c.el_deg:g} +- {c.tolerance_deg:g} deg; "
                "nothing swung. Is an axis blocked or its encoder off, or the pose outside the gimbal's travel?")
