"""The service's manager: the HTTP and WebSocket API, the queue, the history and the lease (docs/service.md).

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
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import quote

from pydantic import BaseModel, ValidationError
from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.middleware import Middleware
from starlette.requests import ClientDisconnect, HTTPConnection, Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from hil._version import __version__
from hil.analysis import summarize_log
from hil.log import LogError, read_log
from hil.reporting import metric_rows, session_series
from hil.service._api_models import (
    FILE_KINDS,
    ITEM_FILE,
    OTHER_FILE,
    BreakLease,
    EndItem,
    MoveItem,
    StartQueue,
    SubmitItem,
    TakeLease,
    openapi_document,
)
from hil.service._auth import AuthError, Caller, Gate
from hil.service._items import ItemError, check_item
from hil.service._lease import LeaseBook, LeaseError
from hil.service._limits import RATE_PER_S, STATUS_TTL_S, RateLimiter
from hil.service._origin import SameOrigin, served_names
from hil.service._store import HistoryRecord, NotInStore, Store, StoreError, StoreUnavailable

_log = logging.getLogger("hil.service")
STATIC = Path(__file__).parent / "static"
WS_SEND_HZ = 2.0  # pages get the live values this often (each message carries every point since the last): a page
# draws them once a second, what a person follows on a 10 s window at a few percent of a core (docs/service.md)
WS_MAX_POINTS = 250  # a page that cannot keep up loses its oldest points beyond this
STATUS_EVERY_S = 1.0  # and the status at least this often (the lease's remaining time, the queue)
WORKER_RESTART_S = 2.0
MAX_BODY_BYTES = 2 << 20  # a request body beyond this is refused (413) before it is read whole
SERIES_POINTS = (2, 20_000, 2000)  # GET /api/history/UID/series: max_points at least, at most, by default
# an item's files are served as what they are, never as a page of the service's: no script runs, no type is guessed
FILE_HEADERS = {"X-Content-Type-Options": "nosniff",
                "Content-Security-Policy": "sandbox; default-src 'none'; img-src data:; style-src 'unsafe-inline'"}


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


# --- the HTTP API ---------------------------------------------------------------------------------


def token_of(conn: HTTPConnection) -> str | None:
    """The request's token: ``Authorization: Bearer`` or the ``hil_token`` cookie. Never the URL (a URL is kept in
    browser histories, proxies' logs and screenshots): a token there is refused, 400."""
    if "token" in conn.query_params:
        raise AuthError(400, "a token goes in the Authorization header or the hil_token cookie, never in the URL; "
                             "open the page without it and give it there")
    auth = conn.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return conn.cookies.get("hil_token")


def error(status: int, message: str, headers: dict[str, str] | None = None) -> JSONResponse:
    """Every error the service answers: ``{"detail": "one line"}``."""
    return JSONResponse({"detail": " ".join(message.split())}, status_code=status, headers=headers)


