"""The emulated lab in one process: the plant, the four boards on their ptys, the clock and the faults.

Clock modes (docs/emulator.md):

- realtime: the world advances one 1 ms tick at each deadline of a precise clock (select-sleep
  then spin, never asyncio timers); the driver applies whatever command arrived last.
- lockstep: after GYRO_SAMPLE k goes out, the world waits for DRIVE_CMD k (or
  ``lockstep_timeout_ms``, counted), then advances one tick with it. Frames the host sent after
  DRIVE_CMD k are handled after that step, whatever the read chunking, so the same seed, config
  and commands give the same bytes on every link. While the stream is off the world is frozen (so
  commands sent before STREAM take effect at tick 0); while the servo link is not delivering
  (stall, latency spike, disconnect) time runs in real time, so the host's watchdog sees the gap.

Host liveness (docs/protocol.md, "Host liveness"): in realtime each board's host timer counts world
ticks, checked in ``step`` only when the earliest expiry is due (one comparison per tick). In lockstep
the boards share one wall-clock timer (the last host frame on any link), judged only when a wait for the host
(DRIVE_CMD, LOCKSTEP_ACK) gives up, against max(host_timeout_ms, lockstep_timeout_ms): a slow but live host never
changes a lockstep run's bytes, and a frozen world (stream off) is never judged.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import tempfile
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

from firmware_stub.boards import DriverBoard, EmulatedBoard, HexapodBoard, ImageBoard, ServoBoard
from firmware_stub.clock import Readers, poll_readers, wait_for, wait_until
from firmware_stub.config import ClockMode, EmulatorConfig, LinkFaults, LinkName, ScheduledFault
from firmware_stub.control import ControlServer
from firmware_stub.link import BoardLink, FaultRecorder
from firmware_stub.plant import CarrierMotion, Plant, load_plant_config
from hil.protocol import BITS_PER_BYTE, CATALOGUE, Board, DriveCmd, Frame
from hil.protocol.swing import Envelope

TICK_S = 1e-3
NEVER = 1 << 62  # a tick that never comes
BOARD_IDS = {LinkName.SERVO: Board.SERVO, LinkName.DRIVER: Board.DRIVER, LinkName.IMAGE: Board.IMAGE,
             LinkName.HEXAPOD: Board.HEXAPOD}


def hexapod_envelope(plant: Plant) -> Envelope:
    """The hexapod's limits from the plant config, in HexAxis order (mm and deg)."""
    h = plant.config.hexapod
    x, y, z, roll, pitch, yaw = h.x, h.y, h.z, h.roll, h.pitch, h.yaw
    return Envelope(
        (x.position_mm, y.position_mm, z.position_mm, roll.angle_deg, pitch.angle_deg, yaw.angle_deg),
        (x.rate_mm_s, y.rate_mm_s, z.rate_mm_s, roll.rate_dps, pitch.rate_dps, yaw.rate_dps),
        (x.accel_mm_s2, y.accel_mm_s2, z.accel_mm_s2, roll.accel_dps2, pitch.accel_dps2, yaw.accel_dps2),
    )


