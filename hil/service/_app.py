"""The service's Starlette app (docs/service.md): the page and its WebSocket feed, the routes of ``_routes`` with
their guards (same origin, rate limits, body size), and the error responses; :func:`build_app` puts them together
around a :class:`~hil.service._manager.Manager`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import FileResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from hil.service._auth import AuthError, Gate
from hil.service._manager import STATUS_EVERY_S, Manager, Page, ServiceOptions
from hil.service._origin import SameOrigin, served_names
from hil.service._routes import API_ROUTES, endpoint, error, token_of

_log = logging.getLogger("hil.service")


STATIC = Path(__file__).parent / "static"
WS_SEND_HZ = 2.0  # pages get the live values this often (each message carries every point since the last): a page
# draws them once a second, what a person follows on a 10 s window at a few percent of a core (docs/service.md)


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
