"""A real session log, made once for the tests of this directory that read one: a short run on the ``sim`` clock."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

SIM_SECONDS = 0.6
SIM_CONTROLLER = {"name": "eso_kf_high_gain", "params": {"kp_counts_per_dps": 6000.0}}


@pytest.fixture(scope="session")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The log of a 0.6 s session (ESO+KF high gain, kp overridden) against the emulated lab in this process."""
    from hil.session import run_sim_session
    from tests.factories import session_config

    config = session_config(duration_s=SIM_SECONDS, seed=4, controller=SIM_CONTROLLER)
    result, _ = asyncio.run(run_sim_session(config, tmp_path_factory.mktemp("sim")))
    assert result.status == "completed", result.message
    assert result.log_path is not None
    return result.log_path
