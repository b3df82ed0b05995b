"""The drive step of one 1 kHz cycle, both axes: the one implementation the session's loop
(hil.session.ControlLoop.on_sample) and the controller replay (hil.replay) share.

Each axis's rate controller steps on its rate command and gyro rate (seed 000 eq 43); the elevation adds the
imbalance feed-forward of a controller that carries a UKF (seed 001), fed the drive applied at the previous cycle;
each drive is then slew-limited against the previous applied drive and clipped to the safety limit, and the
controllers' estimators are told the drive that was actually applied.
"""

from __future__ import annotations

from hil.control.controller import RateController
from hil.control.imbalance_feed import ImbalanceFeed, ProfileClock


class DriveStep:
    """Both axes' controllers, the feed-forward with its profile clock (the swing profile's time, from the hexapod's
    POSEs), and the drive limits; ``u_az``/``u_el`` the last applied drive (counts) and ``ff_el`` the last
    feed-forward (counts)."""

    __slots__ = ("clock", "ctrl_az", "ctrl_el", "feed", "ff_el", "max_drive_counts", "max_slew_counts", "u_az", "u_el")

    def __init__(self, ctrl_az: RateController, ctrl_el: RateController, feed: ImbalanceFeed | None,
                 clock: ProfileClock, *, max_drive_counts: int, max_slew_counts: int) -> None:
        self.ctrl_az, self.ctrl_el, self.feed, self.clock = ctrl_az, ctrl_el, feed, clock
        self.max_drive_counts, self.max_slew_counts = max_drive_counts, max_slew_counts
        self.u_az = self.u_el = 0
        self.ff_el = 0.0

    def step(self, cmd_az_dps: float, cmd_el_dps: float, gyro_y_dps: float, gyro_z_dps: float, *, az_deg: float,
             el_deg: float, t_s: float) -> tuple[int, int]:
        """The drive (az, el counts) for this cycle, applied (see :meth:`applied`); ``t_s`` the session's time (s),
        which the profile clock turns into the swing profile's (only with a feed-forward)."""
        lim, slew = self.max_drive_counts, self.max_slew_counts
        u_az = self.ctrl_az.step(cmd_az_dps, gyro_z_dps)
        feed = self.feed
        if feed is not None:
            self.ff_el = feed.tick(self.clock.at(t_s), gyro_y_dps, az_deg, el_deg, self.u_el)
        u_el = self.ctrl_el.step(cmd_el_dps, gyro_y_dps, self.ff_el)
        u_az = max(-lim, min(lim, max(self.u_az - slew, min(self.u_az + slew, u_az))))
        u_el = max(-lim, min(lim, max(self.u_el - slew, min(self.u_el + slew, u_el))))
        self.applied(u_az, u_el)
        return u_az, u_el

    def applied(self, u_az: int, u_el: int) -> None:
        """The drive the plant got: the step's own, or (open-loop replay) the logged one. The estimators must see it."""
        if u_az != self.ctrl_az.u_counts:
            self.ctrl_az.hold(u_az)
        if u_el != self.ctrl_el.u_counts:
            self.ctrl_el.hold(u_el)
        self.u_az, self.u_el = u_az, u_el

    def disarmed(self) -> None:
        """No drive this cycle (the session is not armed): the next step's slew starts from zero."""
        self.u_az = self.u_el = 0
