"""Hypothesis profiles: "ci" (derandomized, so CI runs are reproducible) when CI is set, else "dev"."""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, deadline=None)
settings.register_profile("dev", deadline=None)
settings.load_profile("ci" if "CI" in os.environ else "dev")
