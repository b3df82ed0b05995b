"""The service's manager: the state behind the HTTP and WebSocket API (``_routes``, ``_app``), the queue, the
history and the lease (docs/service.md).

It owns the state (hil.service.Store, SQLite in the state directory) and the worker process
(hil.service._worker), which owns the ports. Nothing here touches a board: the manager tells the worker what to
run, stop or abort, and passes the worker's live values on to the pages. A slow page or a stuck client costs only
its own buffer (each WebSocket has its own, bounded; newer values replace older ones), never the worker's time.

The queue runs when an operator starts it (``POST /api/queue/start``), one item at a time, the first waiting item
whose user may run now (the lease holder's, when a lease is held); it goes on after a failed item unless started
with ``stop_on_failure``. Every start of the service leaves the queue stopped, whatever it was before: nothing runs
that an operator did not start, also after a crash. An item is checked when submitted (422 with the loader's one
line) and again by the worker just before it runs.

The state store failing (its disk full) never wedges the manager: a request that needs to write answers 507 (503
for another SQLite error) with one line; an item's end that cannot be recorded is kept and recorded once the store
takes writes again, and nothing new starts meanwhile; the background tasks say what happened on stderr and go on.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import sys
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from starlette.websockets import WebSocket

from hil._version import __version__
from hil.service._auth import Caller, Gate
from hil.service._lease import LeaseBook
from hil.service._limits import RATE_PER_S, STATUS_TTL_S, RateLimiter
from hil.service._store import HistoryRecord, Store, StoreError, StoreUnavailable

_log = logging.getLogger("hil.service")
WS_MAX_POINTS = 250  # a page that cannot keep up loses its oldest points beyond this
STATUS_EVERY_S = 1.0  # and the status at least this often (the lease's remaining time, the queue)
WORKER_RESTART_S = 2.0


@dataclass
class ServiceOptions:
    """What `hil serve` was started with."""

    state_dir: Path
    loopback: bool = True
    lab: Path | None = None  # the lab's session file (its ports), without loopback
    emulator: Path | None = None  # the emulated lab's config, with loopback (default: the shipped one)
    emulator_cpu: int | None = -1  # the CPU the emulated lab is pinned to (-1: the last, as the shipped sessions)
    seed: int = 0
    host: str = "127.0.0.1"
    port: int = 8765
    allow_hosts: tuple[str, ...] = ()  # further names the service answers to (its Host check)
    mqtt: Path | None = None  # the service's own broker section (its password from the service's configuration)
    max_rate_per_s: float = RATE_PER_S  # each client's requests a second (bursts of twice that), then 429


class Page:
    """One WebSocket client: its own bounded buffer of live points, sent WS_SEND_HZ times a second."""

    def __init__(self, ws: WebSocket, caller: Caller) -> None:
        self.ws = ws
        self.caller = caller
        self.points: deque[dict[str, Any]] = deque(maxlen=WS_MAX_POINTS)
        self.status_due = True
        self.wake = asyncio.Event()


class Manager:
    """The service's state and its worker. :meth:`start` / :meth:`close` from the app's lifespan."""

    def __init__(self, options: ServiceOptions, gate: Gate, on_ready: Callable[[Manager], None] | None = None,
                 on_fatal: Callable[[str], None] | None = None) -> None:
        self.options = options
        self.gate = gate
        self.store, self.interrupted = Store.open(options.state_dir, log_for=self.log_of)
        self.lease = LeaseBook(self.store)
        self.store_error: str | None = None  # the state store's last failure, until a write succeeds again
        self.unrecorded: dict[str, dict[str, Any]] = {}  # items that ended while the store took no writes
        self._last_status: dict[str, Any] = {}
        self._status_at = -math.inf  # when _last_status was computed (time.monotonic)
        self.limiter = RateLimiter(options.max_rate_per_s, 2 * options.max_rate_per_s)  # each client's requests
        self.worker: asyncio.subprocess.Process | None = None
        self.worker_state = "starting"  # starting | ready | down
        self.worker_info: dict[str, Any] = {}
        self.worker_error = ""
        self.doctor_error = ""
        self.running_uid: str | None = None
        self.progress: dict[str, Any] = {}
        self.ending: str | None = None  # stop | abort asked of the running item
        self.pages: set[Page] = set()
        self.wake = asyncio.Event()
        self._tasks: list[asyncio.Task[Any]] = []
        self._closing = False
        self.started_at = time.time()
        self.on_ready = on_ready  # the first worker holds the lab: the service serves
        self.on_fatal = on_fatal  # the first worker cannot serve (a port held by another bench): the service ends
        self.ever_ready = False
        self.items_run = 0
        waiting = self.store.waiting()
        restarted = waiting > 0 or bool(self.interrupted) or bool(self.store.history(1))
        self.stop_queue("the service restarted" if restarted else "the service started")

    # --- the queue's settings ----------------------------------------------------------------------

    @property
    def queue_running(self) -> bool:
        return bool(self.store.setting("queue_running", False))

    @property
    def queue_stopped(self) -> str | None:
        """Why the queue is stopped (with how many items wait), or None while it runs."""
        if self.queue_running:
            return None
        why = str(self.store.setting("queue_stopped", "") or "stopped")
        waiting = self.store.waiting()
        return f"{why}; {waiting} item{'s' if waiting != 1 else ''} wait{'s' if waiting == 1 else ''}"

    def stop_queue(self, why: str) -> None:
        """Start no further item until an operator starts the queue; ``why`` is shown until then."""
        self.store.set_setting("queue_stopped", why)
        self.store.set_setting("queue_running", False)

    def log_of(self, uid: str) -> str | None:
        """The log an item left in its directory (the newest, for an item of several sessions), or None."""
        logs = sorted((self.options.state_dir / "runs" / uid).glob("*.h5"), key=lambda p: p.stat().st_mtime)
        return str(logs[-1]) if logs else None

    def store_failed(self, what: str, exc: StoreUnavailable) -> None:
        """Say on stderr (once per different failure) that the store refused ``what``; the service goes on."""
        if str(exc) != self.store_error:
            _log.error("%s: %s", what, exc)
            self.store_error = str(exc)
            self.changed()

    def store_ok(self) -> None:
        if self.store_error is not None:
            _log.warning("the state store takes writes again")
            self.store_error = None
            self.changed()

    @property
    def stop_on_failure(self) -> bool:
        return bool(self.store.setting("stop_on_failure", False))

    # --- lifecycle ----------------------------------------------------------------------------------

    async def start(self) -> None:
        for record in self.interrupted:
            _log.warning("item %s (%s) was running when the service stopped: recorded interrupted", record.uid,
                         record.name)
        self._tasks = [asyncio.create_task(self._worker_task(), name="hil-serve-worker"),
                       asyncio.create_task(self._queue_task(), name="hil-serve-queue"),
                       asyncio.create_task(self._status_task(), name="hil-serve-status")]

    async def close(self) -> None:
        self._closing = True
        worker = self.worker
        if worker is not None and worker.returncode is None:
            with contextlib.suppress(OSError, ConnectionError):
                self.send_worker({"op": "quit"})
            try:
                await asyncio.wait_for(worker.wait(), 30.0)
            except TimeoutError:
                worker.kill()
        for task in self._tasks:
            task.cancel()
        await asyncio.wait(self._tasks, timeout=5.0)
        self.store.close()

    # --- the worker ---------------------------------------------------------------------------------

    def _worker_argv(self) -> list[str]:
        o = self.options
        argv = [sys.executable, "-m", "hil.service._worker", "--state-dir", str(o.state_dir), "--seed", str(o.seed)]
        if o.loopback:
            argv.append("--loopback")
            if o.emulator is not None:
                argv += ["--emulator", str(o.emulator)]
            if o.emulator_cpu is not None:
                argv += ["--emulator-cpu", str(o.emulator_cpu)]
        elif o.lab is not None:
            argv += ["--lab", str(o.lab)]
        if o.mqtt is not None:
            argv += ["--mqtt", str(o.mqtt)]
        return argv

    async def _worker_task(self) -> None:
        """Run the worker; when it dies, the running item ends as a fault and a new worker starts."""
        while not self._closing:
            self.worker_state = "starting"
            with (self.options.state_dir / "worker.log").open("ab") as err:
                self.worker = await asyncio.create_subprocess_exec(
                    *self._worker_argv(), stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
                    stderr=err, limit=16 << 20)
            assert self.worker.stdout is not None
            while True:
                line = await self.worker.stdout.readline()
                if not line:
                    break
                try:
                    msg = json.loads(line)
                except ValueError:
                    continue
                try:
                    self._on_worker(msg)
                except Exception:  # a bug here must not stop the manager hearing its worker
                    _log.exception("the worker's %r line could not be handled", msg.get("ev"))
            code = await self.worker.wait()
            self.worker_state = "down"
            if self.running_uid is not None:
                self._finish(self.running_uid, {"status": "fault", "exit_code": 1,
                                                "message": f"the worker process ended (exit code {code}) while it ran",
                                                "log": self.log_of(self.running_uid), "summary": {}})
            self.changed()
            if self._closing:
                return
            if self.worker_error:
                _log.error("the worker cannot serve: %s", self.worker_error)
            await asyncio.sleep(WORKER_RESTART_S)

    def send_worker(self, msg: dict[str, Any]) -> None:
        """One line to the worker (run, stop, abort, status, doctor, quit); StoreError when it is not running."""
        worker = self.worker
        if worker is None or worker.stdin is None or worker.returncode is not None:
            raise StoreError("the worker is not running")
        worker.stdin.write((json.dumps(msg) + "\n").encode())

    def _on_worker(self, msg: dict[str, Any]) -> None:
        ev = msg.pop("ev", "")
        if ev == "ready":
            self.worker_state, self.worker_info, self.worker_error = "ready", msg, ""
            if not self.ever_ready and self.on_ready is not None:
                self.on_ready(self)
            self.ever_ready = True
            _log.info("the worker holds the lab's ports: %s", msg.get("ports"))
            self.changed()
        elif ev == "fatal":
            self.worker_error = str(msg.get("message", ""))
            if not self.ever_ready and self.on_fatal is not None:
                self._closing = True
                self.on_fatal(self.worker_error)
            self.changed()
        elif ev == "status":
            if msg != {k: self.worker_info.get(k) for k in msg}:
                self.worker_info.update(msg)
                self.changed()
        elif ev == "doctor":
            self.doctor_error = str(msg.get("error", ""))
            if not self.doctor_error:
                self.worker_info["doctor"] = msg
            self.changed()
        elif ev == "live":
            self.progress = {"uid": msg.get("uid"), "cycles": msg.get("cycles", 0), "total": msg.get("total", 0)}
            msg["wall_ms"] = time.time() * 1000.0
            for page in self.pages:
                page.points.append(msg)
                page.wake.set()
        elif ev == "started":
            self.changed()
        elif ev == "done":
            uid = str(msg.get("uid"))
            # the boards' state is unknown until the worker has measured it after the item (a stop ramp may run)
            self.worker_info.update(rest=None, safe=None)
            if uid == self.running_uid:
                self._finish(uid, msg)

    def _finish(self, uid: str, done: dict[str, Any]) -> None:
        """The running item ended: its history record (kept here and recorded later if the store takes no writes
        now), and the queue stopped after a failure when it was started with ``stop_on_failure``."""
        self.running_uid, self.ending, self.progress = None, None, {}
        self.items_run += 1
        self.unrecorded[uid] = done
        self._record_ended()
        self.changed()

    def _record_ended(self) -> None:
        """Record the items that ended and are not in the history yet (in the order they ended)."""
        for uid, done in list(self.unrecorded.items()):
            status = str(done.get("status", "fault"))
            code = done.get("exit_code")
            summary = {"exit_code": 1 if code is None and status != "completed" else code,
                       "report": done.get("report"), "metrics": done.get("summary") or {}}
            try:
                record = self.store.finish(uid, status, str(done.get("message", "")),
                                           log_path=done.get("log") or self.log_of(uid), summary=summary)
                if status != "completed" and self.stop_on_failure:
                    self.stop_queue(f"item {record.name} ended {status} (the queue stops on a failure)")
            except StoreUnavailable as exc:
                self.store_failed(f"item {uid} ended {status}; its record waits for the state store", exc)
                return
            except StoreError as exc:
                _log.error("item %s: %s", uid, exc)
            del self.unrecorded[uid]
            self.store_ok()

    # --- the queue ----------------------------------------------------------------------------------

    async def _queue_task(self) -> None:
        while not self._closing:
            self.wake.clear()
            try:
                if self.unrecorded:
                    self._record_ended()
                if not self.unrecorded:  # nothing starts before the items that ended are in the history
                    self._start_next()
            except StoreUnavailable as exc:
                self.store_failed("the queue cannot start its next item", exc)
            except Exception:  # a bug must not stop the queue for good
                _log.exception("the queue's task")
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(1.0):  # also a lease that lapses by itself
                    await self.wake.wait()

    def _start_next(self) -> None:
        if self.running_uid is not None or self.worker_state != "ready" or not self.queue_running:
            return
        lease = self.lease.current()
        item = self.store.start_next(None if lease is None else {lease.holder})
        self.store_ok()
        if item is None:
            return
        self.running_uid = item.uid
        self.progress = {"uid": item.uid, "cycles": 0, "total": 0}
        try:
            self.send_worker({"op": "run", "item": {"uid": item.uid, "kind": item.kind, "file_name": item.file_name,
                                                     "body": item.body, "user": item.user,
                                                     "options": item.options, "files": item.files}})
        except (StoreError, OSError, ConnectionError) as exc:
            self._finish(item.uid, {"status": "fault", "message": f"not started: {exc}"})
        self.changed()

    def changed(self) -> None:
        """Something pages show changed: wake the queue and send every page the status."""
        self._status_at = -math.inf
        self.wake.set()
        for page in self.pages:
            page.status_due = True
            page.wake.set()

    async def _status_task(self) -> None:
        while not self._closing:
            await asyncio.sleep(STATUS_EVERY_S)
            try:
                self.lease.current()  # a lease that lapsed is recorded now, not at the next request
            except StoreUnavailable as exc:
                self.store_failed("the lease's lapse cannot be recorded", exc)
            if self.worker_state == "ready":  # the boards' state, for the next status
                with contextlib.suppress(StoreError, OSError, ConnectionError):
                    self.send_worker({"op": "status"})
            for page in self.pages:
                page.status_due = True
                page.wake.set()

    # --- what the API shows -------------------------------------------------------------------------

    def status(self, caller: Caller | None = None) -> dict[str, Any]:
        """What the page and ``GET /api/status`` show, computed at most every STATUS_TTL_S however many ask (and
        anew after every change). While the state store cannot be read or written, the last status it could give,
        with the store's error."""
        now = time.monotonic()
        if now - self._status_at >= STATUS_TTL_S:
            try:
                self._last_status = self._status(caller)
                self._status_at = now
            except StoreUnavailable as exc:
                self.store_failed("the status", exc)
        return {**self._last_status, "you": None if caller is None else {"user": caller.user, "role": caller.role},
                "store": {"ok": self.store_error is None, "error": self.store_error,
                          "unrecorded": sorted(self.unrecorded)}}

    def _status(self, caller: Caller | None) -> dict[str, Any]:
        now = time.time()
        lease = self.lease.current()
        running = self.store.running()
        info = self.worker_info
        boards = info.get("boards", {})
        return {
            "service": {"version": __version__, "loopback": self.options.loopback, "pid": os.getpid(),
                        "started_at": self.started_at, "lab": "emulated lab (realtime clock)" if self.options.loopback
                        else str(self.options.lab), "auth": "open (localhost)" if self.gate.open else "tokens"},
            "you": None if caller is None else {"user": caller.user, "role": caller.role},
            "worker": {"state": self.worker_state, "error": self.worker_error or None, "ports": info.get("ports", {}),
                       "holder": info.get("holder"), "boards": boards, "doctor": info.get("doctor"),
                       "rest": info.get("rest"), "safe": None if running is not None else info.get("safe")},
            "queue": {"running": self.queue_running, "stop_on_failure": self.stop_on_failure,
                      "waiting": self.store.waiting(), "stopped": self.queue_stopped},
            "store": {"ok": self.store_error is None, "error": self.store_error,
                      "unrecorded": sorted(self.unrecorded)},
            "running": None if running is None else {**running.public(), **self.progress, "uid": running.uid,
                                                     "ending": self.ending},
            "lease": None if lease is None else lease.public(now),
        }

    def item_view(self, uid: str) -> dict[str, Any]:
        """One item as ``GET /api/items/UID`` shows it: running (its progress), done (its record), or queued: its
        ``place`` among the ``waiting`` items (1-based), how many items run before it as things stand (``ahead``:
        the running one, the waiting ones before it that may run, and those of a lease's holder), the lease's
        ``lease_holder`` and ``lease_remaining_s`` when a lease holds it back, and why the queue is stopped."""
        try:
            item = self.store.item(uid)
        except StoreError:
            record = self.store.record(uid)  # StoreError: in neither
            return {"state": "done", **record_view(record)}
        if item.started_at is not None:
            return {"state": "running", **item.public(), **self.progress}
        lease = self.lease.current()
        queue = [(i.uid, i.user, i.started_at is not None) for i in self.store.items()]
        if (item.uid, item.user, False) not in queue:  # it started, or left the queue, meanwhile
            return self.item_view(uid)
        place = queue_place(item.uid, queue, None if lease is None else lease.holder)
        if place["lease_holder"] is not None and lease is not None:
            place["lease_remaining_s"] = round(max(0.0, lease.expires_s - time.time()), 1)
        return {"state": "queued", **item.public(), **place, "queue_stopped": self.queue_stopped}


