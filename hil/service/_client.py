"""The service's client: :class:`Bench` for notebooks and scripts, and what the command line's runs on a
service, `hil queue` and `hil bench` call (docs/service.md, "Clients").

``Bench(url, token=...)``: ``url`` default ``$HIL_BENCH``, ``token`` default ``$HIL_BENCH_TOKEN``. Its
:meth:`Bench.run` and :meth:`Bench.run_async` take what :func:`hil.run` takes and return the same
:class:`hil.RunResult` (its log downloaded next to you, so ``result.log`` is the same ``LogFrames``): a notebook
switches from the emulator to the lab by changing one line::

    result = hil.run("profiles/sessions/demo.yaml")                                   # the emulated lab, here
    result = hil.Bench("http://bench-pc:8765", token=TOKEN).run("profiles/sessions/demo.yaml")  # the lab's bench

A client owns the item it submitted (:meth:`Bench.follow`, which :meth:`Bench.run` and the command line's runs
on a service use): Ctrl-C takes it off the queue or stops its run the normal way, a second Ctrl-C aborts it,
and its end (its record, its log) still comes back; a third leaves it to the service.

Plain HTTP with the standard library (no client dependency); the token goes in a header and nowhere else.
"""

from __future__ import annotations

import contextlib
import getpass
import json
import os
import re
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from hil.api import RunResult
    from hil.config import SessionConfig

# Only the standard library at import: `hil queue` and `hil bench` need nothing more. What a run needs (hil.api,
# hil.config, yaml) loads on first use.

BENCH_ENV = "HIL_BENCH"
TOKEN_ENV = "HIL_BENCH_TOKEN"
POLL_S = 0.25
FINAL = ("done",)
CTRL_C = "Ctrl-C at the client"  # the reason a client's Ctrl-C gives the service when it stops or aborts its item
UID_LEN = 32  # an item's uid: 32 hex digits
UID_MIN = 6  # the shortest prefix of a uid a client resolves (`hil queue list` shows 12)
EXIT_REMOVED = 130  # an item taken off the queue by Ctrl-C: it never ran
OPERATOR_ENDED = {"stopped": 3, "aborted": 130}  # the exit codes of an item an operator (or its client) ended


