"""The emulated boards on their ptys: protocol behaviour, lockstep determinism, faults on the wire.

The emulator runs in a background thread (lockstep unless a test says otherwise) and the test is
the host, speaking the protocol over the ptys with nothing but the codec (tests/firmware_stub/host.py).
"""

from __future__ import annotations

import hashlib
import itertools
import math
import time
from collections.abc import Callable

import pytest

from hil.protocol import (
    CATALOGUE,
    Ack,
    AxisMask,
    DriveCmd,
    DriveDisable,
    DriveEnable,
    DriveFault,
    DriveStatus,
    ErrorCode,
    GyroSample,
    HexapodStart,
    HexapodState,
    HexapodStatus,
    HexAxis,
    Ident,
    IdentRequest,
    LoopTiming,
    MissDistance,
    Nack,
    Pose,
    ServoMode,
    StreamMode,
    TrackCmd,
    TrackMode,
)
from hil.protocol.swing import Segment, segments_to_messages
from tests.firmware_stub.host import Host, running_emulator

PITCH_SWING = Segment(HexAxis.PITCH, 0.0, 30.0, 1.0, 1.0, 0.0, 0.2)  # 1 deg / 1 Hz, the paper's swing

Controller = Callable[[GyroSample], tuple[int, int]]


def rate_damper(g: GyroSample) -> tuple[int, int]:
    """A trivial rate loop: drive against the measured rates."""
    return (int(max(-30000, min(30000, -3000 * g.rate_z_dps))), int(max(-30000, min(30000, -3000 * g.rate_y_dps))))


def stream(host: Host, n: int, controller: Controller | None = rate_damper, timeout_s: float = 2.0) -> list[GyroSample]:
    """Receive n GYRO_SAMPLEs, answering each with DRIVE_CMD (controller None: never answer)."""
    got: list[GyroSample] = []
    port = host["servo"]
    seen = port.cursor  # every sample is answered once, even one that arrived with an earlier reply
    give_up = time.monotonic() + timeout_s + n * 0.05
    while len(got) < n:
        if time.monotonic() > give_up:
            raise TimeoutError(f"only {len(got)} of {n} samples")
        host.pump_all(0.005)
        while seen < len(port.frames) and len(got) < n:
            msg = port.frames[seen].message
            seen += 1
            if isinstance(msg, GyroSample):
                got.append(msg)
                if controller is not None:
                    host["driver"].send(DriveCmd(msg.tick, *controller(msg)))
        port.cursor = seen
    return got


def start_session(host: Host, segments: list[Segment] | None = None) -> None:
    assert isinstance(host.request("driver", DriveEnable(AxisMask.BOTH, True)), Ack)
    assert isinstance(host.request("image", TrackCmd(TrackMode.TRACK, 0)), Ack)
    if segments:
        for msg in segments_to_messages(segments):
            assert isinstance(host.request("hexapod", msg), Ack)
        assert isinstance(host.request("hexapod", HexapodStart()), Ack)
    assert isinstance(host.request("servo", ServoMode(StreamMode.STREAM)), Ack)


def of_type(host: Host, link: str, kind: type) -> list:
    return [f.message for f in host[link].frames if isinstance(f.message, kind)]


# --- identity and basic behaviour ------------------------------------------------------------------


def test_every_board_answers_ident_with_the_catalogue_fingerprint() -> None:
    with running_emulator(clock="lockstep") as emu:
        host = Host(emu.ports())
        for name in ("servo", "driver", "image", "hexapod"):
            host[name].send(IdentRequest())
            ident = host.wait(name, lambda f: isinstance(f.message, Ident)).message
            assert ident.catalogue_fingerprint == CATALOGUE.fingerprint
            assert ident.board.name.lower() == name
            assert ident.firmware_version == "emu-1.0.0"
        host.close()


def test_lockstep_streams_consecutive_ticks_and_moves_the_gimbal_with_the_hexapod() -> None:
    with running_emulator(clock="lockstep", seed=1) as emu:
        host = Host(emu.ports())
        start_session(host, [PITCH_SWING])
        samples = stream(host, 600, controller=lambda g: (0, 0))
        assert [s.tick for s in samples] == list(range(600))
        assert [s.t_us - samples[0].t_us for s in samples[:5]] == [0, 1000, 2000, 3000, 4000]
        # undriven, the elevation axis is dragged by the pitching carrier (friction, back-EMF, imbalance):
        # the gyro sees part of the 2 pi deg/s peak carrier rate once the 0.2 s ramp is over
        peak = max(abs(s.rate_y_dps) for s in samples[300:])
        assert 0.15 < peak < 2 * math.pi + 0.5  # (+ gyro noise)
        poses = of_type(host, "hexapod", Pose)
        assert len(poses) >= 55  # 100 Hz
        p = poses[40]  # t = 0.4 s (tick 401 of the world, profile clock t_ms)
        assert p.pitch_deg == pytest.approx(math.sin(2 * math.pi * (p.t_ms / 1000)), abs=0.03)
        misses = of_type(host, "image", MissDistance)
        assert 55 <= len(misses) <= 61
        assert [m.frame for m in misses] == list(range(len(misses)))
        # undriven, the line of sight drifts off the target: track_valid drops as it leaves the field of view
        half_height = emu.plant.config.camera.half_height_px
        valid = [m for m in misses if m.track_valid]
        assert all(abs(m.miss_y_px) <= half_height for m in valid)
        assert max(abs(m.miss_y_px) for m in valid) > 0.5 * half_height
        first_lost = next(i for i, m in enumerate(misses) if not m.track_valid)
        assert first_lost > 10 and not any(m.track_valid for m in misses[first_lost:first_lost + 3])
        host.close()


