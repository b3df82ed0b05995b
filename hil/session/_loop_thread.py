"""The realtime clock's 1 kHz loop in a thread of its own (docs/performance.md, "The loop thread").

While it runs, :class:`LoopThread` owns the hot direction of two links: it reads the servo link's file descriptor
(the event loop's transport stops reading it: ``pause_reading``) and writes DRIVE_CMD straight to the driver link's.
Per sample: ``select`` on the servo fd with the watchdog's remaining time as the timeout, ``os.read``, the decoder's
fixed-layout GYRO_SAMPLE path (:meth:`Decoder.fast_feed`), :meth:`ControlLoop.on_sample`, and DRIVE_CMD as one
precompiled ``pack`` plus CRC (:class:`FramePacker`) and one ``os.write``. The log row and the telemetry sample are
handed on without blocking (a bytearray append; a non-blocking pipe write). With a capture on the links (hil.link),
each read and each DRIVE_CMD written is queued for it as one tuple on a deque (its writer thread formats and writes).

Everything else stays on the event loop: every other servo frame (ACKs, LOOP_TIMING, IDENT, CLOCK_LATE) is handed
to it with ``call_soon_threadsafe`` and delivered by the link as if it had read it itself, and so are a trip, a
host stall, a lost link and the end of the run. No lock is taken on the hot path: the two threads share only
atomic operations (an ``itertools.count`` for sequence numbers, appends to a bytearray and a deque, single writes
of whole frames, which the tty layer does not interleave).

The watchdog (_watchdog) is the read timeout: the thread looks when its wait runs out, and also whenever it wakes
after that moment (a wait the host stretched: a stopped process restarts ``select`` with the time it had left, so
the silence must be judged on waking, whatever woke it). A silence past the timeout, seen on time, zeroes the drive
from this thread at once (DRIVE_DISABLE on the driver fd), disarms, and asks the session for the fault and any
recovery. A thread runs once; a recovery starts a new one (:meth:`stop` hands the servo link back to the event loop).

GIL: the event loop's callbacks and this thread take turns on the interpreter. Python's default switch interval
(5 ms) would let a callback that holds the GIL when a sample arrives delay the loop by up to 5 ms; while a loop
thread runs, the interval is ``GIL_SWITCH_S`` (docs/performance.md, "The loop thread").
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import select
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from hil.link import RX, TX, Link, LinkError
from hil.protocol import AxisMask, Board, ClockLate, DriveCmd, DriveDisable, Frame, GyroSample
from hil.protocol.framing import FramePacker
from hil.session._host import pin_this_thread, set_fifo
from hil.session._watchdog import Watchdog

READ_SIZE = 4096
GIL_SWITCH_S = 50e-6  # sys.setswitchinterval while a loop thread runs (see the module docstring)


def link_fd(link: Link) -> int | None:
    """The file descriptor under a link, None for a link without one (the sim clock's) or a closed one."""
    return link.fd


def clock_late_s(frames: list[Frame], tick: int) -> float:
    """How late the board said sample ``tick`` went out (its CLOCK_LATE follows the sample in the same write), 0 if
    it did not say so."""
    for frame in frames:
        msg = frame.message
        if msg.__class__ is ClockLate and msg.tick == tick:
            return float(msg.late_us) * 1e-6
    return 0.0


class DriveWriter:
    """DRIVE_CMD for the loop thread: one precompiled pack (sequence numbers shared with the link's encoder) and one
    ``os.write`` on the driver fd. A write the fd does not take whole (its buffer full: the board stopped reading)
    is counted in ``short_writes``; the board's decoder drops the broken frame and its stale timeout zeroes it."""

    def __init__(self, link: Link, fd: int) -> None:
        self.fd = fd
        self._drive = FramePacker(DriveCmd, link.encoder, Board.DRIVER).pack
        self._disable = FramePacker(DriveDisable, link.encoder, Board.DRIVER).pack
        self.short_writes = 0
        self._lock = link.write_lock
        cap = link.capture  # the driver link's capture: each write queued as (t_ns, link id, TX, bytes)
        self._capture = None if cap is None else cap.append
        self._capture_id = 0 if cap is None else cap.id

    def drive(self, tick: int, az_counts: int, el_counts: int) -> None:
        with self._lock:  # the link's: its sequence number, stamp and write go together (SerialLink._write)
            self._write(self._drive(tick, az_counts, el_counts))

    def disable_now(self) -> None:
        with self._lock:
            self._write(self._disable(AxisMask.BOTH))

    def _write(self, frame: bytes) -> None:
        capture = self._capture
        t_ns = time.monotonic_ns() if capture is not None else 0  # stamped before the write: captures sort by time
        try:
            n = os.write(self.fd, frame)
        except BlockingIOError:
            self.short_writes += 1
            return
        if n != len(frame):
            self.short_writes += 1
            frame = frame[:n]
        if capture is not None:
            capture((t_ns, self._capture_id, TX, frame))


class ControlLoopLike(Protocol):
    """What the thread needs of the session's control loop (hil.session.ControlLoop)."""

    armed: bool

    def on_sample(self, g: GyroSample, t_rx: int | None = None) -> None: ...


class LoopThread:
    """One run of the 1 kHz loop on ``servo``'s samples (see the module docstring).

    ``loop.on_sample(g, t_rx_ns)`` is the control loop (its drive writes through ``writer``); ``loop.armed`` says
    whether it drives, and the thread clears it on a trip or an error. The event loop hears of a trip through
    ``on_trip(silent_s)``, of a stall through the watchdog's ``on_host_stall``, of a lost servo link through
    ``servo.lost(exc)``, of an exception in the loop (the drive is disabled first) through ``on_error(reason)``.
    ``cpu``/``rt_priority``: the placement this thread takes for itself (hil.session._host); what it could not take is
    reported through ``on_info``."""

    def __init__(self, servo: Link, writer: DriveWriter, dog: Watchdog, loop: ControlLoopLike, *,
                 on_trip: Callable[[float], None], on_error: Callable[[str], None],
                 cpu: int | None = None, rt_priority: int = 0,
                 on_info: Callable[..., None] | None = None) -> None:
        fd = link_fd(servo)
        if fd is None:
            raise LinkError(f"{servo.name}: the loop thread needs a link with a file descriptor")
        self.servo = servo
        self.fd = fd
        self.writer = writer
        self.dog = dog
        self.loop = loop
        self.on_trip = on_trip
        self.on_error = on_error
        self.cpu = cpu
        self.rt_priority = rt_priority
        self.on_info = on_info
        self.aloop = asyncio.get_running_loop()
        self._stop = False
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._thread = threading.Thread(target=self._main, name="hil-loop", daemon=True)
        self._switch_before: float | None = None

    # --- from the event loop -------------------------------------------------------------------------

    def start(self) -> None:
        """Take the servo link's reading over from the event loop and start."""
        self.servo.pause_reading()
        self._switch_before = sys.getswitchinterval()
        sys.setswitchinterval(GIL_SWITCH_S)
        self._thread.start()

    def arm_watchdog(self) -> None:
        self.dog.arm()
        self._wake()

    def disarm_watchdog(self) -> None:
        self.dog.disarm()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    @property
    def native_id(self) -> int | None:
        """The thread's id for the OS (its CPU affinity, its scheduling), None before it starts."""
        return self._thread.native_id

    def stop(self, timeout_s: float = 1.0) -> None:
        """End the thread and give the servo link's reading back to the event loop (if the link is still open)."""
        self._stop = True
        self._wake()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1
        if self._switch_before is not None:
            sys.setswitchinterval(self._switch_before)
            self._switch_before = None
        if not self._thread.is_alive():
            self.servo.resume_reading()

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # closed, or already holds wake-ups
            os.write(self._wake_w, b"w")

    # --- the thread ------------------------------------------------------------------------------------

    def _place(self) -> None:
        if self.cpu is not None:
            try:
                pin_this_thread(self.cpu)
            except OSError as exc:
                self._info(loop_cpu=None, warning=f"loop thread not pinned to CPU {self.cpu}: {exc.strerror or exc}")
        if self.rt_priority:
            try:
                set_fifo(self.rt_priority)
                self._info(rt_priority=self.rt_priority, thread="hil-loop")
            except OSError as exc:
                self._info(rt_priority=0, warning=f"SCHED_FIFO {self.rt_priority} refused: {exc.strerror or exc}")

    def _info(self, **detail: Any) -> None:
        if self.on_info is not None:
            self.aloop.call_soon_threadsafe(lambda: self.on_info(**detail))  # type: ignore[misc]

    def _main(self) -> None:
        post = self.aloop.call_soon_threadsafe
        try:
            self._place()
            self._run(post)
        except Exception as exc:  # a bug here must end the session safely, not the thread silently
            self.loop.armed = False
            self._disable()
            post(self.on_error, f"loop thread failed: {type(exc).__name__}: {exc}")

    def _run(self, post: Callable[..., Any]) -> None:
        fd, wake = self.fd, self._wake_r
        rlist = [fd, wake]
        dog = self.dog
        clock = dog.clock
        feed = self.servo.decoder.fast_feed(GyroSample)
        deliver = self.servo.deliver
        on_sample = self.loop.on_sample
        monotonic_ns = time.monotonic_ns
        cap = self.servo.capture  # the servo link's capture: each read queued as (t_ns, link id, RX, bytes)
        capture = None if cap is None else cap.append
        cap_id = 0 if cap is None else cap.id
        due: float | None = None  # when the watchdog looks next (absolute, on its clock)
        last_tick: int | None = None  # of the last sample (a held silence that lost none is the host's)
        while not self._stop:
            if not dog.armed:
                due = None
            elif due is None:
                due = dog.last + dog.timeout_s
            ready = select.select(rlist, (), (), None if due is None else max(0.0, due - clock()))[0]
            if due is not None:
                now = clock()
                if now >= due:  # the wait ran out, or this thread was not run until after it did: look now
                    wait = dog.look(now, due)
                    if wait is None:
                        self._trip(now - dog.last)
                        due = None
                        continue
                    due = now + wait
            if not ready:
                continue
            if wake in ready:
                os.read(wake, 64)
                if fd not in ready:
                    continue
            try:
                data = os.read(fd, READ_SIZE)
            except BlockingIOError:
                continue
            except OSError as exc:
                self._lost(post, exc)
                return
            t_rx_ns = monotonic_ns()
            if not data:
                self._lost(post, None)
                return
            if capture is not None:
                capture((t_rx_ns, cap_id, RX, data))
            frames = feed(data)
            for frame in frames:
                msg = frame.message
                if msg.__class__ is GyroSample:
                    if dog.held:
                        lost = None if last_tick is None else (msg.tick - last_tick - 1) & 0xFFFFFFFF
                        if not dog.release(t_rx_ns * 1e-9, clock_late_s(frames, msg.tick), lost):
                            self._trip(t_rx_ns * 1e-9 - dog.last)
                            due = None
                    last_tick = msg.tick
                    dog.last = t_rx_ns * 1e-9
                    on_sample(msg, t_rx_ns)
                else:
                    post(deliver, frame)

    def _trip(self, silent_s: float) -> None:
        """Silence past the watchdog, seen on time: zero the drive from here at once, then tell the session."""
        self.dog.disarm()
        was_armed = self.loop.armed
        self.loop.armed = False
        if was_armed:
            self._disable()
        self.aloop.call_soon_threadsafe(self.on_trip, silent_s)

    def _disable(self) -> None:
        with contextlib.suppress(OSError):
            self.writer.disable_now()

    def _lost(self, post: Callable[..., Any], exc: OSError | None) -> None:
        self.loop.armed = False
        self._disable()
        post(self.servo.lost, LinkError(f"read failed: {exc}") if exc is not None else None)
