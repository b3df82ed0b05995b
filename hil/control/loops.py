"""The two loops of the stabilized platform: the 1 kHz rate loop and the camera-rate tracking loop.

Rate loop (seed 000 eq 43 and Fig. 5): u = u0 - z2/b0, where u0 is a PI law on the rate error and
z2/b0 is the observer's disturbance estimate in DAC counts; the result is rounded and saturated
to the DAC range, and that applied value is what the observer must be fed next.

Tracking loop (seed 000 Fig. 11): miss distance (px) -> line-of-sight rate command (deg/s).
"""

from __future__ import annotations

from dataclasses import dataclass

DAC_MAX_COUNTS = 32767  # signed 16-bit DAC (DRIVE_CMD)


class RateLoop:
    """PI on the rate error plus disturbance compensation, saturated, with conditional-integration anti-windup.

    u_k = sat( kp e_k + I_k - d_k ),  I_{k+1} = I_k + ki e_k h  unless u is saturated and e_k pushes further.

    Units: e in deg/s, kp in counts per deg/s, ki in counts per deg (per deg/s per s), d in counts.
    With the plant d(rate)/dt = k_m u, a P gain kp gives a closed-loop bandwidth of kp * k_m rad/s.
    """

    def __init__(
        self,
        *,
        kp_counts_per_dps: float,
        ki_counts_per_deg: float = 0.0,
        u_max_counts: int = DAC_MAX_COUNTS,
        dt_s: float = 1e-3,
    ) -> None:
        if kp_counts_per_dps < 0 or ki_counts_per_deg < 0:
            raise ValueError("gains must be >= 0")
        if not 0 < u_max_counts <= DAC_MAX_COUNTS:
            raise ValueError(f"u_max_counts must lie in 1..{DAC_MAX_COUNTS}")
        self.kp = kp_counts_per_dps
        self.ki_h = ki_counts_per_deg * dt_s
        self.u_max = u_max_counts
        self.integral_counts = 0.0
        self.u_counts = 0  # the applied (rounded, saturated) output of the last step
        self.saturated = False

    def reset(self) -> None:
        self.integral_counts = 0.0
        self.u_counts = 0
        self.saturated = False

    def step(self, rate_cmd_dps: float, rate_fb_dps: float, disturbance_counts: float = 0.0) -> int:
        error = rate_cmd_dps - rate_fb_dps
        u = round(self.kp * error + self.integral_counts - disturbance_counts)
        u_max = self.u_max
        if u > u_max:
            u, self.saturated = u_max, error > 0
        elif u < -u_max:
            u, self.saturated = -u_max, error < 0
        else:
            self.saturated = False
        if not self.saturated:  # integrate only while it does not drive deeper into saturation
            self.integral_counts += self.ki_h * error
        self.u_counts = u
        return u


@dataclass
class TrackingCounters:
    frames_used: int = 0
    frames_invalid: int = 0  # track_valid false
    frames_late: int = 0  # older than stale_s when they arrived
    frames_out_of_order: int = 0  # frame counter not increasing


class TrackingLoop:
    """One axis of the tracking loop: miss distance (px) at camera rate -> rate command (deg/s) every tick.

    rate_cmd = kp * m + ki * sum(m * dt_frame),  m = miss_px * ifov_deg_per_px (deg of line-of-sight error).

    Frames update the command when they arrive (``on_frame``); the command is held between frames
    (``rate_cmd_dps`` each 1 kHz tick). A frame with track_valid false, or no usable frame for
    ``stale_s``, drops the command to 0 (the rate loop then holds the line of sight inertially
    still) and clears the integral, since a reacquired target may sit elsewhere. A frame whose
    exposure is already older than ``stale_s`` on arrival, or whose counter does not increase, is
    not used. Sign: a positive miss (target right/up) asks for a positive rate.
    """

    def __init__(
        self,
        *,
        kp_per_s: float,
        ki_per_s2: float = 0.0,
        ifov_deg_per_px: float,
        max_rate_dps: float = 30.0,
        stale_s: float = 0.05,
    ) -> None:
        if ifov_deg_per_px <= 0 or max_rate_dps <= 0 or stale_s <= 0:
            raise ValueError("ifov_deg_per_px, max_rate_dps and stale_s must be positive")
        self.kp = kp_per_s
        self.ki = ki_per_s2
        self.ifov = ifov_deg_per_px
        self.max_rate = max_rate_dps
        self.stale_s = stale_s
        self.counters = TrackingCounters()
        self.reset()

    def reset(self) -> None:
        self.integral_deg = 0.0
        self.command_dps = 0.0
        self.last_frame = -1
        self.last_used_s: float | None = None

    def on_frame(self, *, frame: int, miss_px: float, track_valid: bool, t_exposure_s: float, now_s: float) -> None:
        c = self.counters
        if frame <= self.last_frame:
            c.frames_out_of_order += 1
            return
        self.last_frame = frame
        if not track_valid:
            c.frames_invalid += 1
            self.integral_deg = 0.0
            self.command_dps = 0.0
            self.last_used_s = None
            return
        if now_s - t_exposure_s > self.stale_s:
            c.frames_late += 1
            return
        error_deg = miss_px * self.ifov
        if self.last_used_s is not None:
            self.integral_deg += error_deg * (t_exposure_s - self.last_used_s)
        self.last_used_s = t_exposure_s
        cmd = self.kp * error_deg + self.ki * self.integral_deg
        self.command_dps = max(-self.max_rate, min(self.max_rate, cmd))
        c.frames_used += 1

    def rate_cmd_dps(self, now_s: float) -> float:
        """The command for this tick: the last frame's, or 0 once no usable frame came for stale_s."""
        if self.last_used_s is None:
            return 0.0
        if now_s - self.last_used_s > self.stale_s:
            self.integral_deg = 0.0
            self.command_dps = 0.0
            self.last_used_s = None
        return self.command_dps
