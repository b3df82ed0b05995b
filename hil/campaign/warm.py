"""Warm cell processes: a campaign's loopback cells run in worker processes that outlive a cell.

A `hil run` process per cell pays, before its session, an interpreter's start, the bench's imports and the load
of the plant's compiled kernels: most of a short sim-clock cell's wall time (docs/performance.md, "Warm cells").
A warm worker pays them once, then runs cell after cell, each through :func:`hil.session.run`, the function `hil
run` calls, in the worker's main thread (so SIGINT and SIGTERM end the session there as they end `hil run`), with
its file descriptors 1 and 2 sent to the cell's ``stderr.txt`` while it runs. The worker answers with the JSON
record `hil run` prints (:meth:`hil.session.RunResult.record`) and the campaign's metrics of the log, worked out
there (off the campaign process, whose threads share one interpreter). Between cells it starts the next cell's log
writer (:func:`hil.log.prestart_writer`).

One cell at a time per worker: :data:`WARM` lends an idle worker, or starts one, to each cell that runs, so a
campaign running ``jobs`` cells at once keeps ``jobs`` workers. Workers end with the process that started them
(they read EOF on their pipe). A worker that dies (killed, out of memory) takes only its cell, which comes back
an error naming how it ended; the next cell gets a new worker.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import os
import select
import signal
import subprocess
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import Any

from hil.campaign.metrics import compute_metrics, log_health
from hil.config import ConfigError
from hil.control.registry import effective_params
from hil.log import prestart_writer, read_log
from hil.log.ipc import helper_argv, recv, send, spawn_helper
from hil.session import run as run_session

__all__ = ["WARM", "CellHandle", "WarmCell", "WarmCells", "WorkerDied"]

WORKER_ENTRY = "hil.campaign.warm:serve"
INTERRUPTED = {"status": "interrupted", "exit_code": 130, "message": "SIGINT"}  # a cell's record
STARTUP_TIMEOUT_S = 300.0  # the first answer of a new worker: its imports, on a machine that may be busy


class WorkerDied(RuntimeError):
    """A warm worker ended while it ran a cell (``returncode``: its exit status, negative for a signal)."""

    def __init__(self, returncode: int | None) -> None:
        self.returncode = returncode
        how = (f"killed by {signal.Signals(-returncode).name}" if returncode is not None and returncode < 0
               else f"exit status {returncode}")
        super().__init__(f"the cell's process ended ({how})")


class WarmCell:
    """One worker process: :meth:`run` a session file in it, :meth:`send_signal` to it while it runs."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen[bytes] = spawn_helper(helper_argv(WORKER_ENTRY))
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self._wfd, self._rfd = self.proc.stdin.fileno(), self.proc.stdout.fileno()
        self.cells = 0  # cells run so far
        self._lock = threading.Lock()
        self._generation = 0  # the cell the worker is lent for; a handle of an earlier one signals nothing
        self._started = False  # the worker has taken the current cell and listens for SIGINT
        self._pending: int | None = None  # a signal sent before it had

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def begin(self) -> CellHandle:
        """Lend the worker to one cell: the handle a campaign's stop signals it through (:class:`CellHandle`)."""
        with self._lock:
            self._generation += 1
            self._started, self._pending = False, None
            return CellHandle(self, self._generation)

    def signal_cell(self, generation: int, signum: int) -> None:
        """``signum`` to the worker if it still runs cell ``generation``; before it has taken the cell (it ignores
        SIGINT between cells) held and sent as soon as it has."""
        with self._lock:
            if generation != self._generation:
                return  # that cell is over; the worker may be running another campaign's
            if not self._started and signum != signal.SIGKILL:
                self._pending = signum
                return
            self.proc.send_signal(signum)

    def send_signal(self, signum: int) -> None:
        self.proc.send_signal(signum)

    def run(self, session_file: Path, out_dir: Path, stderr_path: Path, timeout_s: float, *,
            analysis: str | None = None, settle_s: float = 1.0) -> dict[str, Any]:
        """Run the session in ``session_file`` on its loopback lab, its log in ``out_dir``: the JSON record `hil run`
        prints, without the summary's metrics; with ``analysis``, ``metrics`` holds the campaign's
        (:func:`hil.campaign.metrics.compute_metrics` of the log, finite ones; ``metrics_error`` if they could not
        be computed), worked out in the worker. TimeoutExpired (the worker killed) after ``timeout_s``;
        :class:`WorkerDied` if it ends. Signals go through the handle of :meth:`begin`."""
        try:
            try:
                send(self._wfd, ("run", str(session_file), str(out_dir), str(stderr_path), analysis, settle_s))
            except OSError:
                raise WorkerDied(self.proc.wait()) from None
            deadline = time.monotonic() + timeout_s
            started = self._reply(deadline, timeout_s)
            with self._lock:
                self._started, pending = True, self._pending
                if pending is not None:
                    self.proc.send_signal(pending)
            if started[0] != "started":
                raise WorkerDied(self.proc.wait())
            reply = self._reply(deadline, timeout_s)
            self.cells += 1
            return reply[1]
        finally:
            with self._lock:  # the cell is over: its handle signals nothing from now on
                self._generation += 1
                self._started, self._pending = False, None

    def _reply(self, deadline: float, timeout_s: float) -> Any:
        """The worker's next message; TimeoutExpired (the worker killed) at ``deadline``, WorkerDied at EOF."""
        ready, _, _ = select.select([self._rfd], [], [], max(0.0, deadline - time.monotonic()))
        if not ready:
            self.kill()
            raise subprocess.TimeoutExpired(WORKER_ENTRY, timeout_s)
        try:
            reply = recv(self._rfd)
        except OSError:
            reply = None
        if reply is None:
            raise WorkerDied(self.proc.wait())
        return reply

    def kill(self) -> None:
        with contextlib.suppress(OSError):
            self.proc.kill()
        self.close()

    def close(self) -> None:
        """End the worker: EOF on its pipe; killed if it has not ended within a few seconds."""
        for pipe in (self.proc.stdin, self.proc.stdout):
            with contextlib.suppress(OSError):
                if pipe is not None:
                    pipe.close()
        try:
            self.proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


