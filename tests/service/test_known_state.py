"""Every item starts from the boards' rest state, measured (docs/service.md, "Between items"): the item after an
abort or a fault waits for the hexapod's stop ramp instead of being refused by it, and the status says what the
boards reported, not what they should be."""

from __future__ import annotations

from pathlib import Path

from tests.service.conftest import Service, short_session, wait_for


def test_the_item_after_an_abort_waits_for_the_stop_ramp_and_runs(service: Service, tmp_path: Path) -> None:
    bench = service.bench(user="kim")
    rest = bench.status()["worker"]["rest"]
    assert rest["ok"] is True and rest["boards"] == {"servo": "stream idle", "driver": "disabled",
                                                     "hexapod": "IDLE at home"}
    swinging = bench.add(short_session(tmp_path, 30.0, name="swinging"))
    wait_for(lambda: bench.item(swinging["uid"]).get("cycles", 0) > 2000, timeout_s=180)  # the table well off home
    bench.abort("test: the next item at once")
    bench.start()  # at once: the hexapod is still ramping home
    after = bench.run(short_session(tmp_path, 1.0, name="after"), out=tmp_path / "out")
    assert after.status == "completed", after.message  # it used to end "PROFILE_LOAD refused: BAD_STATE"
    aborted = bench.item(swinging["uid"])
    assert aborted["status"] == "aborted"
    started = bench.history(2)
    assert [r["name"] for r in started] == ["after", "swinging"]
    assert started[0]["started_at"] > started[1]["ended_at"]
    status = wait_for(lambda: (s := bench.status())["worker"]["rest"] and s, timeout_s=60)  # measured after it
    rest = status["worker"]["rest"]
    assert rest["ok"] is True and rest["boards"] == {"servo": "stream idle", "driver": "disabled",
                                                     "hexapod": "LOADED at home"}  # its profile still loaded
    assert status["worker"]["safe"] == rest["summary"]
