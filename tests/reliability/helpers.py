"""Bad input as a user gives it: `hil` called in-process, with what it printed and what it left behind."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from hil.cli import main


def listing(*roots: Path) -> set[str]:
    """Every path under the roots (the roots themselves included when they exist)."""
    out: set[str] = set()
    for root in roots:
        if root.exists() or root.is_symlink():
            out.add(str(root))
        if root.is_dir():
            for dirpath, dirnames, filenames in os.walk(root):
                out.update(os.path.join(dirpath, n) for n in dirnames + filenames)
    return out


def emulator_run_dirs() -> set[str]:
    """The emulator's run directories in the temp directory (isolated per test by the ``private_tmp`` fixture)."""
    return {p.name for p in Path(tempfile.gettempdir()).glob("hil-emu-*")}


def bad_input(capsys: pytest.CaptureFixture[str], args: list[str], *needles: str) -> str:
    """Run ``hil ARGS`` in-process: exit 2, exactly one line on stderr holding every needle, no traceback."""
    code = main([str(a) for a in args])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


@pytest.fixture
def private_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A temp directory of this test's own (for tempfile and for child processes), so the emulator run
    directories it may leave are this test's alone."""
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    yield tmp


@pytest.fixture
def no_board_contact(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if anything starts an emulator, opens a serial port or builds a session."""

    def touched(*_args: Any, **_kwargs: Any) -> None:
        raise AssertionError("bad input reached the boards")

    import hil.link._transport

    monkeypatch.setattr(hil.session.EmulatorProcess, "start", touched)
    monkeypatch.setattr(hil.link._transport.SerialLink, "open", touched)
    monkeypatch.setattr(hil.session.Session, "__init__", touched)
