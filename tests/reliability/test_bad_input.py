"""A user's broken session file never reaches the boards: `hil run` exits 2 with one line naming the file and the
field, before any emulator starts or any port opens, and leaves nothing behind (docs/reliability.md)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from hil.config import MAX_CONFIG_BYTES, MAX_YAML_NODES, PROFILES, load_session
from tests.factories import session_data, write_yaml
from tests.reliability.helpers import bad_input, emulator_run_dirs, listing

NAN, INF = float("nan"), float("inf")
PITCH = {"axis": "pitch", "amplitude": 1.0, "frequency_hz": 1.0, "duration_s": 5.0}


def run_bad(capsys: pytest.CaptureFixture[str], tmp_path: Path, session: Path, *needles: str) -> str:
    """`hil run SESSION --loopback --out OUT` on bad input: one line, exit 2, no file or emulator left behind."""
    out = tmp_path / "out"
    before, emus = listing(tmp_path), emulator_run_dirs()
    line = bad_input(capsys, ["run", session, "--loopback", "--out", out], *needles)
    assert listing(tmp_path) == before and not out.exists()
    assert emulator_run_dirs() == emus
    return line


# --- numbers: NaN, infinities and values beyond their documented range ---------------------------------------------


@pytest.mark.parametrize(("changes", "field", "reason"), [
    ({"profile": {"segments": [{**PITCH, "phase_deg": INF}]}}, "profile.segments.0.phase_deg", "finite"),
    ({"profile": {"segments": [{**PITCH, "amplitude": NAN}]}}, "profile.segments.0.amplitude", "finite"),
    ({"profile": {"segments": [{**PITCH, "duration_s": 1e9}]}}, "profile.segments.0.duration_s", "3600"),
    ({"profile": {"segments": [{**PITCH, "start_s": 3000.0, "duration_s": 700.0}]}}, "duration_s", "3600 s"),
    ({"profile": {"segments": [{**PITCH, "frequency_hz": 1e6}]}}, "profile.segments.0.frequency_hz", "100"),
    ({"duration_s": INF}, "duration_s", "finite"),
    ({"duration_s": 1e9}, "duration_s", "86400"),
    ({"seed": 2**40}, "seed", "4294967295"),
    ({"tracking": {"max_rate_dps": 1e300}}, "tracking.max_rate_dps", "1000"),
    ({"tracking": {"kp_per_s": NAN}}, "tracking.kp_per_s", "finite"),
    ({"safety": {"watchdog_ms": 1e300}}, "safety.watchdog_ms", "10000"),
    ({"excitation": {"axis": "el", "amplitude_dps": NAN, "freq_hz": 15.0}}, "excitation.sine.amplitude_dps", "finite"),
    ({"excitation": {"duration_s": INF}}, "excitation.sweep.duration_s", "finite"),
    ({"mqtt": {"host": "h", "reconnect_max_s": INF}}, "mqtt.reconnect_max_s", "finite"),
    ({"controller": {"name": "eso", "params": {"kp_counts_per_dps": INF}}}, "kp_counts_per_dps", "finite"),
    ({"controller": {"name": "eso", "params": {"kp_counts_per_dps": 1e300}}}, "kp_counts_per_dps", "100000"),
    ({"controller": {"name": "eso_turbo"}}, "controller", "unknown controller 'eso_turbo'"),
    ({"controller": {"name": "eso", "params": {"omega_o": 1.0}}}, "controller", "unknown parameter 'omega_o'"),
])
def test_a_bad_number_in_a_session_file_never_reaches_a_board(
    *, capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_board_contact: None,
    changes: dict[str, Any], field: str, reason: str,
) -> None:
    session = write_yaml(tmp_path / "bad.yaml", session_data(**changes))
    run_bad(capsys, tmp_path, session, str(session), field, reason)


def test_nan_amplitude_in_an_included_swing_file_names_that_file(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_board_contact: None,
) -> None:
    """The measured failure: NaN passed the envelope check, DRIVE_ENABLE went out, then a traceback."""
    swing = tmp_path / "swing.yaml"
    swing.write_text("segments:\n  - {axis: pitch, amplitude: .nan, frequency_hz: 1.0, duration_s: 5.0}\n")
    session = write_yaml(tmp_path / "s.yaml", session_data(profile="swing.yaml"))
    run_bad(capsys, tmp_path, session, str(session), f"profile: {swing}", "segments.0.amplitude", "finite")


def test_a_bad_controller_file_is_named(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_board_contact: None,
) -> None:
    ctrl = tmp_path / "ctrl.yaml"
    ctrl.write_text("name: eso_kf\nparams: {q_dps2: .inf}\n")
    session = write_yaml(tmp_path / "s.yaml", session_data(controller=str(ctrl)))
    run_bad(capsys, tmp_path, session, str(ctrl), "q_dps2", "finite")


# --- files that are not config files ---------------------------------------------------------------------------------


@pytest.mark.parametrize(("content", "reason"), [
    (bytes(range(128, 256)) * 8, "not UTF-8 text (byte 0x80 at offset 0)"),
    (b"- just\n- a list\n", "expected a mapping at the top level, got list"),
    (b"name: [unclosed\n", "cannot read YAML"),
    (b"seed: " + b"9" * 5000 + b"\n", "cannot read YAML"),
    (b"x: " + b"[" * 100 + b"]" * 100 + b"\n", "nested deeper than 64 levels"),
    (b"a: &a [*a]\n", "an alias refers to a value that contains it"),
    (b"x: &x 1\n" + b"".join(b"y%d: *x\n" % i for i in range(65)), "more than 64 aliases"),
    (b"a: &a [" + b"1, " * 9 + b"1]\n" + b"".join(
        b"l%d: &l%d [%s]\n" % (i, i, b", ".join([b"*l%d" % (i - 1) if i > 1 else b"*a"] * 10)) for i in range(1, 6)),
     f"more than {MAX_YAML_NODES} values once its aliases are expanded"),
])
def test_a_file_that_is_not_a_session_is_one_line(
    *, capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_board_contact: None,
    content: bytes, reason: str,
) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(content)
    run_bad(capsys, tmp_path, bad, str(bad), reason)


def test_an_oversized_file_is_refused_unread(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_board_contact: None,
) -> None:
    big = tmp_path / "big.yaml"
    big.write_bytes(b"#" * (MAX_CONFIG_BYTES + 1))
    run_bad(capsys, tmp_path, big, str(big), f"{MAX_CONFIG_BYTES + 1} bytes", str(MAX_CONFIG_BYTES))


@pytest.mark.parametrize(("path", "reason"), [
    (Path("/dev/zero"), "a character device, not a regular file"),
    (Path("/dev/null"), "a character device, not a regular file"),
    (None, "a directory, not a regular file"),
    (Path("/nonexistent/s.yaml"), "no such file"),
])
def test_a_device_a_directory_or_nothing_as_the_session_file(
    *, capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_board_contact: None,
    path: Path | None, reason: str,
) -> None:
    target = path or tmp_path
    run_bad(capsys, tmp_path, target, str(target), reason)


def test_a_fifo_as_the_session_file_does_not_hang(tmp_path: Path) -> None:
    """A real `hil run` (a FIFO with no writer would block a plain open for ever): exit 2 at once."""
    fifo = tmp_path / "session.yaml"
    os.mkfifo(fifo)
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "hil", "run", str(fifo), "--loopback", "--out", str(out)],
                          capture_output=True, text=True, timeout=60, check=False,
                          env={**os.environ, "TMPDIR": str(tmp_path)})
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert f"{fifo}: a FIFO, not a regular file" in lines[0]
    assert not out.exists() and not list(tmp_path.glob("hil-emu-*"))


def test_a_missing_or_bad_included_file_is_named(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_board_contact: None,
) -> None:
    session = write_yaml(tmp_path / "s.yaml", session_data(hexapod_limits="nope.yaml"))
    run_bad(capsys, tmp_path, session, str(session), "hexapod_limits", f"{tmp_path / 'nope.yaml'}: no such file")
    (tmp_path / "limits.yaml").write_bytes(b"\xff\xfe garbage")
    session = write_yaml(tmp_path / "s.yaml", session_data(hexapod_limits="limits.yaml"))
    run_bad(capsys, tmp_path, session, str(tmp_path / "limits.yaml"), "not UTF-8")


def test_a_missing_emulator_config_is_refused_before_the_emulator_starts(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_board_contact: None,
) -> None:
    data = session_data()
    data["emulator"]["config"] = str(tmp_path / "no-emulator.yaml")
    session = write_yaml(tmp_path / "s.yaml", data)
    run_bad(capsys, tmp_path, session, "emulator.config", f"{tmp_path / 'no-emulator.yaml'}: no such file")


def test_markup_in_a_value_is_printed_as_is(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_board_contact: None,
) -> None:
    """A value holding console markup ('[/]') is shown, not interpreted (it used to raise MarkupError)."""
    session = write_yaml(tmp_path / "s.yaml", session_data(name="[/]"))
    run_bad(capsys, tmp_path, session, "name: String should match pattern", "(got '[/]')")


def test_the_shipped_session_files_still_load() -> None:
    for path in sorted((PROFILES / "sessions").glob("*.yaml")):
        assert load_session(path).duration_s > 0, path


def test_a_line_too_slow_for_the_link_budget_is_refused_before_anything_is_sent(tmp_path: Path) -> None:
    """docs/protocol.md's link budget: 115 200 baud cannot carry GYRO_SAMPLE at 1 kHz (433 kbit/s)."""
    from hil.config import PROFILES, ConfigError, load_session

    data = load_session(PROFILES / "sessions" / "demo.yaml").model_dump(mode="json", exclude_none=True)
    data["safety"].pop("emulator_stall_grace_ms", None)
    data["ports"] = {"servo": {"port": "/dev/nonexistent-servo", "baudrate": 115200},
                     "driver": {"port": "/dev/nonexistent-driver", "baudrate": 460800},
                     "image": {"port": "/dev/nonexistent-image"}, "hexapod": {"port": "/dev/nonexistent-hexapod"}}
    session = tmp_path / "slow.yaml"
    session.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as err:
        load_session(session)
    assert str(err.value) == (f"{session}: ports: servo.baudrate: 115200 baud carries 115.2 kbit/s, and the periodic "
                              "messages servo → host need 433.0 kbit/s (at most 80% of the line, docs/protocol.md "
                              "link budget); use at least 921600 baud on both ends")
    session.write_text(session.read_text().replace("115200", "921600"))
    assert load_session(session).ports.driver.baudrate == 460_800  # the driver's commands fit in 460 800
