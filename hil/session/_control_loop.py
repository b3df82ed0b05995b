"""The session's 1 kHz cycle (:class:`ControlLoop`): per sample, the tracking loops' rate commands, the excitation,
the drive step (hil.control.cycle.DriveStep) and DRIVE_CMD, the loop row of the log and the telemetry sample; per
camera frame and hexapod pose, what the tracking loop and the feed-forward's profile clock need."""

from __future__ import annotations

import time
from array import array
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from hil.config import SessionConfig
from hil.control.controller import RateController
from hil.control.cycle import DriveStep
from hil.control.imbalance_feed import ImbalanceFeed, ProfileClock
from hil.control.loops import TrackingLoop
from hil.control.oracle import TruthSource, bind_truth
from hil.control.registry import build_controller
from hil.control.start_pose import StartPose
from hil.log import SessionLog
from hil.log.schema import LATE_US, LINK_COUNTERS
from hil.protocol import LINKS, NO_LATENCY_US, DriveStatus, GyroSample, LoopTiming, MissDistance
from hil.telemetry import Telemetry

LATE_NS = round(LATE_US * 1000)  # a cycle whose command went out more than 1 ms after its sample arrived is late


@dataclass
class LoopStats:
    cycles: int = 0
    late: int = 0
    missed: int = 0  # samples that never arrived (tick gaps)
    latency_us: array = field(default_factory=lambda: array("f"))
    faults: list[str] = field(default_factory=list)
    recoveries: int = 0
    host_stalls: int = 0  # silences the host caused, not the board: the watchdog woke late, or the emulator's clock
    clock_late: int = 0  # CLOCK_LATE frames: the emulator's clock fired late (its host did not run it in time)
    drive_short_writes: int = 0  # realtime: DRIVE_CMDs the driver's fd did not take whole (hil.session._loop_thread)


class TrackJudge:
    """Was the target tracked? Counts the camera's frames while the loop is armed, the valid ones, and the longest
    stretch without a valid frame once the target was first acquired (board time, from the frames' exposure times).
    While the loop is disarmed (a recovery) nothing drives the gimbal: those frames are not judged, and a stretch
    is counted anew from the first frame after the loop is armed again."""

    def __init__(self, max_lost_s: float) -> None:
        self.max_lost_s = max_lost_s
        self.frames = 0
        self.valid = 0
        self.first_valid_s: float | None = None
        self.last_valid_s: float | None = None
        self.longest_lost_s = 0.0
        self._paused = False

    def on_frame(self, t_exposure_s: float, valid: bool, armed: bool = True) -> None:
        if not armed:
            self._paused = True
            return
        if self._paused and self.last_valid_s is not None:
            self.last_valid_s = t_exposure_s  # the loop is armed again: a lost stretch counts from here
        self._paused = False
        self.frames += 1
        if valid:
            self.valid += 1
            if self.first_valid_s is None:
                self.first_valid_s = t_exposure_s
            self.last_valid_s = t_exposure_s
        elif self.last_valid_s is not None:
            self.longest_lost_s = max(self.longest_lost_s, t_exposure_s - self.last_valid_s)

    def verdict(self) -> str | None:
        """None when the target was tracked; else why not, in one line."""
        if self.valid == 0:
            return (f"tracking: the target was never acquired (0 of {self.frames} frames valid): is it in the "
                    "camera's view at the start pose?")
        if self.longest_lost_s > self.max_lost_s:
            return (f"tracking: the target was lost for {self.longest_lost_s:.2f} s (tracking.max_lost_s "
                    f"{self.max_lost_s:g}); {self.valid} of {self.frames} frames valid")
        return None

    def as_dict(self) -> dict[str, Any]:
        return {"frames": self.frames, "valid": self.valid, "longest_lost_s": round(self.longest_lost_s, 3)}


