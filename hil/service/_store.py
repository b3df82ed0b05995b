"""The service's queue and history, in SQLite in the state directory (docs/service.md).

The queue holds the items the lab submitted, in order; the history one record per item that left the queue, with
its user, times, exit status, log and summary metrics. Every change is one transaction committed before the call
returns (WAL journal, ``synchronous=FULL``), so a service killed with SIGKILL and started again has the same queue
and history. An item that was running when the service died is recorded ``interrupted`` by :meth:`Store.open`'s
recovery and taken off the queue: it is never run again by itself.

The store knows nothing of boards or sessions: an item is the text of a YAML file the command line takes (a
session, an ident session, a campaign) with its kind, its name and who submitted it.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

ItemKind = Literal["session", "ident", "campaign"]
ITEM_KINDS: tuple[str, ...] = ("session", "ident", "campaign")
ExitStatus = Literal["completed", "lost_target", "fault", "stopped", "aborted", "interrupted", "invalid"]
EXIT_STATUSES: tuple[str, ...] = ("completed", "lost_target", "fault", "stopped", "aborted", "interrupted", "invalid")
DB_NAME = "service.sqlite3"
SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS queue (
    uid TEXT PRIMARY KEY, position INTEGER NOT NULL, kind TEXT NOT NULL, name TEXT NOT NULL, user TEXT NOT NULL,
    file_name TEXT NOT NULL, body TEXT NOT NULL, options TEXT NOT NULL, submitted_at TEXT NOT NULL,
    started_at TEXT, files TEXT NOT NULL DEFAULT '{}');
CREATE TABLE IF NOT EXISTS lease_events (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, at TEXT NOT NULL, event TEXT NOT NULL, holder TEXT NOT NULL,
    by TEXT NOT NULL, reason TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS history (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, uid TEXT UNIQUE NOT NULL, kind TEXT NOT NULL, name TEXT NOT NULL,
    user TEXT NOT NULL, file_name TEXT NOT NULL, submitted_at TEXT NOT NULL, started_at TEXT, ended_at TEXT NOT NULL,
    status TEXT NOT NULL, message TEXT NOT NULL, log_path TEXT, summary TEXT NOT NULL);
"""


class StoreError(ValueError):
    """A request the queue cannot do (an unknown item, a position out of range): one line naming it."""

    status = 409  # the HTTP status the API answers it with


class NotInStore(StoreError):
    """No such item in the queue or the history."""

    status = 404


class StoreUnavailable(StoreError):
    """The state store cannot be read or written now (its disk full: 507; locked, read-only, I/O: 503). Nothing
    was changed; the same request succeeds once the disk has room again."""

    def __init__(self, path: Path, exc: sqlite3.Error) -> None:
        full = isinstance(exc, sqlite3.OperationalError) and "full" in str(exc).lower()
        super().__init__(f"the service's state store ({path}) cannot be written: {exc}"
                         + ("; free space on its disk (nothing was changed)" if full else " (nothing was changed)"))
        self.status = 507 if full else 503


def now_iso() -> str:
    """UTC now, ISO 8601 with milliseconds (the times of the queue and the history)."""
    return datetime.now(UTC).isoformat(timespec="milliseconds")


@dataclass(frozen=True)
class QueuedItem:
    """One item in the queue (``started_at`` set while it runs)."""

    uid: str
    position: int
    kind: str
    name: str
    user: str
    file_name: str
    body: str
    options: dict[str, Any] = field(default_factory=dict)
    submitted_at: str = ""
    started_at: str | None = None
    files: dict[str, str] = field(default_factory=dict)  # the item's own files (name -> text)

    def public(self) -> dict[str, Any]:
        """As the API shows it: everything but the files' text (the names of its own files are shown)."""
        out = asdict(self)
        out.pop("body")
        out["files"] = sorted(self.files)
        return out


@dataclass(frozen=True)
class HistoryRecord:
    """One item that left the queue: how it ended, its log and its summary metrics."""

    seq: int
    uid: str
    kind: str
    name: str
    user: str
    file_name: str
    submitted_at: str
    started_at: str | None
    ended_at: str
    status: str
    message: str
    log_path: str | None
    summary: dict[str, Any]

    def public(self) -> dict[str, Any]:
        return asdict(self)


