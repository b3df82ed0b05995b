"""Outputs and logs as inputs: `--out` that is a file, directories that cannot be written, HDF5 files that are not
session logs. Exit 2 and one line; nothing created, nothing changed."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from hil.log import LogError, export_log, read_log, reader, recover_log
from hil.log.reader import NotASessionLog
from tests.factories import session_data, write_yaml
from tests.reliability.helpers import bad_input, listing

CAMPAIGN = Path(__file__).resolve().parents[2] / "profiles" / "campaigns" / "filter-lag-15hz.yaml"


def fake_log(path: Path, groups: tuple[str, ...] = ("loop", "events")) -> Path:
    """A small HDF5 file with the given groups (``loop`` makes it a session log), closed cleanly."""
    with h5py.File(path, "w") as f:
        for g in groups:
            grp = f.create_group(g)
            grp.create_dataset("tick", data=np.arange(1, 11, dtype="u4"))
            grp["tick"].attrs["unit"] = "ticks"
    return path


def crashed_log(path: Path) -> Path:
    """A session log whose writer died with the file open in SWMR mode: it opens only through a SWMR reader."""
    code = ("import h5py, os, sys; f = h5py.File(sys.argv[1], 'w', libver='latest'); "
            "g = f.create_group('loop'); g.create_dataset('tick', data=list(range(1, 101)), maxshape=(None,), "
            "chunks=(16,), dtype='u4'); f.swmr_mode = True; f.flush(); os._exit(0)")
    subprocess.run([sys.executable, "-c", code, str(path)], check=True, timeout=60)
    with pytest.raises(OSError):
        h5py.File(path, "r")  # not closed cleanly
    return path


@pytest.mark.parametrize("command", ["run", "ident", "campaign", "export"])
def test_out_naming_a_file_is_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_board_contact: None, command: str,
) -> None:
    target = tmp_path / "not-a-dir"
    target.write_text("keep me")
    source = {"run": write_yaml(tmp_path / "s.yaml", session_data()), "ident": write_yaml(tmp_path / "s.yaml",
              session_data()), "campaign": CAMPAIGN, "export": fake_log(tmp_path / "log.h5")}[command]
    extra = ["--loopback"] if command in ("run", "ident") else []
    before = listing(tmp_path)
    bad_input(capsys, [command, source, *extra, "--out", target], f"--out {target}: exists and is not a directory")
    assert listing(tmp_path) == before and target.read_text() == "keep me"


def test_out_below_a_file_or_in_an_unwritable_place(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, private_tmp: Path, no_board_contact: None,
) -> None:
    (tmp_path / "f").write_text("")
    session = write_yaml(tmp_path / "s.yaml", session_data())
    bad_input(capsys, ["run", session, "--loopback", "--out", tmp_path / "f" / "sub"], f"{tmp_path / 'f'} is not a "
              "directory")
    log = fake_log(tmp_path / "log.h5")
    bad_input(capsys, ["export", log, "--out", "/proc/1/exported"], "--out /proc/1/exported: /proc/1 is not writable")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f", "log.h5", "s.yaml", "tmp"]


def test_not_a_session_log_for_report_and_export(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    other = fake_log(tmp_path / "other.h5", groups=("data",))
    before = listing(tmp_path)
    bad_input(capsys, ["report", other], f"{other}: not a session log (no /loop group; it has data)")
    bad_input(capsys, ["export", other, "--format", "csv"], f"{other}: not a session log (no /loop group")
    bad_input(capsys, ["recover", other], f"{other}: not a session log")
    assert listing(tmp_path) == before
    empty = fake_log(tmp_path / "empty.h5", groups=())
    bad_input(capsys, ["report", empty, "--json"], "not a session log (no /loop group; it has no groups)")
    with pytest.raises(NotASessionLog):
        read_log(empty)


def test_report_and_export_of_devices_and_directories(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    bad_input(capsys, ["report", "/dev/zero"], "/dev/zero: a character device, not a regular file")
    bad_input(capsys, ["export", "/dev/zero"], "/dev/zero: a character device, not a regular file")
    bad_input(capsys, ["recover", tmp_path / "absent.h5"], "absent.h5: no such file")
    bad_input(capsys, ["report", fake_log(tmp_path / "l.h5"), "--settle-s", "inf"], "--settle-s: inf is not a finite")


def test_export_that_fails_half_way_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    log = fake_log(tmp_path / "log.h5", groups=("loop", "events", "timing"))
    out = tmp_path / "new" / "dir"
    import pyarrow.parquet as pq

    calls = []

    def write_table(table: object, where: Path) -> None:
        calls.append(where)
        if len(calls) == 2:
            raise OSError(28, "No space left on device", str(where))
        Path(where).write_bytes(b"PAR1")

    monkeypatch.setattr(pq, "write_table", write_table)
    with pytest.raises(LogError, match=r"cannot export .*log\.h5: .*new/dir/log\.\w+\.parquet: No space left"):
        export_log(log, "parquet", out)
    assert len(calls) == 2 and not (tmp_path / "new").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.h5"]


def test_recover_when_it_cannot_write_is_one_line_and_changes_nothing(
    capsys: pytest.CaptureFixture[str], tmp_path: Path,
) -> None:
    log = crashed_log(tmp_path / "crashed.h5")
    (tmp_path / "crashed.h5.recover-tmp").mkdir()  # something in the way of the copy
    before, data = listing(tmp_path), log.read_bytes()
    bad_input(capsys, ["recover", log], f"cannot recover {log}", "recover-tmp is in the way")
    assert listing(tmp_path) == before and log.read_bytes() == data
    (tmp_path / "crashed.h5.recover-tmp").rmdir()
    assert recover_log(log).output == log  # and with the way clear it recovers


def test_recover_failing_mid_copy_puts_nothing_in_place(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    log = crashed_log(tmp_path / "crashed.h5")
    data = log.read_bytes()

    def fsync_fails(path: Path) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(reader, "_fsync_path", fsync_fails)
    with pytest.raises(LogError, match=r"^cannot recover .*crashed\.h5: Input/output error \(errno 5\)$"):
        recover_log(log)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["crashed.h5"] and log.read_bytes() == data


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_recover_and_export_in_a_read_only_directory(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    log = crashed_log(ro / "crashed.h5")
    ro.chmod(0o555)
    try:
        bad_input(capsys, ["recover", log], f"cannot recover {log}: cannot write in {ro}")
        bad_input(capsys, ["export", log], f"the log's directory {ro}: {ro} is not writable")
        assert sorted(p.name for p in ro.iterdir()) == ["crashed.h5"]
    finally:
        ro.chmod(0o755)
