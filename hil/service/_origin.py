"""Same origin only (docs/service.md, "Same origin"): what keeps a web page the lab PC's browser opens from driving
the bench through a service on localhost.

Three checks on every request, before any route runs, each refusal one line of JSON:

* ``Host`` must name this service: ``localhost``, ``127.0.0.1``, ``::1``, the address it is bound to (with a
  wildcard address, this machine's own names and addresses) or a name in its ``allow_hosts``; 400 otherwise.
  This is what defeats DNS rebinding: a rebound name reaches the service with the attacker's host name in ``Host``.
* a request that changes state (any method but GET, HEAD, OPTIONS) and every WebSocket must not come from another
  origin: an ``Origin`` header, when sent (browsers always send it on these), must be this service's own
  (``http://`` + the request's ``Host``), and ``Sec-Fetch-Site`` must not be ``cross-site``; 403 otherwise.
* a POST with a body carries ``Content-Type: application/json``; 415 otherwise. A cross-site form or a ``no-cors``
  fetch can only send ``text/plain``, form or multipart bodies without a CORS preflight, and the service answers no
  preflight.

Clients that are not browsers (the command line, ``hil.Bench``, curl, scripts) send no ``Origin`` and pass.

Starlette's own ``TrustedHostMiddleware`` does the ``Host`` check alone and answers a refusal in plain text; the
service's errors are all JSON, and the ``Origin`` and content-type checks belong with it, so this one ASGI middleware
does the three.
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import socket
from collections.abc import Iterable
from urllib.parse import urlsplit

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Receive, Scope, Send

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
LOCAL_NAMES = ("localhost", "127.0.0.1", "::1")
WILDCARD_ADDRESSES = ("0.0.0.0", "::", "")
JSON_TYPE = "application/json"


def split_host(host_header: str) -> tuple[str, str]:
    """``Host`` as (name, port): ``[::1]:8765`` -> (``::1``, ``8765``); the name in lower case."""
    host = host_header.strip().lower()
    if host.startswith("["):
        name, _, rest = host[1:].partition("]")
        return name, rest.removeprefix(":")
    if host.count(":") == 1:
        name, _, port = host.partition(":")
        return name, port
    return host, ""


def served_names(bound: str, allow_hosts: Iterable[str] = ()) -> frozenset[str]:
    """The host names a service bound to ``bound`` answers to: the loopback names, ``bound`` itself, the ones in
    ``allow_hosts``, and, bound to every address, this machine's own names and addresses."""
    names = {*LOCAL_NAMES, *(h.strip().lower().strip("[]") for h in allow_hosts if h.strip())}
    if bound not in WILDCARD_ADDRESSES:
        names.add(bound.lower().strip("[]"))
        return frozenset(names)
    for name in {socket.gethostname(), socket.getfqdn()}:
        names.add(name.lower())
        with contextlib.suppress(OSError):  # a machine whose own name does not resolve: its names still count
            names.update(str(info[4][0]).split("%")[0].lower() for info in socket.getaddrinfo(name, None))
    return frozenset(names)


def _is_loopback(name: str) -> bool:
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


class SameOrigin:
    """The ASGI middleware that does the three checks (module docstring) in front of the service's app."""

    def __init__(self, app: ASGIApp, names: frozenset[str]) -> None:
        self.app = app
        self.names = names

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        refusal = self.refusal(scope)
        if refusal is None:
            await self.app(scope, receive, send)
        elif scope["type"] == "websocket":
            await receive()  # websocket.connect; closing before accepting answers the handshake with 403
            await send({"type": "websocket.close", "code": 1008, "reason": refusal[1][:120]})
        else:
            body = json.dumps({"detail": refusal[1]}).encode()
            headers = [(b"content-type", JSON_TYPE.encode()), (b"content-length", str(len(body)).encode())]
            await send({"type": "http.response.start", "status": refusal[0], "headers": headers})
            await send({"type": "http.response.body", "body": body})

    def refusal(self, scope: Scope) -> tuple[int, str] | None:
        """(status, one line) when the request is refused, else None."""
        headers = Headers(scope=scope)
        host = headers.get("host", "")
        name, _port = split_host(host)
        if not name:
            return 400, "Host: missing; send the service's own address"
        if name not in self.names and not _is_loopback(name):
            return 400, (f"Host: {name[:80]!r} is not a name this service serves (it answers to "
                         f"{', '.join(sorted(self.names))}); start it with allow_host={name[:80]!r} if that name is "
                         "its own")
        method = "WEBSOCKET" if scope["type"] == "websocket" else str(scope.get("method", "GET"))
        if method in SAFE_METHODS:
            return None
        origin = headers.get("origin")
        if origin is not None:
            parts = urlsplit(origin.strip().lower())
            if parts.scheme not in ("http", "https") or split_host(parts.netloc) != split_host(host):
                return 403, (f"Origin: {origin[:80]!r} is not this service's own; a page from another site may not "
                             "change the bench (docs/service.md, \"Same origin\")")
        if headers.get("sec-fetch-site", "").lower() == "cross-site":
            return 403, "Sec-Fetch-Site: cross-site; a page from another site may not change the bench"
        has_body = headers.get("content-length", "0").strip() not in ("", "0") or "transfer-encoding" in headers
        if method == "POST" and has_body:  # a POST with no body has no content to mistype (Origin still checked)
            media = headers.get("content-type", "").split(";")[0].strip().lower()
            if media != JSON_TYPE:
                return 415, (f"Content-Type: {media or 'none'}; send {JSON_TYPE} (an empty body is {{}})")
        return None
