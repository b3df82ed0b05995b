"""Lockstep runs of the shipped sessions give the same logged values as the recorded digests: a change to how the
bench runs its loop (threads, encoders, decoders) must not change what a lockstep run computes.

The digests were recorded with ``python -m tests.session.test_lockstep_golden --update``; run that again only for
a change that is meant to change the results (a new controller default, a new plant), and say so in its commit.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import pytest

from hil.config import PROFILES
from tests.session.helpers import channel_digests, run_session, session_config

GOLDEN = Path(__file__).with_name("lockstep_golden.json")
SESSIONS = sorted(p.stem for p in (PROFILES / "sessions").glob("*.yaml"))
TICKS = 2000


def lockstep_digests(session: str, out: Path) -> dict[str, str]:
    out.mkdir(parents=True, exist_ok=True)
    config = session_config(duration_s=TICKS / 1000, seed=7, **_shipped(session))
    run = run_session(config, out)
    assert run.result.status == "completed", run.result.message
    return channel_digests(run.result.log_path, TICKS)


def _shipped(session: str) -> dict[str, object]:
    """The shipped session's own controller, profile and tracking (paths resolved), over the test base."""
    from hil.config import load_session

    data = load_session(PROFILES / "sessions" / f"{session}.yaml").model_dump()
    return {k: data[k] for k in ("controller", "profile", "tracking", "excitation", "name")}


@pytest.mark.parametrize("session", SESSIONS)
def test_lockstep_results_match_the_recorded_digests(session: str, tmp_path: Path) -> None:
    golden = json.loads(GOLDEN.read_text())[session]
    got = lockstep_digests(session, tmp_path)
    assert set(got) == set(golden)
    changed = sorted(k for k in golden if got[k] != golden[k])
    assert not changed, f"{session}: lockstep results changed in {changed}"


if __name__ == "__main__" and "--update" in sys.argv:
    with tempfile.TemporaryDirectory() as tmp:
        GOLDEN.write_text(json.dumps({s: lockstep_digests(s, Path(tmp) / s) for s in SESSIONS}, indent=1) + "\n")
    print(f"wrote {GOLDEN}")
