"""The service's clients in words (docs/service.md, "Clients"): a uid prefix that several items share is refused
with one line and exit 2, a waiting item's place reads as people say it, and `hil --help` loads neither the client
nor the API. A running service's side of these is tests/service/test_client_owns_item.py."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from hil.cli import main
from hil.cli._bench import duration, ordinal, waiting_line
from hil.service import Bench, BenchError

REPO = Path(__file__).resolve().parents[2]
NOWHERE = "http://127.0.0.1:9"  # nothing listens: a call that reached the network would fail with exit 1
TWINS = {"running": False, "items": [{"uid": "3f2a9c01d2e4" + "0" * 20}, {"uid": "3f2a9c77a0b1" + "1" * 20},
                                     {"uid": "8b0e" + "2" * 28}]}


def test_a_prefix_that_several_items_share_is_refused_naming_them(monkeypatch: pytest.MonkeyPatch,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(Bench, "queue", lambda self: TWINS)
    bench = Bench(NOWHERE)
    assert bench.resolve("8B0E22") == "8b0e" + "2" * 28  # one item starts with it, in any case
    with pytest.raises(BenchError) as err:
        bench.resolve("3f2a9c")
    assert err.value.status == 409
    assert str(err.value) == ("item '3f2a9c': 2 items in the queue start with it (3f2a9c01d2e4, 3f2a9c77a0b1); give "
                              "more of its uid")
    for args in (["queue", "remove", "3f2a9c"], ["queue", "move", "3f2a9c", "0"],
                 ["bench", "abort", "--item", "3f2a9c"]):
        assert main([*args, "--bench", NOWHERE]) == 2
        err_lines = capsys.readouterr().err.strip().splitlines()
        assert err_lines == ["error: item '3f2a9c': 2 items in the queue start with it (3f2a9c01d2e4, 3f2a9c77a0b1); "
                             "give more of its uid"]


def test_a_whole_uid_is_sent_as_it_is_without_asking_the_queue(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_queue(self: Bench) -> dict:
        raise AssertionError("a whole uid needs no look-up")

    monkeypatch.setattr(Bench, "queue", no_queue)
    assert Bench(NOWHERE).resolve(" " + "AB" * 16 + " ") == "ab" * 16


@pytest.mark.parametrize(("n", "said"), [(1, "1st"), (2, "2nd"), (3, "3rd"), (4, "4th"), (11, "11th"), (12, "12th"),
                                         (13, "13th"), (21, "21st"), (22, "22nd"), (101, "101st"), (111, "111th")])
def test_places_read_as_ordinals(n: int, said: str) -> None:
    assert ordinal(n) == said


def test_the_waiting_line_says_the_place_what_runs_first_the_lease_and_the_stopped_queue() -> None:
    view = {"state": "queued", "place": 2, "waiting": 3, "ahead": 1, "lease_holder": "ana",
            "lease_remaining_s": 241.0, "queue_stopped": None}
    assert waiting_line("demo.yaml", "http://bench:8765", view) == (
        "demo.yaml: waiting in http://bench:8765's queue: 2nd of 3; the lease is ana's (4 min left)")
    view = {"state": "queued", "place": 1, "waiting": 1, "ahead": 1, "lease_holder": None,
            "queue_stopped": "stopped by kim; 1 item waits"}
    assert waiting_line("demo.yaml", "http://bench:8765", view) == (
        "demo.yaml: waiting in http://bench:8765's queue: 1st of 1, 1 item to run before it; the queue is stopped "
        "(stopped by kim; 1 item waits): `hil queue start --bench http://bench:8765` starts it")
    assert [duration(s) for s in (40, 89.4, 240, 5399, 9000)] == ["40 s", "89 s", "4 min", "90 min", "2.5 h"]


def test_help_loads_neither_the_client_nor_the_api() -> None:
    code = ("import json, sys\nfrom hil.cli import main\nmain(['--help'])\n"
            "print(json.dumps(sorted(sys.modules)), file=sys.stderr)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO,
                         check=False)
    loaded = set(json.loads(run.stderr.strip().splitlines()[-1]))
    assert "Usage" in run.stdout or "hil" in run.stdout
    assert sorted(loaded & {"hil.service", "hil.api", "hil.config", "pydantic", "numpy", "asyncio",
                            "urllib.request"}) == []
