"""The service's worker process: it owns the lab's ports and runs one item at a time through the same code as
`hil run`, `hil ident` and `hil campaign` (hil.api), while the manager (hil.service._manager) talks to the world.

It claims the boards' ports once, when it starts (TIOCEXCL plus a lock naming the service, hil.link), and holds
them while it serves: a `hil run` or another `hil serve` on them is refused. With ``loopback`` it first starts the
emulated lab on the realtime clock (hil.session.EmulatorProcess) and claims its ports. Every item then runs on
that lab, passed to its run as ``lab=`` (hil.session.BenchLab). Between items the boards are as every session
leaves them: driver disabled, stream idle, hexapod stopped at home.

The manager speaks to it over its stdin and stdout, one JSON object a line (docs/service.md, "The worker"):

* in: ``{"op": "run", "item": {...}}``, ``{"op": "stop", "reason": ...}`` (the normal wind-down),
  ``{"op": "abort", "reason": ...}`` (driver disabled first), ``{"op": "quit"}``;
* out: ``ready`` (ports, holder), ``fatal`` (it cannot serve: why), ``started``, ``live`` (the running item's
  latest values, decimated here to :data:`LIVE_HZ`), ``done`` (status, exit code, message, log, summary).

Nothing the manager does can stall the loop: the item runs in its own thread with its own event loop (the
session's 1 kHz loop in a thread of its own again), the worker never waits on the manager (its lines go out
through a writer thread; live values that cannot go out are replaced by newer ones), and when the manager goes
away (its end of stdin closes: a crash, SIGKILL) the running item is aborted, the driver disabled first, and the
worker exits. The boards' host timeout covers a worker killed outright.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import json
import math
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from hil import api
from hil.boards import REST_TIMEOUT_S, check_boards, wait_for_rest
from hil.config import (
    ConfigError,
    EmulatorRef,
    MqttConfig,
    PortConfig,
    SessionConfig,
    load_model,
    load_session,
    parse_yaml,
)
from hil.link import Holder as PortHolder
from hil.link import LinkError, PortClaims, PortUnavailable, check_ports, claim_ports
from hil.protocol import LINKS
from hil.reporting import Figure, write_session_report
from hil.service._items import IDENT_OPTIONS, ItemError, check_item, write_item
from hil.session import EXIT_STOPPED, SERVICE_RT_PRIORITY, BenchLab, EmulatorProcess, Session, fifo_refusal

LIVE_HZ = 50.0  # the running item's latest values, sent to the manager this often (the page wants >= 20 Hz)
LIVE_CHANNELS = {
    "loop": ("t_s", "rate_err_el_dps", "rate_err_az_dps", "drive_el_counts", "drive_az_counts", "gyro_y_dps",
             "gyro_z_dps"),
    "image": ("miss_x_px", "miss_y_px", "track_valid"),
    "hexapod": ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"),
}
EXIT_INVALID = 2
EXIT_ABORTED = 130  # as SIGINT's: what an operator's abort ends an item with (docs/service.md)
CLAIM_WAIT_S = 15.0  # a previous worker of this lab (its manager killed) aborts its item and lets go within this


def holder_name() -> str:
    """How this worker's port locks name it: the service, by its manager's pid."""
    return f"hil serve (pid {os.getppid()})"


def predecessor(holder: PortHolder | None) -> bool:
    """Is ``holder`` a worker of a service that is gone (its manager dead: it is aborting its item and will let go)
    or of this very service (a worker that died and is being replaced)? Then its ports are waited for; another
    live bench's are refused at once."""
    match = re.fullmatch(r"hil serve \(pid (\d+)\)", holder.session) if holder is not None else None
    if match is None:
        return False
    manager = int(match.group(1))
    if manager == os.getppid():
        return True
    try:
        os.kill(manager, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False


class BoardsNotAtRest(RuntimeError):
    """The boards did not come to their rest state before an item: it is not started."""


class EndedBeforeStart(RuntimeError):
    """The item was stopped or aborted while it waited for the boards' rest state: it is not started."""


class Outbox:
    """The worker's lines to the manager, written by a thread of their own so that nothing here waits on the
    manager: control lines are all kept, in order; a live line waits in a slot of one, replaced by a newer."""

    def __init__(self, stream: Any) -> None:
        self.stream = stream
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.live: str | None = None
        self.dropped_live = 0
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self.thread = threading.Thread(target=self._write, name="hil-worker-out", daemon=True)
        self.thread.start()

    def send(self, event: str, **body: Any) -> None:
        self.lines.put(json.dumps({"ev": event, **body}, default=str, allow_nan=False))
        self._wake.set()

    def send_live(self, body: dict[str, Any]) -> None:
        line = json.dumps({"ev": "live", **body}, default=str, allow_nan=False)
        with self._lock:
            if self.live is not None:
                self.dropped_live += 1
            self.live = line
        self._wake.set()

    def close(self) -> None:
        self.lines.put(None)
        self._wake.set()
        self.thread.join(timeout=5.0)

    def _write(self) -> None:
        while True:
            self._wake.wait()
            self._wake.clear()
            while True:
                try:
                    line = self.lines.get_nowait()
                except queue.Empty:
                    break
                if line is None:
                    return
                if not self._put(line):
                    return
            with self._lock:
                live, self.live = self.live, None
            if live is not None and not self._put(live):
                return

    def _put(self, line: str) -> bool:
        try:
            self.stream.write(line + "\n")
            self.stream.flush()
        except (OSError, ValueError):  # the manager is gone: stdin's EOF ends the worker
            return False
        return True


def finite(value: Any) -> Any:
    """JSON has no NaN: a non-finite float becomes None."""
    return value if not isinstance(value, float) or math.isfinite(value) else None


@dataclass
class Running:
    """The item that runs now: the session it runs (once it exists), that session's event loop, and what the
    manager asked for (``end``: stop or abort)."""

    uid: str
    kind: str
    session: Session | None = None
    loop: asyncio.AbstractEventLoop | None = None
    cycles: int = 0
    total: int = 0
    end: str | None = None
    end_reason: str = ""
    child: subprocess.Popen[str] | None = None
    started_s: float = field(default_factory=time.monotonic)


class Worker:
    """One worker: the lab it holds (:meth:`open_lab`), the item it runs, the lines it sends."""

    def __init__(self, *, state_dir: Path, loopback: bool, lab_session: Path | None, emulator: Path | None,
                 seed: int, outbox: Outbox, emulator_cpu: int | None = -1, mqtt: Path | None = None) -> None:
        self.state_dir = state_dir
        self.loopback = loopback
        self.lab_session = lab_session
        self.emulator_config = emulator
        self.seed = seed
        # the service's own broker (hil serve --mqtt): every session and ident item publishes there, its password
        # read here from the service's configuration; without it an item's own mqtt section (no secret of ours)
        self.mqtt: MqttConfig | None = load_model(MqttConfig, mqtt) if mqtt is not None else None
        self.emulator_cpu = emulator_cpu  # placed as the shipped sessions place it (emulator.cpu: -1, the loop's)
        self.out = outbox
        self.emulator: EmulatorProcess | None = None
        self.lab: BenchLab | None = None
        self.claims: PortClaims | None = None
        self.running: Running | None = None
        self.item_task: asyncio.Task[None] | None = None
        self.identified: set[str] = set()  # boards that answered IDENT (the doctor's, or a session's links opened)
        self.lab_config: SessionConfig | None = None
        self.doctor_report: dict[str, Any] | None = None
        self.rest: dict[str, Any] | None = None  # the boards' rest state as last measured (wait_for_rest)
        # the items' 1 kHz loop threads run SCHED_FIFO where this process may (watching the bench must not move it)
        self.rt_refusal = fifo_refusal(SERVICE_RT_PRIORITY)
        self.rt_priority = 0 if self.rt_refusal else SERVICE_RT_PRIORITY
        self.boards_lock = asyncio.Lock()  # one of: an item, the doctor, the rest check has the ports open
        self.rest_task: asyncio.Task[None] | None = None

    # --- the lab -----------------------------------------------------------------------------------

    def open_lab(self) -> dict[str, str]:
        """Start the emulated lab (``loopback``) or read the lab's ports (``lab_session``), then claim them; the
        ports (link -> path). PortUnavailable or ConfigError: the service cannot serve."""
        if self.loopback:
            placement = EmulatorRef(cpu=self.emulator_cpu).process_args()
            self.emulator = EmulatorProcess(self.emulator_config, clock="realtime", seed=self.seed,
                                            extra_args=placement)
            try:
                started = self.emulator.start()
            except LinkError as exc:
                raise ConfigError(f"the emulated lab did not start: {exc}") from None
            ports = {name: path for name, path in started.items() if name in LINKS}
        else:
            assert self.lab_session is not None
            config = self.lab_config = load_session(self.lab_session)
            if config.ports is None:
                raise ConfigError(f"{self.lab_session}: ports: not set; the lab's session file names its ports")
            ports = {name: port.port for name in LINKS if (port := getattr(config.ports, name)) is not None}
        deadline = time.monotonic() + CLAIM_WAIT_S
        while True:
            try:
                self.claims = claim_ports(ports, holder_name())
                break
            except PortUnavailable as exc:
                if not predecessor(exc.holder) or time.monotonic() > deadline:
                    raise
                time.sleep(0.2)  # a previous worker of this lab is winding its item down
        self.lab = BenchLab({name: PortConfig(port=path) for name, path in ports.items()}, self.claims,
                            emulated=self.loopback, description="emulated lab (realtime)" if self.loopback else
                            str(self.lab_session), on_session=self._on_session)
        return ports

    def close_lab(self) -> None:
        if self.claims is not None:
            self.claims.release()
            self.claims = None
        if self.emulator is not None:
            self.emulator.stop()
            self.emulator = None

    def _on_session(self, session: Session) -> None:
        """A session of the running item exists (from its own thread and event loop)."""
        running = self.running
        if running is None:
            return
        running.session, running.loop = session, asyncio.get_running_loop()
        if running.end is not None:  # asked to end before the session existed
            self._end_session(running)

    async def check_rest(self, timeout_s: float = REST_TIMEOUT_S) -> dict[str, Any]:
        """Wait for the boards' rest state and measure it (hil.boards.wait_for_rest): driver disabled, stream idle,
        hexapod IDLE or LOADED at home; the result, kept for the status."""
        assert self.lab is not None
        ports = {n: p.port for n, p in self.lab.ports.items()
                 if n != "hexapod" or self.lab_config is None or self.lab_config.hexapod.driver_class.uses_link}
        bauds = {n: p.baudrate for n, p in self.lab.ports.items()}
        try:
            rest = (await wait_for_rest(ports, bauds, timeout_s=timeout_s)).as_dict()
        except (LinkError, OSError) as exc:
            rest = {"ok": False, "boards": {}, "summary": f"not measured: {exc}", "at": time.time()}
        self.rest = rest
        return rest

    async def _rest_between_items(self) -> None:
        """After an item: the boards' rest state measured for the status (the next item waits for it)."""
        async with self.boards_lock:
            await self.check_rest()
        self.out.send("status", **self.status())

    async def doctor(self, listen_s: float = 2.0) -> dict[str, Any]:
        """`hil doctor`'s checks on the ports this worker holds (between items only): each port, each board's
        IDENT and fingerprint, a listen to the servo stream. The driver is never enabled, the hexapod never moved."""
        assert self.lab is not None
        ports = {name: port.port for name, port in self.lab.ports.items()}
        bauds = {name: port.baudrate for name, port in self.lab.ports.items()}
        findings = [f for f in await asyncio.to_thread(check_ports, ports, bauds) if f.check != "holder"]  # it is us
        uses_link = self.lab_config is None or self.lab_config.hexapod.driver_class.uses_link
        asked = {name: port for name, port in ports.items() if (name != "hexapod" or uses_link)
                 and all(f.ok for f in findings if f.link == name and f.check == "port")}
        findings += await check_boards(asked, bauds, listen_s=listen_s, claimed=True)
        self.identified = {f.link for f in findings if f.check == "ident" and f.ok}
        self.doctor_report = {"at": time.time(), "ok": all(f.ok for f in findings),
                              "findings": [_json_safe(dataclasses.asdict(f)) for f in findings]}
        return self.doctor_report

    # --- items ------------------------------------------------------------------------------------

    def run(self, item: dict[str, Any]) -> None:
        if self.item_task is not None and not self.item_task.done():
            self.out.send("done", uid=item.get("uid"), status="invalid", exit_code=EXIT_INVALID,
                          message="an item is already running", log=None, summary={})
            return
        # running from now on, also while it waits for the boards (a stop or an abort meanwhile is kept, not lost)
        self.running = running = Running(str(item["uid"]), str(item["kind"]))
        self.item_task = asyncio.get_running_loop().create_task(self._run_item(running, item))

    async def _run_item(self, running: Running, item: dict[str, Any]) -> None:
        async with self.boards_lock:
            await self._run_item_at_rest(running, item)
        self.rest_task = asyncio.get_running_loop().create_task(self._rest_between_items())

    async def _run_item_at_rest(self, running: Running, item: dict[str, Any]) -> None:
        """One item, from the boards' rest state measured just before it (a fault if they do not come to rest)."""
        uid, kind = running.uid, running.kind
        out_dir = self.state_dir / "runs" / uid
        files = item.get("files") or {}
        try:  # again, just before it runs: its own files, its options
            checked = check_item(kind, str(item["file_name"]), str(item["body"]), files=files,
                                 options=item.get("options") or {}, emulated=self.loopback)
        except ItemError as exc:
            self.out.send("done", uid=uid, status="invalid", exit_code=EXIT_INVALID, message=str(exc), log=None,
                          summary={})
            self.running = None
            return
        try:  # whatever fails from here (its directory on a full disk, a bug), the manager hears how it ended
            out_dir.mkdir(parents=True, exist_ok=True)
            if self.lab is not None:  # who ran it goes into the log's provenance (never a token)
                self.lab.extra = {"provenance": {"submitted_by": str(item.get("user", "")), "service_item": uid}}
            rest = await self.check_rest()
            if not rest["ok"]:
                raise BoardsNotAtRest(f"the boards did not come to rest within {REST_TIMEOUT_S:g} s before it "
                                      f"started: {rest['summary']}; nothing was armed (hil bench doctor, and check "
                                      "the lab)")
            if running.end is not None:  # stopped or aborted while it waited for the boards: nothing was armed
                raise EndedBeforeStart(f"{running.end_reason or running.end}, before it started; nothing was armed")
            self.out.send("started", uid=uid, out_dir=str(out_dir), rest=rest)
            if kind == "campaign":
                done = await self._run_campaign(running, str(item["file_name"]), str(item["body"]), files, out_dir)
            else:
                done = await asyncio.to_thread(self._run_session, running, checked.config, kind, out_dir,
                                               checked.options)
        except EndedBeforeStart as exc:
            done = {"status": "stopped" if running.end == "stop" else "aborted", "exit_code": EXIT_STOPPED,
                    "message": str(exc), "log": None, "summary": {}}
        except BoardsNotAtRest as exc:
            done = {"status": "fault", "exit_code": 1, "message": str(exc), "log": None, "summary": {}}
        except (ConfigError, ValueError) as exc:  # refused before anything reached a board, or not fitted
            done = {"status": "invalid" if isinstance(exc, ConfigError) else "fault",
                    "exit_code": EXIT_INVALID if isinstance(exc, ConfigError) else 1,
                    "message": " ".join(str(exc).split()), "log": None, "summary": {}}
        except Exception as exc:  # a bug must end the item, not the worker: the lab stays served
            done = {"status": "fault", "exit_code": 1, "message": f"{type(exc).__name__}: {exc}", "log": None,
                    "summary": {}}
        done["status"] = ended_as(running, done["status"])
        if done["status"] == "aborted":  # an abort that overtook a stop (or a fault it caused) is an abort's exit
            done["exit_code"] = EXIT_ABORTED
        self.running = None
        self.rest = None  # unknown until measured after the item (_rest_between_items)
        self.out.send("done", uid=uid, **done)

    def _run_session(self, running: Running, config: Any, kind: str, out_dir: Path,
                     options: dict[str, Any]) -> dict[str, Any]:
        """A session or an ident item, in this thread (its own event loop), on the lab; then its report."""
        progress = self._progress(running)
        if self.mqtt is not None:
            config = config.model_copy(update={"mqtt": self.mqtt})
        if self.rt_priority and not config.host.rt_priority:
            host = config.host.model_copy(update={"rt_priority": self.rt_priority})
            config = config.model_copy(update={"host": host})
        figures: list[Figure] = []
        if kind == "ident":
            chosen = {k: v for k, v in options.items() if k in IDENT_OPTIONS}  # checked: IdentOptions
            try:
                ident = api.ident(config, out=out_dir, progress=progress, lab=self.lab, **chosen)
            except ConfigError:
                raise
            except ValueError as exc:  # it ran, and its log could not be fitted: the log still comes back
                logs = sorted(out_dir.glob("*.h5"))
                done = {"status": "fault", "exit_code": 1, "message": " ".join(str(exc).split()),
                        "log": str(logs[-1]) if logs else None, "summary": {}, "report": None}
                return with_report(running, done, logs[-1] if logs else None, {})
            result = ident.run
            extra = {"ident": ident.report} if ident.report else {}
            if ident.bode_png is not None:
                figures.append(Figure(ident.bode_png, f"{ident.bode_png.name}: the plant's frequency response and "
                                                      "its fit (hil ident)"))
        else:
            result = api.run(config, out=out_dir, progress=progress, lab=self.lab)
            extra = {}
        summary = {**(result.summary() if result.log_path is not None else {}), **extra}
        done = {"status": result.status, "exit_code": result.exit_code, "message": result.message,
                "log": str(result.log_path) if result.log_path else None, "summary": _json_safe(summary),
                "report": None}
        return with_report(running, done, result.log_path, summary, figures)

    async def _run_campaign(self, running: Running, file_name: str, body: str, files: dict[str, str],
                            out_dir: Path) -> dict[str, Any]:
        """A campaign item: `hil campaign` as a child process (its cells are child processes of their own), on the
        item's file and its own files written into ``out_dir/item`` as they were checked. On the emulated lab its
        cells run on their own emulators, as `hil campaign` runs them; on the lab's hardware on the lab's ports
        (whatever the submitted session says), the worker letting go of them while it runs (each cell claims them)
        and claiming them again after."""
        hardware = not self.loopback
        if hardware:
            body = campaign_on_ports(body, self._lab_ports())
        spec = write_item(out_dir / "item", file_name, body, files)
        cmd = [sys.executable, "-m", "hil", "campaign", str(spec), "--out", str(out_dir / "campaign"), "--json"]
        if hardware:
            cmd.append("--hardware")
            if self.claims is not None:
                self.claims.release()
        try:
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                    start_new_session=True)
            running.child = proc
            if running.end is not None:
                self._end_child(running)
            stdout, stderr = await asyncio.to_thread(proc.communicate)
        finally:
            if hardware and self.lab is not None:
                self.claims = await asyncio.to_thread(claim_ports, {n: p.port for n, p in self.lab.ports.items()},
                                                      holder_name())
                self.lab.claims = self.claims
        code = proc.returncode
        try:
            summary = json.loads(stdout) if stdout.strip() else {}
        except ValueError:
            summary = {}
        status = ("completed" if code == 0 else "invalid" if code == EXIT_INVALID else
                  "stopped" if running.end == "stop" else "aborted" if running.end == "abort" else "fault")
        report = Path(str((summary.get("report") or {}).get("html", out_dir / "campaign" / "report" / "report.html")))
        message = "" if code == 0 else (stderr.strip().splitlines() or [f"exit code {code}"])[-1]
        if code == 1 and summary and not summary.get("passed", True):
            status, message = "completed", "the campaign ran; its acceptance failed"
        return {"status": status, "exit_code": code, "message": message, "log": None,
                "summary": _json_safe(summary), "report": str(report) if report.is_file() else None}

    def _lab_ports(self) -> dict[str, Any]:
        """The lab's ports as a session's ``ports:`` section (its own session's, baud rates included)."""
        if self.lab_config is not None and self.lab_config.ports is not None:
            return self.lab_config.ports.model_dump(mode="json")
        assert self.lab is not None
        return {name: (self.lab.ports[name].model_dump(mode="json") if name in self.lab.ports else None)
                for name in LINKS}

    def _progress(self, running: Running) -> Callable[[int, int], None]:
        def progress(cycles: int, total: int) -> None:
            running.cycles, running.total = cycles, total
        return progress

    def end(self, how: str, reason: str) -> None:
        """Stop (the normal wind-down) or abort (the driver disabled first) the running item."""
        running = self.running
        if running is None:
            return
        if running.end != "abort":  # an abort outranks a stop
            running.end, running.end_reason = how, reason
        if running.child is not None:
            self._end_child(running)
        elif running.session is not None:
            self._end_session(running)

    def _end_session(self, running: Running) -> None:
        session, loop = running.session, running.loop
        if session is None or loop is None:
            return
        with contextlib.suppress(RuntimeError):  # its loop closed meanwhile: the session is over anyway
            if running.end == "abort":
                loop.call_soon_threadsafe(session.interrupt, signal.SIGINT, running.end_reason)
            else:
                loop.call_soon_threadsafe(session.stop, running.end_reason or "stopped")

    @staticmethod
    def _end_child(running: Running) -> None:
        with contextlib.suppress(ProcessLookupError):
            assert running.child is not None
            os.killpg(running.child.pid, signal.SIGINT)  # the campaign ends its cells the safe way

    # --- live values ------------------------------------------------------------------------------

    async def live_task(self) -> None:
        """The running item's latest values, LIVE_HZ times a second, read from its log's buffers (never from
        the loop's own state)."""
        period = 1.0 / LIVE_HZ
        last_sent: dict[str, Any] = {}  # per group, the host time of the row sent last
        while True:
            await asyncio.sleep(period)
            running = self.running
            if running is None:
                last_sent.clear()
                continue
            body: dict[str, Any] = {"uid": running.uid, "cycles": running.cycles, "total": running.total}
            session = running.session
            log = session.log if session is not None else None
            if log is not None:
                for group, names in LIVE_CHANNELS.items():
                    row = log.latest(group)
                    if row is None or row.get("t_host_ns") == last_sent.get(group):
                        continue  # nothing new in this group (a disarmed loop, a camera between frames)
                    last_sent[group] = row.get("t_host_ns")
                    body[group] = {name: finite(float(row[name])) for name in names}
                loop = session.loop_ if session is not None else None
                body["armed"] = bool(loop is not None and loop.armed)
            self.out.send_live(body)

    def status(self) -> dict[str, Any]:
        lab = self.lab
        running = self.running
        session = running.session if running is not None else None
        armed = bool(session is not None and session.loop_ is not None and session.loop_.armed)
        links = session.links if session is not None else {}
        self.identified |= set(links)
        boards = {name: {"port": port.port, "connected": name in links, "identified": name in self.identified,
                         "armed": armed and name in ("driver", "servo")}
                  for name, port in (lab.ports.items() if lab else [])}
        return {"boards": boards, "emulated": self.loopback, "doctor": self.doctor_report, "rest": self.rest,
                "rt_priority": self.rt_priority, "rt_refusal": self.rt_refusal,
                "safe": None if running is not None or self.rest is None else
                (self.rest["summary"] if self.rest["ok"] else f"NOT AT REST: {self.rest['summary']}")}


