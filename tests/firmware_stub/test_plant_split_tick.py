"""The plant's split tick (docs/emulator.md, "The wire"): a tick's drive may take over from the last one's part-way
through the tick (``drive_delay_s``), the same in ``Plant.step_tick`` and ``Plant.run``."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from firmware_stub.plant import CarrierMotion, Plant, load_plant_config
from hil.config import PROFILES


@pytest.fixture(scope="module")
def plant_config() -> Any:
    return load_plant_config(PROFILES / "plant" / "default.yaml")


def drive(n: int) -> np.ndarray:
    """A drive that changes every 20 ticks (DAC counts)."""
    return np.repeat(np.random.default_rng(3).normal(0.0, 400.0, n // 20), 20)


def test_a_whole_tick_of_delay_is_the_drive_one_tick_later(plant_config: Any) -> None:
    u = drive(2000)
    late = Plant(plant_config, 1).run(u, u, np.zeros((2000, 18)), drive_delay_s=1e-3)
    shifted = np.r_[0.0, u[:-1]]
    moved = Plant(plant_config, 1).run(shifted, shifted, np.zeros((2000, 18)))
    for name in late:
        assert np.array_equal(late[name], moved[name]), name


def test_a_split_tick_delays_the_motion_in_proportion_and_step_tick_equals_run(plant_config: Any) -> None:
    """The rate the drive gives lags the undelayed run's by an amount in proportion to the delay (a time shift of a
    smooth response: 1/4, 1/2 and a whole tick)."""
    u = drive(2000)
    zero = np.zeros((2000, 18))
    rate = {d: Plant(plant_config, 1).run(u, u, zero, drive_delay_s=d)["los_rate_y_dps"] for d in (0, 0.25e-3, 0.5e-3,
                                                                                                    1e-3)}
    gap = {d: float(np.abs(rate[d] - rate[0]).mean()) for d in rate}
    assert gap[1e-3] > 1e-3
    assert gap[0.25e-3] / gap[1e-3] == pytest.approx(0.25, abs=0.03)
    assert gap[0.5e-3] / gap[1e-3] == pytest.approx(0.5, abs=0.03)
    plant = Plant(plant_config, 1)
    stepped = []
    for k in range(2000):
        plant.step_tick(u[k], u[k], CarrierMotion.at_rest(), 0.37e-3)
        stepped.append(plant.gyro_dps()[1])
    batch = Plant(plant_config, 1).run(u, u, zero, drive_delay_s=0.37e-3)["gyro_y_dps"]
    assert np.array_equal(np.array(stepped), batch)


def test_run_refuses_a_delay_outside_the_tick(plant_config: Any) -> None:
    with pytest.raises(ValueError, match="drive_delay_s"):
        Plant(plant_config, 1).run(np.zeros(3), np.zeros(3), np.zeros((3, 18)), drive_delay_s=1.5e-3)


