#!/usr/bin/env python3
"""The lab service (`hil serve --loopback`) against running the same sessions without it, side by side in one run.

    .venv/bin/python benchmarks/bench_service.py [--session-s 10] [--rounds 3] [--pages 3] [--pages-cpu 0] [--items 10]
        [--item-s 1] [--item-rounds 2] [--poll-s 20] [--pollers 50] [--poll-hz 10] [--poll-rounds 2]
        [--queued 100] [--restarts 2] [--json PATH] [--keep DIR]

One `hil serve --loopback` (its own process group, a free port, a fresh state directory; the emulated lab on the
realtime clock, started once by the service's worker) serves every part; the sessions are profiles/sessions/demo.yaml
with another duration. Parts, each measured against its peer in alternating rounds (medians over the rounds):

1. ``--rounds`` sessions of ``--session-s`` through the service with ``--pages`` live pages open (each its own
   headless Chromium on http://127.0.0.1:PORT/, pinned to ``--pages-cpu``: off the loop's CPU, the last, as the
   operators' machines are in the lab; ``none`` lets them run anywhere), alternating with the same session by
   ``hil run SESSION --loopback --clock realtime --json`` (a subprocess with its own emulator) and with the same
   session through the service with no page open (the browsers on about:blank): the board-measured latency p50/p99
   (``board_latency_us``), missed and late cycles, from the service's history record and from ``hil run``'s JSON;
   and the cores used meanwhile by the service's processes, the browsers and ``hil run`` (the pages run on the
   bench's own 2 cores here; in the lab they run on the operators' machines). The browsers stay open (idle) while
   ``hil run`` runs, and the service idles beside it (its emulated lab streams nothing but still runs).
2. In those pages: the page's own lag, ``window.hilPage.lagMs`` (``Date.now() - wall_ms`` when a point is plotted;
   ``wall_ms`` is the manager's ``time.time()`` when it got the point from the worker), p95 over the three pages.
   Also end to end: an observer added to each page's WebSocket (before the page loads) notes each live point's
   ``loop.t_s``; the log's row with that ``t_s`` has ``t_host_ns`` (when the bench decoded the sample), made wall
   time with the log's ``log_created_*`` attributes; plot time (``wall_ms + lag``) minus that is the sample's age
   on the screen, and ``wall_ms`` minus it the age when the manager got it (the worker's 50 Hz sampling, the pipe).
3. The service's own cost per queued item: ``--item-rounds`` rounds of ``--items / --item-rounds`` sessions of
   ``--item-s``, queued at once through the service, alternating with the same sessions run one after another by
   ``hil.run`` in this process on a lab served as the worker serves it (one emulator started beforehand, its ports
   claimed, the lab passed to each run as ``lab=``; each timed run is ``hil.run`` plus ``result.summary()``, what
   the worker does).
   Overhead per item = (the last item's ``ended_at`` - the first's ``started_at``) / items - the mean local time
   of one item. Also shown: the manager's gap from one item's end to the next one's start.
4. ``--pollers`` threads each polling ``GET /api/status`` at ``--poll-hz`` (keep-alive http.client) during a
   ``--poll-s`` session through the service, alternating with the same session with one client polling at 2 Hz
   (to measure the status latency unloaded): the session's missed and late cycles and board latency, the status
   latency p50/p99 as the clients saw it (their threads share this process and the machine's cores).
5. ``--queued`` sessions submitted with the queue stopped, then the service SIGKILLed (its whole process group)
   and started again on the same state directory, ``--restarts`` times: the queue's items and the history's records
   before and after (by uid, in order), and the time from starting it again to the API answering and to its worker
   being ready (the worker starts the emulated lab and runs the doctor's 2 s listen first).

Targets (docs/performance.md, "The lab service"): service within 10 % of local on board latency p50 and p99, 0
missed cycles; page lag p95 < 200 ms; overhead < 1 s per item; 0 missed cycles with the pollers; 0 items or records
lost. Exit status non-zero only when something fails to run or an item or record is lost, never on a figure.
Needs Debian's chromium and chromium-driver (/usr/bin/chromium, /usr/bin/chromedriver) and selenium.
"""

from __future__ import annotations

import argparse
import contextlib
import http.client
import json
import os
import platform
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import psutil
import yaml

from hil.config import PROFILES, load_session, session_yaml
from hil.service import Bench, BenchError

CHROMIUM = "/usr/bin/chromium"
PARTS = ("pages", "overhead", "pollers", "watching", "restart")
CHROMEDRIVER = "/usr/bin/chromedriver"
READY_S = 240.0

