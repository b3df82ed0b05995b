"""An interrupted `hil campaign` (SIGINT, SIGTERM): it names the cells done and cut short and the --resume command,
exits 130 / 143, keeps the finished cells, and the printed command finishes the campaign running only the rest."""

from __future__ import annotations

import json
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml

from hil.campaign import load_campaign
from hil.config import PROFILES

CAMPAIGNS = PROFILES / "campaigns"
HIL_EXE = Path(sys.executable).with_name("hil")
HIL = [str(HIL_EXE)] if HIL_EXE.exists() else [sys.executable, "-m", "hil"]
WAIT_S = 600.0  # generous: the machine may be loaded; nothing here depends on how fast a cell runs


def small_campaign(tmp_path: Path) -> Path:
    """The shipped 15 Hz lag campaign cut to 3 cells of 20 s (one controller, seeds 1-3: a second or more each on
    the sim clock, so a signal sent as a cell starts finds it running), in a directory whose name holds a space (the
    resume command quotes it)."""
    data = yaml.safe_load((CAMPAIGNS / "filter-lag-15hz.yaml").read_text())
    data.update(session=str((CAMPAIGNS / data["session"]).resolve()), duration_s=20.0, seeds=[1, 2, 3])
    for p in data["profiles"]:
        p["path"] = str((CAMPAIGNS / p["path"]).resolve())
    folder = tmp_path / "lag campaign"
    folder.mkdir()
    path = folder / "campaign.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def start(args: list[str], cwd: Path) -> subprocess.Popen[str]:
    return subprocess.Popen([*HIL, *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_until(ready: Callable[[], bool], proc: subprocess.Popen[str]) -> None:
    """Poll ``ready`` until true; fail if ``proc`` ends first or nothing happens in WAIT_S."""
    deadline = time.monotonic() + WAIT_S
    while not ready():
        if proc.poll() is not None:
            out, err = proc.communicate()
            raise AssertionError(f"hil campaign ended early ({proc.returncode}):\n{out}\n{err}")
        assert time.monotonic() < deadline, "the campaign made no progress"
        time.sleep(0.05)


def stop(proc: subprocess.Popen[str], signum: int) -> tuple[str, str]:
    proc.send_signal(signum)
    out, err = proc.communicate(timeout=WAIT_S)
    return out, err


def files(folder: Path) -> dict[str, tuple[bytes, int]]:
    """Every file of ``folder``: its bytes and modification time (ns)."""
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(folder.iterdir()) if p.is_file()}


@pytest.mark.slow
def test_sigint_names_the_cells_done_and_cut_short_and_the_printed_resume_runs_only_the_rest(tmp_path: Path) -> None:
    path = small_campaign(tmp_path)
    first, second, third = ids = [s.cell_id for s in load_campaign(path).cells()]
    out = path.parent / "out"
    cells = out / "cells"
    proc = start(["campaign", str(path), "--out", str(out), "--clock", "sim", "--jobs", "1", "--no-report"],
                 tmp_path)
    # the first cell finished and the second one started (its session file is written before its run)
    wait_until(lambda: (cells / first / "result.json").exists() and (cells / second / "session.yaml").exists(),
               proc)
    text, err = stop(proc, signal.SIGINT)
    assert proc.returncode == 130, text + err
    lines = text.splitlines()
    assert lines, f"nothing on stdout; stderr: {err}"
    assert f"1 of 3 cells done: {first}" in lines[0], text
    assert f"cut short: {second}" in lines, text
    assert f"left to run: 2 ({second}, {third})" in lines, text
    command = next(line.split(": ", 1)[1] for line in lines if line.startswith("finish it with: "))
    words = shlex.split(command)
    assert words == ["hil", "campaign", str(path), "--out", str(out), "--clock", "sim", "--jobs", "1",
                     "--no-report", "--resume"]

    kept = files(cells / first)
    before = json.loads((cells / first / "result.json").read_text())
    assert before["status"] == "completed"
    assert json.loads((cells / second / "result.json").read_text())["status"] != "completed"  # stopped, not done
    assert not (cells / third).exists()  # no cell starts once the campaign is stopping
    assert [c["cell_id"] for c in json.loads((out / "campaign.json").read_text())["cells"]] == [first]

    resumed = subprocess.run([*HIL, *words[1:]], cwd=tmp_path, capture_output=True, text=True, timeout=WAIT_S,
                             check=False)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    assert files(cells / first) == kept  # not run again: its log, session file and result untouched
    result = json.loads((out / "campaign.json").read_text())
    assert result["complete"] and [c["cell_id"] for c in result["cells"]] == ids
    assert all(c["status"] == "completed" for c in result["cells"])
    assert result["cells"][0]["metrics"] == before["metrics"]


def test_sigterm_with_json_is_one_object_and_exit_143(tmp_path: Path) -> None:
    path = small_campaign(tmp_path)
    first, second, third = ids = [s.cell_id for s in load_campaign(path).cells()]
    out = path.parent / "out"
    args = ["campaign", str(path), "--out", str(out), "--clock", "sim", "--jobs", "1", "--no-report", "--json"]
    proc = start(args, tmp_path)
    wait_until((out / "cells" / first / "session.yaml").exists, proc)
    text, err = stop(proc, signal.SIGTERM)
    assert proc.returncode == 143, text + err
    data = json.loads(text)  # nothing else on stdout
    assert data["status"] == "interrupted" and data["signal"] == "SIGTERM" and data["exit_code"] == 143
    assert (data["cells_done"], data["cells_total"], data["done"]) == (0, 3, []), data
    assert data["cut_short"] == [first] and data["to_run"] == ids, data
    assert data["resume_command"] == shlex.join(["hil", *args, "--resume"])
    assert not (out / "cells" / second).exists() and not (out / "cells" / third).exists()