class Store:
    """The queue and the history in one SQLite file (``state_dir/service.sqlite3``). Thread-safe: one connection,
    one lock; every method is one committed transaction."""

    def __init__(self, state_dir: Path) -> None:
        state_dir.mkdir(parents=True, exist_ok=True)
        self.path = state_dir / DB_NAME
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=30.0)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.executescript(_SCHEMA)  # its own transaction (executescript commits first)
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(queue)").fetchall()}
        if "files" not in columns:  # a state directory from before items carried their own files
            self._db.execute("ALTER TABLE queue ADD COLUMN files TEXT NOT NULL DEFAULT '{}'")
        with self._tx() as db:
            row = db.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone()
            if row is None:
                db.execute("INSERT INTO meta (key, value) VALUES ('schema', ?)", (str(SCHEMA_VERSION),))
            elif int(row[0]) != SCHEMA_VERSION:
                raise StoreError(f"{self.path}: schema {row[0]}, this service reads {SCHEMA_VERSION}; "
                                 "give another state directory")

    @classmethod
    def open(cls, state_dir: Path, log_for: Callable[[str], str | None] | None = None,
             ) -> tuple[Store, list[HistoryRecord]]:
        """The store, and the items that were running when the service last stopped, now in the history as
        ``interrupted`` with exit code 1 (off the queue: never re-run by themselves); ``log_for(uid)``: the log such
        an item left, linked from its record."""
        store = cls(state_dir)
        return store, store._interrupt_running(log_for)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One write transaction; any SQLite error is a :class:`StoreUnavailable` and nothing is changed."""
        with self._lock:
            try:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    yield self._db
                except BaseException:
                    with suppress(sqlite3.Error):
                        self._db.execute("ROLLBACK")
                    raise
                self._db.execute("COMMIT")
            except sqlite3.Error as exc:
                with suppress(sqlite3.Error):
                    self._db.execute("ROLLBACK")
                raise StoreUnavailable(self.path, exc) from None

    @contextmanager
    def _read(self) -> Iterator[sqlite3.Connection]:
        """The connection for a read; any SQLite error is a :class:`StoreUnavailable`."""
        with self._lock:
            try:
                yield self._db
            except sqlite3.Error as exc:
                raise StoreUnavailable(self.path, exc) from None

    # --- the queue ---------------------------------------------------------------------------------

    def add(self, kind: str, name: str, user: str, file_name: str, body: str, *,
            options: dict[str, Any] | None = None, position: int | None = None,
            files: dict[str, str] | None = None) -> QueuedItem:
        """Queue an item at ``position`` (0 first; None or past the end: last); returns it with its new uid."""
        if kind not in ITEM_KINDS:
            raise StoreError(f"kind={kind!r}: not {', '.join(ITEM_KINDS)}")
        uid = uuid.uuid4().hex
        with self._tx() as db:
            n = db.execute("SELECT COUNT(*) FROM queue").fetchone()[0]
            at = n if position is None else self._check_position(position, n + 1)
            db.execute("UPDATE queue SET position = position + 1 WHERE position >= ?", (at,))
            db.execute("INSERT INTO queue (uid, position, kind, name, user, file_name, body, options, submitted_at, "
                       "files) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                       (uid, at, kind, name, user, file_name, body, json.dumps(options or {}), now_iso(),
                        json.dumps(files or {})))
        return self.item(uid)

    def items(self) -> list[QueuedItem]:
        """The queue in order (a running item first: it left its place when it started)."""
        with self._read() as db:
            rows = db.execute(f"SELECT {_QUEUE_COLUMNS} FROM queue ORDER BY position").fetchall()
        return [_queued(r) for r in rows]

    def running(self) -> QueuedItem | None:
        """The item that runs now, or None (one indexed row: what the status asks for ten times a second)."""
        with self._read() as db:
            row = db.execute(f"SELECT {_QUEUE_COLUMNS} FROM queue WHERE started_at IS NOT NULL").fetchone()
        return None if row is None else _queued(row)

    def waiting(self) -> int:
        """How many items wait."""
        with self._read() as db:
            return int(db.execute("SELECT COUNT(*) FROM queue WHERE started_at IS NULL").fetchone()[0])

    def item(self, uid: str) -> QueuedItem:
        with self._read() as db:
            row = db.execute(f"SELECT {_QUEUE_COLUMNS} FROM queue WHERE uid = ?", (uid,)).fetchone()
        if row is None:
            raise NotInStore(f"item {uid!r}: not in the queue")
        return _queued(row)

    def move(self, uid: str, position: int) -> QueuedItem:
        """Move a waiting item to ``position`` (0 first) among the items that have not started."""
        with self._tx() as db:
            row = db.execute("SELECT position, started_at FROM queue WHERE uid = ?", (uid,)).fetchone()
            if row is None:
                raise NotInStore(f"item {uid!r}: not in the queue")
            if row[1] is not None:
                raise StoreError(f"item {uid!r}: running; a running item cannot move")
            waiting = [r[0] for r in db.execute(
                "SELECT uid FROM queue WHERE started_at IS NULL ORDER BY position").fetchall()]
            to = self._check_position(position, len(waiting))
            waiting.remove(uid)
            waiting.insert(to, uid)
            self._renumber(db, waiting)
        return self.item(uid)

    def remove(self, uid: str) -> QueuedItem:
        """Take a waiting item off the queue (a running one is stopped or aborted instead)."""
        item = self.item(uid)
        if item.started_at is not None:
            raise StoreError(f"item {uid!r}: running; stop or abort it instead")
        with self._tx() as db:
            db.execute("DELETE FROM queue WHERE uid = ?", (uid,))
            self._renumber(db, [r[0] for r in db.execute(
                "SELECT uid FROM queue ORDER BY position").fetchall()])
        return item

    def clear(self, user: str | None = None) -> int:
        """Take every waiting item (of ``user``, when given) off the queue; returns how many."""
        with self._tx() as db:
            n = db.execute("DELETE FROM queue WHERE started_at IS NULL AND (? IS NULL OR user = ?)",
                           (user, user)).rowcount
            self._renumber(db, [r[0] for r in db.execute("SELECT uid FROM queue ORDER BY position").fetchall()])
        return n

    def start_next(self, users: set[str] | None = None) -> QueuedItem | None:
        """Mark the first waiting item (of one of ``users``, when a lease restricts who runs) as running and
        return it; None when there is none or an item already runs."""
        with self._tx() as db:
            if db.execute("SELECT 1 FROM queue WHERE started_at IS NOT NULL").fetchone() is not None:
                return None
            for uid, user in db.execute(
                    "SELECT uid, user FROM queue WHERE started_at IS NULL ORDER BY position").fetchall():
                if users is None or user in users:
                    db.execute("UPDATE queue SET started_at = ? WHERE uid = ?", (now_iso(), uid))
                    self._renumber(db, [r[0] for r in db.execute(
                        "SELECT uid FROM queue ORDER BY position").fetchall()])
                    break
            else:
                return None
        return self.item(uid)

    def finish(self, uid: str, status: str, message: str = "", *, log_path: str | None = None,
               summary: dict[str, Any] | None = None) -> HistoryRecord:
        """The item left the queue (ran, failed validation before it ran, or was interrupted): one history record,
        in the same transaction as its removal from the queue."""
        if status not in EXIT_STATUSES:
            raise StoreError(f"status={status!r}: not {', '.join(EXIT_STATUSES)}")
        with self._tx() as db:
            row = db.execute(f"SELECT {_QUEUE_COLUMNS} FROM queue WHERE uid = ?", (uid,)).fetchone()
            if row is None:
                raise NotInStore(f"item {uid!r}: not in the queue")
            item = _queued(row)
            self._record(db, item, status, message, log_path=log_path, summary=summary)
            db.execute("DELETE FROM queue WHERE uid = ?", (uid,))
            self._renumber(db, [r[0] for r in db.execute("SELECT uid FROM queue ORDER BY position").fetchall()])
        return self.record(uid)

    def _interrupt_running(self, log_for: Callable[[str], str | None] | None) -> list[HistoryRecord]:
        with self._tx() as db:
            rows = db.execute(f"SELECT {_QUEUE_COLUMNS} FROM queue WHERE started_at IS NOT NULL").fetchall()
            for row in rows:
                item = _queued(row)
                self._record(db, item, "interrupted", "the service stopped while it ran; not run again by itself",
                             log_path=log_for(item.uid) if log_for is not None else None,
                             summary={"exit_code": 1})
                db.execute("DELETE FROM queue WHERE uid = ?", (item.uid,))
            self._renumber(db, [r[0] for r in db.execute("SELECT uid FROM queue ORDER BY position").fetchall()])
        return [self.record(r[0]) for r in rows]

    # --- the history -------------------------------------------------------------------------------

    def history(self, limit: int | None = None) -> list[HistoryRecord]:
        """The history, newest first (``limit``: the newest that many)."""
        with self._read() as db:
            rows = db.execute(f"SELECT {_HISTORY_COLUMNS} FROM history ORDER BY seq DESC LIMIT ?",
                                    (-1 if limit is None else limit,)).fetchall()
        return [_record(r) for r in rows]

    def record(self, uid: str) -> HistoryRecord:
        with self._read() as db:
            row = db.execute(f"SELECT {_HISTORY_COLUMNS} FROM history WHERE uid = ?", (uid,)).fetchone()
        if row is None:
            raise NotInStore(f"item {uid!r}: not in the history")
        return _record(row)

    # --- settings that outlive the service ---------------------------------------------------------

    def setting(self, key: str, default: Any = None) -> Any:
        with self._read() as db:
            row = db.execute("SELECT value FROM meta WHERE key = ?", (f"setting.{key}",)).fetchone()
        return default if row is None else json.loads(row[0])

    def set_setting(self, key: str, value: Any) -> None:
        with self._tx() as db:
            db.execute("INSERT INTO meta (key, value) VALUES (?, ?) ON CONFLICT(key) DO UPDATE SET value = "
                       "excluded.value", (f"setting.{key}", json.dumps(value)))

    # --- the lease's record ------------------------------------------------------------------------

    def lease_event(self, event: str, holder: str, by: str, reason: str = "") -> None:
        """One line of the lease's history: taken, released, lapsed or broken (``by`` another operator, with
        ``reason``)."""
        with self._tx() as db:
            db.execute("INSERT INTO lease_events (at, event, holder, by, reason) VALUES (?, ?, ?, ?, ?)",
                       (now_iso(), event, holder, by, " ".join(reason.split())))

    def lease_events(self, limit: int | None = None) -> list[dict[str, Any]]:
        """The lease's history, newest first."""
        with self._read() as db:
            rows = db.execute("SELECT seq, at, event, holder, by, reason FROM lease_events ORDER BY seq DESC "
                                    "LIMIT ?", (-1 if limit is None else limit,)).fetchall()
        return [dict(zip(("seq", "at", "event", "holder", "by", "reason"), r, strict=True)) for r in rows]

    # --- helpers -----------------------------------------------------------------------------------

    @staticmethod
    def _check_position(position: int, n: int) -> int:
        if isinstance(position, bool) or not isinstance(position, int) or position < 0:
            raise StoreError(f"position={position!r}: not an index >= 0")
        return min(position, max(0, n - 1))

    @staticmethod
    def _renumber(db: sqlite3.Connection, uids: list[str]) -> None:
        """Positions 0..n-1 in this order (running items keep the front)."""
        running = [r[0] for r in db.execute("SELECT uid FROM queue WHERE started_at IS NOT NULL").fetchall()]
        order = running + [u for u in uids if u not in running]
        db.executemany("UPDATE queue SET position = ? WHERE uid = ?", [(i, u) for i, u in enumerate(order)])

    @staticmethod
    def _record(db: sqlite3.Connection, item: QueuedItem, status: str, message: str, *, log_path: str | None,
                summary: dict[str, Any] | None) -> None:
        db.execute("INSERT INTO history (uid, kind, name, user, file_name, submitted_at, started_at, ended_at, "
                   "status, message, log_path, summary) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                   (item.uid, item.kind, item.name, item.user, item.file_name, item.submitted_at, item.started_at,
                    now_iso(), status, " ".join(message.split()), log_path, json.dumps(summary or {}, default=str)))


_QUEUE_COLUMNS = "uid, position, kind, name, user, file_name, body, options, submitted_at, started_at, files"
_HISTORY_COLUMNS = ("seq, uid, kind, name, user, file_name, submitted_at, started_at, ended_at, status, message, "
                    "log_path, summary")


def _queued(row: tuple[Any, ...]) -> QueuedItem:
    uid, position, kind, name, user, file_name, body, options, submitted_at, started_at, files = row
    return QueuedItem(uid, position, kind, name, user, file_name, body, json.loads(options), submitted_at,
                      started_at, json.loads(files))


def _record(row: tuple[Any, ...]) -> HistoryRecord:
    seq, uid, kind, name, user, file_name, submitted_at, started_at, ended_at, status, message, log_path, summary = row
    return HistoryRecord(seq, uid, kind, name, user, file_name, submitted_at, started_at, ended_at, status, message,
                         log_path, json.loads(summary))
