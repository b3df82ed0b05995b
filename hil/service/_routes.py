"""The service's HTTP API (docs/service.md): the request plumbing (who calls, bodies, errors as one line), the
handlers of the queue, the history and its files, the items' ends, the doctor and the lease, and the route table
(:data:`API_ROUTES`) the app and ``/openapi.json`` are built from. The state they act on is the manager's
(``_manager``); the app around them is ``_app``.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import time
from collections.abc import Awaitable, Callable, Mapping
from functools import lru_cache
from pathlib import Path, PurePosixPath
from typing import Any, TypeVar
from urllib.parse import quote

from pydantic import BaseModel, ValidationError
from starlette.requests import ClientDisconnect, HTTPConnection, Request
from starlette.responses import FileResponse, JSONResponse, Response

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
from hil.service._auth import AuthError, Caller
from hil.service._items import ItemError, check_item
from hil.service._lease import LeaseError
from hil.service._manager import Manager, record_view
from hil.service._store import HistoryRecord, NotInStore, StoreError, StoreUnavailable

MAX_BODY_BYTES = 2 << 20  # a request body beyond this is refused (413) before it is read whole
SERIES_POINTS = (2, 20_000, 2000)  # GET /api/history/UID/series: max_points at least, at most, by default
# an item's files are served as what they are, never as a page of the service's: no script runs, no type is guessed
FILE_HEADERS = {"X-Content-Type-Options": "nosniff",
                "Content-Security-Policy": "sandbox; default-src 'none'; img-src data:; style-src 'unsafe-inline'"}


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


def error(status: int, message: str, headers: Mapping[str, str] | None = None) -> JSONResponse:
    """Every error the service answers: ``{"detail": "one line"}``."""
    return JSONResponse({"detail": " ".join(message.split())}, status_code=status, headers=headers)


class RequestError(Exception):
    """A request the service refuses before any route logic (a body too large, not JSON): its status, one line."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


Handler = Callable[[Request, Manager, Caller], Awaitable[Response]]
Body = TypeVar("Body", bound=BaseModel)


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


async def body_as(request: Request, model: type[Body]) -> Body:
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
