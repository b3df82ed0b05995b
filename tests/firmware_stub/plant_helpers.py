"""What the plant tests share: constants, config edits and the idealised plant."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from firmware_stub.plant import CarrierMotion, PlantConfig, PlantConfigError, load_plant_config

G0 = 9.80665
D2R = math.pi / 180.0
REST = CarrierMotion.at_rest()


def with_(cfg: PlantConfig, **changes: Any) -> PlantConfig:
    """A copy of ``cfg`` with ``section__field=value`` (or ``field=value``, or ``friction__el__field``) changed; a
    value for a whole section replaces it."""
    d = cfg.model_dump()
    for key, value in changes.items():
        *path, leaf = key.split("__")
        node = d
        for part in path:
            node = node[part]
        node[leaf] = value
    return PlantConfig.model_validate(d)


def ideal(cfg: PlantConfig, *, ideal_gyro: bool = False, **changes: Any) -> PlantConfig:
    """No friction, no imbalance, no gyro noise/bias/quantisation, no centroid noise; with ``ideal_gyro`` also no
    gyro delay and a very wide gyro band. ``changes`` as for :func:`with_`, applied last."""
    base: dict[str, Any] = {
        "friction__az__coulomb_n_m": 0.0, "friction__az__viscous_n_m_s_per_rad": 0.0,
        "friction__el__coulomb_n_m": 0.0, "friction__el__viscous_n_m_s_per_rad": 0.0,
        "imbalance__mass_kg": 0.0,
        "gyro__noise_std_dps": (0.0, 0.0, 0.0), "gyro__bias_dps": (0.0, 0.0, 0.0), "gyro__quantisation_lsb_dps": 0.0,
        "camera__centroid_noise_std_px": 0.0,
    }
    if ideal_gyro:
        base.update(gyro__delay_s=0.0, gyro__bandwidth_hz=1e9)
    return with_(cfg, **{**base, **changes})


def assert_config_error(tmp_path: Path, base: Path, change: Callable[[dict[str, Any]], Any], field: str,
                        reason: str) -> None:
    """The plant file ``base`` with ``change`` applied to its YAML data is refused with one line that starts with
    the file and ``field`` and says ``reason``."""
    data = yaml.safe_load(base.read_text())
    change(data)
    path = tmp_path / "plant.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(PlantConfigError) as exc:
        load_plant_config(path)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(f"{path}: {field}") and reason in msg, msg
    assert isinstance(exc.value, ValueError)