def lockstep_digests(seed: int, n: int = 800) -> dict[str, str]:
    with running_emulator(clock="lockstep", seed=seed) as emu:
        host = Host(emu.ports())
        start_session(host, [PITCH_SWING])
        stream(host, n)
        # stop deterministically: IDLE instead of DRIVE_CMD n, so the world cannot step past sample n
        stream(host, 1, controller=None)
        assert isinstance(host.request("servo", ServoMode(StreamMode.IDLE)), Ack)
        host.pump_all(0.1)
        assert emu.lockstep_timeouts == 0  # a timeout would change the plant's input: not a same-commands run
        digests = {name: hashlib.sha256(bytes(port.raw)).hexdigest() for name, port in host.ports.items()}
        assert all(len(port.raw) > 1000 for port in host.ports.values())
        host.close()
        return digests


@pytest.mark.realtime
def test_realtime_writes_the_sample_first_and_the_other_boards_frames_answered_or_not() -> None:
    with running_emulator(clock="realtime") as emu:
        host = Host(emu.ports(), host_alive_period_s=0.1)
        start_session(host, [PITCH_SWING])
        stream(host, 300)
        frames = [f.message for f in host["servo"].frames]
        timing = [i for i, m in enumerate(frames) if isinstance(m, LoopTiming)]
        assert len(timing) >= 25
        for i in timing:  # LOOP_TIMING for ticks k-20..k-11 follows GYRO_SAMPLE k on the wire
            before = frames[i - 1]
            assert isinstance(before, GyroSample) and before.tick == frames[i].first_tick + 20
        # the image, driver and hexapod frames of a tick wait for its DRIVE_CMD, or for the wait to give up
        counts = [len(of_type(host, "image", MissDistance)), len(of_type(host, "hexapod", Pose)),
                  len(of_type(host, "driver", DriveStatus))]
        stream(host, 300, controller=None)
        grown = [len(of_type(host, "image", MissDistance)), len(of_type(host, "hexapod", Pose)),
                 len(of_type(host, "driver", DriveStatus))]
        assert all(27 <= b - a <= 33 for a, b in zip(counts, grown, strict=True)), (counts, grown)  # 100 Hz
        host.close()


def test_lockstep_is_byte_identical_for_the_same_seed_and_commands() -> None:
    first, second, other = lockstep_digests(5), lockstep_digests(5), lockstep_digests(6)
    assert first == second
    assert other["servo"] != first["servo"]  # the gyro noise follows the seed


# --- the driver -----------------------------------------------------------------------------------


def test_driver_needs_enable_holds_commands_and_drops_stale_ones() -> None:
    with running_emulator(clock="lockstep", lockstep_timeout_ms=2) as emu:
        host = Host(emu.ports())
        assert isinstance(host.request("servo", ServoMode(StreamMode.STREAM)), Ack)
        stream(host, 5, controller=lambda g: (0, 20000))
        nack = host.wait("driver", lambda f: isinstance(f.message, Nack)).message
        assert nack.error == ErrorCode.NOT_ENABLED and nack.msg_id == 0x20
        assert max(map(abs, emu.plant.currents_a())) < 1e-3  # nothing drives while disabled
        assert isinstance(host.request("driver", DriveEnable(AxisMask.EL, False)), Ack)
        stream(host, 50, controller=lambda g: (20000, 20000))
        assert emu.driver.output_counts() == (0, 20000)  # AZ was not enabled
        assert emu.plant.currents_a()[1] > 0.5
        # stop answering: after stale_timeout_ms (20) the output is forced to zero and flagged
        stream(host, 40, controller=None)
        assert emu.driver.output_counts() == (0, 0)
        stale = [r for r in emu.recorder.records if r.kind == "drive_stale"]
        assert len(stale) == 1
        statuses = of_type(host, "driver", DriveStatus)
        assert statuses[-1].faults & DriveFault.STALE_COMMAND and statuses[-1].stale_commands == 1
        # a fresh command clears the flag and drives again
        stream(host, 20, controller=lambda g: (0, -15000))
        assert emu.driver.output_counts() == (0, -15000)
        assert isinstance(host.request("driver", DriveDisable(AxisMask.BOTH)), Ack)
        assert emu.driver.output_counts() == (0, 0)
        host.close()


