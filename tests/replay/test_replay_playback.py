"""Capture playback against boards that misbehave, and the library calls behind `hil replay`: a board that stops
streaming stops the replay, in either timing, which then disarms the boards; the replay's bookkeeping stays bounded
however long it plays; replay_capture and replay_log take what the command line takes and refuse bad input by
name."""

from __future__ import annotations

import contextlib
import os
import re
import select
import threading
import time
import tty
from pathlib import Path
from typing import Any

import pytest

from hil.link import Capture, CaptureError
from hil.protocol import (
    CATALOGUE,
    Ack,
    AxisMask,
    Board,
    Decoder,
    DriveCmd,
    DriveDisable,
    DriveEnable,
    Encoder,
    GyroSample,
    ServoMode,
    StreamMode,
)
from hil.replay import (
    FIRST_SAMPLE_WAIT_S,
    SAMPLE_TIMES_KEPT,
    CapturePlayer,
    Quantiles,
    ReplayError,
    emulator_settings,
    play_capture,
    replay_capture,
    resolve_ports,
)

SAMPLES_IN_CAPTURE = 1000
FIRST_SAMPLE_MS = 10


def write_session_capture(path: Path) -> Path:
    """A 1 kHz session as the bench records it: STREAM, DRIVE_ENABLE, then each of 1000 samples answered 200 us
    later by its DRIVE_CMD, then the session's own DRIVE_DISABLE and SERVO_MODE IDLE."""
    host, servo_enc = Encoder(Board.HOST), Encoder(Board.SERVO)
    ms = 1_000_000
    with Capture(path, meta={"session": "unit", "seed": 0, "session_clock": "realtime"}) as cap:
        servo, driver = cap.link("servo"), cap.link("driver")
        servo.tx(host.encode(ServoMode(StreamMode.STREAM), Board.SERVO), t_ns=0)
        driver.tx(host.encode(DriveEnable(AxisMask.BOTH, False), Board.DRIVER), t_ns=1 * ms)
        for k in range(SAMPLES_IN_CAPTURE):
            t = (FIRST_SAMPLE_MS + k) * ms
            servo.rx(servo_enc.encode(GyroSample(1000 * k, k, 0.0, 0.0, 0.0, 0.0, 0.0), Board.HOST), t_ns=t)
            driver.tx(host.encode(DriveCmd(k, k, -k), Board.DRIVER), t_ns=t + 200_000)
        end = (FIRST_SAMPLE_MS + SAMPLES_IN_CAPTURE) * ms
        driver.tx(host.encode(DriveDisable(AxisMask.BOTH), Board.DRIVER), t_ns=end)
        servo.tx(host.encode(ServoMode(StreamMode.IDLE), Board.SERVO), t_ns=end + 100_000)
    return path


class FakeBoards:
    """The servo and driver boards behind two ptys. Both ACK what expects an ACK; the servo streams a GYRO_SAMPLE
    every millisecond from the SERVO_MODE STREAM that asks for it, ``stream_for`` of them, then falls silent (still
    answering); the driver keeps its enable state and notes every frame it gets with its time."""

    def __init__(self, stream_for: int) -> None:
        self.stream_for = stream_for
        self.fds: dict[str, tuple[int, int]] = {}
        self.ports: dict[str, str] = {}
        for name in ("servo", "driver"):
            master, slave = os.openpty()
            tty.setraw(slave)
            self.fds[name] = (master, slave)
            self.ports[name] = os.ttyname(slave)
        self.boards = {"servo": Board.SERVO, "driver": Board.DRIVER}
        self.dec = {name: Decoder.for_link(board, "board") for name, board in self.boards.items()}
        self.enc = {name: Encoder(board) for name, board in self.boards.items()}
        self.streaming = False
        self.sent_samples: list[float] = []  # when each sample went out
        self.next_due = 0.0
        self.driver_enabled = False
        self.driver_got: list[tuple[float, str]] = []  # (time, message name)
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> FakeBoards:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.done.set()
        self.thread.join(2.0)
        for master, slave in self.fds.values():
            for fd in (master, slave):
                with contextlib.suppress(OSError):
                    os.close(fd)

    def _send(self, name: str, msg: Any) -> None:
        os.write(self.fds[name][0], self.enc[name].encode(msg, Board.HOST))

    def _run(self) -> None:
        masters = {master: name for name, (master, _) in self.fds.items()}
        while not self.done.is_set():
            wait = 0.01 if not self.streaming else max(0.0, self.next_due - time.monotonic())
            ready = select.select(list(masters), (), (), min(wait, 0.01))[0]
            for fd in ready:
                try:
                    data = os.read(fd, 65536)
                except OSError:
                    continue
                for frame in self.dec[masters[fd]].feed(data):
                    self._handle(masters[fd], frame)
            now = time.monotonic()
            if self.streaming and len(self.sent_samples) < self.stream_for and now >= self.next_due:
                k = len(self.sent_samples)
                self._send("servo", GyroSample(1000 * k, k, 0.0, 0.0, 0.0, 0.0, 0.0))
                self.sent_samples.append(now)
                self.next_due += 0.001

    def _handle(self, name: str, frame: Any) -> None:
        msg = frame.message
        spec = CATALOGUE.spec(msg)
        if name == "driver":
            self.driver_got.append((time.monotonic(), spec.name))
            if type(msg) is DriveEnable:
                self.driver_enabled = True
            elif type(msg) is DriveDisable:
                self.driver_enabled = False
        elif type(msg) is ServoMode:
            self.streaming = msg.mode == StreamMode.STREAM
            self.next_due = time.monotonic()
        if spec.reply in ("ACK", "ACK/NACK"):
            self._send(name, Ack(spec.msg_id, frame.seq))


