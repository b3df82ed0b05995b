"""Fixtures of the emulator's tests."""

from __future__ import annotations

import pytest

from firmware_stub.plant import RIGID_PLANT_CONFIG, PlantConfig, load_plant_config


@pytest.fixture(scope="module")
def rigid() -> PlantConfig:
    """The rigid plant (profiles/plant/rigid.yaml: every v2 mechanism off): the physics the plant tests pin against
    analytic solutions. profiles/plant/default.yaml is the same plant with the mechanisms on, each tested on its
    own in test_plant_mechanisms.py."""
    return load_plant_config(RIGID_PLANT_CONFIG)