def test_overcurrent_latches_until_enable_clears_it() -> None:
    boards = {"driver": {"current_limit_a": 0.5, "overcurrent_trip_ms": 3}}
    with running_emulator(clock="lockstep", boards=boards) as emu:
        host = Host(emu.ports())
        start_session(host)
        stream(host, 60, controller=lambda g: (0, 30000))
        trips = [r for r in emu.recorder.records if r.kind == "drive_overcurrent"]
        assert len(trips) == 1 and trips[0].detail["axis"] == "el" and trips[0].detail["current_a"] > 0.5
        assert emu.driver.output_counts() == (0, 0)
        status = of_type(host, "driver", DriveStatus)[-1]
        assert status.faults & DriveFault.OVERCURRENT_EL and not status.enabled & AxisMask.EL
        refused = host.request("driver", DriveEnable(AxisMask.EL, False))
        assert isinstance(refused, Nack) and refused.error == ErrorCode.FAULT_LATCHED
        assert isinstance(host.request("driver", DriveEnable(AxisMask.EL, True)), Ack)
        assert not emu.driver.faults
        host.close()


# --- the hexapod ----------------------------------------------------------------------------------


def test_profile_beyond_the_envelope_is_refused_and_nothing_moves() -> None:
    with running_emulator(clock="lockstep") as emu:
        host = Host(emu.ports())
        limit = emu.plant.config.hexapod.pitch.angle_deg
        too_far = [Segment(HexAxis.X, 0.0, 5.0, 10.0, 0.5), PITCH_SWING._replace(amplitude=limit + 5)]
        msgs = segments_to_messages(too_far)
        assert isinstance(host.request("hexapod", msgs[0]), Ack)
        nack = host.request("hexapod", msgs[1])
        assert isinstance(nack, Nack) and nack.error == ErrorCode.ENVELOPE_POSITION
        assert nack.axis == HexAxis.PITCH and nack.limit == pytest.approx(limit)
        assert nack.value == pytest.approx(limit + 5, rel=1e-3)
        start = host.request("hexapod", HexapodStart())
        assert isinstance(start, Nack) and start.error == ErrorCode.PROFILE_INCOMPLETE
        assert isinstance(host.request("servo", ServoMode(StreamMode.STREAM)), Ack)
        stream(host, 200)
        poses = of_type(host, "hexapod", Pose)
        assert len(poses) >= 19 and all(p[1:] == (0.0,) * 6 for p in poses)
        assert emu.plant.truth()["carrier_q_dps"] == 0.0
        assert of_type(host, "hexapod", HexapodStatus)[-1].state == HexapodState.IDLE
        host.close()


def test_stop_ramps_the_motion_down_and_keeps_the_profile() -> None:
    with running_emulator(clock="lockstep", boards={"hexapod": {"stop_ramp_s": 0.2}}) as emu:
        host = Host(emu.ports())
        start_session(host, [PITCH_SWING._replace(ramp_s=0.0)])
        stream(host, 300)
        from hil.protocol import HexapodStop

        assert isinstance(host.request("hexapod", HexapodStop()), Ack)
        stream(host, 300)
        poses = of_type(host, "hexapod", Pose)
        assert max(abs(p.pitch_deg) for p in poses[-8:]) == 0.0
        states = [r.detail["state"] for r in emu.recorder.records if r.kind == "hexapod_state"]
        assert states == ["LOADED", "RUNNING", "STOPPING", "LOADED"]
        host.close()


# --- faults on the wire ---------------------------------------------------------------------------


def corrupted_sample_ticks(emu) -> set[int]:  # type: ignore[no-untyped-def]
    """World ticks whose GYRO_SAMPLE had bits flipped or bytes dropped, by the emulator's own record."""
    return {r.tick for r in emu.recorder.records
            if r.link == "servo" and r.kind in ("bit_flip", "byte_drop") and r.detail["msg_id"] == 0x10}


