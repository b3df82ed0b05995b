#!/usr/bin/env python3
"""Session log: hot-path cost, and how much a flush stalls a 1 kHz loop thread.

    .venv/bin/python benchmarks/bench_log.py [--seconds 10] [--repeat 3] [--dir DIR] [--json PATH]

Cases, each run --repeat times, interleaved:

* ``none``: the 1 kHz loop thread alone (the machine's own timing noise);
* ``process``: ``hil.log.SessionLog`` as shipped: rows pickled every 100 ms by a flusher thread
  and written by a writer child process (HDF5 SWMR, flush + fsync);
* ``thread``: the same buffering, but the same HDF5 writing code (``H5Sink``) runs in a writer
  thread inside the loop's process, as a thread-based design would.

The loop thread sleeps to 200 us before each 1 ms deadline, then spins on perf_counter; the
lateness of every tick (wake-up minus deadline) is recorded. Each tick it appends one ``loop``
row (22 channels) and one ``timing`` row; every 10th tick an ``image`` and a ``hexapod`` row,
every 100th a ``links`` row, every 1000th an event: 6 groups, 64 datasets, flushed every 100 ms.
A flush that holds the GIL shows up as late ticks. Also measured: the cost of ``append`` and
``event`` (timed in batches of 100 calls), the flush itself (child side: convert + write, HDF5
flush, fsync), and end-to-end throughput (rows appended as fast as possible until ``close``
returns). Target (docs/log-format.md): the stall a flush inflicts on the loop <= 200 us p99.9.
Exit status is non-zero only if a case fails to run or loses rows, never on speed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import h5py
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.log import SCHEMA, SessionLog, read_log
from hil.log.writer import H5Sink, prepare_attrs

ATTRS = {"config": {"bench": "bench_log"}, "ident": {}, "seed": 0}
PERIOD = 1e-3
SPIN = 200e-6

# the 19 loop channels after tick, t_s, t_host_ns: 15 floats, 2 drive counts (int), latency_us, tick_gap
LOOP_REST = (*(float(i) * 0.25 for i in range(3, 18)), 1200, -800, 85.5, 0)
IMAGE = (0.0, 0, 1.5, -2.5, 1, 0)
HEXAPOD = (0.0, 0, 1.0, 2.0, 3.0, 0.1, 0.2, 0.3)
LINKS = tuple(range(20))


class ThreadLog(SessionLog):
    """The alternative design: SessionLog's buffers and hot path, HDF5 written by a thread in this process."""

    def __init__(self, path: Path, flush_interval_s: float = 0.1, fsync: bool = True) -> None:
        self._init_buffers(SCHEMA)
        prepared, json_names = prepare_attrs(ATTRS)
        self.sink = H5Sink(path, prepared, json_names, SCHEMA, fsync=fsync)
        self.interval = flush_interval_s
        self.stats = []  # type: ignore[assignment]
        self.error = None
        self._halt = threading.Event()
        self._writer = threading.Thread(target=self._run, daemon=True)
        self._writer.start()

    def _write(self) -> None:
        t0 = time.perf_counter()
        batches = self._take()
        if batches:
            st = self.sink.write(batches, sync=False)  # as SessionLog: fsync in the background
            st.update(t_start=t0, t_end=time.perf_counter())
            self.stats.append(st)

    def _run(self) -> None:
        while not self._halt.wait(self.interval):
            self._write()

    def close(self) -> None:
        self._halt.set()
        self._writer.join()
        self._write()
        self.sink.close()


def pct(xs: list[float], q: float) -> float:
    ys = sorted(xs)
    return ys[min(len(ys) - 1, int(q * len(ys)))] if ys else float("nan")


FIFO = False  # --fifo: run the loop thread SCHED_FIFO (as a real-time bench would), if permitted