# an observer on the page's WebSocket: every live point's wall_ms and loop.t_s (null before the session's log
# exists), in order (the page itself is untouched)
OBSERVER = """
(() => {
  const Native = window.WebSocket;
  window.__benchPoints = [];
  function Observed(...args) {
    const ws = new Native(...args);
    ws.addEventListener("message", (e) => {
      try {
        const m = JSON.parse(e.data);
        if (m.type === "live") {
          for (const p of m.points) {
            if (p && typeof p.wall_ms === "number") {
              window.__benchPoints.push([p.wall_ms, p.loop ? p.loop.t_s : null, p.uid]);
            }
          }
        }
      } catch (err) { /* not ours to judge */ }
    });
    return ws;
  }
  Observed.prototype = Native.prototype;
  for (const k of ["CONNECTING", "OPEN", "CLOSING", "CLOSED"]) Observed[k] = Native[k];
  window.WebSocket = Observed;
})();
"""
RESET = """
const p = window.hilPage; p.lagMs.length = 0; p.errors.length = 0; window.__benchPoints.length = 0;
return p.points;
"""
COLLECT = """
const p = window.hilPage;
return {lag: p.lagMs.slice(), observed: window.__benchPoints.slice(), points: p.points, frames: p.frames,
        errors: p.errors.slice(), connected: p.connected};
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def med(values: list[float]) -> float:
    values = [v for v in values if v is not None and not np.isnan(v)]
    return statistics.median(values) if values else float("nan")


def iso_s(stamp: str) -> float:
    return datetime.fromisoformat(stamp).timestamp()


def session_file(directory: Path, duration_s: float, name: str) -> Path:
    """The demo session, ``duration_s`` long, as a file that stands on its own (its parts inline)."""
    data = yaml.safe_load(session_yaml(load_session(PROFILES / "sessions" / "demo.yaml")))
    data.update(name=name, duration_s=duration_s)
    path = directory / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def tree_cpu_s(pid: int | None, children: bool = True) -> float:
    """CPU seconds so far of a process (with ``children``: and of its descendants, live or reaped)."""
    if pid is None:
        return 0.0
    try:
        root = psutil.Process(pid)
        procs = [root, *root.children(recursive=True)] if children else [root]
    except psutil.NoSuchProcess:
        return 0.0
    total = 0.0
    for proc in procs:
        with contextlib.suppress(psutil.NoSuchProcess, psutil.AccessDenied):
            t = proc.cpu_times()
            total += t.user + t.system + ((t.children_user + t.children_system) if children else 0.0)
    return total


class CpuMeter:
    """Cores used over an interval by named process trees, and by this process's reaped children (`hil run`)."""

    def __init__(self, **pids: list[int | None]) -> None:
        self.pids = pids

    def _sample(self) -> dict[str, float]:
        out = {"wall": time.monotonic(), "hil_run": sum(resource_children())}
        for name, pids in self.pids.items():
            out[name] = sum(tree_cpu_s(pid, children=name not in ("manager", "bench")) for pid in pids)
        return out

    def __enter__(self) -> CpuMeter:
        self.start = self._sample()
        return self

    def __exit__(self, *exc: object) -> None:
        end = self._sample()
        wall = end["wall"] - self.start["wall"]
        self.cores = {f"{k}_cores": (end[k] - self.start[k]) / wall for k in end if k != "wall"}


def resource_children() -> tuple[float, float]:
    """CPU seconds of this process's reaped children (a finished `hil run` with its emulator and log writer)."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime, usage.ru_stime


def figures(summary: dict[str, Any]) -> dict[str, Any]:
    """What is compared of a session's summary (and the machine's load average when it ended)."""
    board = summary.get("board_latency_us") or {}
    host = summary.get("latency_us") or {}
    return {"board_p50_us": board.get("p50"), "board_p99_us": board.get("p99"), "missed": summary.get("missed_cycles"),
            "late": summary.get("late_cycles"), "host_p50_us": host.get("p50"), "host_p99_us": host.get("p99"),
            "cycles": summary.get("cycles"), "host_stalls": summary.get("host_stalls"), "load1": os.getloadavg()[0]}


# --- the service ---------------------------------------------------------------------------------------------------


@dataclass
class Service:
    state_dir: Path
    port: int = field(default_factory=free_port)
    proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> dict[str, float]:
        """Start it; seconds to the API answering and to the worker being ready."""
        log = (self.state_dir.parent / "serve.log").open("ab")
        t0 = time.monotonic()
        self.proc = subprocess.Popen([sys.executable, "-m", "hil", "serve", "--loopback", "--port", str(self.port),
                                      "--state-dir", str(self.state_dir)], stdout=log, stderr=subprocess.STDOUT,
                                     start_new_session=True)
        api_s = None
        deadline = t0 + READY_S
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"hil serve exited {self.proc.returncode}; see {log.name}")
            try:
                status = self.bench().status()
            except BenchError:
                time.sleep(0.05)
                continue
            if api_s is None:
                api_s = time.monotonic() - t0
            if status["worker"]["state"] == "ready":
                ready_s = time.monotonic() - t0
                self.bench().start()  # every start of a service leaves its queue stopped
                return {"api_s": api_s, "ready_s": ready_s}
            time.sleep(0.05)
        raise RuntimeError(f"hil serve not ready in {READY_S} s; see {log.name}")

    def bench(self) -> Bench:
        return Bench(self.url, token="", user="bench")

    def check(self) -> None:
        """RuntimeError if the service is gone (its exit code: -9 SIGKILL, 0 after SIGINT or SIGTERM)."""
        if self.proc is not None and self.proc.poll() is not None:
            raise RuntimeError(f"hil serve (pid {self.proc.pid}) ended by itself or was ended by someone else, exit "
                               f"code {self.proc.returncode}; see {self.state_dir.parent / 'serve.log'}")

    def kill(self) -> None:
        """SIGKILL the whole process group (manager, worker, emulator) and wait until none is left."""
        assert self.proc is not None
        pgid = self.proc.pid
        os.killpg(pgid, signal.SIGKILL)
        self.proc.wait(30)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                os.killpg(pgid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.05)
        raise RuntimeError(f"process group {pgid} still alive 30 s after SIGKILL")

    def stop(self) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)


def run_on_service(svc: Service, path: Path) -> dict[str, Any]:
    """Submit one session and wait for its history record (polled once a second)."""
    return wait_all(svc, [svc.bench().add(path)["uid"]], poll_s=1.0)[0]


def wait_all(svc: Service, uids: list[str], poll_s: float) -> list[dict[str, Any]]:
    bench = svc.bench()
    try:
        return [bench.wait(uid, poll_s=poll_s) for uid in uids]
    except BenchError:
        svc.check()
        raise


def run_local(path: Path, out: Path) -> tuple[dict[str, Any], float]:
    """`hil run SESSION --loopback --clock realtime --json`: its summary and the process's wall time."""
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "hil", "run", str(path), "--loopback", "--clock", "realtime", "--json",
                           "--out", str(out)], capture_output=True, text=True, check=False)
    wall = time.monotonic() - t0
    if proc.returncode != 0 or not proc.stdout.strip():
        raise RuntimeError(f"hil run exited {proc.returncode}: {proc.stderr.strip()[-500:]}")
    return json.loads(proc.stdout), wall