def ended_as(running: Running, status: str) -> str:
    """How an item ended: ``aborted`` when an operator aborted it, whatever way its session ended then."""
    return "aborted" if running.end == "abort" and status in ("interrupted", "fault", "stopped") else status


def report_dir(log: Path) -> Path:
    """Where a session's report goes: beside its log, named after it (``NAME-DATE-report/``), so that the files of
    several items brought back into one directory keep theirs apart."""
    return log.with_name(f"{log.stem}-report")


def with_report(running: Running, done: dict[str, Any], log: Path | None, summary: dict[str, Any],
                figures: list[Figure] | None = None) -> dict[str, Any]:
    """``done`` with the report of the session whose log is ``log`` (hil.reporting.write_session_report, its
    metrics ``summary``, else the log's own), linked as the item's report. A report that cannot be written leaves
    the item as it ended; its message says why."""
    if log is None or not log.is_file():
        return done
    status = ended_as(running, str(done["status"]))
    notes = [f"Service item {running.uid} ({running.kind}) ended {status}"
             + (f": {done['message']}" if done.get("message") else ".")]
    try:
        files = write_session_report(log, report_dir(log), summary or api.report_log(log), notes=notes,
                                     figures=figures or ())
    except Exception as exc:  # the item ran: whatever its report met, the item ends as it ended
        why = f"its report could not be written ({type(exc).__name__}: {' '.join(str(exc).split())})"
        return {**done, "message": "; ".join(m for m in (str(done.get("message") or ""), why) if m)}
    return {**done, "report": str(files.html)}


