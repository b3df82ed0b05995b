"""The pty self-test end to end: a real emulator process, a real pty, real injected faults."""

from __future__ import annotations

import asyncio
import json

import pytest
from typer.testing import CliRunner

from hil.cli import app, main
from hil.link import LinkError, SerialLink, main_sync
from hil.protocol import CATALOGUE


def test_every_uncorrupted_frame_arrives_once_in_order_under_heavy_faults():
    report = main_sync(ticks=800, seed=7, garbage_rate=0.05, flip_rate=0.03)
    b = report.board
    assert report.failures == []
    assert b["ticks_sent"] == 800
    corrupted = len(b["corrupted_ticks"])
    assert 10 <= corrupted <= 45  # ~3 % of 800, seeded
    assert b["garbage_bursts"] >= 20
    assert report.frames_received == 800 - corrupted
    assert report.lost_untouched == [] and report.corrupted_delivered == []
    assert report.duplicates == 0 and report.out_of_order == 0
    # a single flipped bit is always caught: by the CRC, or earlier by the header checks
    c = report.counters
    assert 1 <= c["crc_errors"] <= corrupted + b["garbage_bursts"]
    assert c["frames_ok"] >= 800 - corrupted  # plus IDENT and ACK
    # every sample the bench saw was answered: the board misses exactly the corrupted ticks
    assert b["missing_commands"] == corrupted
    assert b["commands_received"] == 800 - corrupted


def test_a_board_built_from_another_catalogue_is_refused_naming_both_fingerprints():
    report = main_sync(ticks=200, board_args=("--fingerprint", "0x12345678"))
    assert len(report.failures) == 1
    msg = report.failures[0]
    assert "catalogue mismatch" in msg
    assert "0x12345678" in msg and f"{CATALOGUE.fingerprint:#010x}" in msg
    assert "stub-loopback-1" in msg  # the firmware version
    assert report.frames_received == 0


def test_opening_a_missing_port_names_the_board_and_the_port():
    async def attempt():
        await SerialLink.open("servo", "/dev/does-not-exist-hil")

    with pytest.raises(LinkError, match=r"^servo: cannot open /dev/does-not-exist-hil: "):
        asyncio.run(attempt())


runner = CliRunner()


def test_cli_selftest_json_reports_a_pass():
    result = runner.invoke(app, ["selftest", "--ticks", "300", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["passed"] is True
    assert report["board"]["ticks_sent"] == 300
    assert report["frames_received"] == 300 - len(report["board"]["corrupted_ticks"])


def test_cli_decode_reads_a_hex_capture_and_counts_garbage():
    capture = "00 11 eb 90 01 10 01 10 02 01 1c 40 42 0f 00 e8 03 00 00 20 a1 07 00 70 2f fc ff 00 1b b7 00 80 c3 c9 01 a0 13 ac ff 4c 1c"  # noqa: E501
    result = runner.invoke(app, ["protocol", "decode", "--hex", capture])
    assert result.exit_code == 0, result.output
    assert "GyroSample(t_us=1000000, tick=1000, rate_x_dps=0.5" in result.stdout
    assert "bytes_discarded" in result.stdout


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["protocol", "decode", "/no/such/capture.bin"], "/no/such/capture.bin: no such file"),
        (["protocol", "decode", "--hex", "zz"], "not hex text"),
        (["selftest", "--ticks", "5"], "Invalid value for '--ticks'"),
        (["no-such-command"], "No such command 'no-such-command'"),
    ],
)
def test_cli_bad_input_exits_2_with_one_line_naming_it(args, needle, capsys):
    assert main(args) == 2
    err = capsys.readouterr().err
    assert needle in err
    assert err.count("\n") == 1, err  # exactly one line
    assert "Traceback" not in err


def test_cli_protocol_docs_reports_the_document_up_to_date():
    result = runner.invoke(app, ["protocol", "docs"])
    assert result.exit_code == 0, result.output
    assert "up to date" in result.stdout
