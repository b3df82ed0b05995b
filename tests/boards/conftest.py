"""Fixtures: the test drivers registered as an installed package would be, and the example driver package
(example_pkg/) installed for real with pip into a directory of its own."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.boards import drivers

EXAMPLE_PKG = Path(__file__).with_name("example_pkg")


@pytest.fixture
def test_drivers(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[type[drivers.RecordingHexapod]]:
    """``recording``, ``not_a_driver``, ``incomplete`` and ``missing`` in hil.hexapod_drivers, for this test."""
    monkeypatch.syspath_prepend(str(drivers.register(tmp_path / "site")))
    drivers.RecordingHexapod.instances.clear()
    drivers.RecordingHexapod.hooks.clear()
    yield drivers.RecordingHexapod
    drivers.RecordingHexapod.hooks.clear()


@pytest.fixture(scope="module")
def replay_site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """example_pkg installed with ``pip install --no-deps --no-build-isolation --target`` (offline: it has no
    dependencies to fetch and builds with the standard library)."""
    target = tmp_path_factory.mktemp("replay-site")
    res = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
                          "--no-deps", "--no-build-isolation", "--no-index", "--target", str(target),
                          str(EXAMPLE_PKG)], capture_output=True, text=True, check=False, timeout=300)
    assert res.returncode == 0, res.stderr
    return target
