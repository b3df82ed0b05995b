"""Hypothesis profiles ("ci": derandomized, so CI runs are reproducible, when CI is set; else "dev") and the
markers a test gets from the fixtures it uses."""

from __future__ import annotations

import os

import pytest
from hypothesis import settings

settings.register_profile("ci", derandomize=True, deadline=None)
settings.register_profile("dev", deadline=None)
settings.load_profile("ci" if "CI" in os.environ else "dev")

FIXTURE_MARKERS = {  # a test that uses the fixture gets the marker (pyproject.toml registers them)
    "mqtt_broker": "mqtt",
    "browser": "browser",
    "service": "realtime",  # a `hil serve --loopback`: its emulated lab runs on the realtime clock
}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        for fixture, marker in FIXTURE_MARKERS.items():
            if fixture in getattr(item, "fixturenames", ()):
                item.add_marker(marker)