class RequestError(Exception):
    """A request the service refuses before any route logic (a body too large, not JSON): its status, one line."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


Handler = Callable[[Request, Manager, Caller], Awaitable[Response]]


def endpoint(handler: Handler, *, operator: str | None = None) -> Callable[[Request], Awaitable[Response]]:
    """A route: the caller authenticated (and an operator, for ``operator``: what it does), errors as one line."""

    async def route(request: Request) -> Response:
        manager: Manager = request.app.state.manager
        try:
            caller = manager.gate.caller(token_of(request), request.headers.get("x-hil-user"))
            wait_s = manager.limiter.admit(f"{request.client.host if request.client else '-'} {caller.user}")
            if wait_s is not None:
                limiter = manager.limiter
                return error(429, f"too many requests from {caller.user}: at most {limiter.rate_per_s:g} a "
                                  f"second (bursts of {limiter.burst:g}); again in {wait_s:.2f} s (a page gets the "
                                  "status over /ws)",
                             headers={"Retry-After": str(max(1, math.ceil(wait_s)))})
            if operator is not None:
                manager.gate.require_operator(caller, operator)
            return await handler(request, manager, caller)
        except (AuthError, RequestError) as exc:
            return error(exc.status, str(exc))
        except (ItemError, ValidationError) as exc:
            return error(422, str(exc) if isinstance(exc, ItemError) else _pydantic_line(exc))
        except LeaseError as exc:
            return error(409, str(exc))
        except StoreUnavailable as exc:
            manager.store_failed(f"{request.method} {request.url.path}", exc)
            return error(exc.status, str(exc))
        except StoreError as exc:
            return error(exc.status, str(exc))
        except ClientDisconnect:
            return error(400, "the client went away before its request was read")
    return route


def _pydantic_line(exc: ValidationError) -> str:
    first = exc.errors()[0]
    where = ".".join(str(p) for p in first["loc"])
    return f"body: {where}: {first['msg']}"


async def read_body(request: Request, limit: int = MAX_BODY_BYTES) -> bytes:
    """The request's body, read as it arrives: 413 as soon as it is known to exceed ``limit`` (its Content-Length,
    or the bytes so far), so a large body is never held in memory."""
    declared = request.headers.get("content-length")
    if declared is not None:
        if not declared.strip().isdigit():
            raise RequestError(400, f"Content-Length: {declared[:40]!r} is not a number of bytes")
        if int(declared) > limit:
            raise RequestError(413, f"body: {int(declared)} bytes, more than the {limit} a request may have")
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise RequestError(413, f"body: more than the {limit} bytes a request may have")
        chunks.append(chunk)
    return b"".join(chunks)


async def body_as(request: Request, model: type[BaseModel]) -> Any:
    """The JSON body as ``model``; 413 (too large), 400 (not JSON) or 422 (not the model: one line naming the
    field; a string that is not Unicode text)."""
    raw = await read_body(request)
    try:
        data = json.loads(raw) if raw.strip() else {}
    except (ValueError, RecursionError):  # RecursionError: JSON nested deeper than Python's stack
        raise RequestError(400, "body: not JSON (or nested deeper than JSON bodies here are)") from None
    try:
        json.dumps(data, ensure_ascii=False).encode()
    except UnicodeEncodeError:
        raise ItemError("body: a string holds a lone UTF-16 surrogate (\\ud800-\\udfff): not Unicode text") from None
    return model.model_validate(data)


async def get_status(request: Request, m: Manager, caller: Caller) -> Response:
    return JSONResponse(m.status(caller))


async def get_queue(request: Request, m: Manager, caller: Caller) -> Response:
    return JSONResponse({"running": m.queue_running, "stop_on_failure": m.stop_on_failure,
                         "stopped": m.queue_stopped, "items": [i.public() for i in m.store.items()]})


async def add_item(request: Request, m: Manager, caller: Caller) -> Response:
    sub: SubmitItem = await body_as(request, SubmitItem)
    checked = check_item(sub.kind, sub.file_name, sub.body, files=sub.files, options=sub.options,
                         emulated=m.options.loopback)
    item = m.store.add(sub.kind, checked.name, caller.user, Path(sub.file_name).name, sub.body,
                       options=sub.options, position=sub.position, files=sub.files)
    m.changed()
    return JSONResponse(item.public(), status_code=201)


def require_owner(m: Manager, caller: Caller, owner: str, what: str) -> None:
    """An item is changed (removed, moved, stopped) by the user who submitted it or by the lease holder; another
    operator takes the lease first (breaking a held one with a reason, which the lease history keeps). 403 else."""
    lease = m.lease.current()
    if caller.user == owner or (lease is not None and lease.holder == caller.user):
        return
    how = (f"break {lease.holder}'s lease with a reason first" if lease is not None else
           "take the lease first (hil bench lease), and it is yours to change")
    raise AuthError(403, f"{what}: it is {owner}'s; only {owner} or the lease holder may; {how}")


async def remove_item(request: Request, m: Manager, caller: Caller) -> Response:
    uid = request.path_params["uid"]
    require_owner(m, caller, m.store.item(uid).user, f"remove item {uid[:12]}")
    item = m.store.remove(uid)
    m.changed()
    return JSONResponse(item.public())


async def move_item(request: Request, m: Manager, caller: Caller) -> Response:
    move: MoveItem = await body_as(request, MoveItem)
    uid = request.path_params["uid"]
    require_owner(m, caller, m.store.item(uid).user, f"move item {uid[:12]}")
    item = m.store.move(uid, move.position)
    m.changed()
    return JSONResponse(item.public())


async def clear_queue(request: Request, m: Manager, caller: Caller) -> Response:
    """The lease holder clears every waiting item; another operator only their own (the others are said)."""
    lease = m.lease.current()
    holder = lease is not None and lease.holder == caller.user
    n = m.store.clear(None if holder else caller.user)
    kept = 0 if holder else m.store.waiting()
    m.changed()
    return JSONResponse({"removed": n, "kept": kept, "by": caller.user,
                         **({"note": f"{kept} waiting items of other users kept: only their users or the lease "
                                     "holder may remove them"} if kept else {})})


async def start_queue(request: Request, m: Manager, caller: Caller) -> Response:
    start: StartQueue = await body_as(request, StartQueue)
    was = m.queue_stopped
    m.store.set_setting("stop_on_failure", start.stop_on_failure)
    m.store.set_setting("queue_running", True)
    m.store.set_setting("queue_stopped", "")
    m.changed()
    return JSONResponse({"running": True, "stop_on_failure": start.stop_on_failure, "was_stopped": was,
                         "by": caller.user})


async def stop_queue(request: Request, m: Manager, caller: Caller) -> Response:
    m.stop_queue(f"stopped by {caller.user}")
    m.changed()
    return JSONResponse({"running": False, "stopped": m.queue_stopped,
                         "note": "the running item (if any) goes on; stop or abort it"})


async def get_item(request: Request, m: Manager, caller: Caller) -> Response:
    return JSONResponse(m.item_view(request.path_params["uid"]))


async def get_history(request: Request, m: Manager, caller: Caller) -> Response:
    try:
        limit = int(request.query_params.get("limit", "100"))
    except ValueError:
        raise ItemError("limit: not an integer") from None
    return JSONResponse({"records": [record_view(r) for r in m.store.history(max(1, min(limit, 10_000)))]})


async def get_record(request: Request, m: Manager, caller: Caller) -> Response:
    return JSONResponse(record_view(m.store.record(request.path_params["uid"])))


async def get_log(request: Request, m: Manager, caller: Caller) -> Response:
    record = m.store.record(request.path_params["uid"])
    if not record.log_path or not Path(record.log_path).is_file():
        raise NotInStore(f"item {record.uid!r}: it left no log (status {record.status})")
    return FileResponse(record.log_path, filename=Path(record.log_path).name, media_type="application/x-hdf5")


async def get_report(request: Request, m: Manager, caller: Caller) -> Response:
    record = m.store.record(request.path_params["uid"])
    report = (record.summary or {}).get("report")
    if not report or not Path(report).is_file():
        raise NotInStore(f"item {record.uid!r}: it made no report")
    return FileResponse(report, media_type="text/html")


def item_dir(m: Manager, uid: str) -> tuple[HistoryRecord, Path]:
    """An ended item's record and its directory (``STATE_DIR/runs/UID``); NotInStore (404) for no such item."""
    record = m.store.record(uid)
    return record, m.options.state_dir / "runs" / record.uid