def loop_run(log: Any, seconds: float) -> dict[str, Any]:
    """Run the 1 kHz loop thread for ``seconds``; lateness per tick and append cost, in us."""
    n = int(seconds / PERIOD)
    late = [0.0] * n
    due = [0.0] * n
    cost = [0.0] * n
    clock = time.perf_counter
    ns = time.perf_counter_ns
    mono = time.monotonic_ns

    def body() -> None:
        if FIFO:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
        deadline = clock() + 0.05
        for k in range(n):
            while True:
                rem = deadline - clock()
                if rem <= 0:
                    break
                if rem > SPIN + 50e-6:
                    time.sleep(rem - SPIN)
            late[k] = (clock() - deadline) * 1e6
            due[k] = deadline
            if log is not None:
                row = (k, k * PERIOD, mono(), *LOOP_REST)
                t0 = ns()
                log.append("loop", row)
                log.append("timing", (k, 12.5))
                if k % 10 == 0:
                    log.append("image", (k // 10, *IMAGE))
                    log.append("hexapod", HEXAPOD)
                if k % 100 == 0:
                    log.append("links", (mono(), *LINKS))
                if k % 1000 == 999:
                    log.event("info", k, {"k": k})
                cost[k] = (ns() - t0) / 1e3
            deadline += PERIOD

    th = threading.Thread(target=body, name="loop")
    th.start()
    th.join()
    # ticks due while a flush was under way (from 0.2 ms before it started to 0.2 ms after it ended)
    windows = sorted(
        (st["t_start"] - 2e-4, st.get("t_end", st["t_start"] + st.get("roundtrip_us", 0) / 1e6) + 2e-4)
        for st in getattr(log, "stats", [])
    )
    during = [False] * n
    j = 0
    for k in range(n):
        while j < len(windows) and windows[j][1] < due[k]:
            j += 1
        during[k] = j < len(windows) and windows[j][0] <= due[k]
    in_flush = [x for x, d in zip(late[50:], during[50:], strict=True) if d]
    outside = [x for x, d in zip(late[50:], during[50:], strict=True) if not d]
    late = late[50:]  # the first ticks include thread start-up
    return {
        "ticks": n,
        "ticks_in_flush": len(in_flush),
        "in_flush_p50_us": pct(in_flush, 0.5),
        "in_flush_p99_us": pct(in_flush, 0.99),
        "in_flush_max_us": max(in_flush, default=float("nan")),
        "outside_p99_us": pct(outside, 0.99),
        "outside_max_us": max(outside, default=float("nan")),
        "late_p50_us": pct(late, 0.5),
        "late_p99_us": pct(late, 0.99),
        "late_p999_us": pct(late, 0.999),
        "late_max_us": max(late),
        "ticks_late_gt_200us": sum(x > 200 for x in late),
        "ticks_late_gt_1ms": sum(x > 1000 for x in late),
        "tick_append_p50_us": pct(cost[50:], 0.5) if log is not None else None,
    }


def flush_stats(stats: list[dict[str, float]]) -> dict[str, float]:
    if not stats:
        return {}
    total = [s["write_us"] + s["flush_us"] + s["fsync_us"] for s in stats]
    out = {
        "flushes": len(stats),
        "flush_total_p50_us": pct(total, 0.5),
        "flush_total_max_us": max(total),
        "write_p50_us": pct([s["write_us"] for s in stats], 0.5),
        "fsync_p50_us": pct([s["fsync_us"] for s in stats], 0.5),
    }
    if "ship_us" in stats[0]:
        ship = [s["ship_us"] for s in stats]
        out |= {"ship_p50_us": pct(ship, 0.5), "ship_p99_us": pct(ship, 0.99), "ship_max_us": max(ship)}
    return out


def run_case(case: str, seconds: float, work: Path, run: int) -> dict[str, Any]:
    path = work / f"{case}-{run}.h5"
    if case == "none":
        return {"case": case, "run": run, **loop_run(None, seconds)}
    log = SessionLog(path, attrs=ATTRS) if case == "process" else ThreadLog(path)
    res = loop_run(log, seconds)
    log.close()
    res = {"case": case, "run": run, **res, **flush_stats(list(log.stats))}
    if getattr(log, "error", None):
        raise RuntimeError(log.error)
    data = read_log(path, groups=["loop"])
    if data.rows("loop") != res["ticks"] or not np.array_equal(data.groups["loop"]["tick"], np.arange(res["ticks"])):
        raise RuntimeError(f"{case}: {data.rows('loop')} loop rows back of {res['ticks']}")
    path.unlink()
    return res


def append_cost(work: Path, n: int = 200_000) -> dict[str, float]:
    """append() and event() per call, in us: median and p99 over batches of 100 calls."""
    path = work / "append.h5"
    log = SessionLog(path, attrs=ATTRS)
    rows = [(k, k * PERIOD, k, *LOOP_REST) for k in range(100)]
    per_call = []
    ns = time.perf_counter_ns
    for _ in range(n // 100):
        t0 = ns()
        for row in rows:
            log.append("loop", row)
        per_call.append((ns() - t0) / 100 / 1e3)
    ev = []
    for _ in range(50):
        t0 = ns()
        for k in range(100):
            log.event("state", k, {"from": "idle", "to": "track"})
        ev.append((ns() - t0) / 100 / 1e3)
    log.close()
    path.unlink()
    return {
        "append_p50_us": pct(per_call, 0.5),
        "append_p99_us": pct(per_call, 0.99),
        "event_p50_us": pct(ev, 0.5),
        "event_p99_us": pct(ev, 0.99),
    }


def throughput(work: Path, n: int = 500_000) -> dict[str, float]:
    """Loop rows appended as fast as possible, until close() returns (everything on disk)."""
    path = work / "throughput.h5"
    rows = [(k, k * PERIOD, k + 1, *LOOP_REST) for k in range(1000)]
    log = SessionLog(path, attrs=ATTRS)
    t0 = time.perf_counter()
    for k in range(n):
        log.append("loop", rows[k % 1000])
    t1 = time.perf_counter()
    log.close()
    t2 = time.perf_counter()
    ok = read_log(path, groups=["loop"]).rows("loop") == n
    path.unlink()
    st = list(log.stats)
    child_s = sum(s["write_us"] + s["flush_us"] + s["fsync_us"] for s in st) / 1e6
    if not ok:
        raise RuntimeError("throughput: rows missing")
    return {
        "rows": n,
        "append_rows_per_s": n / (t1 - t0),
        "end_to_end_rows_per_s": n / (t2 - t0),
        "writer_rows_per_s": n / child_s if child_s else float("nan"),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="loop run length per case and repeat")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--dir", type=Path, default=None, help="where to write the logs (default: a temp dir)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--cases", default="none,process,thread")
    ap.add_argument("--fifo", action="store_true", help="loop thread SCHED_FIFO 50 (needs CAP_SYS_NICE)")
    args = ap.parse_args(argv)
    global FIFO  # noqa: PLW0603
    FIFO = args.fifo
    work = Path(tempfile.mkdtemp(prefix="bench_log-", dir=args.dir))
    cases = args.cases.split(",")
    print(
        f"bench_log: {platform.python_version()}, h5py {h5py.version.version}, HDF5 {h5py.version.hdf5_version}, "
        f"nproc {os.cpu_count()}, load {os.getloadavg()[0]:.2f}, "
        f"loop thread {'SCHED_FIFO' if FIFO else 'SCHED_OTHER'}, "
        f"dir {work}"
    )
    results: dict[str, Any] = {"runs": []}
    try:
        results["append"] = a = append_cost(work)
        print(
            f"append(): p50 {a['append_p50_us']:.2f} us, p99 {a['append_p99_us']:.2f} us per call; "
            f"event(): p50 {a['event_p50_us']:.2f} us, p99 {a['event_p99_us']:.2f} us"
        )
        results["throughput"] = t = throughput(work)
        print(
            f"throughput ({t['rows']} loop rows of 22 channels): append {t['append_rows_per_s'] / 1e3:.0f}k rows/s, "
            f"appended->on disk (close returned) {t['end_to_end_rows_per_s'] / 1e3:.0f}k rows/s, "
            f"writer alone {t['writer_rows_per_s'] / 1e3:.0f}k rows/s"
        )
        print(f"\n1 kHz loop thread, {args.seconds:g} s per run, lateness of each tick (wake-up - deadline) in us;")
        print("'in flush': ticks due while a flush ran (cut -> rows in the file)")
        print("flush = the writer's convert + write + H5Fflush, in us (the fsync runs in the background)")
        hdr = (
            f"{'case':<8} {'run':>3} {'p50':>5} {'p99':>6} {'p99.9':>6} {'max':>6} {'>200us':>6} {'>1ms':>5} | "
            f"{'in flush: n':>11} {'p99':>6} {'max':>6} | {'other: p99':>10} {'max':>6} | {'flush p50':>9} {'max':>6}"
        )
        print(hdr)
        for run in range(args.repeat):
            for case in cases:
                r = run_case(case, args.seconds, work, run)
                results["runs"].append(r)
                fl = f"{'-':>9} {'-':>6}"
                if "flushes" in r:
                    fl = f"{r['flush_total_p50_us']:9.0f} {r['flush_total_max_us']:6.0f}"
                print(
                    f"{case:<8} {run:>3} {r['late_p50_us']:5.1f} {r['late_p99_us']:6.0f} {r['late_p999_us']:6.0f} "
                    f"{r['late_max_us']:6.0f} {r['ticks_late_gt_200us']:6d} {r['ticks_late_gt_1ms']:5d} | "
                    f"{r['ticks_in_flush']:11d} {r['in_flush_p99_us']:6.0f} {r['in_flush_max_us']:6.0f} | "
                    f"{r['outside_p99_us']:10.0f} {r['outside_max_us']:6.0f} | {fl}",
                    flush=True,
                )
        print("\nsummary over runs (median of the runs' figures; 'max' = max over runs):")
        summary = {}
        for case in cases:
            rs = [r for r in results["runs"] if r["case"] == case]
            keys = ("late_p50_us", "late_p99_us", "late_p999_us", "late_max_us", "in_flush_p99_us", "in_flush_max_us")
            s = {k: statistics.median(r[k] for r in rs) for k in keys}
            s["late_max_of_max_us"] = max(r["late_max_us"] for r in rs)
            s["in_flush_max_of_max_us"] = max(r["in_flush_max_us"] for r in rs)
            if "flushes" in rs[0]:
                for k in ("flush_total_p50_us", "ship_p50_us", "ship_p99_us"):
                    if k in rs[0]:
                        s[k] = statistics.median(r[k] for r in rs)
                s["flush_total_max_us"] = max(r["flush_total_max_us"] for r in rs)
            summary[case] = s
            line = (
                f"  {case:<8} all ticks: p50 {s['late_p50_us']:.1f}, p99 {s['late_p99_us']:.0f}, "
                f"p99.9 {s['late_p999_us']:.0f}, max {s['late_max_us']:.0f} (max {s['late_max_of_max_us']:.0f}) us"
            )
            if "flush_total_p50_us" in s:
                line += (
                    f"; ticks in a flush: p99 {s['in_flush_p99_us']:.0f}, max {s['in_flush_max_us']:.0f} "
                    f"(max {s['in_flush_max_of_max_us']:.0f}) us; flush p50 {s['flush_total_p50_us'] / 1e3:.1f} ms "
                    f"(max {s['flush_total_max_us'] / 1e3:.1f} ms)"
                )
            if "ship_p50_us" in s:
                line += f"; bench side (cut+pickle, wall) p50 {s['ship_p50_us']:.0f}, p99 {s['ship_p99_us']:.0f} us"
            print(line)
        results["summary"] = summary
        if "process" in summary and "none" in summary:
            pr, no = summary["process"], summary["none"]
            print(
                f"target (flush stall <= 200 us p99.9): process writer p99.9 {pr['late_p999_us']:.0f} us "
                f"vs {no['late_p999_us']:.0f} us with no log at all (machine noise); "
                f"ticks in a flush p99 {pr['in_flush_p99_us']:.0f} us"
            )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
