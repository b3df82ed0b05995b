"""A bench session: connect -> configure -> arm -> load and start the swing -> run -> stop the swing -> disarm.

The 1 kHz loop is driven by the servo board's GYRO_SAMPLE stream: :meth:`ControlLoop.on_sample` runs
on each sample and writes DRIVE_CMD k before it returns, so the board's clock is the loop's clock and
no asyncio timer paces anything. On the realtime clock (real boards, or the emulator in real time) it
runs in a thread of its own that reads the servo link itself (hil.session._loop_thread); in lockstep and sim it
runs inside the servo link's ``data_received`` on the event loop, where the world waits for it anyway.
The same ControlLoop code runs either way. Camera frames update the tracking loop when they arrive;
poses, board timing reports and link counters are logged as they come.

Safety: the watchdog (no GYRO_SAMPLE for ``watchdog_ms``; hil.session._watchdog), a lost link or a driver fault
zero the drive and DISABLE the driver at once, log a fault event, then stop or recover per config.
SIGINT and SIGTERM disable the driver first, stop the hexapod, close the log and end with 130 / 143.

One job: one session's life on the boards, from connecting to safe, with its faults and recoveries, as one state
machine whose every step reads and writes the same state (armed, disarmed, the swing's progress, the fault being
handled): split across files, each half would need the other's internals. The per-sample cycle
(_control_loop), the loop thread, the watchdog and the wind-down (_wind_down) live beside it.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import gc
import logging
import signal
import threading
import time
import traceback
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from hil._version import __version__
from hil.boards import DriverBoard, GuardedHexapod, ImageBoard, Interlock, InterlockClosed, ProtocolHexapod, ServoBoard
from hil.config import ConfigError, PortConfig, SessionConfig
from hil.control.oracle import TruthSource, truth_refusal
from hil.control.registry import needs_truth
from hil.control.start_pose import REACHED, StartPose
from hil.link import Capture, Link, LinkError, PortClaims, SerialLink, claim_ports
from hil.log import SessionLog, free_path
from hil.protocol import (
    LINKS,
    ClockLate,
    DriveStatus,
    Frame,
    GyroSample,
    Ident,
    LoopTiming,
    MissDistance,
)
from hil.protocol.swing import profile_end_s, resume_segments
from hil.session._control_loop import ControlLoop, LoopStats
from hil.session._host import (
    Placement,
    allowed_cpus,
    current_placement,
    pin_process,
    pin_this_thread,
    pin_this_thread_to,
    resolve_cpu,
    restore_placement,
    set_fifo,
)
from hil.session._loop_thread import DriveWriter, LoopThread, link_fd
from hil.session._provenance import collect_provenance
from hil.session._watchdog import EventLoopWatchdog, Watchdog
from hil.session._wind_down import HEXAPOD_HOME_S, TickSwingStart, TickWindDown
from hil.telemetry import Telemetry, TelemetryProcess, schema_units

_log = logging.getLogger("hil.session")
LinkOpener = Callable[[str, PortConfig, Callable[[Frame], None]], Awaitable[Link]]
HOST_ALIVE_S = 0.1  # HOST_ALIVE on every link this often (docs/protocol.md, "Host liveness")
EXIT_OK, EXIT_FAULT, EXIT_SIGINT, EXIT_SIGTERM = 0, 1, 130, 143
EXIT_STOPPED = 3  # ended early on request, the normal way (:meth:`Session.stop`: the service's stop)
EXIT_LOST_TARGET = 4  # ran to its end safely, but tracking was on and never acquired the target or lost it too long


@dataclass
class SessionResult:
    status: str  # completed | fault | interrupted | stopped | lost_target
    exit_code: int
    log_path: Path | None
    stats: LoopStats
    message: str = ""
    telemetry: dict[str, Any] = field(default_factory=dict)  # published, dropped, reconnects (MQTT on)
    capture: dict[str, Any] = field(default_factory=dict)  # path, records, bytes, dropped, error (capture_dir given)
    log_rows: int = 0  # loop rows in the log file (one per cycle while it was written)
    log_error: str | None = None  # why logging stopped early (the session then ended as a fault); None: it did not


def capture_for_session(directory: Path, config: SessionConfig, *, lockstep: bool, emulated: bool = False) -> Capture:
    """The capture of one session (:class:`Session`'s ``capture_dir``): its name, seed and controller in the
    header, and ``session_clock`` lockstep (an emulator in lockstep) or realtime (the lab, or the emulator
    paced). For a session against the emulator (``emulated``, or ``lockstep``, which only the emulator runs) also
    the emulator it ran against: ``emulator_config`` (the config file), ``emulator_clock`` and ``emulator_seed``,
    which a playback's fresh emulator is started with (hil.replay.replay_capture)."""
    meta: dict[str, Any] = {"session": config.name, "seed": config.seed, "controller": config.controller.name,
                            "session_clock": "lockstep" if lockstep else "realtime"}
    if lockstep or emulated:
        meta["emulator_config"] = str(config.emulator.config)
        meta["emulator_clock"] = "lockstep" if lockstep else "realtime"
        meta["emulator_seed"] = config.seed
    return Capture.create(directory, config.name, meta=meta)


class Session:
    """One run of a session config against the boards' serial ports (real or emulated) and its hexapod driver
    (``config.hexapod``: the protocol one on the fourth port, or a driver package's; docs/hexapod-drivers.md)."""

    def __init__(self, config: SessionConfig, ports: dict[str, PortConfig], out_dir: Path, *,
                 watchdog_ms: float | None = None, progress: Callable[[int, int], None] | None = None,
                 log_attrs: dict[str, Any] | None = None, lockstep: bool = False,
                 open_link: LinkOpener | None = None, watchdog: bool = True, emulated: bool = False,
                 capture_dir: Path | None = None, truth: TruthSource | None = None,
                 record_truth: Callable[[int], None] | None = None, claims: PortClaims | None = None) -> None:
        """``lockstep``: the boards are an emulator in lockstep (its world waits for the bench). The bench then
        sends no HOST_ALIVE, which would land at wall-clock moments and change the bytes of the run; the
        emulator judges host liveness by the lockstep itself (docs/protocol.md, "Host liveness").

        ``open_link(name, port, on_frame)`` opens each board's link (default: :meth:`SerialLink.open` on the
        port); the ``sim`` clock passes one that connects to an in-process world (hil.session._sim). ``watchdog``: run
        the sample watchdog (off only in ``sim``, where the world advances with the loop and wall time means
        nothing). ``emulated``: the boards are the emulator on this host, so ``safety.emulator_stall_grace_ms`` applies
        (_watchdog); ignored otherwise. ``capture_dir``: record every link's bytes, both directions, in a capture
        file there (hil.link, docs/capture.md); ValueError with ``open_link`` (the sim clock's links carry no bytes).
        ``truth``: the plant's true state, which only the sim clock has (PlantTruth); a controller that needs
        it (``oracle``) without it is refused here, ConfigError naming ``controller.name``, before anything starts.
        ``record_truth``: called with each loop row's sample counter (the sim clock's truth file, hil.log.truth).
        ``claims``: the ports already claimed by whoever holds them for longer than this session (the service's
        worker, hil.session.BenchLab); the session then claims nothing and lets go of nothing.

        The loop runs in its own thread (_loop_thread) unless ``lockstep`` or ``open_link`` is given: lockstep and
        sim keep it on the event loop, where the boards wait for it and a run's bytes are reproducible."""
        if truth is None and needs_truth(config.controller.name):
            clock = "lockstep" if lockstep else "realtime" if emulated else "hardware"
            raise ConfigError(truth_refusal(config.controller.name, clock))
        self.truth = truth
        self.record_truth = record_truth
        self.config = config
        self.ports = ports
        self.out_dir = out_dir
        self.watchdog_s = (watchdog_ms or config.safety.watchdog_ms) / 1000
        self.progress = progress
        self.extra_attrs = log_attrs or {}
        self.links: dict[str, Link] = {}
        self.servo: ServoBoard | None = None
        self.driver: DriverBoard | None = None
        self.image: ImageBoard | None = None
        self.hexapod: GuardedHexapod | None = None  # the session's driver (config.hexapod), behind the interlock
        self.hexapod_uses_link = config.hexapod.driver_class.uses_link  # else ports.hexapod is never opened
        self.log: SessionLog | None = None
        self.loop_: ControlLoop | None = None
        self.telemetry: Telemetry | None = None
        self.stop_reason: str | None = None
        self.exit_code = EXIT_OK
        self.log_path: Path | None = None
        self._finished: asyncio.Future[str] | None = None
        self._recovering = False
        self._placement_before: Placement | None = None
        self.lockstep = lockstep
        self.open_link = open_link
        self.use_watchdog = watchdog
        self.use_thread = not lockstep and open_link is None
        self.emulated = emulated
        self.stall_grace_s = config.safety.emulator_stall_grace_ms / 1000 if emulated else 0.0
        self.loop_thread: LoopThread | None = None
        self.event_watchdog: EventLoopWatchdog | None = None
        self._loop_cpu: int | None = None
        self.interlock = Interlock()  # closed for good when the session starts to end (finish)
        self._tasks: set[asyncio.Task[Any]] = set()
        self._recovery: asyncio.Task[Any] | None = None
        self._swing_started = False
        self._aloop: asyncio.AbstractEventLoop | None = None  # the session's event loop, once it runs
        self._t0 = time.monotonic()
        if capture_dir is not None and open_link is not None:
            raise ValueError("capture: these links pass messages, not bytes (the sim clock): nothing to capture; "
                             "run on the lockstep clock for the same run over ptys")
        self.capture_dir = capture_dir
        self.capture: Capture | None = None  # opened with the first link, closed after the last (_shutdown)
        self.claims: PortClaims | None = claims  # the ports this session owns, from run() to the end of _shutdown
        self._own_claims = claims is None  # else they are held for longer than the session (BenchLab)
        self._stop_request: str | None = None  # why stop() ended the session early
        self._swing_t0_s = 0.0  # session time (board clock) at which the hexapod's profile clock read 0 ...
        self._profile_offset_s = 0.0  # ... and the session profile's time then (not 0 once a swing was resumed)

    # --- frames from the boards ---------------------------------------------------------------------

    def _on_servo(self, frame: Frame) -> None:
        msg = frame.message
        kind = type(msg)
        if kind is GyroSample:  # the event loop's path (lockstep, sim); the loop thread takes samples itself
            if self.loop_ is not None:
                if self.event_watchdog is not None:
                    self.event_watchdog.feed()
                self.loop_.on_sample(msg)
        elif kind is ClockLate:
            if self.loop_ is not None:
                self.loop_.stats.clock_late += 1
        elif kind is LoopTiming:
            if self.loop_ is not None:
                self.loop_.on_timing(msg)
        elif kind is Ident and self.loop_ is not None and self.loop_.armed:
            self.fault("servo board reset (it announced itself mid-session)")

    def _on_driver(self, frame: Frame) -> None:
        msg = frame.message
        if type(msg) is DriveStatus and self.loop_ is not None:
            self.loop_.on_drive_status(msg)
            if self.loop_.armed and msg.faults & 0x03:
                self.fault(f"driver fault {msg.faults!r}: overcurrent, axes now disabled")
        elif type(msg) is Ident and self.loop_ is not None and self.loop_.armed:
            self.fault("driver board reset (it announced itself mid-session; the power stage is disabled)")

    def _on_image(self, frame: Frame) -> None:
        if type(frame.message) is MissDistance and self.loop_ is not None:
            self.loop_.on_miss(frame.message)

    def _on_hexapod(self, frame: Frame) -> None:
        if self.hexapod is not None:  # the driver keeps its state (HEXAPOD_STATUS) and reports poses
            self.hexapod.handle(frame)

    # --- phases -------------------------------------------------------------------------------------

    async def connect(self) -> None:
        handlers = {"servo": self._on_servo, "driver": self._on_driver, "image": self._on_image,
                    "hexapod": self._on_hexapod}
        for name in self._bench_links():
            await self._open(name, handlers[name])
        if not self.hexapod_uses_link:  # a driver with a connection of its own (or none): no link to open for it
            await self._hexapod_driver(None).identify()

    def _bench_links(self) -> tuple[str, ...]:
        """The links this session opens: the hexapod's only if its driver talks over it."""
        return LINKS if self.hexapod_uses_link else tuple(n for n in LINKS if n != "hexapod")

    def _hexapod_driver(self, link: Link | None) -> GuardedHexapod:
        """The session's hexapod driver, built from ``config.hexapod`` (on ``link`` if it uses the bench's link). A
        recovery that reopened the link builds a new one in place of the old, with the same callbacks."""
        cfg = self.config.hexapod
        driver = cfg.driver_class.create(cfg.options, link, self.interlock)
        if self.hexapod is None:
            self.hexapod = GuardedHexapod(driver, self.interlock, cfg.driver)
            self.hexapod.on_fault = lambda reason: self.fault(f"hexapod: {reason}")
        else:
            self.hexapod.replace(driver)
        return self.hexapod

    async def _open(self, name: str, handler: Callable[[Frame], None]) -> None:
        port = self.ports[name]
        if self.open_link is not None:
            link = await self.open_link(name, port, handler)
        else:
            if self.capture_dir is not None and self.capture is None:
                self.capture = capture_for_session(self.capture_dir, self.config, lockstep=self.lockstep,
                                                   emulated=self.emulated)
            link = await SerialLink.open(name, port.port, port.baudrate, handler, capture=self.capture)
        if self.lockstep:  # a resend would change the bytes of a lockstep run (docs/protocol.md, 6.1)
            link.retry_interval_s = 1.0
            # the world waits until the other boards' frames of a tick are handled before the tick's sample
            link.acknowledge = self.open_link is None and name != "servo"
        self.links[name] = link
        link.closed.add_done_callback(functools.partial(self._link_lost, name))
        if name == "hexapod":
            await self._hexapod_driver(link).identify()
            return
        kinds = {"servo": ServoBoard, "driver": DriverBoard, "image": ImageBoard}
        board = kinds[name](link, self.interlock)
        setattr(self, name, board)
        await board.identify()

    def _link_lost(self, name: str, fut: asyncio.Future[Any]) -> None:
        if self._finished is not None and not self._finished.done():
            self.fault(f"{name} link lost ({fut.result() or 'closed by the board'})")

    def _open_log(self) -> None:
        now = datetime.now(UTC)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.log_path = free_path(self.out_dir / f"{self.config.name}-{now:%Y%m%d-%H%M%S}.h5")
        idents = {name: getattr(self, name).ident_dict() for name in LINKS}

        emulated = self.extra_attrs.get("loopback", self.emulated or self.lockstep or self.open_link is not None)
        attrs = {"config": self.config.model_dump(mode="json"), "ident": idents, "software_version": __version__,
                 "seed": self.config.seed, "start_time_utc": now.isoformat(), "session_name": self.config.name,
                 "controller": self.config.controller.name, **({"clock": "lockstep"} if self.lockstep else {}),
                 **self.extra_attrs,  # the caller's own; a "provenance" of theirs adds to the bench's
                 "provenance": {**collect_provenance(self.config, emulated=bool(emulated)),
                                **self.extra_attrs.get("provenance", {})}}
        self.log = SessionLog(self.log_path, attrs=attrs, flush_interval_s=self.config.logging.flush_interval_s,
                              fsync=self.config.logging.fsync)
        aloop = asyncio.get_running_loop()

        def log_failed(reason: str) -> None:  # from the log's flusher thread
            with contextlib.suppress(RuntimeError):  # the event loop has closed: the session is over anyway
                aloop.call_soon_threadsafe(self._log_failed, reason)

        self.log.on_error = log_failed

    def _log_failed(self, reason: str) -> None:
        """Logging stopped (no space, directory gone, I/O error): a session whose data is lost is a fault, whatever
        ``safety.on_fault`` says; it ends through the normal safe wind-down."""
        if self.loop_ is not None:
            self.fault(reason, recoverable=False)
        self.finish("fault", reason)  # also while a recovery is under way (fault() leaves that one be)

    def _place(self) -> None:
        """The loop's CPU and scheduling class from ``config.host`` (hil.session._host); the helpers are already running
        and are moved off the loop's CPU. With a loop thread, the event loop goes with the helpers and the loop
        thread takes the CPU and the priority itself when it starts. Refusals are logged, never fatal."""
        host_cfg = self.config.host
        self._placement_before = current_placement()
        if host_cfg.loop_cpu is not None:
            helpers = [p for p in (self.log.writer_pid if self.log else None,
                                   getattr(self.telemetry, "pid", None)) if p is not None]
            try:
                cpus = allowed_cpus()
                cpu = resolve_cpu(host_cfg.loop_cpu, cpus)
                if self.use_thread:
                    self._loop_cpu = cpu
                    pin_this_thread_to(set(cpus) - {cpu})
                else:
                    pin_this_thread(cpu)
                for pid in helpers:
                    pin_process(pid, set(cpus) - {cpu})
                self.event("info", loop_cpu=cpu, helper_cpus=sorted(set(cpus) - {cpu}), helper_pids=helpers)
            except (OSError, ValueError) as exc:
                self.event("info", loop_cpu=None, warning=f"host.loop_cpu {host_cfg.loop_cpu} not applied: "
                           f"{getattr(exc, 'strerror', None) or exc}")
        prio = host_cfg.rt_priority
        if prio and not self.use_thread:
            try:  # this thread (the event loop) only; threads started later inherit it, children do not
                set_fifo(prio)
                self.event("info", rt_priority=prio)
            except OSError as exc:
                self.event("info", rt_priority=0, warning=f"SCHED_FIFO {prio} refused: {exc.strerror or exc}")

    def event(self, kind: str, **detail: Any) -> None:
        tick = (self.loop_.last_tick or 0) if self.loop_ else 0
        if _log.isEnabledFor(logging.INFO):  # `hil -v`: what the session does, as its log's events say it
            _log.info("%s %s: %s", self.config.name, kind, " ".join(f"{k}={v}" for k, v in detail.items()))
        if self.log is not None:
            self.log.event(kind, tick, detail)
        if self.telemetry is not None:
            self.telemetry.event(kind, **detail)

    def fault(self, reason: str, *, recoverable: bool = True) -> None:
        """Zero drive and DISABLE now, record it, then stop or recover per config (never once the session is
        ending: the interlock is closed then, and a fault only disables; never when not ``recoverable``)."""
        loop = self.loop_
        if loop is None or (not loop.armed and self._recovering):
            return
        loop.armed = False
        if self.driver is not None:
            with contextlib.suppress(LinkError, OSError):
                self.driver.disable_now()
        self.disarm_watchdog()
        loop.stats.faults.append(reason)
        self.event("fault", reason=reason)
        safety = self.config.safety
        if self.interlock.closed:
            return  # winding down already: no recovery, the session ends as it was going to
        if recoverable and safety.on_fault == "recover" and loop.stats.recoveries < safety.max_recoveries:
            self._recovering = True
            if self._recovery is not None and not self._recovery.done():  # one still resuming the swing
                self._recovery.cancel()
            self._recovery = self._spawn(self._recover(loop.t_s + (loop.t0_s or 0.0)), "recovery")
        else:
            self.finish("fault", reason)

    def _spawn(self, coro: Any, name: str) -> asyncio.Task[Any]:
        """A background task that cannot fail silently: an exception in it ends the session as a fault."""
        task = asyncio.get_running_loop().create_task(coro, name=f"hil-{name}")
        self._tasks.add(task)
        task.add_done_callback(lambda t: self._task_done(t, name))
        return task

    def _task_done(self, task: asyncio.Task[Any], name: str) -> None:
        self._tasks.discard(task)
        if task.cancelled():
            return
        exc = task.exception()
        if exc is not None:
            reason = f"{name} failed: {type(exc).__name__}: {exc}"
            self.event("fault", reason=reason)
            if self.loop_ is not None:
                self.loop_.stats.faults.append(reason)
            self.finish("fault", reason)

    def _on_host_stall(self, late_s: float, silent_s: float, by: str = "bench") -> None:
        """A silence of ``silent_s`` the host caused (_watchdog): the bench's watchdog looked ``late_s`` late
        (``by="bench"``), or the emulator's clock fired ``late_s`` late (``by="emulator"``, CLOCK_LATE)."""
        if self.loop_ is not None:
            self.loop_.stats.host_stalls += 1
        self.event("host_stall", late_by=by, late_ms=round(late_s * 1000, 2), silent_ms=round(silent_s * 1000, 2))

    def _stall_reporter(self) -> Callable[[float, float, str], None]:
        """The loop thread's watchdog's stall report, handed to the event loop."""
        aloop = asyncio.get_running_loop()

        def report(late_s: float, silent_s: float, by: str) -> None:
            aloop.call_soon_threadsafe(self._on_host_stall, late_s, silent_s, by)

        return report

    def _watchdog_trip(self, silent_s: float) -> None:
        self.fault(f"watchdog: no GYRO_SAMPLE for {silent_s * 1000:.1f} ms")

    def _arm(self) -> None:
        """The loop drives, and the watchdog watches it (from now)."""
        assert self.loop_ is not None
        self.loop_.armed = True
        if self.loop_thread is not None:
            self.loop_thread.arm_watchdog()
        elif self.event_watchdog is not None:
            self.event_watchdog.arm()

    def disarm_watchdog(self) -> None:
        if self.loop_thread is not None:
            self.loop_thread.disarm_watchdog()
        if self.event_watchdog is not None:
            self.event_watchdog.disarm()

    def _start_loop_thread(self) -> None:
        """A new loop thread on the servo and driver links as they are now (a thread runs once: a recovery that
        reopened a link starts another). Before the stream starts, so every sample goes to it."""
        assert self.loop_ is not None and self.servo is not None and self.driver is not None
        self._stop_loop_thread()
        fd = link_fd(self.driver.link)
        if fd is None:
            raise LinkError("driver: the loop thread needs a link with a file descriptor")
        writer = DriveWriter(self.driver.link, fd)
        loop = self.loop_
        loop.drive = writer.drive
        dog = Watchdog(self.watchdog_s, self._stall_reporter(), grace_s=self.stall_grace_s)
        self.loop_thread = LoopThread(
            self.servo.link, writer, dog, loop, on_trip=self._watchdog_trip, on_error=self.fault, cpu=self._loop_cpu,
            rt_priority=self.config.host.rt_priority, on_info=lambda **detail: self.event("info", **detail))
        self.loop_thread.start()

    def _stop_loop_thread(self) -> None:
        thread, self.loop_thread = self.loop_thread, None
        if thread is not None:
            thread.stop()
            if self.loop_ is not None:  # DRIVE_CMDs the driver fd did not take whole (its buffer full)
                self.loop_.stats.drive_short_writes += thread.writer.short_writes

    async def _recover(self, fault_t_s: float) -> None:
        """Wait, reopen what was lost, restart the stream, re-arm with fresh controller states, and put the swing
        back where it would be now if the hexapod stopped (:meth:`_resume_swing`).

        Every command that moves something goes through the interlock, so a recovery still under way when
        the session starts to end is refused (and cancelled by :meth:`finish`); any other failure ends the
        session as a fault with a "recovery failed" event."""
        assert self.loop_ is not None
        loop = self.loop_
        try:
            await asyncio.sleep(self.config.safety.recover_after_ms / 1000)
            handlers = {"servo": self._on_servo, "driver": self._on_driver, "image": self._on_image,
                        "hexapod": self._on_hexapod}
            reopened = set()
            for name in self._bench_links():
                link = self.links.get(name)
                if link is None or not link.is_open:
                    reopened.add(name)
                    for _ in range(50):
                        self.interlock.check(f"reopening {name}")
                        try:
                            await self._open(name, handlers[name])
                            break
                        except LinkError:
                            await asyncio.sleep(0.1)
                    else:
                        raise LinkError(f"{name}: did not come back within 5 s")
            assert self.servo is not None and self.driver is not None
            if self.use_thread:
                self.interlock.check("restarting the loop thread")
                self._start_loop_thread()
            # in the start's order: the loop drives from the restarted stream's first sample (in lockstep the
            # world waits for that answer), and the watchdog watches once the stream is on
            await self.driver.enable(clear_faults=True)
            self.interlock.check("re-arming")
            loop.reset_controllers()
            loop.last_tick = None
            loop.stats.recoveries += 1
            loop.armed = True
            await self.servo.start_stream()
            self._arm()
            await self._resume_swing(fault_t_s, fresh_driver="hexapod" in reopened)
            self._recovering = False
            self.event("recovered", recoveries=loop.stats.recoveries)
        except InterlockClosed as exc:
            self.event("info", recovery=f"abandoned: {exc}")
        except Exception as exc:  # any failure ends the session, with its reason logged
            reason = f"recovery failed: {type(exc).__name__ + ': ' if not isinstance(exc, LinkError) else ''}{exc}"
            self.event("fault", reason=reason)
            loop.stats.faults.append(reason)
            self.finish("fault", reason)
        finally:
            if self._recovery is None or self._recovery is asyncio.current_task():  # not one cancelled by a newer one
                self._recovering = False

    def profile_time_s(self) -> float:
        """Where the session's swing profile is now (s of its clock), by the servo board's clock: the profile runs
        from the swing's start whether or not the table follows it."""
        assert self.loop_ is not None
        return self._profile_offset_s + self.loop_.t_s - self._swing_t0_s

    async def _resume_swing(self, fault_t_s: float, *, fresh_driver: bool) -> None:
        """After a recovery: if the hexapod no longer runs the profile (its host timeout parked it: RUNNING ->
        STOPPING -> LOADED at home), load the rest of the profile from where it would be now and start it
        (docs/protocol.md 6.6 allows both in LOADED), logging a ``swing_gap`` event for the span the table did not
        swing (``from_t_s`` .. ``to_t_s``: the loop's ``t_s``, the servo board's clock, from the fault that led here),
        which the summary leaves out. A profile that would have ended by now is not restarted (the gap runs to the
        end). Raises LinkError, ending the session as a fault, when the hexapod cannot be brought back."""
        hexapod, loop = self.hexapod, self.loop_
        if not self._swing_started or hexapod is None or loop is None:
            return
        if fresh_driver:  # built anew on a reopened link: it knows the controller's state at its next report
            await hexapod.await_status(0.3)
        if hexapod.swinging:
            return
        segments = self.config.profile.protocol_segments()
        if hexapod.running and not await hexapod.wait_home(HEXAPOD_HOME_S):  # STOPPING: let it reach home first
            raise LinkError(f"hexapod: still {hexapod.state} {HEXAPOD_HOME_S:g} s after it stopped the swing; "
                            "cannot resume the profile")
        for _ in range(200):  # the profile's time comes from the board's clock: a sample of the restarted stream
            if loop.last_tick is not None:
                break
            await asyncio.sleep(0.005)
        t_profile_s = self.profile_time_s()
        parked = f"the hexapod had stopped the swing ({hexapod.state})"
        if t_profile_s >= profile_end_s(segments):
            self.event("swing_gap", from_t_s=fault_t_s, to_t_s=None, profile_s=round(t_profile_s, 3),
                       reason=f"{parked}; the profile would have ended by now")
            return
        rest = resume_segments(segments, t_profile_s)
        self.interlock.check("resuming the swing")
        await hexapod.load(rest)
        await hexapod.start()
        self._swing_t0_s, self._profile_offset_s = loop.t_s, t_profile_s
        self.event("swing_gap", from_t_s=fault_t_s, to_t_s=loop.t_s + (loop.t0_s or 0.0),
                   profile_s=round(t_profile_s, 3), reason=f"{parked}; resumed at the profile's time")

    # --- the start pose, then the swing -----------------------------------------------------------------

    def _start_pose_from_loop(self, pose: StartPose) -> None:
        """The loop's start pose phase decided, at a sample: from the loop's thread (realtime), or from the event
        loop inside the sample's handler (lockstep and sim)."""
        detail, failure = pose.describe(), (pose.failure() if pose.outcome != REACHED else None)
        if self.use_thread:
            assert self._aloop is not None
            self._aloop.call_soon_threadsafe(self._start_pose_decided, detail, failure, False)
        else:
            self._start_pose_decided(detail, failure, True)

    def _start_pose_decided(self, detail: dict[str, Any], failure: str | None, in_sample: bool) -> None:
        """The phase is logged; the pose reached, the swing starts (lockstep and sim with the emulated hexapod: at
        this very sample, :class:`TickSwingStart`); not reached, the session ends as a fault, nothing swung."""
        self.event("phase", **detail)
        if failure is not None:
            self.fault(failure, recoverable=False)
            return
        if not self.config.profile.protocol_segments() or self.hexapod is None or self.loop_ is None:
            return
        table = self.hexapod.driver
        if in_sample and self.lockstep and isinstance(table, ProtocolHexapod):
            self._swing_started = True  # from here on the shutdown always sends HEXAPOD_STOP
            TickSwingStart(self, self.loop_, table)
        else:
            self._spawn(self._start_swing(), "swing start")

    async def _start_swing(self) -> None:
        """HEXAPOD_START through the interlock, then :meth:`swing_began`. A session that began to end meanwhile (a
        signal, a fault: the interlock is closed) starts no swing, and that is no fault of its own."""
        assert self.hexapod is not None
        try:
            self.interlock.check("HEXAPOD_START")
            self._swing_started = True  # from here on the shutdown always sends HEXAPOD_STOP
            await self.hexapod.start()
        except InterlockClosed as exc:
            self.event("info", swing=f"not started: {exc}")
            return
        self.swing_began()

    def swing_began(self) -> None:
        """The hexapod acknowledged HEXAPOD_START: the profile's t = 0 is now, near enough."""
        assert self.loop_ is not None
        self._swing_started = True
        self._swing_t0_s = self.loop_.t_s
        self.event("state", state="swing started", segments=len(self.config.profile.protocol_segments()))

    def _on_pose(self, t_profile_s: float, pose: tuple[float, ...]) -> None:
        """A POSE, its time on the session's profile clock (a resumed profile's clock starts again at 0)."""
        if self.loop_ is not None:
            self.loop_.on_pose(t_profile_s + self._profile_offset_s, pose)

    def finish(self, status: str, message: str = "") -> None:
        """The session ends: close the interlock (nothing enables, streams or swings again), cancel a recovery
        under way, and let :meth:`run` wind down."""
        self.interlock.close(f"session {status}" + (f": {message}" if message else ""))
        if self._recovery is not None and not self._recovery.done():
            self._recovery.cancel()
            self.event("info", recovery="cancelled: the session is ending")
        if self._finished is not None and not self._finished.done():
            self.stop_reason = message
            self._finished.set_result(status)

    def stop(self, reason: str = "stopped on request") -> None:
        """End the session early the normal way (the service's stop): the swing is stopped while the loop still
        stabilizes, then the driver is disabled, as at the end of the duration; status ``stopped``, exit code
        EXIT_STOPPED. Call it on the session's event loop. :meth:`interrupt` disables the driver first instead."""
        if self._finished is not None and not self._finished.done():
            self._stop_request = reason
            try:
                self.event("info", stop=reason)
            finally:  # whatever recording it did, the session ends
                self.finish("completed", reason)

    def interrupt(self, signum: int = signal.SIGINT, reason: str = "") -> None:
        """End the session as SIGINT (or ``signum``) would: the driver disabled first, then the usual wind-down.
        For a caller that runs the session off the main thread (a notebook, the service), where signals do not reach
        it; call it on the session's event loop (``loop.call_soon_threadsafe(session.interrupt)``). ``reason``: who
        asked and why (the service's abort), in the log's ``signal`` event and the result's message."""
        self._on_signal(signum, reason)

    def _on_signal(self, signum: int, reason: str = "") -> None:
        try:
            if self.driver is not None:  # the driver first, before anything else
                with contextlib.suppress(LinkError, OSError):
                    self.driver.disable_now()
            if self.loop_ is not None:
                self.loop_.armed = False
            self.exit_code = EXIT_SIGINT if signum == signal.SIGINT else EXIT_SIGTERM
            self.event("signal", signal=signal.Signals(signum).name, **({"reason": reason} if reason else {}))
        finally:  # whatever failed above, the session ends
            self.finish("interrupted", reason or signal.Signals(signum).name)

    async def _host_alive_task(self) -> None:
        """HOST_ALIVE on every open link every HOST_ALIVE_S, until the end of the shutdown: the boards' host
        timers expire only when the bench is really gone (docs/protocol.md, "Host liveness")."""
        while True:
            uptime_ms = round((time.monotonic() - self._t0) * 1000)
            for board in (self.servo, self.driver, self.image, self.hexapod):  # a recovery may reopen one
                if board is not None:
                    with contextlib.suppress(LinkError, OSError):
                        board.alive(uptime_ms)
            await asyncio.sleep(HOST_ALIVE_S)

    async def _progress_task(self) -> None:
        total = round(self.config.duration_s * 1000)
        while self.progress is not None:
            self.progress(self.loop_.stats.cycles if self.loop_ else 0, total)
            await asyncio.sleep(0.1)

    def claim_ports(self) -> None:
        """Claim every port this session opens (hil.link), before any is opened: PortUnavailable (bad input, one
        line naming the port and its holder) if one is missing, not a serial port, or held by another bench. The
        sim clock's links open no port."""
        if self.open_link is not None or self.claims is not None:
            return
        self.claims = claim_ports({name: self.ports[name].port for name in self._bench_links()}, self.config.name)

    async def run(self) -> SessionResult:
        """Run the session to its end and return how it ended. Raises PortUnavailable, having opened nothing, if
        its ports cannot be claimed (:meth:`claim_ports`)."""
        self.claim_ports()
        try:
            return await self._run()
        finally:
            if self.claims is not None and self._own_claims:
                self.claims.release()
                self.claims = None

    async def _run(self) -> SessionResult:
        aloop = self._aloop = asyncio.get_running_loop()
        self._finished = aloop.create_future()
        # Signals reach only the main thread's loop; a session run from a worker thread (hil.run inside a
        # notebook's loop) ends on its caller's terms instead.
        signals = (signal.SIGINT, signal.SIGTERM) if threading.current_thread() is threading.main_thread() else ()
        for sig in signals:
            aloop.add_signal_handler(sig, self._on_signal, sig)
        status, message = "fault", ""
        try:
            await self.connect()
            assert self.servo and self.driver and self.image and self.hexapod
            if not self.lockstep:
                self._spawn(self._host_alive_task(), "HOST_ALIVE")
            await self.servo.configure()
            await self.image.track(self.config.tracking.enabled, self.config.tracking.gate_px)
            self._open_log()
            assert self.log is not None
            if self.config.mqtt is not None:
                self.telemetry = TelemetryProcess(self.config.mqtt,  # units from the log's schema, already here
                                                  self.log_path.stem if self.log_path else "session",
                                                  units=schema_units())
                await self.telemetry.start()
            self._place()
            aloop_ = asyncio.get_running_loop()

            def done_in_thread() -> None:
                aloop_.call_soon_threadsafe(self.finish, "completed")

            self.loop_ = ControlLoop(self.config, self.driver.drive, self.log, telemetry=self.telemetry,
                                     duration_ticks=round(self.config.duration_s * 1000),
                                     on_done=done_in_thread if self.use_thread else self._duration_done,
                                     truth=self.truth, record_truth=self.record_truth,
                                     on_start_pose=self._start_pose_from_loop)
            self.loop_.decoders = {name: link.decoder for name, link in self.links.items()}
            self.hexapod.on_pose = self._on_pose
            self.event("state", state="configured")
            if self.claims is not None and self.claims.taken_over:  # their holders died without letting go
                self.event("info", ports_taken_over={n: h.describe() for n, h in self.claims.taken_over.items()})
            segments = self.config.profile.protocol_segments()
            if segments:  # before the driver is enabled: a profile the hexapod refuses ends the session unarmed
                await self.hexapod.load(segments)
                self.event("state", state="profile loaded", segments=len(segments))
            await self.driver.enable(clear_faults=True)
            self.interlock.check("arming")  # a signal may have come while the ACK was on its way
            self.loop_.armed = True  # it drives from the first sample; the watchdog watches once the stream is on
            self.event("state", state="armed")
            if segments and self.loop_.start_pose is None:  # no start pose phase: the swing starts with the stream
                await self._start_swing()  # the profile's t = 0, near enough: the stream starts below
            if self.telemetry:
                self.telemetry.state("running", controller=self.config.controller.name)
            if self.use_thread:
                self._start_loop_thread()
            elif self.use_watchdog:
                self.event_watchdog = EventLoopWatchdog(self.watchdog_s, self._watchdog_trip, self._on_host_stall)
            # what setup built (imports, configs, the log, the controllers) lives as long as the session: moved to
            # the permanent generation, a full collection in the 1 kHz loop traverses only what the loop allocates
            # (a full collection of this process took ~21 ms, four times the default watchdog)
            gc.freeze()
            await self.servo.start_stream()
            self.interlock.check("arming the watchdog")
            self._arm()
            if self.progress is not None:
                self._spawn(self._progress_task(), "progress")
            status = await self._finished
            message = self.stop_reason or ""
            if status == "completed":
                await self._wind_down()
        except InterlockClosed:  # a signal or a fault ended the session while it was still setting up
            status = await self._finished if self._finished.done() else "fault"
            message = self.stop_reason or ""
        except LinkError as exc:
            status, message = "fault", str(exc)
            self.event("fault", reason=message)
        except Exception as exc:  # whatever went wrong, the boards end safe and the log says why
            status, message = "fault", f"{type(exc).__name__}: {exc}"
            self.event("fault", reason=message, traceback=traceback.format_exc(limit=8))
        finally:
            self.finish(status, message)
            shutdown = asyncio.ensure_future(self._shutdown())
            while not shutdown.done():  # a cancellation waits for the boards to be left safe and the log closed
                try:
                    await asyncio.shield(shutdown)
                except asyncio.CancelledError:
                    continue
            shutdown.result()
            for sig in signals:
                aloop.remove_signal_handler(sig)
        log_error = self.log.error if self.log is not None else None
        if log_error is not None and status == "completed":  # it failed at the very end (the last flush, closing)
            status, message = "fault", log_error
            if self.loop_ is not None:
                self.loop_.stats.faults.append(log_error)
        if status == "fault" and self.exit_code == EXIT_OK:
            self.exit_code = EXIT_FAULT
        if status == "completed" and self._stop_request is not None:
            status, message, self.exit_code = "stopped", self._stop_request, EXIT_STOPPED
        verdict = self.loop_.track_judge.verdict() if self.loop_ is not None and self.config.tracking.enabled else None
        if status == "completed" and verdict is not None:  # it ran safely, but did not do what it was for
            status, message, self.exit_code = "lost_target", verdict, EXIT_LOST_TARGET
        stats = self.loop_.stats if self.loop_ else LoopStats()
        telemetry = dataclasses.asdict(self.telemetry.stats) if self.telemetry is not None else {}
        capture = self.capture.summary() if self.capture is not None else {}
        log_path = self.log_path if self.log_path is not None and self.log_path.is_file() else None
        if self.log_path is not None and log_path is None and log_error is None:
            log_error = f"{self.log_path}: the log file is gone"
        return SessionResult(status, self.exit_code, log_path, stats, message, telemetry, capture,
                             log_rows=self.log.rows.get("loop", 0) if self.log is not None else 0,
                             log_error=log_error)

    _ticked: TickWindDown | None = None  # lockstep and sim: the wind-down by the boards' ticks (_duration_done)

    def _duration_done(self) -> None:
        """The loop's last sample of the session (lockstep and sim: on the event loop, inside the sample's handler).
        The wind-down then goes by ticks from the next sample (:class:`TickWindDown`), unless a hexapod driver outside
        the emulated world swings (it moves in wall time)."""
        loop, hexapod = self.loop_, self.hexapod
        table = hexapod.driver if hexapod is not None and self._swing_started else None
        if (self.lockstep and loop is not None and loop.armed and self.servo is not None
                and (table is None or isinstance(table, ProtocolHexapod))):
            self._ticked = TickWindDown(self, loop, self.servo, table, world_waits=self.open_link is None)
        self.finish("completed")

    async def _wind_down(self) -> None:
        """Normal end: stop the swing while still stabilizing, wait until it rests, then disarm.

        Lockstep and sim, with the emulated hexapod: by the boards' ticks (:class:`TickWindDown`), so the run is
        reproducible to its last row. Otherwise in wall time, as the real hexapod moves."""
        assert self.hexapod is not None
        if self._ticked is not None:
            await self._ticked.wait()
            return
        if self._swing_started:
            with contextlib.suppress(LinkError):
                await self.hexapod.stop()
                self.event("state", state="swing stopping")
                if not await self.hexapod.wait_home(HEXAPOD_HOME_S):
                    self.event("info", hexapod=f"still {self.hexapod.state} {HEXAPOD_HOME_S:g} s after the stop")

    async def _shutdown(self) -> None:
        """Driver first, then the swing, the stream, telemetry and the log. Never raises.

        Runs with the interlock closed and every background task but HOST_ALIVE ended, so nothing can undo
        it; the event ``state: safe`` records what each board confirmed."""
        if self.loop_ is not None:
            self.loop_.armed = False
        self.disarm_watchdog()
        self._stop_loop_thread()  # the event loop reads the servo link again (the ACKs of the shutdown)
        alive = [t for t in self._tasks if t.get_name() == "hil-HOST_ALIVE"]
        others = [t for t in self._tasks if t not in alive]
        for task in others:
            task.cancel()
        if others:
            await asyncio.gather(*others, return_exceptions=True)
        outcome: dict[str, str] = {}
        for what, step in (("driver", self._disarm), ("hexapod", self._stop_swing), ("stream", self._stop_stream)):
            try:
                outcome[what] = await step()
            except (LinkError, OSError, TimeoutError) as exc:
                outcome[what] = f"not confirmed: {exc}"
        if self.loop_ is not None or self.log is not None:
            self.event("state", state="safe", **outcome)
        for task in alive:
            task.cancel()
        if alive:
            await asyncio.gather(*alive, return_exceptions=True)
        if self.loop_ is not None:
            self.event("summary", **self.summary_detail())
        if self.telemetry is not None:
            self.telemetry.state("stopped")
            with contextlib.suppress(Exception):
                await self.telemetry.stop()
            if self.log is not None:
                self.log.event("telemetry", self.loop_.last_tick or 0 if self.loop_ else 0,
                               dataclasses.asdict(self.telemetry.stats))
        if self.hexapod is not None:  # its last reports stop here: nothing reaches a closed log
            self.hexapod.on_pose = self.hexapod.on_fault = None
            with contextlib.suppress(LinkError, OSError):
                await self.hexapod.close()
        if self.log is not None:
            self.log.close()
        for link in self.links.values():
            link.close()
        closing = [link.closed for link in self.links.values() if not link.closed.done()]
        if closing:  # the transport closes its port in an executor: wait, or its descriptors outlive the session
            await asyncio.wait(closing, timeout=2.0)
        if self.capture is not None:  # every link closed: the capture has all their bytes
            self.capture.close()
        if self._placement_before is not None:  # the process may go on (a test, a script): give the thread back
            with contextlib.suppress(OSError):
                restore_placement(self._placement_before)

    async def _disarm(self) -> str:
        if self.driver is None or not self.driver.link.is_open:
            return "no link" if self.driver is not None else "never connected"
        self.driver.disable_now()
        await self.driver.disable()
        self.event("state", state="disarmed")
        return "disabled"

    async def _stop_swing(self) -> str:
        if not self._swing_started:
            return "never started"
        if self.hexapod is None or not self.hexapod.connected:
            return "no link"
        await self.hexapod.stop()  # always accepted, also when it has already stopped
        return "stopped"

    async def _stop_stream(self) -> str:
        if self.servo is None or not self.servo.link.is_open:
            return "no link" if self.servo is not None else "never connected"
        await self.servo.stop_stream()
        return "idle"

    def summary_detail(self) -> dict[str, Any]:
        st = self.loop_.stats if self.loop_ else LoopStats()
        lat = sorted(st.latency_us)
        pick = (lambda q: round(lat[min(len(lat) - 1, int(q * len(lat)))], 1)) if lat else (lambda q: None)
        return {"cycles": st.cycles, "late": st.late, "missed": st.missed, "latency_us_p50": pick(0.5),
                "latency_us_p99": pick(0.99), "faults": st.faults, "recoveries": st.recoveries,
                "host_stalls": st.host_stalls, "clock_late": st.clock_late,
                "drive_short_writes": st.drive_short_writes,
                "link_errors": {n: link.decoder.counters.errors() for n, link in self.links.items()},
                **({"tracking": self.loop_.track_judge.as_dict()} if self.loop_ and self.config.tracking.enabled
                   else {})}