def file_kind(path: str) -> tuple[str, str]:
    """A file's kind (log, report, plot, data, config, text, file) and media type, by its suffix."""
    return FILE_KINDS.get(PurePosixPath(path).suffix.lower(), OTHER_FILE)


def confined_file(root: Path, rel: str) -> Path | None:
    """The regular file ``rel`` names inside ``root``, resolved, or None: an absolute path, a ``..``, a path that
    a symlink leads out of ``root`` (checked once resolved), or no such file."""
    if not rel or rel.startswith("/") or "\x00" in rel or ".." in PurePosixPath(rel).parts:
        return None
    try:
        base, real = root.resolve(strict=True), (root / rel).resolve(strict=True)
        return real if real.is_relative_to(base) and real.is_file() else None
    except (OSError, RuntimeError, ValueError):  # no such file, a symlink loop, a name the file system refuses
        return None


def item_files(root: Path) -> list[dict[str, Any]]:
    """Every file of an item's directory that :func:`confined_file` serves: its relative path, size, kind and
    media type, in path order (a symlink to a directory is not walked into)."""
    out = []
    for folder, dirs, names in os.walk(root):
        dirs.sort()
        for name in sorted(names):
            rel = (Path(folder) / name).relative_to(root).as_posix()
            real = confined_file(root, rel)
            if real is not None:
                kind, media = file_kind(rel)
                out.append({"path": rel, "size": real.stat().st_size, "kind": kind, "media_type": media})
    return out


