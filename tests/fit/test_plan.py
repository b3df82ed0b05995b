"""`hil fit --plan SESSION` says what to record on that session's lab (the commands, their durations and why), and
`hil fit --record` refuses to guess where to record."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path

from hil.config import PROFILES, load_session
from hil.fit.record import recording_plan

SESSION = PROFILES / "sessions" / "demo.yaml"


def hil(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil", *args], capture_output=True, text=True, check=False,
                          timeout=120)


def test_the_plan_lists_each_recording_with_a_command_that_runs_on_the_session_s_lab(tmp_path: Path) -> None:
    proc = hil("fit", "--plan", str(SESSION), "--report-dir", str(tmp_path), "--json")
    assert proc.returncode == 0, proc.stderr
    plan = json.loads(proc.stdout)
    kinds = [r["kind"] for r in plan["recordings"]]
    assert kinds.count("static") == 1 and kinds.count("ident") == 2 and kinds.count("swing") >= 1
    assert plan["total_s"] == sum(r["seconds"] for r in plan["recordings"]) > 60
    base = load_session(SESSION)
    for r in plan["recordings"]:
        words = shlex.split(r["command"])
        assert words[:2] == (["hil", "ident"] if r["kind"] == "ident" else ["hil", "run"])
        session = load_session(words[2])  # written beside the report, loads as it is
        assert session.emulator == base.emulator and session.hexapod_limits == base.hexapod_limits
        assert r["why"]
        if r["kind"] == "ident":
            assert words[words.index("--axis") + 1] in ("el", "az")
            assert float(words[words.index("--f-stop-hz") + 1]) > 300
        else:
            assert session.duration_s == r["seconds"]
    assert {"fit-ident-el", "fit-ident-az"} <= {r["name"] for r in plan["recordings"]}


def test_the_plan_s_sessions_keep_the_lab_s_ports() -> None:
    base = load_session(SESSION).model_copy(update={"ports": None})
    with_ports = base.model_validate({**base.model_dump(), "ports": {
        n: {"port": f"/dev/ttyUSB{i}", "baudrate": 2_000_000} for i, n in enumerate(("servo", "driver", "image",
                                                                                      "hexapod"))}})
    for rec in recording_plan(with_ports):
        assert rec.config.ports == with_ports.ports
        assert rec.config.link_baudrates() == dict.fromkeys(("servo", "driver", "image", "hexapod"), 2_000_000)


def test_record_needs_to_be_told_where() -> None:
    proc = hil("fit", "--record", str(SESSION))
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and "--loopback" in proc.stderr and "--hardware" in proc.stderr
    both = hil("fit", "--plan", str(SESSION), "--record", str(SESSION))
    assert both.returncode == 2 and "one session YAML" in both.stderr
