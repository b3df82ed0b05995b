"""Command-line habits: -h, choices in help, completion, -q/-v, --json, `hil check`, errors on stderr."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from hil.config import PROFILES

HIL = [sys.executable, "-m", "hil"]


def hil(*args: str, env: dict[str, str] | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*HIL, *map(str, args)], check=False, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "COLUMNS": "200", **(env or {})}, cwd=cwd)


def session_file(tmp_path: Path, seconds: float) -> Path:
    """The shipped 1 deg / 1 Hz ESO session, ``seconds`` long, as a file with absolute paths."""
    data = yaml.safe_load((PROFILES / "sessions" / "swing-1deg-1hz-eso.yaml").read_text())
    for key in ("controller", "profile", "hexapod_limits"):
        data[key] = str((PROFILES / "sessions" / data[key]).resolve())
    data["emulator"]["config"] = str((PROFILES / "sessions" / data["emulator"]["config"]).resolve())
    data["duration_s"] = seconds
    session = tmp_path / "s.yaml"
    session.write_text(yaml.safe_dump(data))
    return session


@pytest.mark.parametrize(("command", "choices"), [
    (["run"], "realtime|lockstep|sim"), (["ident"], "el|az"), (["export"], "parquet|csv"),
    (["campaign"], "sim|lockstep"), (["check"], "session|campaign|controller|swing|hexapod|emulator|plant"),
    (["emulate"], "realtime|lockstep")])
def test_dash_h_is_help_and_lists_the_choices(command: list[str], choices: str) -> None:
    out = hil(*command, "-h")
    assert out.returncode == 0, out.stderr
    assert "Usage: hil " + command[0] in out.stdout
    assert choices in out.stdout


def test_a_bad_choice_is_one_line_on_stderr_with_exit_2() -> None:
    out = hil("run", "x.yaml", "--clock", "warp")
    assert out.returncode == 2 and out.stdout == ""
    assert len(out.stderr.strip().splitlines()) == 1 and "'warp' is not one of" in out.stderr


def test_shell_completion_completes_commands_and_choices() -> None:
    # the script --install-completion / --show-completion write for bash (without guessing the shell from the
    # process tree, which depends on how the test was started)
    assert "_hil_completion" in hil(env={"_HIL_COMPLETE": "source_bash"}).stdout
    env = {"_HIL_COMPLETE": "complete_bash", "COMP_WORDS": "hil run x --clock ", "COMP_CWORD": "4"}
    assert hil(env=env).stdout.split() == ["realtime", "lockstep", "sim"]
    env = {"_HIL_COMPLETE": "complete_bash", "COMP_WORDS": "hil ch", "COMP_CWORD": "1"}
    assert hil(env=env).stdout.split() == ["check"]


def test_quiet_and_verbose_exclude_each_other() -> None:
    out = hil("-q", "-v", "check", PROFILES / "sessions" / "demo.yaml")
    assert out.returncode == 2 and "choose one" in out.stderr


def test_check_validates_every_kind_and_reports_each_bad_file(tmp_path: Path) -> None:
    good = sorted(PROFILES.glob("*/*.yaml"))
    out = hil("check", *good)
    assert out.returncode == 0, out.stderr
    assert out.stdout.count("ok ") == len(good) and out.stderr == ""
    bad = tmp_path / "bad-controller.yaml"
    bad.write_text("name: eso\nparams: {omega_o_rad_s: -1}\n")
    swing = tmp_path / "swing.yaml"
    swing.write_text("segments: [{axis: pitch, amplitude: 1, frequency_hz: 1, duration_s: 5000}]\n")
    out = hil("check", "--kind", "controller", bad, PROFILES / "controllers" / "eso.yaml")
    assert out.returncode == 2
    assert out.stdout.count("ok ") == 1
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "omega_o_rad_s" in lines[0] and str(bad) in lines[0]
    out = hil("check", "--json", swing, PROFILES / "swing" / "static.yaml")
    assert out.returncode == 2
    data = json.loads(out.stdout)
    assert data["ok"] is False
    assert [f["ok"] for f in data["files"]] == [False, True]
    assert "duration_s" in data["files"][0]["error"] and data["files"][1]["kind"] == "swing"


def test_errors_go_to_stderr_and_results_to_stdout(tmp_path: Path) -> None:
    out = hil("run", tmp_path / "missing.yaml", "--loopback")
    assert out.returncode == 2 and out.stdout == "" and "no such file" in out.stderr
    out = hil("watch", "--broker", "mqtt://127.0.0.1:1", "--seconds", "1")
    assert out.returncode != 0 and out.stdout.strip() == "" and "127.0.0.1" in out.stderr


@pytest.mark.slow
def test_run_json_is_one_document_and_lockstep_board_latency_is_na(tmp_path: Path) -> None:
    session = session_file(tmp_path, 1.0)
    out = hil("-q", "run", session, "--loopback", "--clock", "lockstep", "--out", tmp_path, "--json")
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    assert summary["status"] == "completed" and summary["clock"] == "lockstep"
    assert summary["board_latency_us"]["p50"] is None and "lockstep" in summary["board_latency_us"]["na_reason"]
    text = hil("report", summary["log"])
    assert text.returncode == 0
    board_row = next(line for line in text.stdout.splitlines() if "board-measured" in line)
    assert "n/a" in board_row and "lockstep" in board_row and "0 / 0" not in board_row


@pytest.mark.slow
def test_campaign_and_report_of_a_campaign_dir_speak_json_and_quiet_leaves_out_the_notes(tmp_path: Path) -> None:
    from tests.api.test_api import small_campaign

    path = small_campaign(tmp_path)
    out = hil("campaign", path, "--out", tmp_path / "out", "--json")
    assert out.returncode in (0, 1), out.stderr
    ran = json.loads(out.stdout)
    assert len(ran["cells"]) == 2 and ran["complete"] is True
    assert all(0.55 < c["metrics"]["lag_lpf_cycles"] < 0.75 for c in ran["cells"])
    assert Path(ran["report"]["html"]).is_file()
    again = json.loads(hil("report", tmp_path / "out", "--json").stdout)
    assert [c["metrics"] for c in again["cells"]] == [c["metrics"] for c in ran["cells"]]
    assert again["passed"] == ran["passed"]
    assert "report:" in hil("report", tmp_path / "out").stdout
    assert hil("-q", "report", tmp_path / "out").stdout == ""


@pytest.mark.slow
def test_verbose_logs_what_the_session_does_on_stderr_and_quiet_prints_only_results(tmp_path: Path) -> None:
    session = session_file(tmp_path, 0.5)
    loud = hil("-v", "run", session, "--loopback", "--clock", "sim", "--out", tmp_path)
    assert loud.returncode == 0, loud.stderr
    assert "hil.session" in loud.stderr and "state=armed" in loud.stderr and "state=safe" in loud.stderr
    quiet = hil("-q", "run", session, "--loopback", "--clock", "sim", "--out", tmp_path)
    assert quiet.returncode == 0 and quiet.stderr == ""
    assert "rate error el" in quiet.stdout and "numpy" not in quiet.stdout  # the table, not the provenance note
    assert "numpy" in hil("run", session, "--loopback", "--clock", "sim", "--out", tmp_path).stdout