# --- the pages -----------------------------------------------------------------------------------------------------


@contextlib.contextmanager
def browsers(url: str, n: int, directory: Path, cpu: int | None = None) -> Iterator[list[Any]]:
    """``n`` headless Chromium pages on the service; ``cpu``: the browsers (and every process they start) pinned
    to that CPU, off the one the shipped sessions give the loop and the emulator (the last): in the lab the pages
    run on the operators' machines, not on the bench's cores."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service as DriverService

    drivers: list[Any] = []
    saved = os.sched_getaffinity(0)
    try:
        if cpu is not None:  # the drivers and browsers started now inherit it
            os.sched_setaffinity(0, {cpu})
        for k in range(n):
            options = webdriver.ChromeOptions()
            options.binary_location = CHROMIUM
            for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                         "--disable-background-networking", "--disable-component-update", "--disable-sync",
                         "--no-first-run", "--window-size=1400,1000", f"--user-data-dir={directory / f'chromium{k}'}"):
                options.add_argument(flag)
            driver = webdriver.Chrome(service=DriverService(executable_path=CHROMEDRIVER), options=options)
            drivers.append(driver)
            driver.set_page_load_timeout(120)
            driver.set_script_timeout(60)
            driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": OBSERVER})
            driver.get(url + "/")
        os.sched_setaffinity(0, saved)
        wait_connected(drivers)
        yield drivers
    finally:
        os.sched_setaffinity(0, saved)
        for driver in drivers:
            with contextlib.suppress(Exception):
                driver.quit()


def wait_connected(drivers: list[Any]) -> None:
    deadline = time.monotonic() + 120
    for driver in drivers:
        while not driver.execute_script("return !!(window.hilPage && window.hilPage.connected)"):
            if time.monotonic() > deadline:
                raise RuntimeError("a live page did not connect within 120 s")
            time.sleep(0.2)


def log_wall_ms(log_path: str) -> tuple[np.ndarray, np.ndarray]:
    """The log's /loop t_s and, for each row, the wall time (ms) the bench decoded that sample."""
    with h5py.File(log_path, "r") as f:
        t_s = f["loop/t_s"][:]
        host_ns = f["loop/t_host_ns"][:]
        mono0 = int(f.attrs["log_created_monotonic_ns"])
        unix0 = int(f.attrs["log_created_unix_ns"])
    keep = host_ns > 0
    return t_s[keep], (host_ns[keep] - mono0 + unix0) / 1e6


def page_figures(collected: list[dict[str, Any]], uid: str, log_path: str | None) -> dict[str, Any]:
    """Page lag (the page's own lagMs), and end to end from the log, pooled over the pages."""
    lag: list[float] = []
    e2e: list[float] = []
    manager_age: list[float] = []
    unmatched = 0
    errors: list[str] = []
    t_s, row_ms = log_wall_ms(log_path) if log_path else (np.array([]), np.array([]))
    for page in collected:
        lag += page["lag"]
        errors += page["errors"]
        observed = page["observed"]
        # lagMs and the observed points are in the same order (both since the reset, with no item running then);
        # a point the page skipped (not after the last one in time) would break that: pair only when they agree
        if len(observed) != len(page["lag"]) or not len(t_s):
            unmatched += len(observed)
            continue
        for (wall_ms, ts, point_uid), lag_ms in zip(observed, page["lag"], strict=True):
            # only while the stream runs: before the log exists there is no sample to date a point by, and in the
            # wind-down (the stream stopped, the hexapod on its way home) the points repeat the last sample
            if ts is None or point_uid != uid or not row_ms[0] <= wall_ms <= row_ms[-1]:
                continue
            i = int(np.searchsorted(t_s, ts))
            if i >= len(t_s) or abs(t_s[i] - ts) > 1e-9:
                unmatched += 1
                continue
            e2e.append(wall_ms + lag_ms - row_ms[i])
            manager_age.append(wall_ms - row_ms[i])
    return {"lag_p50_ms": pct(lag, 50), "lag_p95_ms": pct(lag, 95), "lag_max_ms": max(lag, default=float("nan")),
            "e2e_p50_ms": pct(e2e, 50), "e2e_p95_ms": pct(e2e, 95), "age_at_manager_p50_ms": pct(manager_age, 50),
            "age_at_manager_p95_ms": pct(manager_age, 95), "points": len(lag), "matched": len(e2e),
            "unmatched": unmatched, "page_errors": errors,
            "points_per_page": [len(page["lag"]) for page in collected]}


