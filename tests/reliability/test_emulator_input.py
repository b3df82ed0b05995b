"""The emulator's inputs: its config and plant files, its options, and its control socket. A bad config exits 2 with
one line before the run directory or a pty exists; a bad control request gets an error reply and the socket keeps
serving."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from firmware_stub.__main__ import main as emulator_main
from firmware_stub.config import DEFAULT_EMULATOR_CONFIG
from firmware_stub.control import MAX_LINE_BYTES, ControlClient, ControlServer
from firmware_stub.plant import DEFAULT_PLANT_CONFIG
from tests.factories import session_data, write_yaml
from tests.firmware_stub.host import running_emulator
from tests.reliability.helpers import bad_input, emulator_run_dirs


def emulator_bad(capsys: pytest.CaptureFixture[str], args: list[str], *needles: str) -> str:
    """`python -m firmware_stub ARGS` in-process: exit 2, one line with every needle, no run directory left."""
    before = emulator_run_dirs()
    try:
        code = emulator_main([str(a) for a in args])
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert emulator_run_dirs() == before
    return lines[0]


def bad_plant(tmp_path: Path, old: str, new: str) -> Path:
    text = DEFAULT_PLANT_CONFIG.read_text()
    assert old in text
    plant = tmp_path / "plant.yaml"
    plant.write_text(text.replace(old, new))
    config = tmp_path / "emulator.yaml"
    config.write_text(f"clock: realtime\nplant: {plant.name}\n")
    return config


@pytest.mark.parametrize(("old", "new", "field"), [
    ("delay_s: 0.5e-3", "delay_s: .nan", "gyro.delay_s: Input should be a finite number"),
    ("inertia_kg_m2: 0.05", "inertia_kg_m2: .inf", "motor_el.inertia_kg_m2: Input should be a finite number"),
    ("frame_rate_hz: 100.0", "frame_rate_hz: 1.0e+9", "camera.frame_rate_hz: Input should be less than or equal"),
    ("internal_step_s: 2.0e-4", "internal_step_s: 3.0e-4", "internal_step_s"),
])
def test_a_bad_plant_is_one_line_naming_both_files_and_leaves_no_run_directory(
    *, capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, old: str, new: str, field: str,
) -> None:
    config = bad_plant(tmp_path, old, new)
    emulator_bad(capsys, ["--config", config], f"{config}: plant: {tmp_path / 'plant.yaml'}: {field}")


def test_hil_emulate_with_a_bad_plant_leaves_nothing(tmp_path: Path) -> None:
    """The measured failure, as a user runs it: a traceback and a `hil-emu-*` directory left in the temp dir."""
    config = bad_plant(tmp_path, "delay_s: 0.5e-3", "delay_s: .nan")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    proc = subprocess.run([sys.executable, "-m", "hil", "emulate", "--config", str(config)], capture_output=True,
                          text=True, timeout=60, check=False, env={**os.environ, "TMPDIR": str(tmp)})
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "gyro.delay_s" in lines[0] and str(config) in lines[0]
    assert list(tmp.iterdir()) == [] and proc.stdout == ""


@pytest.mark.parametrize(("content", "needle"), [
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + bytes(range(256)), "not UTF-8 text (byte 0x89 at offset 0)"),
    (b"clock: lockstep\nlockstep_timeout_ms: .nan\n", "lockstep_timeout_ms: Input should be a finite number"),
    (b"clock: lockstep\nfaults: [{at_s: .inf, link: servo, kind: stall}]\n", "faults.0.at_s: Input should be a finite"),
    (b"links: {servo: {bit_error_rate: .nan}}\n", "links.servo.bit_error_rate: Input should be a finite"),
    (b"boards: {driver: {bus_voltage_v: -.inf}}\n", "boards.driver.bus_voltage_v: Input should be a finite"),
    (b"x: &x 1\ny: *x\n", "anchors and aliases are not used in emulator files"),
    (b"seed: [" * 80 + b"]" * 80, "nested deeper than 64 levels"),
    (b"- 1\n", "expected a mapping at the top level, got list"),
])
def test_a_bad_emulator_config_names_the_file(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, content: bytes, needle: str,
) -> None:
    config = tmp_path / "emulator.yaml"
    config.write_bytes(content)
    emulator_bad(capsys, ["--config", config], str(config), needle)


def test_a_fifo_device_or_directory_as_the_config(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path,
) -> None:
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    for path in (fifo, Path("/dev/zero"), tmp_path):
        emulator_bad(capsys, ["--config", path], f"{path}: not a regular file")
    emulator_bad(capsys, ["--config", tmp_path / "absent.yaml"], "absent.yaml: cannot read: No such file")


@pytest.mark.parametrize(("args", "needle"), [
    (["--seconds", "nan"], "--seconds: nan is not in (0, 86400]"),
    (["--seconds", "inf"], "--seconds: inf is not in (0, 86400]"),
    (["--seconds", "-1"], "--seconds: -1.0 is not in (0, 86400]"),
    (["--seed", "-3"], "--seed: -3 is not in 0..4294967295"),
    (["--rt-priority", "200"], "--rt-priority: 200 is not in 0..99"),
    (["--fingerprint", "0x1ffffffff"], "--fingerprint: 0x1ffffffff is not a 32-bit number"),
    (["--fingerprint", "zz"], "argument --fingerprint: invalid"),
    (["--clock", "sundial"], "argument --clock: invalid choice: 'sundial'"),
    (["--fault-log", "{tmp}/no/dir/f.jsonl"], "--fault-log {tmp}/no/dir/f.jsonl: no directory {tmp}/no/dir"),
    (["--fault-log", "{tmp}"], "--fault-log {tmp}: exists and is not a regular file"),
    (["--ports-file", "{tmp}"], "--ports-file {tmp}: exists and is not a regular file"),
])
def test_bad_options_are_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, args: list[str], needle: str,
) -> None:
    emulator_bad(capsys, [a.format(tmp=tmp_path) for a in args], needle.format(tmp=tmp_path))


def test_a_good_run_leaves_nothing_either(capsys: pytest.CaptureFixture[str], tmp_path: Path,
                                          private_tmp: Path) -> None:
    ports = tmp_path / "ports.json"
    assert emulator_main(["--config", str(DEFAULT_EMULATOR_CONFIG), "--seconds", "0.05", "--ports-file",
                          str(ports)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert json.loads(out[0])["servo"] and json.loads(out[-1])["tick"] == 50
    assert list(private_tmp.iterdir()) == [] and not ports.exists()


# --- the control socket ----------------------------------------------------------------------------------------------


def raw_call(path: str, line: bytes) -> dict[str, Any]:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(5)
        s.connect(path)
        s.sendall(line + b"\n")
        buf = b""
        while not buf.endswith(b"\n"):
            chunk = s.recv(65536)
            if not chunk:
                break
            buf += chunk
    return json.loads(buf)


@pytest.mark.parametrize(("request_line", "error"), [
    (b'{"cmd": "inject", "link": "servo", "kind": "stall", "duration_ms": 1e400}',
     "inject: duration_ms: Input should be a finite number (got inf)"),
    (b'{"cmd": "inject", "link": "servo", "kind": "stall", "duration_ms": NaN}', "inject: duration_ms: Input should "
                                                                                   "be a finite number"),
    (b'{"cmd": "inject", "link": "servo", "kind": "stall", "duration_ms": 1e9}', "inject: duration_ms: Input should "
                                                                                  "be less than or equal to 600000"),
    (b'{"cmd": "inject", "link": "servo", "kind": "garbage", "n_bytes": 0}', "inject: n_bytes: Input should be "
                                                                              "greater than or equal to 1"),
    (b'{"cmd": "inject", "link": "camera", "kind": "stall"}', "inject: link: Input should be"),
    (b'{"cmd": "inject", "link": "servo", "kind": "meltdown"}', "inject: kind: Input should be"),
    (b'{"cmd": "inject", "link": "servo", "kind": "stall", "when": 3}', "inject: when: Extra inputs are not permitted"),
    (b'{"cmd": "set_faults", "link": "servo", "bit_error_rate": 2}', "set_faults: (top level): faults: bit_error_rate"),
    (b'{"cmd": "set_faults", "link": "servo", "bit_flip": 0.1}', "set_faults: (top level): bit_flip: not a LinkFaults"),
    (b'{"cmd": "records", "since": -1}', "records: since: Input should be greater than or equal to 0"),
    (b'{"cmd": "reboot"}', "unknown command 'reboot'"),
    (b'{"cmd": ["status"]}', "unknown command ['status']"),
    (b'[1, 2]', "expected a JSON object"),
    (b'{"cmd": ', "Expecting value"),
    (b'\xff\xfe', "Expecting value"),
])
def test_the_control_socket_answers_bad_requests_and_keeps_serving(request_line: bytes, error: str) -> None:
    with running_emulator(clock="lockstep") as emu:
        path = emu.ports()["control"]
        reply = raw_call(path, request_line)
        assert set(reply) == {"error"} and error in reply["error"], reply
        assert not emu.recorder.records  # nothing was injected
        with ControlClient(path) as ctl:  # still serving, on a new connection
            assert ctl.call("status")["tick"] == 0
            assert ctl.call("inject", link="servo", kind="stall", duration_ms=20)["ok"]
        assert [r.kind for r in emu.recorder.records] == ["stall"]


def test_an_overlong_request_is_refused_and_its_client_dropped() -> None:
    with running_emulator(clock="lockstep") as emu:
        path = emu.ports()["control"]
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(5)
            s.connect(path)
            s.sendall(b"x" * (MAX_LINE_BYTES + 70_000))  # no newline: it would grow without bound
            reply = s.makefile("rb").readline()
        assert json.loads(reply) == {"error": f"a request longer than {MAX_LINE_BYTES} bytes"}
        with ControlClient(path) as ctl:
            assert ctl.call("status")["streaming"] is False


def test_a_failing_handler_is_that_request_s_error(tmp_path: Path) -> None:
    def handler(request: dict[str, Any]) -> dict[str, Any]:
        return {"ok": True} if request["cmd"] == "status" else {"x": round(float("inf"))}

    server = ControlServer(tmp_path / "c.sock", handler)
    client = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        client.connect(str(server.path))
        server._accept(0.0)
        (fd,) = server.clients
        for line, want in ((b'{"cmd": "stop"}', {"error": "stop: OverflowError: cannot convert float infinity to "
                                                           "integer"}), (b'{"cmd": "status"}', {"ok": True})):
            client.sendall(line + b"\n")
            server._serve(fd)
            assert json.loads(client.recv(65536)) == want
    finally:
        client.close()
        server.close()


def test_hil_run_loopback_with_a_bad_emulator_plant_is_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path,
) -> None:
    """The bench starts the emulator, which refuses its plant before it makes anything: the bench relays that one
    line (hil.session._loopback), and no log, run directory or process is left."""
    config = bad_plant(tmp_path, "delay_s: 0.5e-3", "delay_s: .nan")
    data = session_data()
    data["emulator"]["config"] = str(config)
    session = write_yaml(tmp_path / "s.yaml", data)
    out = tmp_path / "out"
    bad_input(capsys, ["run", session, "--loopback", "--out", out],
              f"the emulator did not start: {config}: plant: {tmp_path / 'plant.yaml'}: gyro.delay_s")
    assert not out.exists() and list(private_tmp.iterdir()) == []
