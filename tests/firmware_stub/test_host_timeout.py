"""The boards' side of host liveness, resends and addressing (docs/protocol.md, "Host liveness").

Most tests build the emulator in this process and step its world by hand (realtime config: each board's
host timer counts world ticks), so every expiry lands on an exact tick. Frames go over the real ptys: the
test writes a frame, then lets the emulator read it at the current tick. The lockstep tests run the
emulator's own loop in a thread (tests/firmware_stub/host.py).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import time
from collections.abc import Iterator
from typing import Any

from firmware_stub.clock import poll_readers
from firmware_stub.config import LinkName, load_emulator_config
from firmware_stub.emulator import Emulator
from firmware_stub.link import FaultRecord
from hil.protocol import (
    Ack,
    AxisMask,
    Board,
    DriveCmd,
    DriveEnable,
    DriveFault,
    DriveStatus,
    ErrorCode,
    Heartbeat,
    HexapodStart,
    HexapodState,
    HexAxis,
    HostAlive,
    IdentRequest,
    Nack,
    ServoMode,
    StreamMode,
    TrackCmd,
    TrackMode,
    encode_frame,
)
from hil.protocol.swing import ZERO6, Segment, segments_to_messages
from tests.firmware_stub.host import BOARD_OF, Host, running_emulator
from tests.firmware_stub.test_emulator import rate_damper, start_session, stream

SWING = Segment(HexAxis.PITCH, 0.0, 30.0, 1.0, 1.0, 0.0, 0.2)  # 1 deg / 1 Hz for 30 s
LINKS = ("servo", "driver", "image", "hexapod")


class Bench:
    """The host's end of an emulator whose world the test steps: ``send`` writes a frame on a pty and
    returns once the emulator has read (and handled) it at the current world tick."""

    def __init__(self, emu: Emulator) -> None:
        self.emu = emu
        self.host = Host(emu.ports())
        self.seq = dict.fromkeys(LINKS, 0)

    def send(self, link: str, message: Any, *, seq: int | None = None, src: int = Board.HOST,
             dst: int | None = None) -> int:
        if seq is None:
            seq, self.seq[link] = self.seq[link], (self.seq[link] + 1) & 0xFFFF
        data = encode_frame(message, src=src, dst=BOARD_OF[link] if dst is None else dst, seq=seq)
        counters = self.emu.links[LinkName(link)].decoder.counters
        target = counters.bytes + len(data)
        os.write(self.host[link].fd, data)
        give_up = time.monotonic() + 5
        while counters.bytes < target:
            assert time.monotonic() < give_up, f"{link}: the emulator did not read the frame"
            poll_readers(self.emu.readers(), 0.01)
        return seq

    def reply(self, link: str, seq: int, nth: int = 1) -> Ack | Nack:
        """The ``nth`` ACK/NACK answering host frame ``seq`` on ``link``."""
        replies: list[Ack | Nack] = []

        def match(frame: Any) -> bool:
            if isinstance(frame.message, Ack | Nack) and frame.message.seq == seq:
                replies.append(frame.message)
            return len(replies) == nth

        self.host.wait(link, match)
        return replies[-1]

    def command(self, link: str, message: Any) -> Ack | Nack:
        return self.reply(link, self.send(link, message))

    def tx_frames(self, link: str) -> int:
        return self.emu.links[LinkName(link)].stats.tx_frames

    def run(self, ticks: int, drive: tuple[int, int] | None = None, alive_every: int = 0,
            alive_links: tuple[str, ...] = ("servo", "image", "hexapod")) -> None:
        """Step the world; with ``drive``, answer each sample with DRIVE_CMD; HOST_ALIVE every ``alive_every``."""
        emu = self.emu
        for _ in range(ticks):
            emu.step()
            emu.servo.on_written(time.perf_counter())
            if drive is not None and emu.servo.streaming and emu.servo.last_delivered is not None:
                self.send("driver", DriveCmd(emu.servo.last_delivered, *drive))
            if alive_every and emu.tick % alive_every == 0:
                for link in alive_links:
                    self.send(link, HostAlive(emu.tick))
            if emu.tick % 50 == 0:
                self.host.pump_all()  # keep the ptys drained

    def records(self, kind: str) -> list[FaultRecord]:
        return [r for r in self.emu.recorder.records if r.kind == kind]


@contextlib.contextmanager
def stepped(**boards: Any) -> Iterator[Bench]:
    emu = Emulator(load_emulator_config(clock="realtime", boards=boards or None))
    bench = Bench(emu)
    try:
        yield bench
    finally:
        bench.host.close()
        emu.close()


def start_everything(bench: Bench) -> None:
    """Driver enabled, tracking on, the swing running, the stream on (all at world tick 0)."""
    assert isinstance(bench.command("driver", DriveEnable(AxisMask.BOTH, True)), Ack)
    assert isinstance(bench.command("image", TrackCmd(TrackMode.TRACK, 0)), Ack)
    for msg in segments_to_messages([SWING]):
        assert isinstance(bench.command("hexapod", msg), Ack)
    assert isinstance(bench.command("hexapod", HexapodStart()), Ack)
    assert isinstance(bench.command("servo", ServoMode(StreamMode.STREAM)), Ack)


# --- host timeout -----------------------------------------------------------------------------------


def test_a_silent_host_disables_the_driver_homes_the_hexapod_and_stops_the_stream() -> None:
    with stepped(hexapod={"stop_ramp_s": 0.2}) as bench:
        emu = bench.emu
        start_everything(bench)
        bench.run(300, drive=(1000, 2000), alive_every=100)  # the last frames from the host: tick 300
        assert emu.driver.output_counts() == (1000, 2000)
        bench.run(499)  # silent for 499 ms: nothing yet
        assert not bench.records("host_timeout")
        assert emu.driver.enabled == AxisMask.BOTH and emu.servo.streaming
        assert emu.hexapod.hex_state == HexapodState.RUNNING and emu.hexapod.pose != ZERO6
        bench.run(1)  # 500 ms: every board the host talked to protects itself, in the same tick
        timeouts = bench.records("host_timeout")
        assert sorted(r.link for r in timeouts) == sorted(LINKS)
        assert {(r.tick, r.detail["silence_ms"], r.detail["timeout_ms"]) for r in timeouts} == {(800, 500, 500)}
        assert emu.driver.enabled == 0 and emu.driver.output_counts() == (0, 0)
        disable = bench.records("drive_disable")
        assert [(r.tick, r.detail) for r in disable] == [(800, {"axes": 3, "cause": "host_timeout"})]
        assert not emu.servo.streaming
        assert [r.detail for r in bench.records("servo_stream")][-1] == {"streaming": False, "cause": "host_timeout"}
        sent = emu.servo.samples_sent
        # the hexapod ramps home over stop_ramp_s, then rests with its profile loaded
        bench.run(300)
        states = [(r.tick, r.detail["state"]) for r in bench.records("hexapod_state")]
        assert states[-2:] == [(800, "STOPPING"), (1000, "LOADED")]
        assert emu.hexapod.pose == ZERO6 and len(emu.hexapod.segments) == 1
        assert emu.tick == 1100 and emu.servo.samples_sent == sent  # no sample since
        # safe until commanded: a further second of silence changes nothing
        bench.run(1000)
        assert len(bench.records("host_timeout")) == 4 and emu.driver.enabled == 0
        assert emu.hexapod.hex_state == HexapodState.LOADED and not emu.servo.streaming
        # a new command re-arms that board's timer (only that board's)
        assert isinstance(bench.command("driver", DriveEnable(AxisMask.EL, False)), Ack)
        bench.run(499)
        assert emu.driver.enabled == AxisMask.EL
        bench.run(1)
        again = bench.records("host_timeout")[4:]
        assert [(r.link, r.tick, r.detail["silence_ms"]) for r in again] == [("driver", 2600, 500)]
        assert emu.driver.enabled == 0
        assert emu.summary()["host_timeouts"] == 5


def test_host_alive_every_100_ms_keeps_every_board_running_and_gets_no_reply() -> None:
    with stepped() as bench:
        emu = bench.emu
        start_everything(bench)
        for link in LINKS:  # accepted silently: not a single frame in reply
            before = bench.tx_frames(link)
            bench.send(link, HostAlive(0))
            assert bench.tx_frames(link) == before, link
        bench.run(2000, alive_every=100, alive_links=LINKS)  # no DRIVE_CMD at all: HOST_ALIVE alone
        assert not bench.records("host_timeout")
        assert emu.driver.enabled == AxisMask.BOTH  # stale (no DRIVE_CMD), but still enabled
        assert emu.hexapod.hex_state == HexapodState.RUNNING
        assert emu.servo.streaming and emu.servo.samples_sent == 2000
        bench.host.pump_all(0.05)
        assert not [f for link in LINKS for f in bench.host[link].frames if isinstance(f.message, Nack)]


def test_timer_arms_on_the_first_host_frame_and_ignores_dropped_frames() -> None:
    with stepped() as bench:
        emu = bench.emu
        bench.send("servo", IdentRequest())  # the servo board hears the host at tick 0
        for _ in range(6):  # frames that are not the host talking to the board do not feed its timer
            bench.send("servo", DriveStatus(0, AxisMask(0), 0, 0.0, 0.0, 24.0, 0))
            bench.send("driver", DriveEnable(AxisMask.BOTH, False), src=Board.SERVO)
            bench.send("image", IdentRequest(), dst=Board.HEXAPOD)
            bench.run(100)
        # only the servo board was ever talked to: the others have nothing to protect
        assert [(r.link, r.tick) for r in bench.records("host_timeout")] == [("servo", 500)]
        assert emu.driver.enabled == 0


# --- resent commands --------------------------------------------------------------------------------


def test_a_resent_command_gets_the_same_reply_without_a_second_action() -> None:
    with stepped() as bench:
        emu = bench.emu
        segments = [SWING, SWING._replace(axis=HexAxis.YAW), SWING._replace(axis=HexAxis.ROLL)]
        load = segments_to_messages(segments)
        assert isinstance(bench.command("hexapod", load[0]), Ack)
        seq = bench.send("hexapod", load[1])
        before = bench.tx_frames("hexapod")
        assert bench.send("hexapod", load[1], seq=seq) == seq  # the reply was lost: resent, same seq
        assert bench.tx_frames("hexapod") == before + 1  # the reply again, nothing else
        assert bench.reply("hexapod", seq, nth=1) == bench.reply("hexapod", seq, nth=2) == Ack(0x40, seq)
        assert len(emu.hexapod.segments) == 2  # not appended twice (else: NACK BAD_VALUE on index 2 below)
        assert isinstance(bench.command("hexapod", load[2]), Ack)
        assert len(emu.hexapod.segments) == 3 and emu.hexapod.hex_state == HexapodState.LOADED
        start = bench.send("hexapod", HexapodStart())
        bench.run(50)
        bench.send("hexapod", HexapodStart(), seq=start)  # a second START would be NACKed BAD_STATE
        assert bench.reply("hexapod", start, nth=2) == Ack(0x41, start)
        assert emu.hexapod.start_tick == 0
        assert [r.detail["state"] for r in bench.records("hexapod_state")] == ["LOADED", "RUNNING"]
        # a NACK is repeated as it was, even when the command would now be accepted
        emu.driver.faults = DriveFault.OVERCURRENT_EL  # latched: DRIVE_ENABLE without clear_faults is refused
        refused = bench.send("driver", DriveEnable(AxisMask.BOTH, False))
        emu.driver.faults = DriveFault(0)
        bench.send("driver", DriveEnable(AxisMask.BOTH, False), seq=refused)
        first, again = bench.reply("driver", refused), bench.reply("driver", refused, nth=2)
        assert first == again and isinstance(first, Nack) and first.error == ErrorCode.FAULT_LATCHED
        assert emu.driver.enabled == 0 and not bench.records("drive_enable")
        # DRIVE_CMD has no reply: the same seq twice is two commands
        assert isinstance(bench.command("driver", DriveEnable(AxisMask.BOTH, False)), Ack)
        bench.send("driver", DriveCmd(50, 100, 200), seq=9)
        bench.send("driver", DriveCmd(51, 300, 400), seq=9)
        assert emu.driver.cmd == [300, 400] and emu.driver.last_cmd_tick == 51
        # a reset forgets the last command: the same START is a new one (NACKed, no profile after power-on)
        emu.inject("hexapod", "reset")
        bench.send("hexapod", HexapodStart(), seq=start)
        nack = bench.reply("hexapod", start, nth=3)
        assert isinstance(nack, Nack) and nack.error == ErrorCode.PROFILE_INCOMPLETE
        assert emu.summary()["links"]["hexapod"]["board"]["resent_replies"] == 2


# --- addressing -------------------------------------------------------------------------------------


def test_frames_not_for_the_board_are_dropped_and_counted_not_answered() -> None:
    with stepped() as bench:
        emu = bench.emu
        before = {link: bench.tx_frames(link) for link in LINKS}
        bench.send("servo", DriveStatus(0, AxisMask(0), 0, 0.0, 0.0, 24.0, 0))  # a board's message
        bench.send("servo", DriveCmd(0, 100, 100))  # the driver's command on the servo link
        bench.send("driver", DriveEnable(AxisMask.BOTH, False), src=Board.IMAGE)  # not from the host
        bench.send("servo", IdentRequest(), dst=Board.DRIVER)  # for another board
        assert {link: bench.tx_frames(link) for link in LINKS} == before  # no NACK, no reply
        assert emu.driver.enabled == 0 and emu.driver.last_cmd_tick is None
        summary = emu.summary()
        assert (summary["misaddressed_frames"], summary["wrong_link_frames"]) == (2, 2)
        assert summary["links"]["servo"]["board"]["dropped"] == {"misaddressed": 1, "wrong_link": 2}
        assert summary["links"]["driver"]["board"]["dropped"] == {"misaddressed": 1, "wrong_link": 0}
        assert isinstance(bench.command("servo", ServoMode(StreamMode.IDLE)), Ack)  # the link still works


# --- lockstep -----------------------------------------------------------------------------------------


def lockstep_bytes(host_alive: bool) -> tuple[dict[str, str], int]:
    """sha256 of each link's bytes over 1001 samples (one HEARTBEAT per board), and the HOST_ALIVEs the
    driver received; with ``host_alive`` the host also sends HOST_ALIVE every 50 samples on three links."""
    with running_emulator(clock="lockstep", seed=3) as emu:
        host = Host(emu.ports())
        start_session(host, [SWING])

        def control(sample: Any) -> tuple[int, int]:
            if host_alive and sample.tick % 50 == 25:
                for link in ("driver", "image", "hexapod"):
                    host[link].send(HostAlive(sample.tick))
            return rate_damper(sample)

        stream(host, 1001, control)
        stream(host, 1, controller=None)
        assert isinstance(host.request("servo", ServoMode(StreamMode.IDLE)), Ack)
        host.pump_all(0.1)
        assert emu.lockstep_timeouts == 0
        # at tick 1000 the driver had DRIVE_ENABLE and DRIVE_CMD 0..998: HOST_ALIVE is not counted
        assert [f.message.rx_frames for f in host["driver"].frames if isinstance(f.message, Heartbeat)] == [1000]
        digests = {name: hashlib.sha256(bytes(port.raw)).hexdigest() for name, port in host.ports.items()}
        host.close()
        return digests, emu.driver.uncounted_rx_frames


def test_lockstep_host_alive_changes_no_byte_the_boards_send() -> None:
    quiet, none_received = lockstep_bytes(host_alive=False)
    chatty, received = lockstep_bytes(host_alive=True)
    assert (none_received, received) == (0, 20)
    assert chatty == quiet  # HEARTBEAT's rx_frames leaves HOST_ALIVE out in lockstep


def test_lockstep_judges_the_host_only_when_a_wait_for_drive_cmd_gives_up() -> None:
    boards = {"host_timeout_ms": 100, "hexapod": {"stop_ramp_s": 0.1}}
    with running_emulator(clock="lockstep", lockstep_timeout_ms=1500, boards=boards) as emu:
        host = Host(emu.ports())
        assert isinstance(host.request("driver", DriveEnable(AxisMask.BOTH, True)), Ack)
        for msg in segments_to_messages([SWING]):
            assert isinstance(host.request("hexapod", msg), Ack)
        assert isinstance(host.request("hexapod", HexapodStart()), Ack)

        def timeouts() -> list[FaultRecord]:
            return [r for r in emu.recorder.records if r.kind == "host_timeout"]

        time.sleep(0.3)  # stream off: the world is frozen and never judged
        assert not timeouts() and emu.driver.enabled == AxisMask.BOTH
        assert isinstance(host.request("servo", ServoMode(StreamMode.STREAM)), Ack)
        stream(host, 100)
        time.sleep(0.4)  # a slow host: 4x host_timeout_ms, but inside the lockstep wait
        stream(host, 100)
        assert not timeouts() and emu.lockstep_timeouts == 0
        # the host goes silent: the wait gives up after lockstep_timeout_ms, and the boards it talked to protect
        give_up = time.monotonic() + 10
        while len(timeouts()) < 3:
            assert time.monotonic() < give_up, "no host timeout"
            time.sleep(0.05)
        records = timeouts()
        assert sorted(r.link for r in records) == ["driver", "hexapod", "servo"]  # nobody talked to the image board
        assert all(r.detail["silence_ms"] >= 1500 and r.detail["timeout_ms"] == 1500 for r in records)
        assert {r.tick for r in records} == {201}  # sample 200 went out at tick 201 and was never answered
        assert emu.lockstep_timeouts == 1 and not emu.servo.streaming and emu.driver.enabled == 0
        time.sleep(0.2)  # frozen again: the hexapod stays where it stopped, nothing more happens
        assert emu.hexapod.hex_state == HexapodState.STOPPING and emu.tick == 201
        assert len(timeouts()) == 3 and emu.lockstep_timeouts == 1
        # the host returns: the world runs, the ramp completes; the driver stays off until enabled
        assert isinstance(host.request("servo", ServoMode(StreamMode.STREAM)), Ack)
        stream(host, 150)
        assert emu.hexapod.hex_state == HexapodState.LOADED and emu.hexapod.pose == ZERO6
        assert emu.driver.enabled == 0
        host.close()


def test_lockstep_judges_a_host_frozen_after_its_last_frame_at_the_first_timeout() -> None:
    """A host that answers another board (here HOST_ALIVE on the hexapod link) during a wait for DRIVE_CMD and then
    freezes is judged once it has been silent for the timeout, at the tick it left unanswered: not a wait later,
    by when a host frozen for twice the timeout would be back and find its boards still armed."""
    boards = {"host_timeout_ms": 100}
    with running_emulator(clock="lockstep", lockstep_timeout_ms=600, boards=boards) as emu:
        host = Host(emu.ports())
        assert isinstance(host.request("driver", DriveEnable(AxisMask.BOTH, True)), Ack)
        assert isinstance(host.request("servo", ServoMode(StreamMode.STREAM)), Ack)
        stream(host, 100)
        time.sleep(0.4)  # inside the wait for DRIVE_CMD 100
        host["hexapod"].send(HostAlive(100))
        heard = time.monotonic()
        give_up = heard + 10
        while not [r for r in emu.recorder.records if r.kind == "host_timeout"]:
            assert time.monotonic() < give_up, "no host timeout"
            time.sleep(0.01)
        judged_after_s = time.monotonic() - heard
        records = [r for r in emu.recorder.records if r.kind == "host_timeout"]
        assert {r.tick for r in records} == {101}, records  # sample 100 (tick 101) was the one left unanswered
        assert all(600 <= r.detail["silence_ms"] < 1200 for r in records), records
        assert judged_after_s >= 0.6, judged_after_s
        assert emu.lockstep_timeouts == 1 and not emu.servo.streaming and emu.driver.enabled == 0
        host.close()


def test_host_timeout_zero_disables_the_timer() -> None:
    with stepped(host_timeout_ms=0) as bench:
        start_everything(bench)
        bench.run(1500)
        assert not bench.records("host_timeout") and bench.emu.driver.enabled == AxisMask.BOTH