# --- part 1 and 2 --------------------------------------------------------------------------------------------------


def part_pages(svc: Service, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    path = session_file(work, args.session_s, "svc-pages")
    warm = session_file(work, 2.0, "warmup")
    rounds: list[dict[str, Any]] = []
    with browsers(svc.url, args.pages, work, None if args.pages_cpu == "none" else int(args.pages_cpu)) as drivers:
        assert svc.proc is not None
        meter_pids = {"service": [svc.proc.pid], "pages": [d.service.process.pid for d in drivers]}
        run_on_service(svc, warm)  # the worker's first item and hil run's first start pay for cold caches
        run_local(warm, work / "local")
        for r in range(args.rounds):
            for driver in drivers:
                driver.execute_script(RESET)
            with CpuMeter(**meter_pids) as cpu:
                record = run_on_service(svc, path)
            time.sleep(0.5)  # the last points reach the pages
            collected = [driver.execute_script(COLLECT) for driver in drivers]
            svc_row = {"side": "service", "round": r, "status": record["status"], **figures(record["summary"]),
                       "wall_s": iso_s(record["ended_at"]) - iso_s(record["started_at"]), **cpu.cores,
                       **page_figures(collected, record["uid"], record.get("log_path"))}
            rounds.append(svc_row)
            print(f"  round {r} service: {fmt_row(svc_row)}; lag p95 {svc_row['lag_p95_ms']:.0f} ms, end to end p95 "
                  f"{svc_row['e2e_p95_ms']:.0f} ms", flush=True)
            with CpuMeter(**meter_pids) as cpu:
                summary, wall = run_local(path, work / "local")
            local_row = {"side": "local", "round": r, "status": summary["status"], **figures(summary), "wall_s": wall,
                         **cpu.cores}
            rounds.append(local_row)
            print(f"  round {r} local:   {fmt_row(local_row)}", flush=True)
            for driver in drivers:  # the browsers stay, idle on a blank page, as while hil run ran
                driver.get("about:blank")
            with CpuMeter(**meter_pids) as cpu:
                record = run_on_service(svc, path)
            bare_row = {"side": "service, no page", "round": r, "status": record["status"],
                        **figures(record["summary"]), "wall_s": iso_s(record["ended_at"]) - iso_s(record["started_at"]),
                        **cpu.cores}
            rounds.append(bare_row)
            print(f"  round {r} no page: {fmt_row(bare_row)}", flush=True)
            for driver in drivers:
                driver.get(svc.url + "/")
            wait_connected(drivers)
    return {"rounds": rounds}


def fmt_row(row: dict[str, Any]) -> str:
    cores = ", ".join(f"{k.removesuffix('_cores')} {v:.2f}" for k, v in row.items() if k.endswith("_cores"))
    return (f"{row['status']}, board latency p50 {row['board_p50_us']:.0f} us p99 {row['board_p99_us']:.0f} us, "
            f"missed {row['missed']}, late {row['late']}, wall {row['wall_s']:.1f} s, load {row['load1']:.1f}; "
            f"cores: {cores}")


# --- part 3 --------------------------------------------------------------------------------------------------------


@contextlib.contextmanager
def served_lab() -> Iterator[Any]:
    """An emulated lab held as the service's worker holds it (one emulator, its ports claimed): the lab to pass
    to each run."""
    from hil.config import PortConfig
    from hil.link import claim_ports
    from hil.protocol import LINKS
    from hil.session import BenchLab, EmulatorProcess

    emulator = EmulatorProcess(None, clock="realtime", seed=0)
    ports = {name: path for name, path in emulator.start().items() if name in LINKS}
    claims = claim_ports(ports, f"bench_service (pid {os.getpid()})")
    try:
        yield BenchLab({name: PortConfig(port=p) for name, p in ports.items()}, claims, emulated=True,
                       description="emulated lab (realtime), bench_service")
    finally:
        claims.release()
        emulator.stop()


def part_overhead(svc: Service, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    from hil import api

    bench = svc.bench()
    per_round = max(1, args.items // args.item_rounds)
    paths = [session_file(work, args.item_s, f"item{k}") for k in range(per_round)]
    rounds = []
    with served_lab() as lab:
        api.run(load_session(paths[0]), out=work / "inproc", lab=lab).summary()  # warm-up: the first run's imports
        for r in range(args.item_rounds):
            bench.stop_queue()
            uids = [bench.add(p)["uid"] for p in paths]
            bench.start()
            records = wait_all(svc, uids, poll_s=0.5)
            starts = [iso_s(rec["started_at"]) for rec in records]
            ends = [iso_s(rec["ended_at"]) for rec in records]
            span = ends[-1] - starts[0]
            item_s = [e - s for s, e in zip(starts, ends, strict=True)]
            gaps = [starts[k + 1] - ends[k] for k in range(len(records) - 1)]
            local_s = []
            for p in paths:
                t0 = time.monotonic()
                result = api.run(load_session(p), out=work / "inproc", lab=lab)
                result.summary()
                local_s.append(time.monotonic() - t0)
                if result.status != "completed":
                    raise RuntimeError(f"local item: {result.status}: {result.message}")
            row = {"round": r, "items": len(records), "statuses": sorted({rec["status"] for rec in records}),
                   "span_s": span, "service_item_s": span / len(records), "service_item_median_s": med(item_s),
                   "gap_median_s": med(gaps), "gap_max_s": max(gaps, default=0.0),
                   "local_item_s": statistics.mean(local_s), "local_item_median_s": med(local_s),
                   "missed": [rec["summary"].get("missed_cycles") for rec in records]}
            row["overhead_s"] = row["service_item_s"] - row["local_item_s"]
            rounds.append(row)
            print(f"  round {r}: {len(records)} items, service {row['service_item_s']:.2f} s an item (span "
                  f"{span:.1f} s, gap median {row['gap_median_s'] * 1000:.0f} ms), local {row['local_item_s']:.2f} s "
                  f"an item: overhead {row['overhead_s']:.2f} s", flush=True)
    return {"rounds": rounds}


# --- part 4 --------------------------------------------------------------------------------------------------------


class Pollers:
    """``n`` threads, each polling GET /api/status at ``hz`` on its own keep-alive connection."""

    def __init__(self, port: int, n: int, hz: float) -> None:
        self.port, self.n, self.period = port, n, 1.0 / hz
        self.latencies: list[list[float]] = [[] for _ in range(n)]
        self.errors = 0
        self.late = 0
        self._stop = threading.Event()
        self.threads = [threading.Thread(target=self._poll, args=(k,), daemon=True) for k in range(n)]

    def __enter__(self) -> Pollers:
        self.t0 = time.monotonic()
        for t in self.threads:
            t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        for t in self.threads:
            t.join(15)
        self.elapsed = time.monotonic() - self.t0

    def _poll(self, k: int) -> None:
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10)
        due = time.monotonic() + self.period * k / self.n  # spread over the period
        lat = self.latencies[k]
        while not self._stop.is_set():
            wait = due - time.monotonic()
            if wait > 0:
                self._stop.wait(wait)
                if self._stop.is_set():
                    break
            t = time.perf_counter()
            try:
                conn.request("GET", "/api/status", headers={"X-Hil-User": f"poller{k}"})
                resp = conn.getresponse()
                resp.read()
                if resp.status != 200:
                    raise OSError(f"HTTP {resp.status}")
                lat.append((time.perf_counter() - t) * 1000.0)
            except (OSError, http.client.HTTPException):
                self.errors += 1
                conn.close()
                conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10)
            due += self.period
            now = time.monotonic()
            if due < now:
                self.late += 1
                due = now
        conn.close()

    def figures(self) -> dict[str, Any]:
        lat = [v for lst in self.latencies for v in lst]
        return {"requests": len(lat), "per_s": len(lat) / self.elapsed, "errors": self.errors, "late": self.late,
                "status_p50_ms": pct(lat, 50), "status_p99_ms": pct(lat, 99), "status_max_ms": max(lat, default=0.0)}


def part_pollers(svc: Service, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    path = session_file(work, args.poll_s, "svc-polled")
    assert svc.proc is not None
    meter_pids = {"service": [svc.proc.pid], "manager": [svc.proc.pid], "bench": [os.getpid()]}
    rounds = []
    for r in range(args.poll_rounds):
        for side, n, hz in ((f"{args.pollers} clients at {args.poll_hz:g} Hz", args.pollers, args.poll_hz),
                            ("1 client at 2 Hz", 1, 2.0)):
            with CpuMeter(**meter_pids) as cpu, Pollers(svc.port, n, hz) as pollers:
                record = run_on_service(svc, path)
            row = {"side": side, "round": r,
                   "status": record["status"], **figures(record["summary"]),
                   "wall_s": iso_s(record["ended_at"]) - iso_s(record["started_at"]), **pollers.figures(), **cpu.cores}
            rounds.append(row)
            print(f"  round {r} {row['side']}: {fmt_row(row)}; status p50 {row['status_p50_ms']:.1f} ms p99 "
                  f"{row['status_p99_ms']:.1f} ms, {row['per_s']:.0f} req/s, {row['errors']} errors", flush=True)
    return {"rounds": rounds}


# --- part 6 --------------------------------------------------------------------------------------------------------


def part_watching(svc: Service, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    """``--pages`` live pages and ``--pollers`` status pollers on the service while a session runs, alternating with
    the same session by a plain ``hil run`` (the pages on about:blank, no poller): what watching costs the loop."""
    path = session_file(work, args.session_s, "svc-watched")
    warm = session_file(work, 2.0, "warmup-watched")
    rounds: list[dict[str, Any]] = []
    cpu_pin = None if args.watch_pages_cpu == "none" else int(args.watch_pages_cpu)
    watched = f"service, {args.pages} pages + {args.pollers} pollers"
    with browsers(svc.url, args.pages, work / "watching", cpu_pin) as drivers:
        assert svc.proc is not None
        meter_pids = {"service": [svc.proc.pid], "pages": [d.service.process.pid for d in drivers]}
        run_on_service(svc, warm)
        run_local(warm, work / "local")
        for r in range(args.watch_rounds):
            for driver in drivers:
                driver.get("about:blank")
            with CpuMeter(**meter_pids) as cpu:
                summary, wall = run_local(path, work / "local")
            local_row = {"side": "hil run", "round": r, "status": summary["status"], **figures(summary),
                         "wall_s": wall, **cpu.cores}
            rounds.append(local_row)
            print(f"  round {r} hil run: {fmt_row(local_row)}", flush=True)
            for driver in drivers:
                driver.get(svc.url + "/")
            wait_connected(drivers)
            with CpuMeter(**meter_pids) as cpu, Pollers(svc.port, args.pollers, args.poll_hz) as pollers:
                record = run_on_service(svc, path)
            frames = [driver.execute_script("return window.hilPage.frames") for driver in drivers]
            row = {"side": watched, "round": r, "status": record["status"], **figures(record["summary"]),
                   "wall_s": iso_s(record["ended_at"]) - iso_s(record["started_at"]), **cpu.cores,
                   **pollers.figures(), "page_cores": cpu.cores["pages_cores"] / max(1, len(drivers)),
                   "page_frames": min(frames)}
            rounds.append(row)
            print(f"  round {r} watched: {fmt_row(row)}; {row['page_cores']:.3f} core a page, "
                  f"{row['per_s']:.0f} status/s answered", flush=True)
    return {"rounds": rounds, "watched": watched}


# --- part 5 --------------------------------------------------------------------------------------------------------


def status_ms(port: int, n: int) -> dict[str, float]:
    """``n`` GET /api/status one after another on one keep-alive connection: latency p50 and p99 in ms."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    lat = []
    for _ in range(n):
        t = time.perf_counter()
        conn.request("GET", "/api/status")
        resp = conn.getresponse()
        resp.read()
        lat.append((time.perf_counter() - t) * 1000.0)
    conn.close()
    return {"p50_ms": pct(lat, 50), "p99_ms": pct(lat, 99)}


def snapshot(bench: Bench) -> tuple[list[str], list[str], bool]:
    queue = bench.queue()
    history = bench.history(limit=10_000)
    return [i["uid"] for i in queue["items"]], [h["uid"] for h in history], bool(queue["running"])


def part_restart(svc: Service, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    bench = svc.bench()
    path = session_file(work, 1.0, "queued")
    bench.stop_queue()
    empty = status_ms(svc.port, 300)
    t0 = time.monotonic()
    for _ in range(args.queued):
        bench.add(path)
    submit_s = time.monotonic() - t0
    queued = status_ms(svc.port, 300)
    print(f"  {args.queued} items submitted in {submit_s:.1f} s; GET /api/status p50 {empty['p50_ms']:.1f} ms with "
          f"the queue empty, {queued['p50_ms']:.1f} ms with {args.queued} waiting", flush=True)
    rows = []
    for r in range(args.restarts):
        items, history, _ = snapshot(bench)
        svc.kill()
        times = svc.start()
        items_after, history_after, running_after = snapshot(bench)
        row = {"round": r, "items_before": len(items), "items_after": len(items_after),
               "history_before": len(history), "history_after": len(history_after),
               "items_same": items == items_after, "history_same": history == history_after,
               "lost_items": len(set(items) - set(items_after)), "lost_records": len(set(history) - set(history_after)),
               "queue_still_stopped": not running_after, **times}
        rows.append(row)
        print(f"  restart {r}: items {len(items)} -> {len(items_after)}, history {len(history)} -> "
              f"{len(history_after)}, same order {row['items_same'] and row['history_same']}; API after "
              f"{times['api_s']:.1f} s, ready after {times['ready_s']:.1f} s", flush=True)
    bench.clear()
    bench.start()
    return {"submit_s": submit_s, "status_empty": empty, "status_queued": queued, "rounds": rows}


# --- the report ----------------------------------------------------------------------------------------------------


def side_medians(rows: list[dict[str, Any]], side: str, keys: list[str]) -> dict[str, float]:
    mine = [r for r in rows if r["side"] == side]
    return {k: med([r[k] for r in mine]) for k in keys}


def report(results: dict[str, Any], args: argparse.Namespace) -> None:
    """Each part's tables, for those that ran."""
    if "pages" in results:
        report_pages(results, args)
    if "overhead" in results:
        report_overhead(results, args)
    if "pollers" in results:
        report_pollers(results, args)
    if "watching" in results:
        report_watching(results, args)
    if "restart" in results:
        report_restart(results, args)


def report_pages(results: dict[str, Any], args: argparse.Namespace) -> None:
    keys = ["board_p50_us", "board_p99_us", "missed", "late", "host_p50_us", "host_p99_us", "wall_s", "service_cores",
            "pages_cores", "hil_run_cores", "load1"]
    p1 = results["pages"]["rounds"]
    svc = side_medians(p1, "service", [*keys, "lag_p50_ms", "lag_p95_ms", "e2e_p50_ms", "e2e_p95_ms",
                                       "age_at_manager_p50_ms", "age_at_manager_p95_ms"])
    loc = side_medians(p1, "local", keys)
    bare = side_medians(p1, "service, no page", keys)
    print(f"\n### 1-2. A {args.session_s:g} s session: service with {args.pages} live pages vs `hil run` "
          f"({args.rounds} rounds, medians)\n")
    print("| | board latency p50 us | board latency p99 us | missed cycles (max) | late cycles | host latency p50 us "
          "| host latency p99 us | wall s | cores: service / pages / hil run | load average |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, m, side in ((f"service, {args.pages} pages open", svc, "service"),
                          ("`hil run` (own emulator)", loc, "local"), ("service, no page", bare, "service, no page")):
        worst = max(r["missed"] for r in p1 if r["side"] == side)
        print(f"| {name} | {m['board_p50_us']:.0f} | {m['board_p99_us']:.0f} | {m['missed']:.0f} ({worst}) | "
              f"{m['late']:.0f} | {m['host_p50_us']:.0f} | {m['host_p99_us']:.0f} | {m['wall_s']:.1f} | "
              f"{m['service_cores']:.2f} / {m['pages_cores']:.2f} / {m['hil_run_cores']:.2f} | {m['load1']:.1f} |")
    for name, m in (("service with pages / local", svc), ("service, no page / local", bare)):
        print(f"| {name} | {m['board_p50_us'] / loc['board_p50_us']:.2f} | "
              f"{m['board_p99_us'] / loc['board_p99_us']:.2f} | | | | | | | |")
    print("\n| page lag (lagMs) p50 / p95 ms | end to end p50 / p95 ms | age at the manager p50 / p95 ms | "
          "points a page a round |")
    print("|---:|---:|---:|---:|")
    per_page = [n for r in p1 if r["side"] == "service" for n in r["points_per_page"]]
    print(f"| {svc['lag_p50_ms']:.0f} / {svc['lag_p95_ms']:.0f} | {svc['e2e_p50_ms']:.0f} / {svc['e2e_p95_ms']:.0f} | "
          f"{svc['age_at_manager_p50_ms']:.0f} / {svc['age_at_manager_p95_ms']:.0f} | {med(per_page):.0f} |")


def report_overhead(results: dict[str, Any], args: argparse.Namespace) -> None:
    p3 = results["overhead"]["rounds"]
    print(f"\n### 3. Overhead per queued item ({args.items} items of {args.item_s:g} s in {args.item_rounds} rounds)\n")
    print("| round | service s an item (span / items) | local s an item (mean) | overhead s | end-to-start gap median "
          "ms | missed cycles |")
    print("|---:|---:|---:|---:|---:|---:|")
    for r in p3:
        print(f"| {r['round']} | {r['service_item_s']:.2f} | {r['local_item_s']:.2f} | {r['overhead_s']:.2f} | "
              f"{r['gap_median_s'] * 1000:.0f} | {max(r['missed'])} |")
    print(f"| median | | | {med([r['overhead_s'] for r in p3]):.2f} | | |")


def report_pollers(results: dict[str, Any], args: argparse.Namespace) -> None:
    p4 = results["pollers"]["rounds"]
    print(f"\n### 4. A {args.poll_s:g} s session with {args.pollers} clients polling /api/status at "
          f"{args.poll_hz:g} Hz ({args.poll_rounds} rounds, medians)\n")
    print("| | missed cycles (max) | late cycles | board latency p50 / p99 us | status p50 ms | status p99 ms | "
          "requests/s | errors | cores: manager / service / clients | load average |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for side in dict.fromkeys(r["side"] for r in p4):
        m = side_medians(p4, side, ["missed", "late", "board_p50_us", "board_p99_us", "status_p50_ms", "status_p99_ms",
                                    "per_s", "errors", "manager_cores", "service_cores", "bench_cores", "load1"])
        worst = max(r["missed"] for r in p4 if r["side"] == side)
        print(f"| {side} | {m['missed']:.0f} ({worst}) | {m['late']:.0f} | {m['board_p50_us']:.0f} / "
              f"{m['board_p99_us']:.0f} | {m['status_p50_ms']:.1f} | {m['status_p99_ms']:.1f} | {m['per_s']:.0f} | "
              f"{m['errors']:.0f} | {m['manager_cores']:.2f} / {m['service_cores']:.2f} / {m['bench_cores']:.2f} | "
              f"{m['load1']:.1f} |")


def report_watching(results: dict[str, Any], args: argparse.Namespace) -> None:
    rows, watched = results["watching"]["rounds"], results["watching"]["watched"]
    keys = ["board_p50_us", "board_p99_us", "missed", "late", "wall_s", "service_cores", "pages_cores", "hil_run_cores",
            "load1"]
    loc = side_medians(rows, "hil run", keys)
    seen = side_medians(rows, watched, [*keys, "page_cores", "per_s", "status_p99_ms", "page_frames"])
    print(f"\n### 6. A {args.session_s:g} s session watched by {args.pages} pages and {args.pollers} pollers at "
          f"{args.poll_hz:g} Hz vs a plain `hil run` ({args.watch_rounds} rounds, medians)\n")
    print("| | board latency p50 / p99 us | late cycles | missed | cores: service / pages / hil run | load average |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, m in ((watched, seen), ("`hil run`", loc)):
        print(f"| {name} | {m['board_p50_us']:.0f} / {m['board_p99_us']:.0f} | {m['late']:.0f} | {m['missed']:.0f} | "
              f"{m['service_cores']:.2f} / {m['pages_cores']:.2f} / {m['hil_run_cores']:.2f} | {m['load1']:.1f} |")
    ratio_p99 = seen["board_p99_us"] / loc["board_p99_us"]
    ratio_late = (seen["late"] + 1) / (loc["late"] + 1)
    print(f"| watched / `hil run` | p99 **{ratio_p99:.2f}x** | **{ratio_late:.2f}x** (+1 each) | | | |")
    print(f"\nOne page: **{seen['page_cores']:.3f}** of a core ({seen['page_frames']:.0f} redraws in the session); "
          f"status answered {seen['per_s']:.0f}/s, p99 {seen['status_p99_ms']:.0f} ms. Per round:\n")
    for r in rows:
        print(f"- round {r['round']} {r['side']}: p99 {r['board_p99_us']:.0f} us, late {r['late']}, missed "
              f"{r['missed']}" + (f", {r['page_cores']:.3f} core a page" if "page_cores" in r else ""))


def report_restart(results: dict[str, Any], args: argparse.Namespace) -> None:
    p5 = results["restart"]
    print(f"\n### 5. {args.queued} queued items, SIGKILL, start again ({args.restarts} times)\n")
    print("| restart | queue before / after | history before / after | lost | same order | queue still stopped | "
          "API answers s | worker ready s |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in p5["rounds"]:
        print(f"| {r['round']} | {r['items_before']} / {r['items_after']} | {r['history_before']} / "
              f"{r['history_after']} | {r['lost_items'] + r['lost_records']} | "
              f"{'yes' if r['items_same'] and r['history_same'] else 'no'} | "
              f"{'yes' if r['queue_still_stopped'] else 'no'} | {r['api_s']:.1f} | {r['ready_s']:.1f} |")
    print(f"\n{args.queued} items submitted in {p5['submit_s']:.1f} s. GET /api/status, one client, 300 in a row: "
          f"p50 / p99 {p5['status_empty']['p50_ms']:.1f} / {p5['status_empty']['p99_ms']:.1f} ms with the queue "
          f"empty, {p5['status_queued']['p50_ms']:.1f} / {p5['status_queued']['p99_ms']:.1f} ms with "
          f"{args.queued} items waiting.")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session-s", type=float, default=10.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--pages", type=int, default=3)
    ap.add_argument("--pages-cpu", default="0" if (os.cpu_count() or 1) >= 2 else "none",
                    help="pin the browsers to this CPU (default 0: off the loop's, the last), or none")
    ap.add_argument("--items", type=int, default=10)
    ap.add_argument("--item-s", type=float, default=1.0)
    ap.add_argument("--item-rounds", type=int, default=2)
    ap.add_argument("--poll-s", type=float, default=20.0)
    ap.add_argument("--pollers", type=int, default=50)
    ap.add_argument("--poll-hz", type=float, default=10.0)
    ap.add_argument("--poll-rounds", type=int, default=2)
    ap.add_argument("--queued", type=int, default=100)
    ap.add_argument("--restarts", type=int, default=2)
    ap.add_argument("--watch-rounds", type=int, default=3)
    ap.add_argument("--watch-pages-cpu", default="none",
                    help="part 6: pin its browsers to this CPU, or none (default: anywhere, as on the bench's own PC)")
    ap.add_argument("--parts", default=",".join(PARTS), help=f"which parts, comma-separated (default all: "
                    f"{','.join(PARTS)})")
    ap.add_argument("--json", type=str, default=None)
    ap.add_argument("--keep", type=Path, default=None, help="keep the service's state and logs in this directory")
    args = ap.parse_args(argv)
    for exe in (CHROMIUM, CHROMEDRIVER):
        if not Path(exe).is_file():
            sys.exit(f"{exe}: missing; install Debian's chromium and chromium-driver")
    print(f"machine: {os.cpu_count()} CPUs, {platform.platform()}, Python {platform.python_version()}; load average "
          f"{os.getloadavg()[0]:.1f} at the start", flush=True)
    tmp = None
    if args.keep is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_service-")
        work = Path(tmp.name)
    else:
        work = args.keep
        work.mkdir(parents=True, exist_ok=True)
    svc = Service(work / "state")
    svc.state_dir.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {}
    t_all = time.monotonic()
    try:
        results["first_start"] = svc.start()
        print(f"hil serve at {svc.url}: API after {results['first_start']['api_s']:.1f} s, worker ready after "
              f"{results['first_start']['ready_s']:.1f} s", flush=True)
        parts = set(args.parts.split(","))
        if "pages" in parts:
            print("1-2. sessions with live pages, against hil run", flush=True)
            results["pages"] = part_pages(svc, args, work)
        if "overhead" in parts:
            print("3. overhead per queued item", flush=True)
            results["overhead"] = part_overhead(svc, args, work)
        if "pollers" in parts:
            print("4. status pollers", flush=True)
            results["pollers"] = part_pollers(svc, args, work)
        if "watching" in parts:
            print("6. watching: pages and pollers together, against hil run", flush=True)
            results["watching"] = part_watching(svc, args, work)
        if "restart" in parts:  # last: it kills the service
            print("5. SIGKILL and restart", flush=True)
            results["restart"] = part_restart(svc, args, work)
    finally:
        svc.stop()
        if tmp is not None:
            tmp.cleanup()
    results["elapsed_s"] = time.monotonic() - t_all
    results["load_average_end"] = os.getloadavg()
    report(results, args)
    print(f"\n{results['elapsed_s'] / 60:.1f} min; load average at the end {os.getloadavg()[0]:.1f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, **results},
                                              indent=2, default=str))
    lost = sum(r["lost_items"] + r["lost_records"] for r in results.get("restart", {}).get("rounds", []))
    return 1 if lost else 0


if __name__ == "__main__":
    sys.exit(main())
