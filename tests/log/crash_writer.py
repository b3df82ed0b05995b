"""Child process for the crash tests: logs a known pattern at 1 kHz, in real time, until killed.

    python -m tests.log.crash_writer PATH SECONDS

Prints ``writer_pid N`` then ``started`` on stdout, then ``flushed N`` whenever the writer has acknowledged more
loop rows as flushed (those must survive any kill). The pattern (``pattern_row``) is a function of
the group and the row index only, except ``t_host_ns``, which is the real monotonic time, so the
test can tell how close to the kill the surviving rows reach.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from hil.log import SCHEMA, SessionLog
from hil.log.schema import Group, group_by_name

ATTRS = {"config": {"test": "crash"}, "ident": {"servo": {"firmware_version": "1.2.3"}}, "seed": 1234}
GROUPS = group_by_name(SCHEMA)
EVERY = {"loop": 1, "timing": 1, "image": 10, "hexapod": 10, "drive": 10, "links": 100}  # rows every N loop ticks


def pattern_value(dtype: str, ci: int, k: int) -> int | float | bytes:
    """Row k, channel ci: a value the dtype holds exactly."""
    if dtype == "f8":
        return k * 0.001 + ci
    if dtype == "f4":
        return ((k * 7 + ci) % 2000) * 0.25 - 250.0
    if dtype == "i4":
        return (k * 3 + ci) % 20001 - 10000
    if dtype == "u4":
        return k + ci * 1_000_000
    if dtype == "u1":
        return (k + ci) % 256
    if dtype == "i8":
        return k * 1000 + ci + 1
    raise ValueError(dtype)


def pattern_row(group: Group, k: int, t_host_ns: int | None = None) -> tuple[int | float | bytes, ...]:
    row = [pattern_value(c.dtype, ci, k) for ci, c in enumerate(group.channels)]
    if t_host_ns is not None and "t_host_ns" in [c.name for c in group.channels]:
        row[[c.name for c in group.channels].index("t_host_ns")] = t_host_ns
    return tuple(row)


def expected_columns(group: Group, n: int) -> dict[str, np.ndarray]:
    """The first n rows of the pattern, by channel, in the channels' dtypes (t_host_ns left out)."""
    rows = [pattern_row(group, k) for k in range(n)]
    return {
        c.name: np.array([r[ci] for r in rows], dtype=c.dtype)
        for ci, c in enumerate(group.channels)
        if c.name != "t_host_ns"
    }


def log_tick(log: SessionLog, k: int) -> None:
    now = time.monotonic_ns()
    for name, every in EVERY.items():
        if k % every == 0:
            log.append(name, pattern_row(GROUPS[name], k // every, now))
    if k % 250 == 0:
        log.event("info", k, {"k": k})


def main() -> None:
    path, seconds = sys.argv[1], float(sys.argv[2])
    log = SessionLog(path, attrs=ATTRS)
    print(f"writer_pid {log.writer_pid}", flush=True)
    print("started", flush=True)
    deadline = time.perf_counter()
    flushed = 0
    for k in range(int(seconds * 1000)):
        while (rem := deadline - time.perf_counter()) > 0:
            if rem > 3e-4:
                time.sleep(rem - 2e-4)
        log_tick(log, k)
        if log.rows.get("loop", 0) != flushed:
            flushed = log.rows["loop"]
            print(f"flushed {flushed}", flush=True)
        deadline += 1e-3
    log.close()
    print("done", flush=True)


if __name__ == "__main__":
    main()