def queue_place(uid: str, queue: list[tuple[str, str, bool]], holder: str | None) -> dict[str, Any]:
    """Where the waiting item ``uid`` stands in ``queue`` ((uid, user, running) in order) while ``holder`` (or
    nobody) holds the lease: its ``place`` of ``waiting`` (1-based), how many items run before it (``ahead``), and
    ``lease_holder`` when the lease holds it back (see Manager.item_view)."""
    waiting = [(u, user) for u, user, running in queue if not running]
    place = next(n for n, (u, _user) in enumerate(waiting) if u == uid)
    held = holder is not None and waiting[place][1] != holder
    ahead = len(queue) - len(waiting)  # the running item
    ahead += sum(1 for _u, user in waiting[:place] if holder is None or held or user == holder)
    if held:
        ahead += sum(1 for _u, user in waiting[place + 1:] if user == holder)
    return {"place": place + 1, "waiting": len(waiting), "ahead": ahead, "lease_holder": holder if held else None,
            "lease_remaining_s": None}


def record_view(record: HistoryRecord) -> dict[str, Any]:
    """A history record as the API shows it, with the links to its files."""
    out = record.public()
    summary = out.pop("summary") or {}
    out["exit_code"] = summary.get("exit_code")
    out["summary"] = summary.get("metrics", {})
    base = f"/api/history/{record.uid}"
    out["links"] = {"record": base, "files": f"{base}/files",
                    **({"log": f"{base}/log", "series": f"{base}/series"} if record.log_path else {}),
                    **({"report": f"{base}/report"} if summary.get("report") else {})}
    out["report_path"] = summary.get("report")
    return out