async def get_files(request: Request, m: Manager, caller: Caller) -> Response:
    record, root = item_dir(m, request.path_params["uid"])
    files = await asyncio.to_thread(item_files, root)
    base = f"/api/history/{record.uid}/files"
    return JSONResponse({"uid": record.uid, "files": [{**f, "href": f"{base}/{quote(f['path'])}"} for f in files]})


async def get_file(request: Request, m: Manager, caller: Caller) -> Response:
    record, root = item_dir(m, request.path_params["uid"])
    rel = request.path_params["path"]
    path = await asyncio.to_thread(confined_file, root, rel)
    if path is None:
        raise NotInStore(f"item {record.uid!r}: no file {rel[:200]!r} in its directory "
                         f"(GET /api/history/{record.uid}/files lists them)")
    return FileResponse(path, media_type=file_kind(rel)[1], filename=PurePosixPath(rel).name,
                        content_disposition_type="inline", headers=FILE_HEADERS)


@lru_cache(maxsize=8)  # the page asks for the same few items again and again
def log_series(path: str, mtime_ns: int, size: int, max_points: int) -> dict[str, Any]:
    """A log's charts (hil.reporting.session_series) and metrics (hil.analysis.summarize_log), as plain data; a log
    that is not rewritten (its time and size) is read once for each ``max_points``."""
    data = read_log(path)
    metrics = metric_rows(summarize_log(path, data=data))
    return {"log": Path(path).name, "max_points": max_points,
            "charts": [chart.as_json() for chart in session_series(data, max_points)],
            "metrics": [{"metric": name, "value": value, "unit": unit} for name, value, unit in metrics]}


async def get_series(request: Request, m: Manager, caller: Caller) -> Response:
    record = m.store.record(request.path_params["uid"])
    low, high, default = SERIES_POINTS
    try:
        max_points = max(low, min(int(request.query_params.get("max_points", default)), high))
    except ValueError:
        raise ItemError("max_points: not an integer") from None
    log = Path(record.log_path) if record.log_path else None
    if log is None or not log.is_file():
        raise NotInStore(f"item {record.uid!r}: it left no log (status {record.status})")
    try:
        stat = log.stat()
        series = await asyncio.to_thread(log_series, str(log), stat.st_mtime_ns, stat.st_size, max_points)
    except (LogError, OSError, KeyError, ValueError) as exc:
        raise NotInStore(f"item {record.uid!r}: its log cannot be read ({exc})") from None
    return JSONResponse({"uid": record.uid, "name": record.name, "kind": record.kind, "status": record.status,
                         **series})


async def end_item(request: Request, m: Manager, caller: Caller) -> Response:
    how = "abort" if request.url.path.endswith("/abort") else "stop"
    end: EndItem = await body_as(request, EndItem)
    if m.running_uid is None:
        raise StoreError("no item is running")
    if end.uid is not None and end.uid != m.running_uid:
        raise StoreError(f"item {end.uid!r}: not the running item")
    lease = m.lease.current()
    if how == "stop" and lease is not None and lease.holder != caller.user:  # an abort is an alarm: anyone's
        raise AuthError(403, f"stop item {m.running_uid[:12]}: the bench is leased to {lease.holder}; break the "
                             "lease with a reason first (or abort, if something is wrong)")
    if m.ending != "abort":
        m.ending = how
    if how == "abort":  # an operator's alarm: nothing arms the boards again until someone starts the queue
        m.stop_queue(f"aborted by {caller.user}" + (f": {end.reason}" if end.reason else ""))
    m.send_worker({"op": how, "reason": f"{how} by {caller.user}" + (f": {end.reason}" if end.reason else "")})
    m.changed()
    return JSONResponse({"uid": m.running_uid, "ending": m.ending, "queue_running": m.queue_running})


async def run_doctor(request: Request, m: Manager, caller: Caller) -> Response:
    if m.running_uid is not None:
        raise StoreError("an item is running; the hardware checks run between items")
    m.send_worker({"op": "doctor"})
    return JSONResponse({"note": "the checks run now (about 3 s); GET /api/status shows them (worker.doctor)"},
                        status_code=202)


async def get_lease(request: Request, m: Manager, caller: Caller) -> Response:
    lease = m.lease.current()
    return JSONResponse({"lease": None if lease is None else lease.public(time.time()),
                         "events": m.store.lease_events(20)})


