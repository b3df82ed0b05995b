"""A service killed with SIGKILL: the item that ran is aborted by its worker (the driver disabled first, the log
closed) and recorded ``interrupted``, never run again by itself; the queue and the history come back whole
(docs/service.md, docs/reliability.md)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest

from hil.session import EmulatorProcess
from tests.factories import short_session
from tests.service.conftest import Service, free_port, wait_for


@pytest.mark.slow
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

    again = Service(state, port=svc.port).start(start_queue=False)
    try:
        bench = again.bench(user="kim")
        record = bench.item(long["uid"])
        assert record["state"] == "done" and record["status"] == "interrupted"
        assert "not run again" in record["message"]
        assert record["exit_code"] == 1 and record["links"]["log"].endswith("/log")  # the log it left, linked
        assert Path(record["log_path"]) == logs[0]
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


@pytest.mark.slow
@pytest.mark.parametrize("attempt", range(3))
def test_a_restarted_service_runs_nothing_until_an_operator_starts_the_queue(tmp_path: Path, attempt: int) -> None:
    """The manager SIGKILLed while an item runs and items wait, then the same `hil serve` again: the queue is
    stopped and says why, and no item starts (the old behaviour started the next one 5.5 s after the restart) until
    an operator starts it."""
    state = tmp_path / "state"
    svc = Service(state).start()
    try:
        bench = svc.bench(user="kim")
        long = bench.add(short_session(tmp_path, 60.0, name="long"))
        waiting = [bench.add(short_session(tmp_path, 1.0, name=f"w{i}"))["uid"] for i in range(2)]
        wait_for(lambda: bench.item(long["uid"]).get("cycles", 0) > 300, timeout_s=180)
        assert bench.queue()["running"] is True
        os.kill(svc.proc.pid, signal.SIGKILL)  # the manager only: its worker aborts the item and lets go
        svc.proc.wait(10)
    finally:
        svc.stop(signal.SIGKILL)
    again = Service(state, port=svc.port).start(start_queue=False)
    try:
        bench = again.bench(user="kim")
        queue = bench.queue()
        assert queue["running"] is False and queue["stopped"] == "the service restarted; 2 items wait"
        assert [i["uid"] for i in queue["items"]] == waiting
        assert bench.item(waiting[0])["queue_stopped"] == "the service restarted; 2 items wait"
        time.sleep(10.0)  # twice as long as the old service took to start the next item by itself
        assert [i["started_at"] for i in bench.queue()["items"]] == [None, None]
        assert [r["name"] for r in bench.history()] == ["long"]  # interrupted, and nothing else ran
        started = bench.start()
        assert started["running"] is True and started["was_stopped"] == "the service restarted; 2 items wait"
        assert bench.wait(waiting[0])["status"] == "completed"
    finally:
        again.stop()


@pytest.mark.slow
def test_a_killed_worker_s_item_is_a_fault_with_exit_code_1_and_its_log_linked(tmp_path: Path) -> None:
    """The worker SIGKILLed mid-item: the item is recorded fault, exit code 1, with the log it left on disk linked
    (it used to be recorded with neither), a new worker takes the lab and the queue goes on."""
    svc = Service(tmp_path / "state").start()
    try:
        bench = svc.bench(user="kim")
        long = bench.add(short_session(tmp_path, 60.0, name="long"))
        wait_for(lambda: bench.item(long["uid"]).get("cycles", 0) > 300, timeout_s=180)
        worker_pid = int(bench.status()["worker"]["holder"].split()[1])
        os.kill(worker_pid, signal.SIGKILL)
        record = bench.wait(long["uid"])
        assert record["status"] == "fault" and record["exit_code"] == 1
        assert "the worker process ended" in record["message"]
        assert record["links"]["log"] == f"/api/history/{long['uid']}/log"
        assert Path(record["log_path"]).parent == svc.state_dir / "runs" / long["uid"]
        after = bench.run(short_session(tmp_path, 1.0, name="after"), out=tmp_path / "out")
        assert after.status == "completed"
    finally:
        svc.stop()


HOLD = """
import json, sys, time
from hil.link import claim_ports
claims = claim_ports(json.loads(sys.argv[1]), sys.argv[2])
print("held", flush=True)
time.sleep(float(sys.argv[3]))
claims.release()
"""


def hold_ports(ports: dict[str, str], session: str, seconds: float) -> subprocess.Popen[str]:
    """Another process holding ``ports`` under ``session``'s name for ``seconds``."""
    proc = subprocess.Popen([sys.executable, "-c", HOLD, json.dumps(ports), session, str(seconds)],
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


@pytest.mark.slow
def test_a_lab_service_waits_for_a_dead_services_worker_and_refuses_a_live_bench(tmp_path: Path) -> None:
    """`hil serve --lab` started again at once after its manager was SIGKILLed finds the ports still held by the
    old worker (aborting its item): a holder named for a service whose manager is gone is waited for. A holder
    that is another live bench is refused at once, exit 2."""
    with EmulatorProcess(clock="realtime", extra_args=["--ports-file", str(tmp_path / "ports.json")]) as lab_boards:
        ports = {n: p for n, p in lab_boards.ports.items() if n != "control"}
        lab = short_session(tmp_path, 1.0, name="lab", ports={n: {"port": p} for n, p in ports.items()})
        dead = hold_ports(ports, "hil serve (pid 999999999)", 8.0)  # no such manager: its worker is winding down
        svc = Service(tmp_path / "state", args=("--lab", str(lab))).start(wait=False)
        try:
            t0 = time.monotonic()
            status = svc.wait_ready()
            waited_s = time.monotonic() - t0
            assert dead.wait(30) == 0
            assert status["worker"]["ports"] == ports and waited_s > 3.0  # it waited for them
        finally:
            svc.stop()
        live = hold_ports(ports, f"hil serve (pid {os.getpid()})", 60.0)  # a live manager: another bench
        try:
            t0 = time.monotonic()
            run = subprocess.run([sys.executable, "-m", "hil", "serve", "--lab", str(lab), "--port",
                                  str(free_port()), "--state-dir", str(tmp_path / "other")], capture_output=True,
                                 text=True, timeout=120, check=False)
            took_s = time.monotonic() - t0
        finally:
            live.kill()
            live.wait()
    assert run.returncode == 2 and "in use by pid" in run.stderr and took_s < 60, run.stderr