def test_bit_errors_lose_exactly_the_corrupted_frames() -> None:
    links = {"servo": {"bit_error_rate": 3e-4, "drop_byte_rate": 1e-4}}
    with running_emulator(clock="lockstep", lockstep_timeout_ms=2, links=links) as emu:
        host = Host(emu.ports())
        start_session(host)
        samples = stream(host, 1500)
        got_ticks = {s.t_us // 1000 for s in samples}
        first, last = min(got_ticks), max(got_ticks)
        sent = set(range(first, last + 1))
        bad = corrupted_sample_ticks(emu) & sent
        assert 30 < len(bad) < 200  # ~8 % of 27-byte frames at these rates
        assert got_ticks == sent - bad
        c = host["servo"].decoder.counters
        assert c.crc_errors + c.bad_lengths > 0.5 * len(bad)
        host.close()


def test_garbage_bursts_are_all_discarded_and_no_frame_is_lost() -> None:
    with running_emulator(clock="lockstep", links={"servo": {"garbage_rate": 0.05}}) as emu:
        host = Host(emu.ports())
        start_session(host)
        samples = stream(host, 1000)
        assert [s.tick for s in samples] == list(range(1000))
        host.pump_all(0.05)
        garbage = sum(r.detail["n_bytes"] for r in emu.recorder.records if r.kind == "garbage")
        assert garbage > 20 * 16
        c = host["servo"].decoder.counters
        assert c.bytes_discarded == garbage
        host.close()


def test_stall_silences_the_board_for_its_duration() -> None:
    faults = [{"at_s": 0.3, "link": "servo", "kind": "stall", "duration_ms": 25}]
    with running_emulator(clock="lockstep", faults=faults) as emu:
        host = Host(emu.ports())
        start_session(host)
        samples = stream(host, 500)
        ticks = [s.tick for s in samples]
        gaps = [(a, b) for a, b in itertools.pairwise(ticks) if b != a + 1]
        assert len(gaps) == 1 and gaps[0][1] - gaps[0][0] == 26  # 25 samples never sent
        stall = next(r for r in emu.recorder.records if r.kind == "stall")
        assert stall.tick == 300 and stall.detail["duration_ms"] == 25
        host.close()


@pytest.mark.realtime
def test_latency_spike_delays_samples_without_losing_them() -> None:
    with running_emulator(clock="realtime") as emu:
        host = Host(emu.ports(), host_alive_period_s=0.1)
        start_session(host)
        stream(host, 100)
        from firmware_stub.control import ControlClient

        with ControlClient(emu.ports()["control"]) as ctl:
            assert ctl.call("inject", link="servo", kind="latency_spike", duration_ms=8)["ok"]
        samples = stream(host, 300)
        ticks = [s.tick for s in samples]
        assert ticks == list(range(ticks[0], ticks[0] + 300))
        time.sleep(0.05)
        lat = emu.servo.latencies_us
        assert max(lat) > 6_000  # the held samples' commands came >= 6 ms after the board wrote them
        host.close()


def test_board_reset_restarts_sequence_and_disables_the_driver() -> None:
    with running_emulator(clock="lockstep", lockstep_timeout_ms=2) as emu:
        host = Host(emu.ports())
        start_session(host)
        stream(host, 50, controller=lambda g: (0, 5000))
        emu.inject("driver", "reset")
        ident = host.wait("driver", lambda f: isinstance(f.message, Ident))
        assert ident.seq == 0
        stream(host, 10, controller=lambda g: (0, 5000))
        assert emu.driver.output_counts() == (0, 0)
        nack = host.wait("driver", lambda f: isinstance(f.message, Nack)).message
        assert nack.error == ErrorCode.NOT_ENABLED
        assert [r.kind for r in emu.recorder.records if r.link == "driver"][-1:] == ["reset"]
        host.close()


@pytest.mark.realtime
def test_disconnect_hangs_up_and_the_same_path_serves_again() -> None:
    with running_emulator(clock="realtime") as emu:
        host = Host(emu.ports())
        emu.inject("image", "disconnect", duration_ms=100)
        time.sleep(0.03)
        host.pump_all(0.01)
        assert host["image"].hangups >= 1
        time.sleep(0.15)
        host["image"].reopen()
        host["image"].send(IdentRequest())
        assert host.wait("image", lambda f: isinstance(f.message, Ident)).message.board == 0x30
        kinds = [r.kind for r in emu.recorder.records if r.link == "image"]
        assert kinds == ["disconnect", "reconnect"]
        host.close()


@pytest.mark.realtime
def test_a_host_that_reconnects_is_served_again() -> None:
    with running_emulator(clock="realtime") as emu:
        host = Host(emu.ports(), host_alive_period_s=0.1)
        start_session(host)
        stream(host, 100)
        host["servo"].close()
        time.sleep(0.1)  # the board keeps streaming into the void (the pty absorbs or drops it)
        host["servo"].reopen()
        host["servo"].decoder.reset()
        assert isinstance(host.request("servo", ServoMode(StreamMode.STREAM)), Ack)
        samples = stream(host, 160)
        # a loaded machine may still deliver a few samples of the old stream before the restarted one
        start = next(i for i, s in enumerate(samples) if s.tick < 5)
        restarted = [s.tick for s in samples[start:]]
        assert start <= 50 and restarted == list(range(restarted[0], restarted[0] + len(restarted)))
        host.close()