async def take_lease(request: Request, m: Manager, caller: Caller) -> Response:
    take: TakeLease = await body_as(request, TakeLease)
    lease = m.lease.take(caller.user, take.ttl_s)
    m.changed()
    return JSONResponse(lease.public(time.time()))


async def release_lease(request: Request, m: Manager, caller: Caller) -> Response:
    m.lease.release(caller.user)
    m.changed()
    return JSONResponse({"lease": None})


async def break_lease(request: Request, m: Manager, caller: Caller) -> Response:
    brk: BreakLease = await body_as(request, BreakLease)
    broken = m.lease.break_(caller.user, brk.reason)
    m.changed()
    return JSONResponse({"broken": broken.public(time.time()), "by": caller.user})


async def openapi(request: Request, m: Manager, caller: Caller) -> Response:
    return JSONResponse(openapi_document(API_ROUTES, __version__))


async def index(request: Request) -> Response:
    return FileResponse(STATIC / "index.html", media_type="text/html")


async def live_socket(ws: WebSocket) -> None:
    """The page's feed: ``status`` messages (on every change, and every STATUS_EVERY_S) and ``live`` messages
    (the running item's points since the last message, WS_SEND_HZ times a second)."""
    manager: Manager = ws.app.state.manager
    try:
        caller = manager.gate.caller(token_of(ws), ws.headers.get("x-hil-user"))
    except AuthError as exc:  # accepted, then closed: a browser sees the code and the reason (not a bare 403)
        await ws.accept()
        await ws.close(code=4401, reason=str(exc)[:120])
        return
    await ws.accept()
    page = Page(ws, caller)
    manager.pages.add(page)
    receiver = asyncio.create_task(_drain(ws))
    period = 1.0 / WS_SEND_HZ
    try:
        while not receiver.done():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(page.wake.wait(), STATUS_EVERY_S)
            page.wake.clear()
            if page.status_due:
                page.status_due = False
                await ws.send_text(json.dumps({"type": "status", **manager.status(caller)}, default=str))
            if page.points:
                points = list(page.points)
                page.points.clear()
                await ws.send_text(json.dumps({"type": "live", "points": points}))  # NaN is None already
            await asyncio.sleep(period)
    except (WebSocketDisconnect, RuntimeError, ConnectionError):
        pass
    finally:
        manager.pages.discard(page)
        receiver.cancel()


async def _drain(ws: WebSocket) -> None:
    """Read (and ignore) what the page sends, so a close is noticed."""
    with contextlib.suppress(WebSocketDisconnect, RuntimeError):
        while True:
            msg = await ws.receive()
            if msg.get("type") == "websocket.disconnect":
                return


