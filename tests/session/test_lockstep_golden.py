"""Lockstep runs of the shipped sessions give the same logged values as the recorded digests: a change to how the
bench runs its loop (threads, encoders, decoders) must not change what a lockstep run computes.

Each session is run as shipped, with the wire's time and the start pose phase (the defaults), and without both
(``links.wire_time: false``, ``start_pose.enabled: false``): the digests without them are those recorded before
the wire was modelled and before sessions had a start pose phase, so turning both off restores that bench exactly.

The digests were recorded with ``python -m tests.session.test_lockstep_golden --update``; run that again only for
a change that is meant to change the results (a new controller default, a new plant), and say so in its commit.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import pytest

from hil.config import PROFILES, load_session, read_yaml_mapping
from hil.session import emulator_for_plant
from tests.factories import run_session, session_config
from tests.session.helpers import channel_digests

GOLDEN = Path(__file__).with_name("lockstep_golden.json")
SESSIONS = sorted(p.stem for p in (PROFILES / "sessions").glob("*.yaml"))
TICKS = 2000


WIRES = ("wire", "no_wire")


def lockstep_digests(session: str, wire: str, out: Path) -> dict[str, str]:
    out.mkdir(parents=True, exist_ok=True)
    config = session_config(duration_s=TICKS / 1000, seed=7, **_shipped(session, wire, out))
    run = run_session(config, out)
    assert run.result.status == "completed", run.result.message
    return channel_digests(run.result.log_path, TICKS)


def _shipped(session: str, wire: str, out: Path) -> dict[str, object]:
    """The shipped session's own controller, profile and tracking (paths resolved), over the test base; ``no_wire``:
    the base's emulated lab with ``links.wire_time: false``, and no start pose phase."""
    data = load_session(PROFILES / "sessions" / f"{session}.yaml").model_dump()
    shipped = {k: data[k] for k in ("controller", "profile", "tracking", "excitation", "name")}
    if wire == "no_wire":
        base = session_config().emulator.model_dump()
        lab = Path(base["config"])
        plant = lab.parent / read_yaml_mapping(lab)["plant"]
        shipped["emulator"] = {**base, "config": emulator_for_plant(plant, out, base=lab, wire_time=False)}
        shipped["start_pose"] = {"enabled": False}
    return shipped


@pytest.mark.parametrize("wire", WIRES)
@pytest.mark.parametrize("session", SESSIONS)
def test_lockstep_results_match_the_recorded_digests(session: str, wire: str, tmp_path: Path) -> None:
    golden = json.loads(GOLDEN.read_text())[wire][session]
    got = lockstep_digests(session, wire, tmp_path)
    assert set(got) == set(golden)
    changed = sorted(k for k in golden if got[k] != golden[k])
    assert not changed, f"{session} ({wire}): lockstep results changed in {changed}"


if __name__ == "__main__" and "--update" in sys.argv:
    with tempfile.TemporaryDirectory() as tmp:
        GOLDEN.write_text(json.dumps({w: {s: lockstep_digests(s, w, Path(tmp) / w / s) for s in SESSIONS}
                                      for w in WIRES}, indent=1) + "\n")
    print(f"wrote {GOLDEN}")