@pytest.fixture(scope="module")
def session_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_session_capture(tmp_path_factory.mktemp("playback") / "session.hilcap")


# The fake boards run in this process, where a loaded machine may not run them for a while: a watchdog that such a
# pause does not trip (the stream's end still comes well before the capture's), and the last replies awaited as long
# as they take (the wait ends as soon as they are in)
WATCHDOG_S = 0.3
LINGER_S = 5.0


def stopped_after_ms(stopped: str) -> float:
    """How long the stream had been silent when the replay's watchdog stopped it, from its reason."""
    found = re.fullmatch(r"watchdog: no GYRO_SAMPLE for (\d+) ms .*", stopped)
    assert found, stopped
    return float(found[1])


@pytest.mark.parametrize("timing", ["samples", "clock"])
def test_a_board_that_stops_streaming_stops_the_replay_which_disarms_it(session_capture: Path, timing: str) -> None:
    with FakeBoards(stream_for=200) as boards:
        r = play_capture(session_capture, boards.ports, timing=timing, watchdog_s=WATCHDOG_S, linger_s=LINGER_S)
    assert stopped_after_ms(r.stopped) >= 1000 * WATCHDOG_S  # never before the watchdog's time; later if not run
    assert r.stream_started and r.samples == 200
    # the replay disarmed what it had armed: the driver disabled, the stream idled, both answered
    assert r.safe_end == ["DRIVE_DISABLE", "SERVO_MODE"]
    assert r.commands == r.answered == 4  # STREAM, DRIVE_ENABLE; the replay's own DRIVE_DISABLE and IDLE
    assert not boards.driver_enabled
    names = [name for _, name in boards.driver_got]
    assert names[-1] == "DRIVE_DISABLE" and names.count("DRIVE_DISABLE") == 1
    drive_cmds = [t for t, name in boards.driver_got if name == "DRIVE_CMD"]
    assert len(drive_cmds) == r.links["driver"].sent["DRIVE_CMD"] < SAMPLES_IN_CAPTURE
    # the board heard the DRIVE_DISABLE no sooner than the watchdog's time after its last sample
    assert boards.driver_got[-1][0] - boards.sent_samples[-1] >= WATCHDOG_S
    if timing == "samples":  # each DRIVE_CMD waits for its sample: not one more than the board streamed
        assert len(drive_cmds) == 200
    else:  # on the capture's clock: DRIVE_CMD went on past the stream's end, until the watchdog ran out
        assert len(drive_cmds) > 200


def test_on_the_capture_clock_no_drive_goes_before_the_stream_starts(session_capture: Path) -> None:
    with FakeBoards(stream_for=0) as boards:  # acknowledges STREAM, streams nothing
        t0 = time.monotonic()
        r = play_capture(session_capture, boards.ports, timing="clock", linger_s=LINGER_S)
        took = time.monotonic() - t0
    assert r.stopped == "no GYRO_SAMPLE: the servo board did not start its stream"
    assert not r.stream_started and r.links["driver"].sent["DRIVE_CMD"] == 0 and r.answered == r.commands
    assert [name for _, name in boards.driver_got] == ["DRIVE_ENABLE", "DRIVE_DISABLE"] and not boards.driver_enabled
    assert took >= FIRST_SAMPLE_WAIT_S  # the whole wait for the first sample, then the safe end