class BenchError(RuntimeError):
    """The service refused a request or cannot be reached: one line (``status``: the HTTP status, 0 unreachable;
    422 is bad input, as exit code 2 is at the command line)."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


def bench_url(url: str | None) -> str:
    """``url``, or ``$HIL_BENCH``; ConfigError naming both when neither is set or the URL is not http(s)."""
    url = url or os.environ.get(BENCH_ENV, "")
    if not url:
        raise _config_error(f"bench: no service given; pass its URL, or set {BENCH_ENV}")
    parsed = urllib.parse.urlparse(url)
    if parsed.scheme not in ("http", "https") or not parsed.netloc:
        raise _config_error(f"bench={url!r}: not an http:// or https:// URL of a `hil serve`")
    return url.rstrip("/")


def _config_error(message: str) -> Exception:
    """A :class:`hil.config.ConfigError` (hil.config loads only to refuse: the client's import stays light)."""
    from hil.config import ConfigError  # noqa: PLC0415  (loaded on first use: `hil queue` stays fast)

    return ConfigError(message)


class Bench:
    """A `hil serve` service (docs/service.md): its queue, history, lease, and runs that return RunResults."""

    def __init__(self, url: str | None = None, token: str | None = None, *, user: str | None = None,
                 timeout_s: float = 30.0) -> None:
        self.url = bench_url(url)
        self._token = token if token is not None else os.environ.get(TOKEN_ENV) or None
        try:
            default_user = getpass.getuser()
        except (KeyError, OSError):
            default_user = "local"
        self.user = user or default_user
        self.timeout_s = timeout_s

    def __repr__(self) -> str:  # never the token
        return f"Bench({self.url!r}, user={self.user!r})"

    # --- HTTP ---------------------------------------------------------------------------------------

    def call(self, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
        """One API call; the JSON answer, or BenchError with the service's one line."""
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.url + path, data=data, method=method, headers=self._headers())
        if data is not None:
            request.add_header("Content-Type", "application/json")
        try:
            with urllib.request.urlopen(request, timeout=self.timeout_s) as response:
                raw = response.read()
        except urllib.error.HTTPError as exc:
            raise BenchError(exc.code, _detail(exc)) from None
        except (urllib.error.URLError, OSError) as exc:
            reason = getattr(exc, "reason", exc)
            raise BenchError(0, f"{self.url}: cannot reach the service ({reason}); is `hil serve` running "
                                "there?") from None
        return json.loads(raw) if raw else None

    def _headers(self) -> dict[str, str]:
        headers = {"X-Hil-User": self.user, "Accept": "application/json"}
        if self._token:
            headers["Authorization"] = f"Bearer {self._token}"
        return headers

    def download(self, path: str, dest: Path) -> Path:
        request = urllib.request.Request(self.url + path, headers=self._headers())
        try:
            with urllib.request.urlopen(request, timeout=self.timeout_s) as response:
                tmp = dest.with_name(dest.name + ".part")
                with tmp.open("wb") as f:
                    while chunk := response.read(1 << 20):
                        f.write(chunk)
                tmp.replace(dest)
        except urllib.error.HTTPError as exc:
            raise BenchError(exc.code, _detail(exc)) from None
        except (urllib.error.URLError, OSError) as exc:
            raise BenchError(0, f"{self.url}: cannot download {path}: {getattr(exc, 'reason', exc)}") from None
        return dest

    def download_item(self, uid: str, out_dir: str | Path) -> list[Path]:
        """Every file an ended item wrote (its log, report, plots, an ident's passes and fit, a campaign's cells)
        into ``out_dir``, their paths relative to the item's directory kept; the paths written. A listed path that
        would lead out of ``out_dir`` is refused (BenchError 502) before anything is written."""
        out = Path(out_dir)
        base = f"/api/history/{_quoted(uid)}/files"
        listed = [PurePosixPath(str(f["path"])) for f in self.call("GET", base)["files"]]
        for rel in listed:
            if rel.is_absolute() or not rel.parts or ".." in rel.parts:
                raise BenchError(502, f"item {uid}: the service listed {str(rel)!r}, not a path inside the item")
        written = []
        for rel in listed:
            dest = out.joinpath(*rel.parts)
            try:
                dest.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise BenchError(0, f"{dest.parent}: cannot write the item's files there ({exc})") from None
            written.append(self.download(f"{base}/{urllib.parse.quote(rel.as_posix())}", dest))
        return written

    # --- the API, one method a call -----------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        return self.call("GET", "/api/status")

    def queue(self) -> dict[str, Any]:
        return self.call("GET", "/api/queue")

    def add(self, file: str | Path | SessionConfig, *, kind: str = "session", options: dict[str, Any] | None = None,
            position: int | None = None) -> dict[str, Any]:
        """Submit a session, ident or campaign file (checked here first, as the CLI would, then by the service), with
        its own files (:func:`item_text`)."""
        file_name, body, files = item_text(file, kind)
        return self.call("POST", "/api/queue/items",
                         {"kind": kind, "file_name": file_name, "body": body, "files": files, "options": options or {},
                          **({"position": position} if position is not None else {})})

    def remove(self, uid: str) -> dict[str, Any]:
        """Take a waiting item off the queue; ``uid`` may be a unique prefix of it (:meth:`resolve`)."""
        return self.call("DELETE", f"/api/queue/items/{_quoted(self.resolve(uid))}")

    def move(self, uid: str, position: int) -> dict[str, Any]:
        """Move a waiting item to ``position`` (0 first); ``uid`` may be a unique prefix of it."""
        return self.call("POST", f"/api/queue/items/{_quoted(self.resolve(uid))}/move",
                         {"position": position})

    def resolve(self, uid: str) -> str:
        """The uid of the item in the queue that ``uid`` names: the whole uid (taken as it is), or a prefix of at
        least :data:`UID_MIN` characters (`hil queue list` shows 12) that one item's uid starts with. BenchError,
        one line: 422 too short, 404 no item in the queue (naming it when it has ended), 409 several."""
        want = uid.strip().lower()
        if len(want) == UID_LEN:
            return want
        if len(want) < UID_MIN:
            raise BenchError(422, f"item {uid!r}: give at least {UID_MIN} characters of its uid "
                                  "(`hil queue list` shows 12)")
        matches = [i["uid"] for i in self.queue()["items"] if i["uid"].startswith(want)]
        if len(matches) == 1:
            return str(matches[0])
        if matches:
            shown = ", ".join(m[:12] for m in matches)
            raise BenchError(409, f"item {uid!r}: {len(matches)} items in the queue start with it ({shown}); "
                                  "give more of its uid")
        ended = [r for r in self.history(limit=1000) if r["uid"].startswith(want)]
        if len(ended) == 1:
            raise BenchError(404, f"item {uid!r}: not in the queue; it ended {ended[0]['status']} at "
                                  f"{ended[0]['ended_at']}")
        raise BenchError(404, f"item {uid!r}: no item in the queue has a uid that starts with it "
                              "(`hil queue list` shows them)")

    def clear(self) -> dict[str, Any]:
        return self.call("POST", "/api/queue/clear", {})

    def start(self, stop_on_failure: bool = False) -> dict[str, Any]:
        return self.call("POST", "/api/queue/start", {"stop_on_failure": stop_on_failure})

    def stop_queue(self) -> dict[str, Any]:
        return self.call("POST", "/api/queue/stop", {})

    def item(self, uid: str) -> dict[str, Any]:
        """An item as it stands: queued (its place, who runs before it, the lease and the queue's state), running
        (cycles of total) or done (its history record)."""
        return self.call("GET", f"/api/items/{_quoted(uid)}")

    def history(self, limit: int = 100) -> list[dict[str, Any]]:
        return self.call("GET", f"/api/history?limit={int(limit)}")["records"]

    def stop(self, reason: str = "", uid: str | None = None) -> dict[str, Any]:
        """Stop the running item the normal way (the swing stopped while stabilizing, then the driver disabled);
        with ``uid`` (or a unique prefix of it), only if that item is the one running."""
        uid = None if uid is None else self.resolve(uid)
        return self.call("POST", "/api/bench/stop", {"reason": reason, "uid": uid})

    def abort(self, reason: str = "", uid: str | None = None) -> dict[str, Any]:
        """Abort the running item: the driver disabled first; with ``uid``, only if that item is the one running."""
        uid = None if uid is None else self.resolve(uid)
        return self.call("POST", "/api/bench/abort", {"reason": reason, "uid": uid})

    def doctor(self) -> dict[str, Any]:
        """Run `hil doctor`'s checks on the service's ports (between items); the status then shows them."""
        return self.call("POST", "/api/bench/doctor", {})

    def lease(self, ttl_s: float = 300.0) -> dict[str, Any]:
        """Take (or renew) the lease: only your items run until it lapses (renew within ``ttl_s``)."""
        return self.call("POST", "/api/lease", {"ttl_s": ttl_s})

    @contextlib.contextmanager
    def leased(self, ttl_s: float = 30.0) -> Iterator[dict[str, Any]]:
        """Hold the lease while the ``with`` block runs: taken now, renewed every third of ``ttl_s`` by a thread of
        this process, released at the end. If this process dies (a cancelled CI job), the renewals stop and the
        lease lapses by itself within ``ttl_s``."""
        lease = self.lease(ttl_s)
        done = threading.Event()

        def renew() -> None:
            while not done.wait(ttl_s / 3):
                with contextlib.suppress(BenchError):
                    self.lease(ttl_s)

        thread = threading.Thread(target=renew, name="hil-bench-lease", daemon=True)
        thread.start()
        try:
            yield lease
        finally:
            done.set()
            thread.join(timeout=self.timeout_s)
            with contextlib.suppress(BenchError):
                self.release()

    def release(self) -> dict[str, Any]:
        return self.call("DELETE", "/api/lease")

    def break_lease(self, reason: str) -> dict[str, Any]:
        return self.call("POST", "/api/lease/break", {"reason": reason})

    # --- a run, as hil.run ---------------------------------------------------------------------------

    def wait(self, uid: str, *, progress: Callable[[dict[str, Any]], None] | None = None,
             poll_s: float = POLL_S) -> dict[str, Any]:
        """Follow an item until it is done; its history record. ``progress`` gets each view of it meanwhile."""
        while True:
            view = self.item(uid)
            if view["state"] in FINAL:
                return view
            if progress is not None:
                progress(view)
            time.sleep(poll_s)

    def follow(self, uid: str, *, progress: Callable[[dict[str, Any]], None] | None = None,
               say: Callable[[str], None] | None = None, label: str | None = None,
               poll_s: float = POLL_S) -> dict[str, Any]:
        """:meth:`wait` for an item this client submitted, and own it: Ctrl-C (KeyboardInterrupt) takes it off the
        queue if it still waits, or stops its run the normal way (the swing stopped while the loop stabilizes, then
        the driver disabled), with the reason ``Ctrl-C at the client (USER)``; a second Ctrl-C aborts it (the
        driver disabled first). Each says what it did in one line through ``say`` (default: stderr), each line
        starting with ``label`` (default ``item UID``). Its end is still waited for, so the record (and the log)
        come back: ``stopped`` (exit code 3), ``aborted`` (130), or ``removed`` (130, a record of this client's:
        it never ran). A third Ctrl-C leaves at once (KeyboardInterrupt), the item going on without this client."""
        say = say or _say
        label = label or f"item {uid[:12]}"
        presses = handled = 0
        while True:
            try:
                while handled < presses:
                    handled += 1
                    removed = self._ctrl_c(uid, handled, say, label)
                    if removed is not None:
                        return removed
                return self.wait(uid, progress=progress, poll_s=poll_s)
            except KeyboardInterrupt:
                presses += 1
                if presses >= 3:
                    say(f"{label}: Ctrl-C a third time: leaving now; item {uid[:12]} goes on without this client "
                        f"(its record and log stay in {self.url}'s history)")
                    raise

    def _ctrl_c(self, uid: str, press: int, say: Callable[[str], None], label: str) -> dict[str, Any] | None:
        """What a Ctrl-C of :meth:`follow` asks of the service (``press``: 1 or 2); a record of the item when it
        took it off the queue, else None (the item's end is then waited for)."""
        short = uid[:12]
        reason = f"{CTRL_C} ({self.user})" + (", a second time" if press > 1 else "")
        view = self.item(uid)
        if view["state"] == "queued":
            try:
                item = self.remove(uid)
            except BenchError as exc:
                if exc.status not in (404, 409):  # 404, 409: it started (or ended) meanwhile
                    raise
                view = self.item(uid)
            else:
                say(f"{label}: Ctrl-C: took item {short} off the queue before it ran")
                return {**item, "state": "done", "status": "removed", "exit_code": EXIT_REMOVED,
                        "message": f"taken off the queue before it ran: {reason}", "summary": {}, "links": {},
                        "log_path": None}
        if view["state"] == "running":
            how = "stop" if press == 1 else "abort"
            try:
                getattr(self, how)(reason, uid=uid)
            except BenchError as exc:
                if exc.status not in (404, 409):  # it ended meanwhile: its record comes next
                    raise
            else:
                if how == "stop":
                    say(f"{label}: Ctrl-C: stopping item {short} the normal way (the swing stops while the loop "
                        "stabilizes, then the driver is disabled); Ctrl-C again aborts it")
                else:
                    say(f"{label}: Ctrl-C again: aborting item {short} (the driver disabled first); waiting for "
                        "its end (Ctrl-C once more leaves without it)")
                return None
        say(f"{label}: Ctrl-C: item {short} has ended already; fetching what it left")
        return None

    def run(self, config: SessionConfig | str | Path, *, out: str | Path | None = None,
            progress: Callable[[int, int], None] | None = None,
            on_view: Callable[[dict[str, Any]], None] | None = None, kind: str = "session",
            options: dict[str, Any] | None = None, say: Callable[[str], None] | None = None) -> RunResult:
        """Run a session on the service's lab, as :func:`hil.run` runs it here: submit, wait its turn, follow,
        download the log into ``out`` (default the session's ``logging.dir``). ``progress(cycles, total)`` as
        hil.run's; ``on_view`` gets the item's every view (its place in the queue while it waits). Ctrl-C ends the
        item as :meth:`follow` says (``say`` gets its lines), and the result is then the item's: ``stopped``,
        ``aborted`` or ``removed``."""
        return self.run_item(config, out=out, progress=progress, on_view=on_view, kind=kind, options=options,
                             say=say)[0]

    def run_item(self, config: SessionConfig | str | Path, *, out: str | Path | None = None,
                 progress: Callable[[int, int], None] | None = None,
                 on_view: Callable[[dict[str, Any]], None] | None = None, kind: str = "session",
                 options: dict[str, Any] | None = None,
                 say: Callable[[str], None] | None = None) -> tuple[RunResult, dict[str, Any]]:
        """:meth:`run`, and the item's history record (its summary: an ident's fit under ``ident``)."""
        from hil.config import SessionConfig, load_session  # noqa: PLC0415  (loaded on first use: `hil queue` stays fast)

        config = config if isinstance(config, SessionConfig) else load_session(config)
        out_dir = Path(out) if out is not None else config.logging.dir
        out_dir.mkdir(parents=True, exist_ok=True)
        item = self.add(config, kind=kind, options=options)

        def follow(view: dict[str, Any]) -> None:
            if on_view is not None:
                on_view(view)
            if progress is not None and view.get("state") == "running" and view.get("total"):
                progress(int(view.get("cycles", 0)), int(view["total"]))

        label = item.get("file_name") or f"item {item['uid'][:12]}"
        record = self.follow(item["uid"], progress=follow, say=say, label=label)
        try:
            return self.result(record, out_dir), record
        except KeyboardInterrupt:
            (say or _say)(f"{label}: Ctrl-C: leaving without its files; they stay in {self.url}'s history (item "
                          f"{record['uid'][:12]})")
            raise

    async def run_async(self, config: SessionConfig | str | Path, **options: Any) -> RunResult:
        """:meth:`run`, awaitable inside a running event loop (a notebook's)."""
        import asyncio  # noqa: PLC0415  (loaded on first use: `hil queue` stays fast)

        return await asyncio.to_thread(self.run, config, **options)

    @staticmethod
    def exit_code(record: dict[str, Any]) -> int:
        """The exit code an item's record stands for, as the command line's (docs/service.md, "Items and their
        outcome"): 3 ``stopped`` and 130 ``aborted`` whatever way the session wound down (a stop that an abort
        overtook), else the record's own (2 ``invalid`` and 1 when it has none)."""
        status, code = record.get("status"), record.get("exit_code")
        if status in OPERATOR_ENDED:
            return OPERATOR_ENDED[status]
        return int(code) if code is not None else (2 if status == "invalid" else 1)

    def result(self, record: dict[str, Any], out_dir: Path) -> RunResult:
        """A history record as a :class:`hil.RunResult`, every file of its item downloaded into ``out_dir``
        (:meth:`download_item`; its ``log_path`` the log's copy there)."""
        from hil.api import RunResult  # noqa: PLC0415  (loaded on first use: `hil queue` stays fast)
        from hil.session import LoopStats, SessionResult  # noqa: PLC0415  (loaded on first use: `hil queue` stays fast)

        log_path = None
        links = record.get("links") or {}
        if links.get("files"):  # every file it wrote, its log among them (at the top of its directory)
            files = self.download_item(record["uid"], out_dir)
            log = out_dir / Path(record.get("log_path") or "").name
            log_path = log if links.get("log") and log in files else None
        elif links.get("log"):  # a service that lists no files: its log alone
            name = Path(record.get("log_path") or f"{record['uid']}.h5").name
            log_path = self.download(links["log"], out_dir / name)
        status = record["status"]
        exit_code = self.exit_code(record)
        message = record.get("message", "")
        session = SessionResult(status, exit_code, log_path, LoopStats(), message)
        return RunResult(status=status, exit_code=exit_code, message=message, log_path=log_path,
                         clock=f"bench {self.url}", session=session)


NOT_SENT: dict[str, Any] = {"ports": True, "emulator": True, "logging": {"dir"}}  # what the service does not use
_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]+")


