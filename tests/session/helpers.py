"""What a session left, read back: its events, its channels compared or digested (sessions are built in
tests/factories.py)."""

from __future__ import annotations

import asyncio
import hashlib
from pathlib import Path
from typing import Any

import numpy as np

from hil.log.reader import read_log
from hil.session import Session


async def wait_cycles(session: Session, n: int, timeout_s: float = 30.0) -> None:
    """Until the session's loop has run n cycles."""
    for _ in range(int(timeout_s / 0.005)):
        if session.loop_ is not None and session.loop_.stats.cycles >= n:
            return
        await asyncio.sleep(0.005)
    raise TimeoutError(f"the session did not reach {n} cycles")


def logged_events(log_path: Path) -> list[tuple[str, dict[str, Any]]]:
    """The events of a session log as (kind, detail) pairs, decoded as the log's reader does (a detail cut at the
    log's detail length comes back as ``{"text": ...}``)."""
    from hil.log import read_log_frames

    return [(e["kind"], e["detail"]) for e in read_log_frames(log_path, groups=["events"]).event_details()]


HOST_CLOCK = {"t_host_ns", "latency_us"}  # the host's own monotonic clock: differs between any two runs


def within_session(group: str, g: dict, loop: dict, ticks: int) -> int:  # type: ignore[type-arg]
    """Rows of ``group`` that belong to the session's first ``ticks`` ticks (after them, the wind-down depends
    on how long the host took to start it: wall time in lockstep)."""
    if group == "loop":
        return ticks
    if group == "image":  # frames exposed before the last sample of the session, board clock
        return int(np.count_nonzero(np.asarray(g["t_exposure_s"]) <= loop["t_s"][ticks - 1]))
    if group == "timing":
        return int(np.count_nonzero(np.asarray(g["tick"]) < ticks))
    if group == "drive":  # DRIVE_STATUS every 10 world ticks, logged beside the loop tick it arrived after
        return int(np.count_nonzero(np.asarray(g["loop_tick"]) < ticks))
    return ticks // 10  # hexapod: POSE every 10 world ticks from the first


def assert_same_channels(a: Path, b: Path, ticks: int) -> int:
    """Every dataset of /loop, /image, /hexapod, /timing and /drive in the session's first ``ticks`` ticks equal,
    the host's clock aside. Returns the number of values compared."""
    la, lb = read_log(a), read_log(b)
    compared = 0
    for group in ("loop", "image", "hexapod", "timing", "drive"):
        ga, gb = la.groups[group], lb.groups[group]
        assert set(ga) == set(gb), group
        n = within_session(group, ga, la.groups["loop"], ticks)
        assert n == within_session(group, gb, lb.groups["loop"], ticks), group
        for channel in sorted(set(ga) - HOST_CLOCK):
            x, y = np.asarray(ga[channel])[:n], np.asarray(gb[channel])[:n]
            assert len(x) == n and len(y) == n, (group, channel, len(x), len(y), n)
            np.testing.assert_array_equal(x, y, err_msg=f"/{group}/{channel}")
            compared += n
    return compared


def channel_digests(log_path: Path, ticks: int) -> dict[str, str]:
    """SHA-256 of every /loop, /image, /hexapod and /timing dataset over the session's first ``ticks`` ticks, the
    host's clock aside: what a lockstep run reproduces byte for byte."""
    log = read_log(log_path)
    out = {}
    for group in ("loop", "image", "hexapod", "timing"):
        g = log.groups[group]
        n = within_session(group, g, log.groups["loop"], ticks)
        for channel in sorted(set(g) - HOST_CLOCK):
            data = np.ascontiguousarray(np.asarray(g[channel])[:n])
            out[f"/{group}/{channel}"] = f"{data.dtype.str}:{n}:{hashlib.sha256(data.tobytes()).hexdigest()[:16]}"
    return out