class CellHandle:
    """A warm worker as one cell has it: :meth:`send_signal` reaches the worker only while it runs that cell."""

    def __init__(self, worker: WarmCell, generation: int) -> None:
        self.worker, self.generation = worker, generation

    def send_signal(self, signum: int) -> None:
        self.worker.signal_cell(self.generation, signum)


class WarmCells:
    """The idle warm workers of this process."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._idle: list[WarmCell] = []

    def lend(self) -> WarmCell:
        """An idle worker that is still alive, or a new one."""
        with self._lock:
            while self._idle:
                worker = self._idle.pop()
                if worker.alive():
                    return worker
                worker.close()
        return WarmCell()

    def give_back(self, worker: WarmCell) -> None:
        """A worker whose cell ended: kept for the next cell if it is still alive."""
        if not worker.alive():
            worker.close()
            return
        with self._lock:
            self._idle.append(worker)

    def close(self) -> None:
        """End every idle worker (those lent out end when given back, or with this process)."""
        with self._lock:
            idle, self._idle = self._idle, []
        for worker in idle:
            worker.close()

    def __len__(self) -> int:
        with self._lock:
            return len(self._idle)


WARM = WarmCells()


# --- the worker's side -----------------------------------------------------------------------


@contextlib.contextmanager
def _output_to(path: str) -> Any:
    """File descriptors 1 and 2 (and sys.stdout, sys.stderr) to ``path`` inside the block."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for f in (fd, *saved):
            os.close(f)


