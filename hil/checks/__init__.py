"""`hil check`: any config file of the bench or the emulator validated by its own loader, nothing run.

A package of its own because it sits above every loader it dispatches to (session, campaign, tune's controller,
fit's targets, the emulator's plant): below the faces, above fit."""

from hil.checks._checks import check_config_file

__all__ = [
    "check_config_file",
]
