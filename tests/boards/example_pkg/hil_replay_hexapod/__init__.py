"""A swing table that is only software: it accepts any profile and, once started, reports the profile's pose on a
timer, as a real controller reports what it applied. It needs no port and no hardware, so a session can run its
controllers against a swing that the log records, or a bench can be checked without its hexapod.

Select it in a session file (after ``pip install`` of this package)::

    hexapod: {driver: replay, rate_hz: 100, stop_ramp_s: 0.5}
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from typing import Any

from pydantic import Field

from hil.boards import HexapodDriver, HexapodOptions
from hil.protocol.swing import Profile, Segment, profile_end_s

__all__ = ["ReplayHexapod", "ReplayOptions"]


class ReplayOptions(HexapodOptions):
    """The session's ``hexapod`` section for this driver (``driver: replay`` aside)."""

    rate_hz: float = Field(100.0, gt=0, le=1000, description="poses reported per second")
    stop_ramp_s: float = Field(0.5, gt=0, le=60, description="after stop, the pose falls to home over this long")
    serial_number: str = Field("replay-0", max_length=64, description="recorded in the log's ident")


class ReplayHexapod(HexapodDriver):
    """The ``replay`` driver: profile time is the event loop's clock since :meth:`start`."""

    Options = ReplayOptions
    uses_link = False  # no serial port: ports.hexapod and the emulator's hexapod link are left alone

    def __init__(self, options: ReplayOptions) -> None:
        self.options = options
        self.profile = Profile(())
        self.end_s = 0.0
        self.reported: list[tuple[float, tuple[float, ...]]] = []  # every pose sent to on_pose
        self._task: asyncio.Task[None] | None = None
        self._t0 = 0.0
        self._stop_at: float | None = None  # profile time of the stop, once stopped

    async def identify(self) -> dict[str, Any]:
        return self.ident_dict()

    def ident_dict(self) -> dict[str, Any]:
        return {"model": "replay", "serial_number": self.options.serial_number, "rate_hz": self.options.rate_hz}

    async def load(self, segments: Sequence[Segment]) -> None:
        if self.running:
            raise RuntimeError("a profile is running: stop it first")
        self.profile = Profile(segments)
        self.end_s = profile_end_s(segments)

    async def start(self) -> None:
        if not self.profile.segments:
            raise RuntimeError("no profile loaded")
        if self.running:
            raise RuntimeError("already running")
        loop = asyncio.get_running_loop()
        self._t0, self._stop_at = loop.time(), None
        self._task = loop.create_task(self._report(), name="replay-hexapod")

    async def stop(self) -> None:
        if self.running and self._stop_at is None:
            self._stop_at = asyncio.get_running_loop().time() - self._t0

    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    @property
    def state(self) -> str:
        if not self.running:
            return "idle"
        return "running" if self._stop_at is None else "stopping"

    async def close(self) -> None:
        task, self._task = self._task, None
        if task is not None and not task.done():
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    def pose_at(self, t_s: float) -> tuple[float, ...]:
        """The pose reported at profile time ``t_s``: the profile's, scaled down to home after a stop."""
        pose = self.profile(t_s)[0]
        if self._stop_at is not None:
            scale = max(0.0, 1.0 - (t_s - self._stop_at) / self.options.stop_ramp_s)
            pose = tuple(scale * p for p in pose)
        return pose

    async def _report(self) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / self.options.rate_hz
        while True:
            t_s = loop.time() - self._t0
            done = t_s >= self.end_s or (self._stop_at is not None and t_s >= self._stop_at + self.options.stop_ramp_s)
            pose = (0.0,) * 6 if done else self.pose_at(t_s)
            self.reported.append((t_s, pose))
            if self.on_pose is not None:
                self.on_pose(t_s, pose)
            if done:
                return
            await asyncio.sleep(period)
