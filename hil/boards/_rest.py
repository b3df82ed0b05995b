"""The boards' rest state, measured (docs/service.md, "Between items"): what a lab service checks before each item
instead of assuming it, so that every item starts from the same known state whatever the one before it did.

At rest means, from the boards' own periodic reports: the motor driver has no axis enabled (DRIVE_STATUS), the
servo board sends no GYRO_SAMPLE (its stream idle), and the hexapod is IDLE or LOADED, not RUNNING or STOPPING
(HEXAPOD_STATUS), at its home pose (POSE within :data:`HOME_MM` and :data:`HOME_DEG`). A hexapod still ramping
home after a fault or an abort is waited for. A board found otherwise is made safe with the commands every session's
shutdown sends (DRIVE_DISABLE, SERVO_MODE IDLE, HEXAPOD_STOP: none of them enables or starts anything; HEXAPOD_STOP
ramps the table home), and waited for again. HOST_ALIVE goes to every board meanwhile, so no host timer expires.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from hil.link import LinkError, SerialLink
from hil.protocol import (
    AxisMask,
    Board,
    DriveDisable,
    DriveStatus,
    Frame,
    GyroSample,
    HexapodState,
    HexapodStatus,
    HexapodStop,
    HostAlive,
    Pose,
    ServoMode,
    StreamMode,
)

REST_TIMEOUT_S = 30.0  # a hexapod's stop ramp and return home take a few seconds; a board not at rest by then is not
SETTLED_S = 0.3  # at rest for this long, every board heard from at least once in it
QUIET_S = 0.1  # no GYRO_SAMPLE for this long: the stream is idle (a streaming board sends one every 1 ms)
HOME_MM = 0.5  # the hexapod's pose within this of home, each translation
HOME_DEG = 0.05  # and each rotation
HOST_ALIVE_S = 0.1
MAKE_SAFE_AFTER_S = 1.0  # a board still not at rest this long after the check began is sent its safe command
BOARDS = {"servo": Board.SERVO, "driver": Board.DRIVER, "hexapod": Board.HEXAPOD}


@dataclass
class RestState:
    """What the boards reported: ``boards`` each link's state in words, ``ok`` all at rest, ``waited_s`` how long
    it took, ``made_safe`` the commands sent to boards found moving."""

    ok: bool
    boards: dict[str, str]
    waited_s: float
    made_safe: list[str] = field(default_factory=list)

    def describe(self) -> str:
        """One line: ``driver disabled, servo stream idle, hexapod LOADED at home``."""
        return ", ".join(f"{name} {state}" for name, state in self.boards.items())

    def as_dict(self) -> dict[str, Any]:
        return {"ok": self.ok, "boards": self.boards, "waited_s": round(self.waited_s, 3),
                "made_safe": self.made_safe, "at": time.time(), "summary": self.describe()}


class _Reports:
    """The latest periodic report of each board, as the links decode them."""

    def __init__(self) -> None:
        self.enabled: int | None = None
        self.hex_state: int | None = None
        self.pose: tuple[float, ...] | None = None
        self.last_sample_s: float | None = None
        self.heard: dict[str, float] = {}

    def on_frame(self, name: str) -> Any:
        def handle(frame: Frame) -> None:
            msg, now = frame.message, time.monotonic()
            if isinstance(msg, DriveStatus):
                self.enabled, self.heard["driver"] = int(msg.enabled), now
            elif isinstance(msg, HexapodStatus):
                self.hex_state, self.heard["hexapod"] = int(msg.state), now
            elif isinstance(msg, Pose):
                self.pose = tuple(float(v) for v in msg[1:])
            elif isinstance(msg, GyroSample):
                self.last_sample_s = now
            if name == "servo":
                self.heard["servo"] = now
        return handle

    def states(self, now_s: float, links: set[str]) -> dict[str, tuple[bool, str]]:
        """Each link's (at rest, in words) as of ``now_s``."""
        out: dict[str, tuple[bool, str]] = {}
        if "driver" in links:
            out["driver"] = ((self.enabled == 0, "disabled") if self.enabled is not None and self.enabled == 0 else
                             (False, "not heard from") if self.enabled is None else
                             (False, f"enabled ({AxisMask(self.enabled).name})"))
        if "servo" in links:
            streaming = self.last_sample_s is not None and now_s - self.last_sample_s < QUIET_S
            out["servo"] = (not streaming, "streaming" if streaming else "stream idle")
        if "hexapod" in links:
            if self.hex_state is None:
                out["hexapod"] = (False, "not heard from")
            else:
                state = HexapodState(self.hex_state).name
                home = self.pose is not None and all(abs(v) <= HOME_MM for v in self.pose[:3]) and all(
                    abs(v) <= HOME_DEG for v in self.pose[3:])
                resting = self.hex_state in (HexapodState.IDLE, HexapodState.LOADED)
                where = "at home" if home else "off home" if self.pose is not None else "pose not heard"
                out["hexapod"] = (resting and home, f"{state} {where}")
        return out


