"""Hypothesis profiles ("ci": derandomized, so CI runs are reproducible, when CI is set; else "dev"), the port
claims of a parallel worker, and the markers a test gets from the fixtures it uses."""

from __future__ import annotations

import os
import tempfile

import pytest
from hypothesis import settings

settings.register_profile("ci", derandomize=True, deadline=None)
settings.register_profile("dev", deadline=None)
settings.load_profile("ci" if "CI" in os.environ else "dev")

# Tests run on parallel workers (pytest-xdist) share the machine's pseudo-terminals, whose numbers the kernel hands
# out again as soon as an emulator closes them: a port claim one worker's session still holds on a closed pty would
# refuse another worker's new emulator that got the same number. Each worker keeps its claims in its own directory
# (the child processes it starts inherit it); within a worker, claims meet as on a lab's machine.
if (worker := os.environ.get("PYTEST_XDIST_WORKER")) and "HIL_LOCK_DIR" not in os.environ:
    os.environ["HIL_LOCK_DIR"] = os.path.join(tempfile.gettempdir(), f"hil-locks-{worker}")

FIXTURE_MARKERS = {  # a test that uses the fixture gets the markers (pyproject.toml registers them)
    "mqtt_broker": ("mqtt",),
    "browser": ("browser",),
    # a `hil serve --loopback`: its emulated lab runs on the realtime clock, and it takes 5-10 s to start
    "service": ("realtime", "slow"),
}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        for fixture, markers in FIXTURE_MARKERS.items():
            if fixture in getattr(item, "fixturenames", ()):
                for marker in markers:
                    item.add_marker(marker)