def test_the_sample_times_kept_stay_bounded_however_long_the_stream(session_capture: Path) -> None:
    player = CapturePlayer(session_capture, {"servo": "/dev/null", "driver": "/dev/null"}, timing="clock")
    n = 3 * SAMPLE_TIMES_KEPT
    for k in range(n):  # a clock-timed replay awaits none of them: they must be let go all the same
        player._on_frame("servo", GyroSample(1000 * k, k, 0.0, 0.0, 0.0, 0.0, 0.0), 1_000_000 * k)
    assert player.samples == n and player.last_sample_rx == 1_000_000 * (n - 1)
    assert len(player._sample_rx) == len(player._sample_order) == SAMPLE_TIMES_KEPT
    # a sample let go is not taken for a lost one: a write timed from it goes out at once
    assert player._await_sample((0, 5), 0) == 1_000_000 * (n - SAMPLE_TIMES_KEPT - 1)
    assert player._await_sample((0, n - 1), 0) == 1_000_000 * (n - 1) and player.samples_lost == 0


def test_write_lateness_quantiles_in_fixed_memory() -> None:
    q = Quantiles()
    assert q.quantile(0.5) != q.quantile(0.5)  # NaN while empty
    size = len(q.buckets)
    for v in range(0, 10_000_000, 10):  # 0 .. 10 ms in 10 ns steps: a million writes
        q.add(v)
    assert len(q.buckets) == size and q.count == 1_000_000 and q.max == 9_999_990
    assert abs(q.quantile(0.5) - 5_000_000) < 0.008 * 5_000_000
    assert abs(q.quantile(0.99) - 9_900_000) < 0.008 * 9_900_000
    small = Quantiles()
    for v in (3, 5, 5, 7, 100):  # exact below 128 ns
        small.add(v)
    assert small.quantile(0.5) == 5.0 and small.quantile(1.0) == 100.0 and small.quantile(0.0) == 3.0
    small.add(-4)  # a write that went out early counts as on time
    assert small.quantile(0.0) == 0.0


def test_replay_capture_resolves_ports_and_refuses_bad_input_by_option(session_capture: Path, tmp_path: Path) -> None:
    ports_file = tmp_path / "ports.json"
    ports_file.write_text('{"servo": "/dev/a", "driver": "/dev/b", "control": "/tmp/x.sock"}')
    assert resolve_ports(["driver=/dev/c"], ports_file) == {"servo": "/dev/a", "driver": "/dev/c"}
    assert resolve_ports({"image": "/dev/d"}) == {"image": "/dev/d"}
    for kwargs, message in (
        ({"ports": ["gimbal=/dev/null"]}, "^ports='gimbal=/dev/null': not LINK=PATH"),
        ({"ports": ["servo"]}, "^ports='servo': not LINK=PATH"),
        ({"ports": "servo=/dev/null"}, "^ports='servo=/dev/null': give a list"),
        ({"ports_file": tmp_path / "none.json"}, "^ports_file: .*none.json: no such file"),
        ({"ports": ["servo=/dev/null"], "clock": "lockstep"}, "^clock= and seed= start a fresh emulator"),
        ({"ports": ["servo=/dev/null"], "seed": 1}, "^clock= and seed= start a fresh emulator"),
        ({"timing": "wall"}, "^timing='wall': not samples or clock"),
        ({"clock": "sim"}, "^clock='sim': not lockstep or realtime"),
        ({"seed": -1}, "^seed=-1: not an integer >= 0"),
        ({"record_dir": session_capture}, "^record_dir="),
    ):
        with pytest.raises(ReplayError, match=message):
            replay_capture(session_capture, **kwargs)
        assert "\n" not in message
    with pytest.raises(CaptureError, match=r"no \.hilcap capture"):
        replay_capture(tmp_path, ports=["servo=/dev/null"])
    assert issubclass(ReplayError, ValueError) and issubclass(CaptureError, ValueError)


def test_a_fresh_emulator_takes_the_captured_clock_seed_and_config(tmp_path: Path) -> None:
    config = tmp_path / "emulator.yaml"
    config.write_text("clock: realtime\n")
    # a realtime session against the emulator: its config, clock and seed come back
    meta = {"session_clock": "realtime", "seed": 9, "emulator_config": str(config), "emulator_clock": "realtime",
            "emulator_seed": 9}
    assert emulator_settings(meta).as_dict() == {"config": str(config), "clock": "realtime", "seed": 9}
    assert emulator_settings(meta, clock="lockstep", seed=2).as_dict() == {"config": str(config),
                                                                          "clock": "lockstep", "seed": 2}
    # the lab's boards: no emulator recorded, so the emulator's default config on the session's clock and seed
    assert emulator_settings({"session_clock": "realtime", "seed": 4}).as_dict() == {"config": None,
                                                                                      "clock": "realtime", "seed": 4}
    assert emulator_settings({}).as_dict() == {"config": None, "clock": "lockstep", "seed": 0}
    with pytest.raises(ReplayError, match=r"the captured emulator config .*gone\.yaml is not a file here"):
        emulator_settings({**meta, "emulator_config": str(tmp_path / "gone.yaml")})
