"""`hil serve`: the bench as a lab service (docs/service.md). A face, like the command line: a manager process
(HTTP and WebSocket API, the queue, the history, the lease; its state in SQLite) and a worker process that owns
the ports and runs one item at a time through the same code as `hil run` (hil.api).

- :class:`Store` (``_store``): the queue and the history; :class:`LeaseBook` (``_lease``): who holds the bench;
  :func:`check_item` (``_items``): what a client submits, checked by its kind's own loader.
- :func:`build_app` (``_app``): the Starlette app, its WebSocket and its routes (``_routes``; ``_api_models``: the
  bodies, the OpenAPI document) around the :class:`Manager` (``_manager``); :class:`Gate` (``_auth``): tokens and
  roles.
- The worker (``_worker``, ``python -m hil.service._worker``): the lab's ports, the items, the live values.
- :class:`Bench` (``_client``): the client (notebooks; the command line's runs on a service, `hil queue`,
  `hil bench`).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from hil.service._app import build_app
    from hil.service._auth import AuthError, Caller, Gate, TokenFile, is_loopback_host, load_tokens
    from hil.service._client import Bench, BenchError, bench_url, item_text
    from hil.service._items import IDENT_OPTIONS, MAX_ITEM_BYTES, CheckedItem, IdentOptions, ItemError, check_item
    from hil.service._lease import Lease, LeaseBook, LeaseError
    from hil.service._manager import Manager, ServiceOptions, record_view
    from hil.service._routes import API_ROUTES
    from hil.service._store import (
        EXIT_STATUSES,
        ITEM_KINDS,
        HistoryRecord,
        QueuedItem,
        Store,
        StoreError,
    )

__all__ = ["API_ROUTES", "EXIT_STATUSES", "IDENT_OPTIONS", "ITEM_KINDS", "MAX_ITEM_BYTES", "AuthError", "Bench",
           "BenchError", "Caller", "CheckedItem", "Gate", "HistoryRecord", "IdentOptions", "ItemError", "Lease",
           "LeaseBook", "LeaseError", "Manager", "QueuedItem", "ServiceOptions", "Store", "StoreError", "TokenFile",
           "bench_url", "build_app", "check_item", "is_loopback_host", "item_text", "load_tokens", "record_view"]

# each name loads its module on first use: a client (`hil queue`, `hil bench`, a notebook's Bench) loads only
# _client, never the manager's web stack nor the items' loaders
_FROM = {
    **dict.fromkeys(("AuthError", "Caller", "Gate", "TokenFile", "is_loopback_host", "load_tokens"), "_auth"),
    **dict.fromkeys(("Bench", "BenchError", "bench_url", "item_text"), "_client"),
    **dict.fromkeys(("IDENT_OPTIONS", "MAX_ITEM_BYTES", "CheckedItem", "IdentOptions", "ItemError", "check_item"),
                    "_items"),
    **dict.fromkeys(("Lease", "LeaseBook", "LeaseError"), "_lease"),
    **dict.fromkeys(("Manager", "ServiceOptions", "record_view"), "_manager"),
    "API_ROUTES": "_routes",
    "build_app": "_app",
    **dict.fromkeys(("EXIT_STATUSES", "ITEM_KINDS", "HistoryRecord", "QueuedItem", "Store", "StoreError"), "_store"),
}


def __getattr__(name: str) -> Any:
    module = _FROM.get(name)
    if module is None:
        raise AttributeError(f"module 'hil.service' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"hil.service.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