def run_cell_here(session_file: str, out_dir: str, analysis: str | None = None,
                  settle_s: float = 1.0) -> dict[str, Any]:
    """One cell in this process, on its loopback lab with its log in ``out_dir``: the JSON record `hil run` prints
    (its exit code 2 and one line on stderr for bad input, as there) but the summary's metrics; with ``analysis``,
    the campaign's metrics of the log under ``metrics`` (or ``metrics_error``) and its :func:`log_health` (the
    session's own drive limit) under ``health``."""
    try:
        record = run_session(session_file, loopback=True, out=out_dir).record(summary={})
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return {"status": "error", "exit_code": 2, "message": str(exc)}
    except KeyboardInterrupt:  # SIGINT outside the session's own handler (before it armed, after it ended)
        return dict(INTERRUPTED)
    except Exception as exc:  # a bug must end the cell, not the worker
        traceback.print_exc()
        return {"status": "error", "exit_code": 1, "message": f"{type(exc).__name__}: {exc}"}
    log = record.get("log")
    if analysis is not None and log and Path(log).exists():
        try:
            data = read_log(log)  # once, for the metrics and the health check
            computed = compute_metrics(log, analysis, settle_s, data=data)
            record["metrics"] = {k: v for k, v in computed.items() if math.isfinite(v)}
            controller = (data.attrs.get("config") or {}).get("controller") or {}  # the session's, as it ran
            u_max = float(effective_params({"name": controller.get("name"), "params": controller.get("params") or {}})
                          ["u_max_counts"])
            record["health"] = log_health(log, settle_s, u_max, data=data)
        except (ValueError, KeyError, OSError) as exc:
            record["metrics_error"] = f"metrics: {exc}"
        except KeyboardInterrupt:
            record["metrics_error"] = "metrics: interrupted"
        except Exception as exc:  # a bug must fail the cell, not the worker
            traceback.print_exc()
            record["metrics_error"] = f"metrics: {type(exc).__name__}: {exc}"
    return record


class _CellSigint:
    """The worker's SIGINT handler: a KeyboardInterrupt while a cell runs (:meth:`arm` to :meth:`disarm`). One that
    arrives after the cell was announced but before it is armed (the worker still setting up its output) is held
    and raised as it arms; one between cells is dropped (:meth:`announce` forgets it)."""

    def __init__(self) -> None:
        self.armed = False
        self.pending = False

    def __call__(self, signum: int, frame: Any) -> None:
        if self.armed:
            raise KeyboardInterrupt
        self.pending = True

    def announce(self) -> None:
        self.pending = False
        signal.signal(signal.SIGINT, self)

    def arm(self) -> None:
        self.armed = True
        if self.pending:
            self.pending = False
            raise KeyboardInterrupt

    def disarm(self) -> None:
        self.armed = False
        signal.signal(signal.SIGINT, self)  # the session's event loop leaves Python's default handler behind


def _run_armed(sigint: _CellSigint, session_file: str, out_dir: str, analysis: str | None,
               settle_s: float) -> dict[str, Any]:
    try:
        sigint.arm()
        return run_cell_here(session_file, out_dir, analysis, settle_s)
    except KeyboardInterrupt:
        return dict(INTERRUPTED)
    finally:
        sigint.disarm()


def serve() -> None:
    """The worker's main loop: requests on stdin, replies on stdout, until EOF. A SIGINT between cells is dropped
    (a Ctrl-C in the terminal reaches the whole process group; the campaign passes it on to the cells running)."""
    rfd, wfd = 0, os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)  # a stray print never reaches the reply pipe
    os.close(devnull)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    sigint = _CellSigint()
    signal.signal(signal.SIGINT, sigint)
    prestart_writer()
    while True:
        message = recv(rfd)
        if message is None:
            return
        _, session_file, out_dir, stderr_path, analysis, settle_s = message
        sigint.announce()
        send(wfd, ("started",))  # from now on a SIGINT ends this cell (the campaign holds one sent before)
        try:
            with _output_to(stderr_path):
                record = _run_armed(sigint, session_file, out_dir, analysis, settle_s)
        except KeyboardInterrupt:  # in the few instructions between the cell's end and its disarming
            sigint.disarm()
            record = dict(INTERRUPTED)
        send(wfd, ("done", record))
        gc.unfreeze()  # the session froze what its setup built; let what it left behind be collected
        gc.collect()
        prestart_writer()  # the next cell's log writer starts while this worker waits
