"""The service's queue and history (hil.service.Store): order, moves, the lease's filter, one history record per
item, and nothing lost when the service is killed (docs/service.md)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.service import Store, StoreError

REPO = Path(__file__).resolve().parents[2]


def names(store: Store) -> list[str]:
    return [i.name for i in store.items()]


def test_items_queue_in_order_and_move_and_leave(tmp_path: Path) -> None:
    store, interrupted = Store.open(tmp_path)
    assert interrupted == []
    a, b, c = (store.add("session", n, "ana", f"{n}.yaml", f"name: {n}\n") for n in "abc")
    assert names(store) == ["a", "b", "c"] and [i.position for i in store.items()] == [0, 1, 2]
    store.add("ident", "first", "ben", "f.yaml", "x", position=0)
    assert names(store) == ["first", "a", "b", "c"]
    store.move(c.uid, 1)
    assert names(store) == ["first", "c", "a", "b"]
    store.move(c.uid, 99)  # past the end: last
    assert names(store) == ["first", "a", "b", "c"]
    assert store.remove(a.uid).name == "a" and names(store) == ["first", "b", "c"]
    assert [i.position for i in store.items()] == [0, 1, 2]
    assert "body" not in b.public() and b.public()["user"] == "ana"
    with pytest.raises(StoreError, match=r"^item 'nope': not in the queue$"):
        store.move("nope", 0)
    with pytest.raises(StoreError, match=r"^position=-1: not an index >= 0$"):
        store.move(b.uid, -1)
    with pytest.raises(StoreError, match=r"^kind='plot': not session, ident, campaign$"):
        store.add("plot", "p", "ana", "p.yaml", "")
    assert store.clear() == 3 and store.items() == []


def test_one_item_runs_at_a_time_and_a_lease_runs_only_its_holder_s(tmp_path: Path) -> None:
    store, _ = Store.open(tmp_path)
    ana = store.add("session", "ana-1", "ana", "a.yaml", "")
    ben = store.add("session", "ben-1", "ben", "b.yaml", "")
    store.add("session", "ana-2", "ana", "a2.yaml", "")
    first = store.start_next(users={"ben"})
    assert first is not None and first.uid == ben.uid and first.started_at is not None
    assert names(store)[0] == "ben-1"  # a running item is first
    assert store.start_next() is None  # one at a time
    with pytest.raises(StoreError, match="running; a running item cannot move"):
        store.move(ben.uid, 2)
    with pytest.raises(StoreError, match="running; stop or abort it instead"):
        store.remove(ben.uid)
    assert store.clear() == 2 and names(store) == ["ben-1"]  # clearing leaves the running item
    rec = store.finish(ben.uid, "fault", "watchdog:\n no GYRO_SAMPLE", log_path="/logs/b.h5",
                       summary={"cycles": 1200, "miss_std_px": 0.8})
    assert (rec.status, rec.message, rec.log_path, rec.summary["cycles"]) == (
        "fault", "watchdog: no GYRO_SAMPLE", "/logs/b.h5", 1200)
    assert rec.user == "ben" and rec.started_at is not None and rec.ended_at >= rec.started_at >= rec.submitted_at
    assert store.items() == [] and [r.uid for r in store.history()] == [ben.uid]
    with pytest.raises(StoreError, match=r"^status='done': not completed, lost_target, fault"):
        store.finish(ana.uid, "done")
    with pytest.raises(StoreError, match="not in the queue"):
        store.finish(ana.uid, "completed")  # cleared


def test_a_setting_outlives_the_store(tmp_path: Path) -> None:
    store, _ = Store.open(tmp_path)
    assert store.setting("queue_running", False) is False
    store.set_setting("queue_running", True)
    store.set_setting("stop_on_failure", {"after": 2})
    store.close()
    again, _ = Store.open(tmp_path)
    assert again.setting("queue_running") is True and again.setting("stop_on_failure") == {"after": 2}


WRITER = """
import sys
from pathlib import Path
from hil.service import Store
store, _ = Store.open(Path(sys.argv[1]))
first = store.add("session", "running", "ana", "r.yaml", "name: r")
store.start_next()
print("started", first.uid, flush=True)
k = 0
while True:
    item = store.add("session", f"item-{k}", "ana", f"{k}.yaml", f"name: item-{k}")
    if k % 3 == 2:
        store.finish(store.items()[1].uid, "completed", "done")
    print(item.uid, flush=True)
    k += 1
"""


def test_a_service_killed_mid_write_loses_nothing_and_runs_nothing_again(tmp_path: Path) -> None:
    """SIGKILL while items are being added and finished: every change that returned is there after a restart, and
    the item that was running is in the history as interrupted, off the queue."""
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path)], stdout=subprocess.PIPE, text=True,
                            cwd=REPO)
    assert proc.stdout is not None
    started = proc.stdout.readline().split()
    assert started[0] == "started"
    returned: list[str] = []
    give_up = time.monotonic() + 60
    while len(returned) < 150:
        returned.append(proc.stdout.readline().strip())
        assert time.monotonic() < give_up
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(10)
    store, interrupted = Store.open(tmp_path)
    assert [r.uid for r in interrupted] == [started[1]] and interrupted[0].status == "interrupted"
    queued = {i.uid for i in store.items()}
    finished = {r.uid for r in store.history()}
    assert all(uid in queued or uid in finished for uid in returned)  # nothing that returned was lost
    assert started[1] not in queued and store.start_next() is not None  # the next item runs, not the interrupted
    assert all(i.started_at is None for i in store.items()[1:])
    assert [i.position for i in store.items()] == list(range(len(store.items())))


def test_the_running_item_and_the_number_waiting(tmp_path: Path) -> None:
    store, _ = Store.open(tmp_path)
    assert store.running() is None and store.waiting() == 0
    for n in "abc":
        store.add("session", n, "ana", f"{n}.yaml", f"name: {n}\n")
    started = store.start_next()
    assert started is not None and store.running() == store.item(started.uid) and store.waiting() == 2
    store.finish(started.uid, "completed")
    assert store.running() is None and store.waiting() == 2