class Emulator:
    """The world the boards live in. ``run()`` blocks until ``request_stop()`` (or max_ticks)."""

    def __init__(self, config: EmulatorConfig, *, run_dir: Path | None = None, fault_log: Path | None = None,
                 fingerprint: int = CATALOGUE.fingerprint, link_factory: type[BoardLink] = BoardLink,
                 control: bool = True) -> None:
        """``link_factory`` makes each board's link (a pty by default; :class:`firmware_stub.sim.MessageLink`
        passes messages in-process); ``control``: open the control socket."""
        self.config = config
        self.tick = 0
        self.deadline: float | None = None
        self.stop_requested = False
        self.lockstep_timeouts = 0
        self._own_run_dir = run_dir is None
        self.run_dir = Path(tempfile.mkdtemp(prefix="hil-emu-")) if run_dir is None else run_dir
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.recorder = FaultRecorder(fault_log)
        self.plant = Plant(load_plant_config(config.plant), config.seed)
        wire = self.wire_time = config.links.wire_time
        self.links = {name: link_factory(name, BOARD_IDS[name], self.run_dir, config.link_faults(name),
                                      seed=config.seed, recorder=self.recorder,
                                      byte_time_s=BITS_PER_BYTE / config.links.link(name).baudrate if wire else 0.0)
                      for name in LinkName}
        # lockstep and sim: DRIVE_CMD k acts this long after tick k (the sample's wire, the host, the command's wire);
        # whole ticks of it wait in a delay line, the rest splits the tick's hold (Plant.step_tick)
        self.drive_delay_s = config.drive_delay_s()
        whole_ticks = int(self.drive_delay_s / TICK_S + 1e-9)
        self._drive_in_tick_s = self.drive_delay_s - whole_ticks * TICK_S
        self._drive_line: deque[tuple[float, float]] = deque([(0.0, 0.0)] * whole_ticks, maxlen=whole_ticks + 1)
        self.servo = ServoBoard(self, self.links[LinkName.SERVO], fingerprint)
        self.driver = DriverBoard(self, self.links[LinkName.DRIVER], fingerprint)
        self.image = ImageBoard(self, self.links[LinkName.IMAGE], fingerprint)
        self.hexapod = HexapodBoard(self, self.links[LinkName.HEXAPOD], hexapod_envelope(self.plant), fingerprint)
        self.boards: dict[LinkName, EmulatedBoard] = {
            LinkName.SERVO: self.servo, LinkName.DRIVER: self.driver, LinkName.IMAGE: self.image,
            LinkName.HEXAPOD: self.hexapod}
        self._link_list = tuple(self.links.values())
        self._before_sample = (self.driver, self.hexapod, self.image)  # then the servo's GYRO_SAMPLE
        self._acked_links = tuple(self.links[name] for name in (LinkName.DRIVER, LinkName.HEXAPOD, LinkName.IMAGE))
        self.lockstep = config.clock is ClockMode.LOCKSTEP
        self.inbox: dict[LinkName, deque[tuple[Frame, float]]] = {name: deque() for name in LinkName}
        self.schedule: deque[ScheduledFault] = deque(sorted(config.faults, key=lambda f: f.at_s))
        self.awaiting: int | None = None  # lockstep: the tick whose DRIVE_CMD releases the next step
        self.released = False
        # host liveness: realtime, the next world tick at which a board's host timer may expire; lockstep,
        # the perf_counter() time of the last host frame on any link (the boards' shared timer)
        realtime_timer = config.clock is ClockMode.REALTIME and config.boards.host_timeout_ms > 0
        self.host_check_tick = self.servo.host_timeout_ticks if realtime_timer else NEVER
        self.host_heard_s = -math.inf
        self.control = ControlServer(self.run_dir / "control.sock", self.handle_control) if control else None
        self.started_wall = time.time()

    # --- what the host connects to -----------------------------------------------------------------

    def ports(self) -> dict[str, str]:
        """Board -> serial port path (stable symlinks), plus the control socket."""
        ports = {name.value: str(link.path) for name, link in self.links.items()}
        return ports if self.control is None else {**ports, "control": str(self.control.path)}

    # --- inputs ------------------------------------------------------------------------------------

    def readers(self) -> Readers:
        readers: dict[int, Callable[[float], None]] = {} if self.control is None else self.control.fds()
        for name, link in self.links.items():
            if link.fd is not None:
                def on_readable(t: float, name: LinkName = name) -> None:
                    self._on_readable(name, t)
                readers[link.fd] = on_readable
        return readers

    def _on_readable(self, name: LinkName, t_rx: float) -> None:
        self.inbox[name].extend((frame, t_rx) for frame in self.links[name].receive())
        self.drain(name)

    def drain(self, name: LinkName) -> None:
        """Hand the frames waiting from ``name`` to its board (lockstep: the driver's stop after the awaited
        DRIVE_CMD; the rest wait for the step)."""
        box, board = self.inbox[name], self.boards[name]
        while box and not (name is LinkName.DRIVER and self.released):
            frame, t_rx = box.popleft()
            if not board.receive(frame, t_rx):
                continue  # dropped and counted by the board
            self.host_heard_s = max(self.host_heard_s, t_rx)  # held driver frames may be handled after later ones
            if self.awaiting is not None and type(frame.message) is DriveCmd and frame.message.tick == self.awaiting:
                self.released = True  # lockstep: the rest of the inbox waits for the step

    # --- the world's tick --------------------------------------------------------------------------

    def step(self) -> None:
        """Advance the world one tick: plant (with the driver's output and the hexapod's motion), faults due,
        then every board's periodic output (the servo board's GYRO_SAMPLE last). A board whose host timer
        expires at the new tick (realtime) protects itself before its periodic output."""
        u_az: float
        u_el: float
        u_az, u_el = self.driver.output_counts()
        if self.deadline is None:  # lockstep and sim: the modelled delay
            delay_s = self._drive_in_tick_s
            if self._drive_line.maxlen != 1:
                self._drive_line.append((u_az, u_el))
                u_az, u_el = self._drive_line[0]
        elif self.wire_time:  # realtime: when the command that set the output arrived on the driver's wire
            delay_s = min(max(self.driver.acted_s - (self.deadline - TICK_S), 0.0), TICK_S)
        else:
            delay_s = 0.0
        pose, rate, accel = self.hexapod.motion(self.tick)
        self.hexapod.pose = pose
        self.plant.step_tick(u_az, u_el, CarrierMotion(pose, rate, accel), delay_s)
        tick = self.tick = self.tick + 1
        self.recorder.now_tick = tick
        if tick >= self.host_check_tick:
            self.host_check_tick = min(board.check_host_timer(tick) for board in self.boards.values())
        while self.schedule and round(self.schedule[0].at_s * 1000) <= tick:
            f = self.schedule.popleft()
            self.inject(f.link, f.kind, f.duration_ms, f.n_bytes)
        for link in self._link_list:
            if link.reconnect_at >= 0 or link.held:
                link.on_tick(tick)
        for board in self._before_sample:
            board.on_tick(tick)
        if self.lockstep:
            self._await_host_reads()
        self.servo.on_tick(tick)
        if tick % 100 == 0:
            self.recorder.flush()

    def inject(self, link: LinkName | str, kind: str, duration_ms: float = 0.0, n_bytes: int = 64) -> None:
        name = LinkName(link)
        target = self.links[name]
        ticks = round(duration_ms)
        if kind == "stall":
            target.stall(ticks, self.tick)
        elif kind == "latency_spike":
            target.latency_spike(ticks, self.tick)
        elif kind == "disconnect":
            self.inbox[name].clear()
            target.disconnect(ticks, self.tick)
        elif kind == "reset":
            self.inbox[name].clear()
            self.boards[name].reboot()
        elif kind == "garbage":
            target.garbage(n_bytes)
        else:
            raise ValueError(f"unknown fault kind {kind!r} (stall, latency_spike, reset, disconnect, garbage)")

    # --- the clock ---------------------------------------------------------------------------------

    def run(self, max_ticks: int | None = None) -> None:
        end = None if max_ticks is None else self.tick + max_ticks
        if self.config.clock == ClockMode.LOCKSTEP:
            self._run_lockstep(end)
        else:
            self._run_realtime(end)
        self.recorder.flush()

    def _done(self, end: int | None) -> bool:
        return self.stop_requested or (end is not None and self.tick >= end)

    def _run_realtime(self, end: int | None) -> None:
        """Each tick: wait for DRIVE_CMD k (at most until PREP_S before the next deadline), advance the
        world and prepare its output, then write GYRO_SAMPLE k exactly at the deadline.

        The other boards' frames of tick k go out once DRIVE_CMD k is in (or the wait gives up). Real
        boards each have their own clock and hardware; this one process, which may share a CPU with the
        bench, would otherwise spend the measured interval writing them (three more writes, each a
        kworker wake-up), and their arrival phase against the servo clock is arbitrary anyway."""
        t0, base = time.perf_counter(), self.tick
        prep_s = self.config.realtime_prep_us * 1e-6
        while not self._done(end):
            self.deadline = t0 + (self.tick - base + 1) * TICK_S
            self.awaiting = self.servo.last_delivered
            self.drain(LinkName.DRIVER)
            if self.awaiting is not None and not self.released:
                wait_for(lambda: self.released, self.deadline - prep_s - time.perf_counter(), self.readers(),
                         lambda: self.stop_requested)
            self.awaiting = None
            for name, link in self.links.items():
                if name is not LinkName.SERVO:
                    link.flush()
            if time.perf_counter() - self.deadline > 0.5:  # suspended (SIGSTOP, debugger): do not race to catch up
                self.recorder.record("servo", "clock_slip", behind_s=round(time.perf_counter() - self.deadline, 3))
                t0, base = time.perf_counter() - TICK_S, self.tick
                continue
            for link in self.links.values():
                link.defer()
            self.step()
            servo_link = self.links[LinkName.SERVO]
            wire_s = servo_link.wire_s(servo_link.pending_bytes)  # written when its last byte would arrive
            self.servo.announce_late(wait_until(self.deadline + wire_s, self.readers()))
            servo_link.flush()
            self.servo.on_written(time.perf_counter(), wire_s)
            self.released = False
            self.drain(LinkName.DRIVER)

    def _run_lockstep(self, end: int | None) -> None:
        self.deadline = None
        paced_next = 0.0
        while not self._done(end):
            if not self.servo.streaming:
                poll_readers(self.readers(), 0.02)  # frozen until the host starts the stream
                paced_next = 0.0
                continue
            self.step()
            self.servo.on_written(time.perf_counter())
            self.released = False
            k = self.servo.last_delivered
            if k is not None:
                paced_next = 0.0
                self.awaiting = k
                self.drain(LinkName.DRIVER)
                answered = self._await_host(lambda: self.released or not self.servo.streaming)
                if not answered and self.servo.streaming:
                    self.lockstep_timeouts += 1
                    self._judge_host_lockstep()
                self.awaiting = None
                self.released = False
                self.drain(LinkName.DRIVER)
            elif self.servo.streaming:  # the sample did not reach the host: let real time pass
                paced_next = paced_next + TICK_S if paced_next else time.perf_counter() + TICK_S
                wait_until(paced_next, self.readers())

    def _await_host_reads(self) -> None:
        """Lockstep, before the tick's GYRO_SAMPLE: wait until the host has handled what the other boards sent this
        tick (its LOCKSTEP_ACK of their last frame), so it handles them before the sample whatever order the ptys
        deliver them in, as the sim clock does. Only on a link where the host acknowledges; one it leaves
        unacknowledged for ``lockstep_timeout_ms`` is counted and not waited for again until it acknowledges."""
        links = self._acked_links
        if not (links[0].unacknowledged or links[1].unacknowledged or links[2].unacknowledged):
            return
        acked = self._await_host(lambda: not any(link.unacknowledged for link in links))
        if not acked and not self.stop_requested:
            for link in links:
                if link.unacknowledged:
                    self.lockstep_timeouts += 1
                    self.recorder.record(link.name, "ack_timeout", seq=link.sent_seq)
                    link.forget_acks()
            self._judge_host_lockstep()

    def _host_judge_ms(self) -> float:
        """Lockstep: the host silence (ms of wall time, any link) after which the boards protect themselves,
        max(host_timeout_ms, lockstep_timeout_ms); 0 when the boards have no host timer."""
        host_timeout_ms = self.config.boards.host_timeout_ms
        return max(host_timeout_ms, self.config.lockstep_timeout_ms) if host_timeout_ms else 0.0

    def _await_host(self, condition: Callable[[], bool]) -> bool:
        """Lockstep: serve the links until ``condition()`` holds (True), for ``lockstep_timeout_ms``; its caller
        judges the host when it does not (:meth:`_judge_host_lockstep`). A wait that runs out less than another
        ``lockstep_timeout_ms`` before the host's silence reaches that judgement's timeout (a host that answered
        another board and then froze) waits on until it does, so a frozen host is judged at its first timeout,
        never a whole wait (and a tick) later."""

        def stop() -> bool:
            return self.stop_requested

        timeout_s = self.config.lockstep_timeout_ms / 1000
        if wait_for(condition, timeout_s, self.readers(), stop):
            return True
        rest_s = self._host_judge_ms() / 1000 - (time.perf_counter() - self.host_heard_s)
        return 0 < rest_s <= timeout_s and self.servo.streaming and wait_for(condition, rest_s, self.readers(), stop)

    def _judge_host_lockstep(self) -> None:
        """Lockstep, after a wait for the host (DRIVE_CMD, LOCKSTEP_ACK) gave up: if no host frame came on any link for
        max(host_timeout_ms, lockstep_timeout_ms) of wall time, every board the host had talked to protects itself."""
        timeout_ms = self._host_judge_ms()
        if not timeout_ms or not self.servo.streaming:
            return
        silence_ms = (time.perf_counter() - self.host_heard_s) * 1000
        if silence_ms >= timeout_ms:
            for board in self.boards.values():
                if board.host_heard_tick is not None:
                    board.host_lost(round(silence_ms), timeout_ms)

    def request_stop(self) -> None:
        self.stop_requested = True

    # --- control socket ----------------------------------------------------------------------------

    def handle_control(self, request: dict[str, Any]) -> dict[str, Any]:
        cmd = request.get("cmd")
        if cmd == "status":
            return self.summary()
        if cmd == "inject":
            self.inject(request["link"], request["kind"], float(request.get("duration_ms", 0.0)),
                        int(request.get("n_bytes", 64)))
            return {"ok": True, "tick": self.tick}
        if cmd == "set_faults":
            name = LinkName(request["link"])
            fields = {k: v for k, v in request.items() if k not in ("cmd", "link")}
            link = self.links[name]
            link.set_faults(LinkFaults.model_validate({**link.faults.model_dump(), **fields}))
            self.recorder.record(name, "set_faults", **fields)
            return {"ok": True, "tick": self.tick, "faults": link.faults.model_dump()}
        if cmd == "records":
            since = int(request.get("since", 0))
            return {"tick": self.tick, "records": [r.as_dict() for r in self.recorder.records[since:]],
                    "next": len(self.recorder.records)}
        if cmd == "stop":
            self.request_stop()
            return {"ok": True}
        raise ValueError(f"unknown command {cmd!r} (status, inject, set_faults, records, stop)")

    def summary(self) -> dict[str, Any]:
        return {
            "clock": self.config.clock.value,
            "seed": self.config.seed,
            "tick": self.tick,
            "sim_s": round(self.tick * TICK_S, 3),
            "wall_s": round(time.time() - self.started_wall, 3),
            "streaming": self.servo.streaming,
            "servo": self.servo.summary(),
            "driver": {"enabled": int(self.driver.enabled), "faults": int(self.driver.faults),
                       "stale_commands": self.driver.stale_commands},
            "hexapod": {"state": self.hexapod.hex_state.name, "segments": len(self.hexapod.segments)},
            "lockstep_timeouts": self.lockstep_timeouts,
            "host_timeout_ms": self.config.boards.host_timeout_ms,
            "host_timeouts": sum(board.host_timeouts for board in self.boards.values()),
            "misaddressed_frames": sum(board.dropped.misaddressed for board in self.boards.values()),
            "wrong_link_frames": sum(board.dropped.wrong_link for board in self.boards.values()),
            "links": {name.value: {**asdict(link.stats), "rx": link.decoder.counters.as_dict(),
                                   "board": self.boards[name].counters()}
                      for name, link in self.links.items()},
            "fault_records": len(self.recorder.records) + self.recorder.dropped,
        }

    def close(self) -> None:
        """Close every pty and socket and remove the run directory: nothing is left behind."""
        for link in self.links.values():
            link.close()
        if self.control is not None:
            self.control.close()
        self.recorder.close()
        if self._own_run_dir:
            shutil.rmtree(self.run_dir, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                self.run_dir.rmdir()

    def __enter__(self) -> Emulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
