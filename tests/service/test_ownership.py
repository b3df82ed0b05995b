"""Who may do what to an item (docs/service.md, "Ownership and audit"): a waiting item is changed by its submitter
or the lease holder, another operator takes the lease first (breaking a held one with a reason); a running item is
stopped by its owner, aborted by any operator; every stop and abort says who and why in the history and the log;
a token never rides in a URL."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest
import websockets
from websockets.exceptions import ConnectionClosed

from hil.log import read_log_frames
from hil.service import BenchError
from tests.factories import short_session
from tests.service.conftest import Service, wait_for


@pytest.mark.slow
def test_another_operators_items_are_theirs_until_the_lease_says_otherwise(service: Service, tmp_path: Path) -> None:
    ana, kim = service.bench(user="ana"), service.bench(user="kim")
    ana.stop_queue()
    try:
        mine = ana.add(short_session(tmp_path, 1.0, name="anas"))
        kims = kim.add(short_session(tmp_path, 1.0, name="kims"))
        for call in (lambda: kim.remove(mine["uid"]), lambda: kim.move(mine["uid"], 1)):
            with pytest.raises(BenchError) as refused:
                call()
            assert refused.value.status == 403
            assert "it is ana's; only ana or the lease holder may; take the lease first" in str(refused.value)
        cleared = kim.call("POST", "/api/queue/clear", {})
        assert cleared["removed"] == 1 and cleared["kept"] == 1 and "kept" in cleared["note"]
        assert [i["uid"] for i in ana.queue()["items"]] == [mine["uid"]]
        kim.lease(ttl_s=60)  # the lease holder may
        try:
            kim.move(mine["uid"], 0)
            kim.remove(mine["uid"])
        finally:
            kim.release()
        assert ana.queue()["items"] == [] and kims["uid"] not in [i["uid"] for i in ana.queue()["items"]]
    finally:
        ana.start()


@pytest.mark.slow
def test_a_stop_is_the_lease_holders_an_abort_anyones_and_both_say_who_and_why(service: Service,
                                                                            tmp_path: Path) -> None:
    ana, kim = service.bench(user="ana"), service.bench(user="kim")
    ana.lease(ttl_s=120)
    item = ana.add(short_session(tmp_path, 30.0, name="long"))
    wait_for(lambda: ana.item(item["uid"]).get("cycles", 0) > 500, timeout_s=180)
    with pytest.raises(BenchError) as refused:
        kim.stop(reason="mine now")
    assert refused.value.status == 403 and "the bench is leased to ana; break the lease" in str(refused.value)
    kim.abort(reason="smoke from the driver")  # an alarm: any operator, lease or not
    record = ana.wait(item["uid"])
    assert record["status"] == "aborted" and record["exit_code"] == 130
    assert record["message"] == "abort by kim: smoke from the driver"
    assert ana.queue()["stopped"].startswith("aborted by kim: smoke from the driver")
    events = read_log_frames(record["log_path"], groups=["events"]).event_details()
    signal = next(e["detail"] for e in events if e["kind"] == "signal")
    assert signal == {"signal": "SIGINT", "reason": "abort by kim: smoke from the driver"}
    ana.release()
    ana.start()


@pytest.mark.slow
def test_a_token_in_the_url_is_refused_and_said_why(tmp_path: Path) -> None:
    tokens = tmp_path / "tokens.yaml"
    secret = "a-long-operator-token-0123456789"
    tokens.write_text(f"tokens:\n  - {{user: ana, role: operator, token: {secret}}}\n")
    svc = Service(tmp_path / "state", args=("--loopback", "--token-file", str(tokens)), token=secret).start()
    try:
        with pytest.raises(BenchError) as refused:
            svc.bench(token="").call("GET", f"/api/status?token={secret}")
        assert refused.value.status == 400 and "never in the URL" in str(refused.value)

        async def first(url: str, **kw: object) -> tuple[int | None, str]:
            try:
                async with websockets.connect(url, open_timeout=30, **kw) as ws:  # type: ignore[arg-type]
                    return None, json.loads(await asyncio.wait_for(ws.recv(), 30))["type"]
            except ConnectionClosed as exc:
                return (exc.rcvd.code if exc.rcvd else None), (exc.rcvd.reason if exc.rcvd else "")

        code, reason = asyncio.run(first(f"ws://127.0.0.1:{svc.port}/ws?token={secret}"))
        assert code == 4401 and "never in the URL" in reason
        code, kind = asyncio.run(first(f"ws://127.0.0.1:{svc.port}/ws",
                                       additional_headers={"Cookie": f"hil_token={secret}"}))
        assert code is None and kind == "status"
    finally:
        svc.stop()
