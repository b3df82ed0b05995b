"""`hil serve`: the bench as a lab service (docs/service.md). A manager process (HTTP and WebSocket API, the
queue, the history, the lease; its state in SQLite) and a worker process that owns the ports and runs one item at a
time through the same session code as `hil run`.

This package so far holds the queue and the history (:class:`Store`) the lease (:class:`LeaseBook`) and
the check of what a client submits (:func:`check_item`)."""

from hil.service._items import CheckedItem, ItemError, check_item
from hil.service._lease import Lease, LeaseBook, LeaseError
from hil.service._store import (
    EXIT_STATUSES,
    ITEM_KINDS,
    HistoryRecord,
    QueuedItem,
    Store,
    StoreError,
)

__all__ = ["EXIT_STATUSES", "ITEM_KINDS", "CheckedItem", "HistoryRecord", "ItemError", "Lease", "LeaseBook",
           "LeaseError", "QueuedItem", "Store", "StoreError", "check_item"]
