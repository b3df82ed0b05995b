"""A service killed with SIGKILL: the item that ran is aborted by its worker (the driver disabled first, the log
closed) and recorded ``interrupted``, never run again by itself; the queue and the history come back whole
(docs/service.md, docs/reliability.md)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import h5py

from tests.service.conftest import Service, short_session, wait_for


def test_a_manager_killed_mid_run_leaves_the_boards_safe_and_a_restart_keeps_queue_and_history(
        tmp_path: Path) -> None:
    state = tmp_path / "state"
    svc = Service(state).start()
    try:
        bench = svc.bench(user="kim")
        done = bench.run(short_session(tmp_path, 1.0, name="before"), out=tmp_path / "out")
        assert done.status == "completed"
        bench.stop_queue()
        waiting = [bench.add(short_session(tmp_path, 1.0, name=f"w{i}"))["uid"] for i in range(5)]
        long = bench.add(short_session(tmp_path, 60.0, name="long"), position=0)
        bench.start()  # the long one goes first
        wait_for(lambda: bench.item(long["uid"]).get("cycles", 0) > 500, timeout_s=180)
        bench.stop_queue()  # so that the restarted service does not start the waiting items by itself
        worker_pid = bench.status()["worker"]["holder"].split()[1]
        os.kill(svc.proc.pid, signal.SIGKILL)  # the manager only: its worker sees its stdin close
        svc.proc.wait(10)
        wait_for(lambda: not Path(f"/proc/{worker_pid}").exists(), timeout_s=60)  # it aborted, let go, exited
    finally:
        svc.stop(signal.SIGKILL)
    logs = list((state / "runs" / long["uid"]).glob("*.h5"))
    assert len(logs) == 1
    with h5py.File(logs[0], "r") as f:  # a log closed by its session: SWMR ended, the abort in its events
        kinds = [bytes(k).decode() for k in f["events/kind"][:]]
        rows = len(f["loop/tick"])
    assert "signal" in kinds and 500 < rows < 60_000

    again = Service(state, port=svc.port).start()
    try:
        bench = again.bench(user="kim")
        record = bench.item(long["uid"])
        assert record["state"] == "done" and record["status"] == "interrupted"
        assert "not run again" in record["message"]
        assert [i["uid"] for i in bench.queue()["items"]] == waiting  # the same queue, in the same order
        names = [r["name"] for r in bench.history()]
        assert names == ["long", "before"]
        bench.start()
        last = bench.wait(waiting[-1])
        assert last["status"] == "completed"
        time.sleep(0.5)
        assert [r["name"] for r in bench.history()][:6] == ["w4", "w3", "w2", "w1", "w0", "long"]
    finally:
        again.stop()