class ControlLoop:
    """Per-axis controllers and tracking loops; everything that happens per sample and per frame."""

    def __init__(self, config: SessionConfig, drive: Callable[[int, int, int], None], log: SessionLog, *,
                 telemetry: Telemetry | None, duration_ticks: int, on_done: Callable[[], None],
                 truth: TruthSource | None = None, record_truth: Callable[[int], None] | None = None,
                 on_start_pose: Callable[[StartPose], None] | None = None) -> None:
        """``drive(tick, az_counts, el_counts)`` sends DRIVE_CMD; ``on_done`` is called once, at the last tick of
        the run (from the loop's own thread: it must hand over to the event loop itself if it needs it), which is
        ``duration_ticks`` samples after the start pose phase ended. ``on_start_pose(phase)``: called once, from the
        same thread, at the sample that ended the start pose phase (``phase.outcome``), before that sample's drive is
        computed: the sample is the run's first when the pose was reached. ``truth``:
        the plant's true state (the sim clock's hil.session.PlantTruth), which only the ``oracle`` controller reads.
        ``record_truth(tick)``: called with each loop row's sample counter (the sim clock's hil.session.TruthLog)."""
        self.config = config
        self.truth = truth
        self.record_truth = record_truth
        self.drive = drive
        self.log = log
        self.telemetry = telemetry
        self.duration_ticks = duration_ticks
        self.on_done = on_done
        self.stats = LoopStats()
        self.armed = False
        self.last_tick: int | None = None
        self.t_wraps = 0
        self.last_t_us = 0
        self.t0_s: float | None = None
        self.t_s = 0.0
        self.limits = config.safety
        self.decoders: dict[str, Any] = {}
        self.frames: deque[tuple[int, MissDistance]] = deque()  # (board time to use it, us; frame)
        self.apply_after_us = round(config.tracking.apply_after_ms * 1000)
        self.excitation = config.excitation
        self.excite_el = config.excitation is None or config.excitation.axis == "el"
        self.track_judge = TrackJudge(config.tracking.max_lost_s)
        # the start pose phase (hil.control.start_pose), while not None; the run's time and cycles count from its end
        self.start_pose = StartPose(config.start_pose) if config.start_pose.enabled else None
        self.on_start_pose = on_start_pose
        self.run_t0_s = 0.0  # self.t_s at the run's first sample
        self.run_cycles0 = 0  # cycles before it
        self.reset_controllers()

    def reset_controllers(self) -> None:
        c = self.config.controller
        self.ctrl_az: RateController = build_controller(c.name, c.params)
        self.ctrl_el: RateController = build_controller(c.name, c.params)
        bind_truth(self.ctrl_az, self.truth, "az")  # the oracle reads the plant's truth; the others, nothing
        bind_truth(self.ctrl_el, self.truth, "el")
        tr = self.config.tracking
        kw = {"kp_per_s": tr.kp_per_s, "ki_per_s2": tr.ki_per_s2, "ifov_deg_per_px": tr.ifov_deg_per_px,
              "max_rate_dps": tr.max_rate_dps, "stale_s": tr.stale_s}
        self.track_az, self.track_el = TrackingLoop(**kw), TrackingLoop(**kw)
        # seed 001's imbalance feed-forward (elevation), for a controller that carries a UKF
        imbalance = self.ctrl_el.imbalance
        self.imbalance_feed = None if imbalance is None else ImbalanceFeed(
            imbalance, self.config.profile.protocol_segments(), dt_s=1e-3)
        self.profile_clock = ProfileClock()
        self.drive_step = DriveStep(self.ctrl_az, self.ctrl_el, self.imbalance_feed, self.profile_clock,
                                    max_drive_counts=self.limits.max_drive_counts,
                                    max_slew_counts=self.limits.max_slew_counts)

    # --- the 1 kHz cycle -------------------------------------------------------------------------------

    def on_sample(self, g: GyroSample, t_rx: int | None = None) -> None:
        """One cycle for sample ``g``, read at ``t_rx`` (monotonic ns; default: now). Latency is counted from
        ``t_rx`` to DRIVE_CMD written."""
        if t_rx is None:
            t_rx = time.monotonic_ns()
        gap = 0 if self.last_tick is None else max(0, g.tick - self.last_tick - 1)
        self.last_tick = g.tick
        if g.t_us < self.last_t_us:
            self.t_wraps += 1
        self.last_t_us = g.t_us
        t_s = (g.t_us + (self.t_wraps << 32)) / 1e6
        if self.t0_s is None:
            self.t0_s = t_s
        self.t_s = t_s - self.t0_s
        st = self.stats
        st.missed += gap
        while self.frames and self.frames[0][0] < g.t_us + (self.t_wraps << 32):
            self._use_frame(self.frames.popleft()[1])
        pose = self.start_pose
        if pose is not None and self.armed and pose.judge(t_s, g.az_deg, g.el_deg) is not None:
            self._end_start_pose(pose, st.cycles)
            pose = self.start_pose
        if pose is not None:  # the position hold: no tracking, no excitation
            cmd_az, cmd_el = pose.rate_cmds_dps(g.az_deg, g.el_deg)
        else:
            tracking = self.config.tracking.enabled
            cmd_az = self.track_az.rate_cmd_dps(t_s) if tracking else 0.0
            cmd_el = self.track_el.rate_cmd_dps(t_s) if tracking else 0.0
            exc = self.excitation
            if exc is not None:
                if self.excite_el:
                    cmd_el += exc.rate_dps(self.t_s - self.run_t0_s)
                else:
                    cmd_az += exc.rate_dps(self.t_s - self.run_t0_s)
        step = self.drive_step
        if self.armed:
            u_az, u_el = step.step(cmd_az, cmd_el, g.rate_y_dps, g.rate_z_dps, az_deg=g.az_deg, el_deg=g.el_deg,
                                   t_s=self.t_s)
            self.drive(g.tick, u_az, u_el)
        else:
            u_az = u_el = 0
            step.disarmed()
        latency_ns = time.monotonic_ns() - t_rx
        st.cycles += 1
        if latency_ns > LATE_NS:
            st.late += 1
        st.latency_us.append(latency_ns / 1000)
        az, el = self.ctrl_az, self.ctrl_el
        self.log.append("loop", (
            g.tick, t_s, t_rx, g.rate_x_dps, g.rate_y_dps, g.rate_z_dps, g.az_deg, g.el_deg,
            cmd_az, cmd_el, az.rate_fb_dps, el.rate_fb_dps, cmd_az - g.rate_z_dps, cmd_el - g.rate_y_dps,
            az.disturbance_counts, el.disturbance_counts, 0.0, step.ff_el, u_az, u_el, latency_ns / 1000,
            gap))
        if self.record_truth is not None:
            self.record_truth(g.tick)
        if self.telemetry is not None:
            self.telemetry.sample(t_s, lambda: {
                "gyro_y_dps": g.rate_y_dps, "gyro_z_dps": g.rate_z_dps, "rate_err_el_dps": cmd_el - g.rate_y_dps,
                "rate_err_az_dps": cmd_az - g.rate_z_dps, "drive_az_counts": u_az, "drive_el_counts": u_el,
                "az_deg": g.az_deg, "el_deg": g.el_deg, "latency_us": latency_ns / 1000})
        if st.cycles % 100 == 0:
            self._log_links(t_rx)
        if st.cycles - self.run_cycles0 == self.duration_ticks and self.start_pose is None:
            self.on_done()

    def _end_start_pose(self, pose: StartPose, cycles: int) -> None:
        """The start pose phase decided at this sample: reached, the run starts here (tracking from fresh loops, the
        excitation's and the duration's clocks from 0); the session hears of it either way."""
        if pose.outcome == "reached":
            self.start_pose = None
            self.run_t0_s, self.run_cycles0 = self.t_s, cycles
            self.track_az.reset()
            self.track_el.reset()
        if self.on_start_pose is not None:
            self.on_start_pose(pose)
        if pose.outcome != "reached":  # reported once; the session disarms
            pose.outcome = None
            self.on_start_pose = None

    def _log_links(self, t_ns: int) -> None:

        row: list[int] = [t_ns]
        for name in LINKS:
            dec = self.decoders.get(name)
            totals = {} if dec is None else dec.counters.totals()
            row += [totals.get(counter, 0) for counter in LINK_COUNTERS]
        self.log.append("links", [min(v, 0xFFFFFFFF) if i else v for i, v in enumerate(row)])

    def on_timing(self, t: LoopTiming) -> None:
        for i, lat in enumerate(t.latency_us):
            self.log.append("timing", (t.first_tick + i, float("nan") if lat == NO_LATENCY_US else float(lat)))

    def on_miss(self, m: MissDistance) -> None:
        """Log the frame now; feed it to the tracking loop at a board time fixed by its exposure time."""
        t_exp_us = m.t_exposure_us + (self.t_wraps << 32)
        self.log.append("image", (m.frame, t_exp_us / 1e6, time.monotonic_ns(), m.miss_x_px, m.miss_y_px,
                                  int(m.track_valid), self.last_tick or 0))
        self.track_judge.on_frame(t_exp_us / 1e6, bool(m.track_valid), self.armed and self.start_pose is None)
        if self.telemetry is not None:
            self.telemetry.miss(m.miss_x_px, m.miss_y_px, m.track_valid)
        self.frames.append((t_exp_us + self.apply_after_us, m))

    def _use_frame(self, m: MissDistance) -> None:
        t_exp = (m.t_exposure_us + (self.t_wraps << 32)) / 1e6
        if self.config.tracking.enabled:
            self.track_az.on_frame(frame=m.frame, miss_px=m.miss_x_px, track_valid=m.track_valid,
                                   t_exposure_s=t_exp, now_s=self.t_s + (self.t0_s or 0.0))
            self.track_el.on_frame(frame=m.frame, miss_px=m.miss_y_px, track_valid=m.track_valid,
                                   t_exposure_s=t_exp, now_s=self.t_s + (self.t0_s or 0.0))

    def on_drive_status(self, m: DriveStatus) -> None:
        """Log the driver's report (its state and measured currents)."""
        self.log.append("drive", (time.monotonic_ns(), self.last_tick or 0, *m))  # the group's fields are m's

    def on_pose(self, t_profile_s: float, pose: tuple[float, ...]) -> None:
        self.log.append("hexapod", (t_profile_s, time.monotonic_ns(), *pose))
        self.profile_clock.on_pose(t_profile_s, self.t_s)