def campaign_on_ports(body: str, ports: dict[str, Any]) -> str:
    """A checked campaign's text with ``ports`` (a session's ``ports:`` section, every link named, None for one the
    lab lacks) last in its overrides: on the lab's hardware its cells open the lab's ports, never a submitted one."""
    data = parse_yaml(body)
    overrides = data.get("overrides") or {}
    data["overrides"] = {**overrides, "ports": {name: ports.get(name) for name in LINKS}}
    return yaml.safe_dump(data, sort_keys=False)


def _json_safe(obj: Any) -> Any:
    """``obj`` with NaN and infinities as None and paths as text: JSON for the manager."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, float):
        return finite(obj)
    if isinstance(obj, int | str | bool) or obj is None:
        return obj
    return str(obj)


async def serve(worker: Worker) -> int:
    """Open the lab, then obey the manager's lines until it says quit or goes away."""
    try:
        ports = await asyncio.to_thread(worker.open_lab)
    except (ConfigError, PortUnavailable, OSError) as exc:
        worker.out.send("fatal", message=" ".join(str(exc).split()))
        await asyncio.to_thread(worker.close_lab)
        return EXIT_INVALID
    try:
        await worker.doctor()
    except (LinkError, OSError, ValueError) as exc:  # the checks report; a check that cannot run is said so
        worker.doctor_report = {"at": time.time(), "ok": False, "findings": [], "error": str(exc)}
    await worker.check_rest()
    holder = PortHolder.this_process(holder_name())
    worker.out.send("ready", ports=ports, holder=holder.describe(), pid=os.getpid(), **worker.status())
    live = asyncio.get_running_loop().create_task(worker.live_task())
    reader = asyncio.StreamReader(limit=4 << 20)
    loop = asyncio.get_running_loop()
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
    try:
        while True:
            line = await reader.readline()
            if not line:  # the manager is gone: nothing may stay armed
                worker.end("abort", "the service's manager went away")
                break
            try:
                msg = json.loads(line)
            except ValueError:
                continue
            op = msg.get("op")
            if op == "run":
                worker.run(msg["item"])
            elif op in ("stop", "abort"):
                worker.end(op, str(msg.get("reason", op)))
            elif op == "status":
                worker.out.send("status", **worker.status())
            elif op == "doctor":
                if worker.running is not None or (worker.item_task is not None and not worker.item_task.done()):
                    worker.out.send("doctor", error="an item is running; the checks run between items")
                else:
                    async with worker.boards_lock:  # after the rest check between items, if one runs
                        report = await worker.doctor()
                    worker.out.send("doctor", **report)
                    worker.out.send("status", **worker.status())
            elif op == "quit":
                worker.end("abort", "the service is stopping")
                break
        if worker.item_task is not None:
            await worker.item_task
        if worker.rest_task is not None:
            worker.rest_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await worker.rest_task
    finally:
        live.cancel()
        await asyncio.to_thread(worker.close_lab)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hil.service._worker", description=__doc__.split("\n\n")[0])
    parser.add_argument("--state-dir", type=Path, required=True)
    parser.add_argument("--loopback", action="store_true")
    parser.add_argument("--lab", type=Path, default=None)
    parser.add_argument("--emulator", type=Path, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--emulator-cpu", type=int, default=None, help="pin the emulated lab to this CPU")
    parser.add_argument("--mqtt", type=Path, default=None, help="the service's broker (an MQTT section's YAML)")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the manager ends the worker (quit, or its stdin closing)
    stdout = os.fdopen(os.dup(sys.stdout.fileno()), "w", buffering=1)
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())  # a stray print must not corrupt the manager's lines
    outbox = Outbox(stdout)
    worker = Worker(state_dir=args.state_dir, loopback=args.loopback, lab_session=args.lab, emulator=args.emulator,
                    seed=args.seed, outbox=outbox, emulator_cpu=args.emulator_cpu, mqtt=args.mqtt)
    try:
        return asyncio.run(serve(worker))
    finally:
        outbox.close()


if __name__ == "__main__":
    sys.exit(main())
