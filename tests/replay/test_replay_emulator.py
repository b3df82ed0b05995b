"""`hil replay CAPTURE --to-emulator`: a captured session's frames played back at a fresh emulator. In lockstep, with
the same seed, the boards accept every frame and answer with the very samples the capture holds; a capture cut
mid-run, or a stream that never starts, ends with the boards left safe by the replay itself."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest
from typer.testing import CliRunner

from hil.cli import app
from hil.link import RECORD_OVERHEAD, CaptureReader, decode_capture, link_decoder
from hil.protocol import CATALOGUE, DriveCmd, GyroSample, HexapodStop
from hil.replay import CapturePlayer, PlaybackResult, ReplayError, play_capture
from hil.session import EmulatorProcess
from tests.replay.conftest import CapturedRun

runner = CliRunner()


# A lockstep emulator streams at the pace the machine lets it: a watchdog far above any pause of a loaded machine
# (the replay's 100 ms is a board's; test_replay_playback tests it against boards that stop streaming), and the last
# replies awaited as long (the wait ends as soon as they are in)
LOADED = {"watchdog_s": 1.0, "linger_s": 5.0}


def play(capture: Path, seed: int = 3, **kwargs: object) -> PlaybackResult:
    kwargs = {**LOADED, **kwargs}
    with EmulatorProcess(None, clock="lockstep", seed=seed) as emu:
        return play_capture(capture, {k: v for k, v in emu.ports.items() if k != "control"}, **kwargs)


def captured(run: CapturedRun) -> tuple[int, int]:
    return captured_in(run.capture)


def captured_in(capture: Path) -> tuple[int, int]:
    """Samples the bench received and the last DRIVE_CMD tick it sent, in the capture."""
    frames = list(decode_capture(capture))
    samples = sum(type(f.frame.message) is GyroSample for f in frames)
    last_drive = max(f.frame.message.tick for f in frames if type(f.frame.message) is DriveCmd)
    return samples, last_drive


def lockstep_commands(run: CapturedRun) -> int:
    """IDENT_REQs and commands in a lockstep capture: the 16 of a realtime run, but the wind-down's HEXAPOD_STOP goes
    out every 10 ticks until the table rests (hil.session.TickWindDown), not once."""
    stops = sum(type(f.frame.message) is HexapodStop for f in decode_capture(run.capture, directions=["tx"]))
    assert stops > 50
    return 16 + stops - 2


def test_a_lockstep_capture_played_to_a_fresh_emulator_is_answered_frame_for_frame(lockstep_run: CapturedRun,
                                                                                   tmp_path: Path) -> None:
    samples, last_drive = captured(lockstep_run)
    r = play(lockstep_run.capture, record_dir=tmp_path)
    assert r.stopped == "" and r.safe_end == []  # the capture ended safe by itself
    assert r.frames_sent == r.frames_in_capture > samples
    assert r.commands == r.answered == lockstep_commands(lockstep_run)  # every IDENT_REQ and command: IDENT or ACK
    assert all(lp.nacked == 0 and not lp.nacks and lp.unanswered == 0 and lp.write_stalls == 0
               for lp in r.links.values())
    assert r.links["driver"].sent["DRIVE_CMD"] == last_drive + 1
    assert r.drive_enabled_seen and last_drive - 10 <= r.drive_last_tick <= last_drive  # its 100 Hz DRIVE_STATUS
    # the stream the replayed STREAM started is the captured one: the same samples, tick by tick; only the
    # one sample after the disarm may differ (whether DRIVE_DISABLE lands before that step races in lockstep)
    assert r.stream_started and r.samples == r.samples_compared == samples
    assert r.samples_equal >= samples - 1 and r.first_differing_tick in (-1, samples - 1)
    assert r.loop_timing["missing"] == 0 and r.loop_timing["ticks_reported"] >= samples - 20
    for name, lp in r.links.items():  # what came back is what the bench received
        assert lp.received == lp.captured_rx, name
    # the replay's own capture holds what it sent and got
    assert r.record is not None
    frames = list(decode_capture(r.record))
    assert sum(type(f.frame.message) is DriveCmd for f in frames) == last_drive + 1
    assert sum(type(f.frame.message) is GyroSample for f in frames) == samples
    assert CaptureReader(r.record).meta["replay_of"] == str(lockstep_run.capture)


@pytest.mark.slow
@pytest.mark.realtime
def test_a_realtime_capture_played_to_a_realtime_emulator_answers_each_sample_with_its_drive(
        realtime_run: CapturedRun, tmp_path: Path) -> None:
    tx = list(decode_capture(realtime_run.capture, directions=["tx"]))
    sent = Counter((f.link, CATALOGUE.spec(f.frame.message).name) for f in tx)
    drive_ticks = [f.frame.message.tick for f in tx if type(f.frame.message) is DriveCmd]
    with EmulatorProcess(None, clock="realtime", seed=3) as emu:
        r = play_capture(realtime_run.capture, {k: v for k, v in emu.ports.items() if k != "control"},
                         record_dir=tmp_path, **LOADED)
    overflow = emu.summary["links"]["servo"]["tx_overflow_bytes"]  # what the replay did not read in time: lost
    assert r.stopped == "" and r.safe_end == [] and r.answered == r.commands == 16
    # every frame the capture holds went out whole: as many HOST_ALIVE as the session's pace made, no more
    assert all(lp.write_stalls == 0 for lp in r.links.values()) and r.drive_enabled_seen
    assert Counter({(name, m): n for name, lp in r.links.items() for m, n in lp.sent.items()}) == sent
    # DRIVE_CMD k went out once the replayed stream's sample k was in, however late the machine let either come
    assert r.stream_started and r.record is not None
    frames = list(decode_capture(r.record))
    rx_at = {f.frame.message.tick: f.t_ns for f in frames if type(f.frame.message) is GyroSample}
    drives = [(f.frame.message.tick, f.t_ns) for f in frames if type(f.frame.message) is DriveCmd]
    assert [k for k, _ in drives] == drive_ticks and len(rx_at) == r.samples
    assert all(t > rx_at[k] for k, t in drives if k in rx_at)
    assert overflow > 0 or (r.samples_lost == 0 and all(k in rx_at for k, _ in drives))
    # the board measured each DRIVE_CMD against its own sample of the tick, or reported it missing (over 10 ms late,
    # or none): it measured no more than were sent, and every miss it counted is in a report the replay got
    t = r.loop_timing
    assert t["ticks_reported"] > 0 and t["ticks_reported"] - t["missing"] <= len(drive_ticks)
    assert overflow > 0 or t["missing"] == t["missing_total"]


def sample_record_end(capture: Path, after: int) -> int:
    """Where the first record past byte ``after`` that completes a GYRO_SAMPLE ends in the file."""
    reader = CaptureReader(capture)
    servo = link_decoder("servo", "rx")
    end = reader.data_offset
    for rec in reader:
        end += RECORD_OVERHEAD + len(rec.data)
        frames = servo.feed(rec.data) if (rec.link, rec.direction) == ("servo", "rx") else []
        if end > after and any(type(f.message) is GyroSample for f in frames):
            return end
    raise AssertionError(f"{capture}: no GYRO_SAMPLE after byte {after}")


def test_a_capture_cut_mid_run_is_played_then_the_replay_disarms(lockstep_run: CapturedRun, tmp_path: Path) -> None:
    data = lockstep_run.capture.read_bytes()
    cut = tmp_path / "cut.hilcap"
    # as a killed session leaves it: streaming, enabled, swinging; its last sample not yet answered, the record after
    # it cut short
    cut.write_bytes(data[: sample_record_end(lockstep_run.capture, len(data) // 2) + 7])
    held, last_drive = captured_in(cut)
    assert held == last_drive + 2
    r = play(cut)
    assert r.stopped == ""
    assert r.safe_end == ["DRIVE_DISABLE", "HEXAPOD_STOP", "SERVO_MODE"]
    assert r.answered == r.commands and all(lp.nacked == 0 for lp in r.links.values())
    assert r.links["driver"].sent["DRIVE_CMD"] == last_drive + 1
    # every sample the capture holds came back, equal: the unanswered last one too, which the board sends on the last
    # DRIVE_CMD and the replay awaits before its safe end can reach the board
    assert r.samples_compared == r.samples_equal == held > 500 and r.first_differing_tick == -1
    assert r.samples_lost == 0
    assert r.links["driver"].acked == 3  # IDENT, DRIVE_ENABLE and the replay's DRIVE_DISABLE


@pytest.mark.slow
def test_a_stream_that_never_starts_stops_the_replay_before_any_drive(lockstep_run: CapturedRun) -> None:
    # without the servo link nothing starts the stream: no sample comes, so no DRIVE_CMD may go
    r = play(lockstep_run.capture, links={"driver", "image", "hexapod"})
    assert r.stopped == "no GYRO_SAMPLE: the servo board did not start its stream"
    assert r.links["driver"].sent["DRIVE_CMD"] == 0 and r.links["driver"].sent["DRIVE_ENABLE"] == 1
    # the swing starts after the start pose phase, inside the stream: no HEXAPOD_START went, so none to stop
    assert r.safe_end == ["DRIVE_DISABLE"] and r.links["hexapod"].sent["HEXAPOD_START"] == 0
    assert r.answered == r.commands == 8  # 3 IDENT_REQ, TRACK_CMD, 2 PROFILE_LOAD, ENABLE; DISABLE
    assert not r.stream_started and r.samples == 0


def test_ports_must_cover_the_links_the_capture_sent_on(lockstep_run: CapturedRun) -> None:
    with pytest.raises(ReplayError, match=r"no port for link.*servo"):
        play_capture(lockstep_run.capture, {"driver": "/dev/null"})


def test_the_cli_plays_a_capture_to_a_fresh_emulator_and_reports_json(lockstep_run: CapturedRun, tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    for name, value in LOADED.items():  # the command line has no options for these
        monkeypatch.setitem(CapturePlayer.__init__.__kwdefaults__, name, value)
    samples, last_drive = captured(lockstep_run)
    result = runner.invoke(app, ["replay", str(lockstep_run.capture.parent), "--to-emulator", "--json",
                                 "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)  # the JSON alone: nothing else on stdout
    assert data["emulator"] == {"config": str(lockstep_run.session.config.emulator.config), "clock": "lockstep",
                                "seed": 3}  # the fresh emulator ran as the captured one did
    assert data["answered"] == data["commands"] == lockstep_commands(lockstep_run) and data["stopped"] == ""
    assert data["links"]["driver"]["sent"]["DRIVE_CMD"] == last_drive + 1 and data["samples"] == samples
    assert json.loads((tmp_path / f"replay-{lockstep_run.capture.stem}.json").read_text())["samples"] == samples
    assert len(list(tmp_path.glob("*.hilcap"))) == 1


def test_the_cli_replays_a_log_and_refuses_what_does_not_fit(lockstep_run: CapturedRun, tmp_path: Path) -> None:
    log = str(lockstep_run.log)
    result = runner.invoke(app, ["replay", log, "--controller", "eso_kf", "--params", "omega_o_rad_s=500",
                                 "--settle", "0.5", "--out", str(tmp_path), "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["controller"]["replayed"] == {"name": "eso_kf", "params": {"omega_o_rad_s": 500}}
    assert data["axes"]["el"]["drive_diff_rms_counts"] > 0 and Path(data["plot"]).is_file()
    table = runner.invoke(app, ["replay", log, "--settle", "0.5", "--out", str(tmp_path)])
    assert table.exit_code == 0 and "drive minus logged (rms)" in table.stdout
    for args, message in (
        ([log, "--controller", "lqr"], "unknown controller 'lqr'"),
        ([log, "--params", "omega_o_rad_s"], "--params omega_o_rad_s: 'omega_o_rad_s' is not k=v"),
        ([log, "--to-emulator", "--controller", "eso"], "--controller/--params replay a log"),
        ([str(lockstep_run.capture), "--controller", "eso"], "a capture; play it back with --to-emulator"),
        ([log, "--port", "servo=/dev/null"], "go with --to-emulator"),
        ([str(lockstep_run.capture), "--to-emulator", "--port", "gimbal=/dev/null"],
         "--port gimbal=/dev/null: not LINK=PATH"),
        ([log, "--to-emulator"], "not a capture"),
    ):
        bad = runner.invoke(app, ["replay", *args])
        assert bad.exit_code == 2, (args, bad.output)
        assert message in bad.output, (args, bad.output)