# (method, path, handler, operator action or None, request model, summary): the one table the app and
# /openapi.json are both built from
API_ROUTES: list[tuple[str, str, Handler, str | None, type[BaseModel] | None, str]] = [
    ("GET", "/api/status", get_status, None, None, "The service, the worker and its boards, the queue, the lease."),
    ("GET", "/api/queue", get_queue, None, None, "The queue in order (the running item first)."),
    ("POST", "/api/queue/items", add_item, "submit", SubmitItem,
     "Submit an item (the text of a session, ident or campaign YAML); 422 with the loader's one line."),
    ("DELETE", "/api/queue/items/{uid}", remove_item, "remove an item", None, "Take a waiting item off the queue."),
    ("POST", "/api/queue/items/{uid}/move", move_item, "move an item", MoveItem,
     "Move a waiting item to a position (0 first)."),
    ("POST", "/api/queue/clear", clear_queue, "clear the queue", None, "Take every waiting item off the queue."),
    ("POST", "/api/queue/start", start_queue, "start the queue", StartQueue,
     "Run the queue's items one after another."),
    ("POST", "/api/queue/stop", stop_queue, "stop the queue", None,
     "Start no further item (the running one goes on)."),
    ("GET", "/api/items/{uid}", get_item, None, None, "One item: queued, running (with its progress) or done."),
    ("GET", "/api/history", get_history, None, None, "The history, newest first (?limit=N)."),
    ("GET", "/api/history/{uid}", get_record, None, None, "One history record with its summary metrics."),
    ("GET", "/api/history/{uid}/log", get_log, None, None, "The item's log file (HDF5)."),
    ("GET", "/api/history/{uid}/report", get_report, None, None,
     "The item's report: a session's or an ident's, or a campaign's (one HTML file, its plots inside)."),
    ("GET", "/api/history/{uid}/files", get_files, None, None,
     "Every file the item wrote (its log, report, plots, fit, cells): relative path, size, kind, media type."),
    ("GET", ITEM_FILE, get_file, None, None,
     "One file of the item's directory, by its relative path (404 for a path that leads out of it)."),
    ("GET", "/api/history/{uid}/series", get_series, None, None,
     "The item's log as charts (rate error, drive, miss distance, gyro, pose: each channel with its unit, "
     "decimated to ?max_points=N by its envelope) and its metrics."),
    ("POST", "/api/bench/stop", end_item, "stop the running item", EndItem,
     "Stop the running item the normal way (the swing stopped while stabilizing, then the driver disabled)."),
    ("POST", "/api/bench/abort", end_item, "abort the running item", EndItem,
     "Abort the running item: the driver disabled first."),
    ("POST", "/api/bench/doctor", run_doctor, "check the hardware", None,
     "Run hil doctor's checks on the held ports between items (ports, IDENT, a 2 s listen to the stream)."),
    ("GET", "/api/lease", get_lease, None, None, "The lease in force and its recent history."),
    ("POST", "/api/lease", take_lease, "take the lease", TakeLease,
     "Take (or renew) the lease for ttl_s seconds; 409 if another operator holds it."),
    ("DELETE", "/api/lease", release_lease, "release the lease", None, "Release your lease."),
    ("POST", "/api/lease/break", break_lease, "break the lease", BreakLease,
     "Break another operator's lease, with a reason that goes into the lease history."),
    ("GET", "/openapi.json", openapi, None, None, "This API, as OpenAPI 3.1."),
]


def build_app(options: ServiceOptions, gate: Gate, *, on_ready: Callable[[Manager], None] | None = None,
              on_fatal: Callable[[str], None] | None = None) -> Starlette:
    """The Starlette app of one service: the API routes, the WebSocket, the page and its static files."""

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        manager = Manager(options, gate, on_ready, on_fatal)
        app.state.manager = manager
        await manager.start()
        try:
            yield
        finally:
            await manager.close()

    by_path: dict[str, dict[str, Callable[[Request], Awaitable[Response]]]] = {}
    for method, path, handler, op, _model, _summary in API_ROUTES:  # {path}: the rest of the URL, slashes and all
        by_path.setdefault(path.replace("{path}", "{path:path}"), {})[method] = endpoint(handler, operator=op)
    routes: list[Any] = [Route(path, by_method(handlers), methods=list(handlers))  # one route: a right Allow
                         for path, handlers in by_path.items()]
    routes += [WebSocketRoute("/ws", live_socket), Route("/", index, methods=["GET"]),
               Mount("/static", app=StaticFiles(directory=STATIC), name="static")]
    names = served_names(options.host, options.allow_hosts)
    return Starlette(routes=routes, lifespan=lifespan, middleware=[Middleware(SameOrigin, names=names)],
                     exception_handlers={HTTPException: http_error, Exception: server_error})


def by_method(handlers: dict[str, Callable[[Request], Awaitable[Response]]]) -> Callable[[Request],
                                                                                          Awaitable[Response]]:
    """One route for every method of a path, so that a 405 lists them all in ``Allow``."""

    async def route(request: Request) -> Response:
        method = "GET" if request.method == "HEAD" else request.method
        return await handlers[method](request)
    return route


async def http_error(request: Request, exc: Exception) -> Response:
    """Starlette's own refusals (no such route, a method the route does not take) as the service's JSON."""
    assert isinstance(exc, HTTPException)
    detail = {404: f"{request.url.path[:120]}: no such route (GET /openapi.json lists them)",
              405: f"{request.method} {request.url.path[:120]}: not a method this route takes"}.get(
                  exc.status_code, str(exc.detail))
    return error(exc.status_code, detail, headers=exc.headers)


async def server_error(request: Request, exc: Exception) -> Response:
    """A bug: its traceback on the service's stderr, one line of JSON to the client (never the traceback)."""
    _log.error("%s %s: %s", request.method, request.url.path, type(exc).__name__, exc_info=exc)
    return error(500, f"the service failed on this request ({type(exc).__name__}); its stderr has the details")