async def wait_for_rest(ports: Mapping[str, str], bauds: Mapping[str, int], *,
                        timeout_s: float = REST_TIMEOUT_S) -> RestState:
    """Open the links of ``ports`` (of servo, driver and hexapod; the ports already this process's, as `hil serve`'s
    worker holds them), listen to the boards' reports until every board is at rest for :data:`SETTLED_S` or
    ``timeout_s`` passes, and close them again. A board still moving after :data:`MAKE_SAFE_AFTER_S` is sent its
    safe command once. Never enables or starts anything; LinkError only for a port that cannot be opened."""
    reports = _Reports()
    links: dict[str, SerialLink] = {}
    t0 = time.monotonic()
    made_safe: list[str] = []
    try:
        for name, port in ports.items():
            if name in BOARDS:
                links[name] = await SerialLink.open(name, port, bauds[name], reports.on_frame(name))
        settled_since: float | None = None
        last_alive = 0.0
        while True:
            now = time.monotonic()
            if now - last_alive >= HOST_ALIVE_S:
                last_alive = now
                for name, link in links.items():
                    with contextlib.suppress(LinkError, OSError):
                        link.send(HostAlive(round((now - t0) * 1000) & 0xFFFFFFFF), BOARDS[name])
            states = reports.states(now, set(links))
            heard = all(now - reports.heard.get(name, -1e9) < 1.0 for name in links)
            if heard and all(ok for ok, _ in states.values()):
                settled_since = settled_since if settled_since is not None else now
                if now - settled_since >= SETTLED_S:
                    return RestState(True, {n: s for n, (_, s) in states.items()}, now - t0, made_safe)
            else:
                settled_since = None
            if now - t0 >= timeout_s:
                return RestState(False, {n: s for n, (_, s) in states.items()}, now - t0, made_safe)
            if now - t0 >= MAKE_SAFE_AFTER_S and not made_safe:
                made_safe = _make_safe(links, states)
            await asyncio.sleep(0.02)
    finally:
        for link in links.values():
            link.close()
        closing = [link.closed for link in links.values() if not link.closed.done()]
        if closing:
            await asyncio.wait(closing, timeout=2.0)


def _make_safe(links: Mapping[str, SerialLink], states: Mapping[str, tuple[bool, str]]) -> list[str]:
    """The shutdown's own safe commands to the boards found moving; what was sent, in words."""
    sent: list[str] = []
    safe = {"driver": DriveDisable(AxisMask.BOTH), "servo": ServoMode(StreamMode.IDLE), "hexapod": HexapodStop()}
    for name, (ok, state) in states.items():
        if ok or (name == "hexapod" and state.startswith("STOPPING")):  # a stop ramp under way: wait for it
            continue
        with contextlib.suppress(LinkError, OSError):
            links[name].send(safe[name], BOARDS[name])
            sent.append(f"{type(safe[name]).__name__} to the {name} ({state})")
    return sent
