"""hil: hardware-in-the-loop bench for airborne electro-optical stabilized platforms.

The public API (docs/api.md), for notebooks and scripts; the `hil` command line is a thin layer over it:

    import hil
    config = hil.load_session("profiles/sessions/demo.yaml")
    result = hil.run(config, clock="sim")          # await hil.run_async(...) inside a running event loop
    result.log.loop                                 # the 1 kHz channels as a DataFrame, units in .attrs["units"]
    campaign = hil.run_campaign("profiles/campaigns/swing-rate-error.yaml", jobs=2)
    campaign.table()
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from hil._version import __version__

__all__ = ["LABS", "Bench", "BenchLab", "CampaignRun", "ConfigError", "IdentRun", "Lab", "RunResult", "SessionConfig",
           "__version__", "check_file", "load_campaign", "load_session", "read_log", "replay_capture", "replay_log",
           "report", "run", "run_async", "run_campaign"]

if TYPE_CHECKING:
    from hil.api import (
        LABS,
        BenchLab,
        CampaignRun,
        IdentRun,
        Lab,
        RunResult,
        check_file,
        load_campaign,
        read_log,
        replay_capture,
        replay_log,
        report,
        run,
        run_async,
        run_campaign,
    )
    from hil.config import ConfigError, SessionConfig, load_session
    from hil.service import Bench

# hil.api.ident and hil.api.tune are not here: hil.ident and hil.tune are packages, and a package's name would
# hide a function of that name once imported (tests/api/test_api.py)
_FROM = {"Bench": "hil.service", "LABS": "hil.api", "BenchLab": "hil.api", "Lab": "hil.api", "CampaignRun": "hil.api",
         "IdentRun": "hil.api", "replay_capture": "hil.api",
         "replay_log": "hil.api",
         "RunResult": "hil.api", "check_file": "hil.api", "load_campaign": "hil.api",
         "read_log": "hil.api", "report": "hil.api", "run": "hil.api", "run_async": "hil.api",
         "run_campaign": "hil.api", "ConfigError": "hil.config", "SessionConfig": "hil.config",
         "load_session": "hil.config"}


def __getattr__(name: str) -> Any:
    """The API loads on first use, so `import hil` (and the emulator, which imports hil.protocol) stays light."""
    module = _FROM.get(name)
    if module is None:
        raise AttributeError(f"module 'hil' has no attribute {name!r}")

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
