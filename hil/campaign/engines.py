"""Where a campaign's cells run: an engine maps a function over items and yields each result as it completes.

``local`` (:class:`LocalEngine`): threads of this process, ``jobs`` at a time; a campaign cell is a ``hil run``
subprocess of its own, so the threads only wait. ``dask`` (:class:`DaskEngine`): a dask.distributed cluster,
either one started here (a ``LocalCluster`` of worker processes with one thread each) or an existing scheduler
with workers on other machines (``dask scheduler`` / ``dask worker``, dask-jobqueue on SLURM or PBS). A task
whose worker dies is run again on another worker by the scheduler; one that raises is tried ``retries`` more
times.

    with open_engine("dask", jobs=4) as engine:
        for item, result in engine.map_cells(fn, items):   # fn(item) -> result, in completion order
            ...

``fn`` must be picklable by reference or by value (a module-level function or a ``functools.partial`` of one)
for the dask engine, and importable on the workers: they need this project installed.

A KeyboardInterrupt (Ctrl-C, or :class:`Interrupted` raised by a SIGTERM handler) while ``map_cells`` waits
cancels the items not started and comes out as :class:`Interrupted` naming the items that were running; the
local engine does not wait for them (their threads run on), so the caller can stop them first.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import signal
import socket
import uuid
from collections.abc import Callable, Collection, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any, Protocol, Self, TypeVar, runtime_checkable
from urllib.parse import urlsplit

_log = logging.getLogger("hil.campaign")

T = TypeVar("T")
R = TypeVar("R")
KeyFn = Callable[[Any], str]
OnError = Callable[[Any, BaseException], Any]

ENGINES = ("local", "dask")
SCHEMES = ("tcp", "tls")
DEFAULT_PORT_HINT = "tcp://HOST:8786"


class EngineError(ValueError):
    """Bad engine option or an unreachable cluster (one line, naming the option)."""


class Interrupted(KeyboardInterrupt):
    """A signal that stops the cells: ``signum`` (SIGINT or SIGTERM); ``running``, as :meth:`Engine.map_cells`
    raises it, the keys of the items that were running when it came."""

    def __init__(self, signum: int = signal.SIGINT, running: Iterable[str] = ()) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)
        self.running = list(running)

    @classmethod
    def during(cls, exc: BaseException, running: Iterable[str]) -> Interrupted:
        """``exc`` (a KeyboardInterrupt, perhaps an Interrupted naming its signal) with the items ``running``."""
        return cls(getattr(exc, "signum", signal.SIGINT), running)


@runtime_checkable
class Engine(Protocol):
    """What runs cells. ``remote``: the cells run where this process's files are not theirs (their outputs come
    back as data, or through ``shared_dir``); ``slots``: how many run at once now."""

    name: str
    remote: bool
    shared_dir: Path | None

    @property
    def slots(self) -> int: ...

    def open(self) -> Engine: ...

    def close(self) -> None: ...

    def map_cells(self, fn: Callable[[T], R], items: Iterable[T], *, key: KeyFn | None = None,
                  on_error: OnError | None = None, in_flight: int | None = None) -> Iterator[tuple[T, R]]:
        """``fn(item)`` for every item, yielding ``(item, result)`` as each completes. ``items`` is read lazily,
        at most ``in_flight`` items submitted and not yet yielded (defaults: see each engine). ``on_error(item,
        exc)`` turns a failed item into a result; without it the first failure is raised (and the items not yet
        started are cancelled). ``key(item)``: a readable task name. Closing the iterator early cancels the items
        not yet started. A KeyboardInterrupt cancels them too and is raised as :class:`Interrupted` naming (by
        ``key``) the items that were running."""
        ...

    def __enter__(self) -> Engine: ...

    def __exit__(self, *exc: object) -> None: ...


class _Base:
    name = "engine"
    remote = False
    shared_dir: Path | None = None

    def open(self) -> Self:
        return self

    def close(self) -> None:
        return None

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()


class LocalEngine(_Base):
    """``jobs`` threads in this process (a ThreadPoolExecutor). ``in_flight`` defaults to ``jobs``. On a
    KeyboardInterrupt the running items are not waited for: their threads end when ``fn`` returns."""

    name = "local"

    def __init__(self, jobs: int = 1) -> None:
        if jobs < 1:
            raise EngineError(f"jobs={jobs}: need at least 1")
        self.jobs = jobs

    @property
    def slots(self) -> int:
        return self.jobs

    def map_cells(self, fn: Callable[[T], R], items: Iterable[T], *, key: KeyFn | None = None,
                  on_error: OnError | None = None, in_flight: int | None = None) -> Iterator[tuple[T, R]]:
        limit = max(1, in_flight or self.jobs)
        it = iter(items)
        pending: dict[Future[R], T] = {}
        pool = ThreadPoolExecutor(max_workers=self.jobs, thread_name_prefix="hil-cell")
        wait_running = True
        try:
            while True:
                for item in itertools.islice(it, max(0, limit - len(pending))):
                    pending[pool.submit(fn, item)] = item
                if not pending:
                    return
                finished, _ = wait(pending, return_when=FIRST_COMPLETED)
                ready = []
                for future in finished:
                    item = pending.pop(future)
                    try:
                        ready.append((item, future.result()))
                    except Exception as exc:
                        if on_error is None:
                            raise
                        ready.append((item, on_error(item, exc)))
                for item in itertools.islice(it, max(0, limit - len(pending))):  # busy while the caller works
                    pending[pool.submit(fn, item)] = item
                yield from ready
        except KeyboardInterrupt as exc:
            wait_running = False
            running = [key(item) if key is not None else repr(item) for f, item in pending.items() if f.running()]
            raise Interrupted.during(exc, running) from None
        finally:
            for future in pending:
                future.cancel()
            pool.shutdown(wait=wait_running, cancel_futures=True)


def check_scheduler(address: str) -> str:
    """``address`` if it is a scheduler address (``tcp://HOST:PORT`` or ``tls://HOST:PORT``), else EngineError."""
    try:
        parts = urlsplit(address)
        port = parts.port
    except ValueError:
        port, parts = None, None
    if (parts is None or parts.scheme not in SCHEMES or not parts.hostname or port is None
            or parts.path not in ("", "/") or parts.query or parts.fragment):
        raise EngineError(f"scheduler={address!r}: not a scheduler address ({DEFAULT_PORT_HINT})")
    return address.rstrip("/")


def _reachable(address: str, timeout_s: float) -> None:
    parts = urlsplit(address)
    try:
        with socket.create_connection((parts.hostname, parts.port), timeout=timeout_s):
            pass
    except OSError as exc:
        why = exc.strerror or str(exc) or type(exc).__name__
        raise EngineError(f"scheduler={address!r}: cannot connect ({why}); is `dask scheduler` running there?"
                          ) from None


def _writable_here(path: str) -> str | None:
    """Runs on a worker: None if ``path`` is a directory it may write into, else why not."""
    target = Path(path)
    if not target.is_dir():
        return f"{path} is not a directory there"
    if not os.access(target, os.W_OK | os.X_OK):
        return f"{path} is not writable there"
    return None


class DaskEngine(_Base):
    """A dask.distributed cluster. ``scheduler``: an existing scheduler's address (``tcp://HOST:8786``); None
    starts a LocalCluster here with ``workers`` processes of one thread each (closed with the engine). With a
    scheduler, ``workers`` waits until that many workers have joined. ``shared_dir``: a directory every worker and
    this process see at the same path, where the workers leave the cells' files (else they come back as bytes).
    ``retries``: how many more times a cell that raises is tried (a cell whose worker dies is run again by the
    scheduler anyway, up to its ``distributed.scheduler.allowed-failures``). ``in_flight`` defaults to every item
    of a collection at once (the scheduler queues them), else twice the cluster's threads."""

    name = "dask"
    remote = True

    def __init__(self, scheduler: str | None = None, *, workers: int | None = None,
                 shared_dir: str | Path | None = None, retries: int = 2, connect_timeout_s: float = 10.0) -> None:
        _require_distributed()
        self.scheduler = check_scheduler(scheduler) if scheduler is not None else None
        if workers is not None and workers < 1:
            raise EngineError(f"workers={workers}: need at least 1")
        self.workers = workers
        self.shared_dir = check_shared_dir(shared_dir) if shared_dir is not None else None
        self.retries = retries
        self.connect_timeout_s = connect_timeout_s
        self.client: Any = None
        self.cluster: Any = None

    def open(self) -> DaskEngine:
        """Start the LocalCluster or connect to the scheduler (EngineError naming the scheduler if it cannot)."""
        if self.client is not None:
            return self
        from distributed import Client, LocalCluster  # noqa: PLC0415  (heavy and optional: only the dask engine needs it)

        try:
            if self.scheduler is None:
                self.cluster = LocalCluster(n_workers=self.workers or 1, threads_per_worker=1, processes=True,
                                            dashboard_address=None)
                self.client = Client(self.cluster, set_as_default=False)
            else:
                _reachable(self.scheduler, self.connect_timeout_s)
                try:
                    self.client = Client(self.scheduler, timeout=self.connect_timeout_s, set_as_default=False)
                except (OSError, TimeoutError) as exc:
                    raise EngineError(f"scheduler={self.scheduler!r}: cannot connect ({exc})") from None
                if self.workers is not None:
                    _log.warning("waiting for %d dask workers on %s", self.workers, self.scheduler)
                    self.client.wait_for_workers(self.workers)
                elif not self.client.nthreads():
                    _log.warning("no dask workers on %s yet: cells wait for `dask worker %s`", self.scheduler,
                                 self.scheduler)
            if self.shared_dir is not None:
                # a worker that goes away during the check is left out (on_error: its exception, not a raise)
                for worker, why in self.client.run(_writable_here, str(self.shared_dir), on_error="return").items():
                    if isinstance(why, BaseException):
                        _log.warning("dask worker %s did not answer the shared_dir check (%s: %s); left out of it",
                                     worker, type(why).__name__, why)
                    elif why is not None:
                        raise EngineError(f"shared_dir={str(self.shared_dir)!r}: {why} (worker {worker})")
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        client, cluster, self.client, self.cluster = self.client, self.cluster, None, None
        with contextlib.suppress(OSError, TimeoutError):
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()

    @property
    def address(self) -> str | None:
        """The scheduler's address (the LocalCluster's once started)."""
        return self.client.scheduler.address if self.client is not None else self.scheduler

    @property
    def slots(self) -> int:
        """Worker threads in the cluster now."""
        return sum(self.open().client.nthreads().values())

    def map_cells(self, fn: Callable[[T], R], items: Iterable[T], *, key: KeyFn | None = None,
                  on_error: OnError | None = None, in_flight: int | None = None) -> Iterator[tuple[T, R]]:
        from distributed import as_completed  # noqa: PLC0415  (heavy and optional: only the dask engine needs it)

        client = self.open().client
        token = uuid.uuid4().hex[:8]
        sized = isinstance(items, Collection)
        it = iter(items)
        counter = itertools.count()
        pending: dict[Any, tuple[Any, T]] = {}
        queue = as_completed(loop=client.loop)

        def refill() -> None:
            limit = in_flight or (None if sized else max(1, 2 * self.slots))
            while limit is None or len(pending) < limit:
                item = next(it, _END)
                if item is _END:
                    return
                name = f"{key(item) if key is not None else 'hil-cell'}-{token}-{next(counter)}"
                future = client.submit(fn, item, key=name, retries=self.retries, pure=False)
                pending[future.key] = (future, item)
                queue.add(future)

        try:
            refill()
            while pending:
                future = next(queue)
                _, item = pending.pop(future.key)
                try:
                    result = future.result()
                except Exception as exc:
                    if on_error is None:
                        raise
                    result = on_error(item, exc)
                future.release()
                refill()
                yield item, result
        except KeyboardInterrupt as exc:
            running: list[str] = []
            with contextlib.suppress(Exception):  # best effort: the tasks the workers are executing now
                held = {k for keys in client.run(_executing).values() for k in keys}
                running = [key(item) if key is not None else repr(item)
                           for name, (_, item) in pending.items() if str(name) in held]
            raise Interrupted.during(exc, running) from None
        finally:
            if pending:
                with contextlib.suppress(Exception):
                    client.cancel([f for f, _ in pending.values()])


_END: Any = object()


def _executing(dask_worker: Any) -> list[str]:
    """Runs on a worker (``client.run``): the keys of the tasks it is executing now."""
    return [str(ts.key) for ts in dask_worker.state.executing]


def _require_distributed() -> None:
    try:
        import distributed  # noqa: F401, PLC0415  (optional: its absence is handled here)
    except ImportError:
        raise EngineError("engine='dask': needs dask.distributed (pip install 'dask[distributed]')") from None


def check_shared_dir(path: str | Path) -> Path:
    """``path`` as an absolute path if it is an existing directory this process may write into."""
    target = Path(path).absolute()
    if not target.is_dir():
        raise EngineError(f"shared_dir={str(path)!r}: not a directory (create it on the shared filesystem)")
    if not os.access(target, os.W_OK | os.X_OK):
        raise EngineError(f"shared_dir={str(path)!r}: not writable")
    return target


def check_options(engine: str | Engine = "local", *, hardware: bool = False, scheduler: str | None = None,
                  workers: int | None = None, shared_dir: str | Path | None = None) -> None:
    """Refuse a bad combination of engine options (EngineError naming the option), connecting to nothing."""
    if not isinstance(engine, str):
        if not isinstance(engine, Engine):
            raise EngineError(f"engine: {engine!r} is not local, dask or an Engine")
        return
    if engine not in ENGINES:
        raise EngineError(f"engine={engine!r}: not local or dask")
    if engine == "local":
        for option, value in (("scheduler", scheduler), ("workers", workers), ("shared_dir", shared_dir)):
            if value is not None:
                shown = value if isinstance(value, int) else str(value)
                raise EngineError(f"{option}={shown!r}: only with engine='dask'")
        return
    if hardware:
        raise EngineError("engine='dask': hardware=True cells run on this machine's ports one at a time; "
                          "use engine='local'")
    _require_distributed()
    if scheduler is not None:
        check_scheduler(scheduler)
    if workers is not None and workers < 1:
        raise EngineError(f"workers={workers}: need at least 1")
    if shared_dir is not None:
        check_shared_dir(shared_dir)


def open_engine(engine: str = "local", *, jobs: int = 1, scheduler: str | None = None, workers: int | None = None,
                shared_dir: str | Path | None = None) -> Engine:
    """An engine by name, not yet started (use it as a context manager, or call ``open()`` and ``close()``).
    ``dask`` without ``scheduler`` starts a LocalCluster of ``workers`` (default ``jobs``) processes."""
    check_options(engine, scheduler=scheduler, workers=workers, shared_dir=shared_dir)
    if engine == "local":
        return LocalEngine(jobs)
    return DaskEngine(scheduler, workers=workers if workers is not None or scheduler is not None else jobs,
                      shared_dir=shared_dir)