def portable_session(config: SessionConfig) -> str:
    """A loaded session as the service takes it: its parts inline, without what the service does not use (its
    ports, its emulator, its log directory: the service runs it on its own lab), so it names no file of this
    machine's (docs/service.md, "A submitted item stands on its own")."""
    from hil.config import session_yaml  # noqa: PLC0415  (loaded on first use: `hil queue` stays fast)

    return session_yaml(config, exclude=NOT_SENT)


def item_text(file: str | Path | SessionConfig, kind: str) -> tuple[str, str, dict[str, str]]:
    """(file name, text, the item's own files) of an item, as the service wants it: a session as loaded here
    (:func:`portable_session`); a campaign as loaded here, with its base session (as a session is sent) and its
    profiles as the item's own files (``session.yaml``, ``profiles/NAME.yaml``), named relatively. ConfigError for
    a file that does not load, as the command line says it."""
    import yaml  # noqa: PLC0415  (loaded on first use: `hil queue` stays fast)

    from hil.campaign import load_campaign  # noqa: PLC0415  (loaded on first use: `hil queue` stays fast)
    from hil.config import ConfigError, SessionConfig, load_session, read_text_file  # noqa: PLC0415  (loaded on first use: `hil queue` stays fast)

    if isinstance(file, SessionConfig):
        return f"{file.name}.yaml", portable_session(file), {}
    path = Path(file)
    if kind != "campaign":
        return path.name, portable_session(load_session(path)), {}
    campaign = load_campaign(path)
    try:
        session = load_session(campaign.session)
    except ConfigError as exc:
        raise ConfigError(f"{path}: session: {exc}") from None
    files = {"session.yaml": portable_session(session)}
    data = campaign.model_dump(mode="json", exclude_none=True)
    data["session"] = "session.yaml"
    named: dict[Path, str] = {}
    for entry, dumped in zip(campaign.profiles, data["profiles"], strict=True):
        if entry.path not in named:
            stem = _UNSAFE.sub("-", entry.path.stem).strip(".-")[:60] or "profile"
            name = f"profiles/{stem}.yaml"
            n = 1
            while name in files:
                n += 1
                name = f"profiles/{stem}-{n}.yaml"
            try:
                files[name] = read_text_file(entry.path)
            except ValueError as exc:
                raise ConfigError(f"{path}: profiles: {exc}") from None
            named[entry.path] = name
        dumped["path"] = named[entry.path]
    return path.name, yaml.safe_dump(data, sort_keys=False), files


def _detail(exc: urllib.error.HTTPError) -> str:
    try:
        body = json.loads(exc.read() or b"{}")
        return str(body.get("detail", "")) or f"HTTP {exc.code}"
    except (ValueError, OSError):
        return f"HTTP {exc.code} {exc.reason}"


def _quoted(uid: str) -> str:
    """A uid as one segment of a URL's path."""
    return urllib.parse.quote(uid, safe="")


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)
