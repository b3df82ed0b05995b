"""`hil serve`: the bench as a lab service (docs/service.md). A manager process (HTTP and WebSocket API, the
queue, the history, the lease; its state in SQLite) and a worker process that owns the ports and runs one item at a
time through the same session code as `hil run`.

This package so far holds the queue and the history (:class:`Store`) and the lease (:class:`LeaseBook`)."""

from hil.service._lease import Lease, LeaseBook, LeaseError
from hil.service._store import (
    EXIT_STATUSES,
    ITEM_KINDS,
    HistoryRecord,
    QueuedItem,
    Store,
    StoreError,
)

__all__ = ["EXIT_STATUSES", "ITEM_KINDS", "HistoryRecord", "Lease", "LeaseBook", "LeaseError", "QueuedItem", "Store",
           "StoreError"]
