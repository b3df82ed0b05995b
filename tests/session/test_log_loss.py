"""A lost log is a fault: a disk that fills, a log directory deleted mid-session, and a session whose log cannot
fit are never reported as completed (docs/reliability.md)."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil import api
from hil.cli.session import print_result
from hil.config import ConfigError
from hil.log import read_log
from hil.session import Session
from tests.factories import run_session, session_config, session_data, write_yaml
from tests.reliability.helpers import bad_input, no_board_contact
from tests.session.helpers import wait_cycles

FILL_AT_CYCLES = 1500
__all__ = ["no_board_contact"]  # the fixture, used by name


@contextlib.contextmanager
def small_filesystem(where: Path, size_mb: int) -> Iterator[Path]:
    """A tmpfs of ``size_mb`` at ``where`` (root only: skipped elsewhere), unmounted afterwards."""
    where.mkdir()
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("mounting a small filesystem needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(where)], check=False,
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False, capture_output=True)


def fill(directory: Path) -> int:
    """Fill the filesystem of ``directory`` to the last byte, as another program would; returns the bytes."""
    written = 0
    block = b"\0" * (1 << 16)
    with (directory / "filler").open("wb", buffering=0) as f:
        try:
            while True:
                written += f.write(block)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC, exc
    return written


def lab_emulator_state(emulator: dict) -> tuple[int, bool]:  # type: ignore[type-arg]
    return emulator["driver"]["enabled"], emulator["streaming"]


def test_a_disk_that_fills_mid_session_ends_it_as_a_fault_with_the_rows_kept(tmp_path: Path) -> None:
    config = session_config(duration_s=4.0, safety={"on_fault": "recover"})  # a lost log is never recovered
    with small_filesystem(tmp_path / "disk", 32) as disk:
        async def fill_mid_session(_emulator: object, session: Session) -> None:
            await wait_cycles(session, FILL_AT_CYCLES, timeout_s=120)
            fill(disk)

        run = run_session(config, disk, during=fill_mid_session)
        result = run.result
        assert result.status == "fault" and result.exit_code == 1, result
        assert "No space left on device" in result.message, result.message
        assert result.log_error is not None and "No space left on device" in result.log_error
        assert result.stats.recoveries == 0
        cycles = result.stats.cycles
        # the rows after the disk filled lost (how many made it first depends on the flushes and the chunks HDF5 had
        # already allocated, not on the bench: beside two CPU hogs none had been flushed when the disk filled)
        assert 0 <= result.log_rows < cycles and cycles > FILL_AT_CYCLES, (result.log_rows, cycles)
        assert result.log_path is not None and result.log_path.is_file()
        assert len(read_log(result.log_path).groups["loop"]["tick"]) == result.log_rows  # every row it kept
    assert lab_emulator_state(run.emulator) == (0, False)  # the normal safe wind-down: driver off, stream idle


def test_the_log_directory_deleted_mid_session_ends_it_as_a_fault_naming_no_file(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = session_config(duration_s=4.0)
    logs = tmp_path / "logs"
    logs.mkdir()

    async def delete_mid_session(_emulator: object, session: Session) -> None:
        await wait_cycles(session, FILL_AT_CYCLES, timeout_s=120)
        shutil.rmtree(logs)

    run = run_session(config, logs, during=delete_mid_session)
    result = run.result
    assert result.status == "fault" and result.exit_code == 1, result
    assert "its directory was removed while the session ran" in result.message, result.message
    assert result.log_path is None and result.log_error is not None
    # how soon the loss is seen depends on the writer's next flush: on an idle machine well before the 4000th cycle,
    # beside two CPU hogs once after it (4291); either way the session ends as a fault, never completed
    assert lab_emulator_state(run.emulator) == (0, False)
    # what `hil run --json` prints of it: no file named, and the reason instead of "killed or crashed"
    print_result(api.RunResult(result.status, result.exit_code, result.message, result.log_path, "lockstep",
                               result), json_out=True)
    printed = json.loads(capsys.readouterr().out)
    assert printed["log"] is None and printed["status"] == "fault"
    assert "its directory was removed" in printed["log_error"]
    assert printed["cycles_run"] == result.stats.cycles


def test_a_session_whose_log_cannot_fit_is_refused_before_it_starts(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], no_board_contact: None) -> None:
    with small_filesystem(tmp_path / "disk", 2) as disk:
        session = write_yaml(tmp_path / "long.yaml", session_data(duration_s=600.0, logging={"dir": str(disk)}))
        bad_input(capsys, ["run", session, "--loopback"], "logging.dir", "MB free", "needs about")
        assert list(disk.iterdir()) == []
        with pytest.raises(ConfigError, match="needs about"):  # the same through the Python API
            api.prepare_run(session)
        short = write_yaml(tmp_path / "short.yaml", session_data(duration_s=1.0, logging={"dir": str(disk)}))
        with pytest.raises(ConfigError, match="needs about"):  # a 1 s session's log needs ~4 MB too
            api.prepare_run(short)
