"""`hil serve --loopback` for real: a worker that owns the emulated lab's ports, the queue and its history, stop
and abort, the lease, two users at once, a refusal of a second bench on the service's ports, and the OpenAPI
document (docs/service.md)."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import pytest
import yaml

from hil.service import API_ROUTES, BenchError
from tests.factories import short_session
from tests.service.conftest import Service, free_port, wait_for

REPO = Path(__file__).resolve().parents[2]


def hil(*args: str, env: dict[str, str] | None = None, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil", *args], capture_output=True, text=True, timeout=timeout,
                          cwd=REPO, env=env, check=False)


@pytest.mark.slow
def test_a_session_runs_through_the_service_and_comes_back_as_a_run_result(service: Service,
                                                                          tmp_path: Path) -> None:
    bench = service.bench(user="ana")
    views: list[dict] = []
    result = bench.run(short_session(tmp_path, 2.0), out=tmp_path / "logs", on_view=views.append)
    assert result.status == "completed" and result.exit_code == 0, result.message
    assert result.log_path is not None and result.log_path.parent == tmp_path / "logs"
    loop = result.log.loop
    assert 1900 <= len(loop) <= 7500  # 2 s at 1 kHz, and the wind-down (the hexapod home in <= 5 s)
    assert loop.attrs["units"]["rate_err_el_dps"] == "deg/s"
    provenance = result.log.provenance  # who submitted it, beside the software and the plant
    assert provenance["submitted_by"] == "ana" and len(provenance["service_item"]) == 32
    assert provenance["hil_version"] and provenance["plant"]["sha256"]
    summary = result.summary()
    assert summary["cycles"] >= 1900 and summary["rate_error_el_dps"]["std"] > 0
    record = bench.history(limit=1)[0]
    assert record["user"] == "ana" and record["status"] == "completed" and record["exit_code"] == 0
    assert record["submitted_at"] <= record["started_at"] <= record["ended_at"]
    assert record["summary"]["cycles"] == summary["cycles"]
    assert record["links"]["log"].endswith("/log")
    assert any(v["state"] == "running" for v in views)
    status = wait_for(lambda: (s := bench.status())["worker"]["safe"] and s, timeout_s=60)  # measured after it
    assert status["running"] is None and status["worker"]["safe"].startswith("driver disabled")


def test_the_status_carries_the_hardware_checks_and_they_run_again_on_request(service: Service) -> None:
    first = service.bench().status()["worker"]["doctor"]
    checks = {(f["link"], f["check"]): f for f in first["findings"]}
    assert first["ok"], [f for f in first["findings"] if not f["ok"]]
    for link in ("servo", "driver", "image", "hexapod"):
        assert checks[(link, "ident")]["values"]["catalogue_fingerprint"] == checks[("servo", "ident")]["values"][
            "catalogue_fingerprint"]
    stream = checks[("servo", "servo stream")]
    assert 990 <= stream["values"]["board_rate_hz"] <= 1010
    run = subprocess.run([sys.executable, "-m", "hil", "bench", "doctor", "--bench", service.url, "--json"],
                         capture_output=True, text=True, timeout=120, cwd=REPO, check=False)
    assert run.returncode == 0, run.stderr
    again = json.loads(run.stdout)
    assert again["at"] > first["at"] and again["ok"]
    boards = service.bench().status()["worker"]["boards"]
    assert all(b["identified"] for b in boards.values())


def test_a_bad_item_is_refused_when_submitted_with_the_loaders_one_line(service: Service, tmp_path: Path) -> None:
    bench = service.bench()
    good = short_session(tmp_path)
    text = good.read_text().replace("duration_s: 2.0", "duration_s: -1")
    with pytest.raises(BenchError) as err:
        bench.call("POST", "/api/queue/items", {"kind": "session", "file_name": "bad.yaml", "body": text})
    assert err.value.status == 422
    assert str(err.value).startswith("bad.yaml: duration_s") and "\n" not in str(err.value)
    with pytest.raises(BenchError) as err:
        bench.call("POST", "/api/queue/items", {"kind": "recipe", "file_name": "x.yaml", "body": "a: 1"})
    assert err.value.status == 422 and "kind" in str(err.value)
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    run = hil("queue", "add", str(bad), "--bench", service.url)
    assert run.returncode == 2 and "bad.yaml" in run.stderr and "duration_s" in run.stderr
    assert bench.queue()["items"] == []


@pytest.mark.slow
def test_stop_winds_down_normally_and_abort_disables_first(service: Service, tmp_path: Path) -> None:
    bench = service.bench(user="ben")
    for how, status, code in (("stop", "stopped", 3), ("abort", "aborted", 130)):
        item = bench.add(short_session(tmp_path, 30.0, name=f"long-{how}"))
        wait_for(lambda uid=item["uid"]: bench.item(uid).get("cycles", 0) > 500, timeout_s=180)
        with pytest.raises(BenchError) as err:  # the hardware checks wait for the boards to be free
            bench.doctor()
        assert err.value.status == 409 and "between items" in str(err.value)
        waiting = bench.add(short_session(tmp_path, 1.0, name=f"after-{how}"))
        answer = getattr(bench, how)(reason="test")
        record = bench.wait(item["uid"])
        assert record["status"] == status and record["exit_code"] == code, record
        # a stop lets the queue go on; an abort stops it: nothing arms the boards until an operator starts it
        assert answer["queue_running"] is (how == "stop") and bench.queue()["running"] is (how == "stop")
        if how == "abort":
            time.sleep(2.0)
            assert bench.item(waiting["uid"])["state"] == "queued"
            bench.start()
        assert bench.wait(waiting["uid"])["status"] == "completed"
        assert record["summary"]["cycles"] < 20_000  # ended well before its 30 s
        with h5py.File(record["log_path"], "r") as f:
            events = [bytes(k).decode() for k in f["events/kind"][:]]
        assert ("signal" in events) == (how == "abort")  # abort: the SIGINT path, the driver disabled first


@pytest.mark.slow
def test_two_users_submitting_at_once_both_run_one_after_the_other(service: Service, tmp_path: Path) -> None:
    results: dict[str, object] = {}

    def run(user: str) -> None:
        results[user] = service.bench(user=user).run(short_session(tmp_path, 1.5, name=f"from-{user}"),
                                                     out=tmp_path / user)

    threads = [threading.Thread(target=run, args=(u,)) for u in ("cy", "di")]
    for t in threads:
        t.start()
    for t in threads:
        t.join(600)
    assert {u: r.status for u, r in results.items()} == {"cy": "completed", "di": "completed"}  # type: ignore[attr-defined]
    records = [r for r in service.bench().history(limit=10) if r["user"] in ("cy", "di")][:2]
    first, second = sorted(records, key=lambda r: r["started_at"])
    assert first["ended_at"] <= second["started_at"]  # one after the other


@pytest.mark.slow
def test_while_a_lease_is_held_only_its_holders_items_run(service: Service, tmp_path: Path) -> None:
    eve, fay = service.bench(user="eve"), service.bench(user="fay")
    eve.lease(ttl_s=60)
    with pytest.raises(BenchError) as err:
        fay.lease(ttl_s=60)
    assert err.value.status == 409 and "eve" in str(err.value)
    try:
        theirs = fay.add(short_session(tmp_path, 1.0, name="fays"))
        mine = eve.add(short_session(tmp_path, 1.0, name="eves"))
        assert eve.wait(mine["uid"])["status"] == "completed"
        assert fay.item(theirs["uid"])["state"] == "queued"  # submitted first, still waiting
        fay.break_lease("eve is at lunch")
        assert fay.wait(theirs["uid"])["status"] == "completed"
    finally:
        with pytest.raises(BenchError):
            eve.release()  # broken: eve holds nothing now
    events = fay.call("GET", "/api/lease")["events"]
    assert events[0]["event"] == "broken" and events[0]["by"] == "fay" and events[0]["reason"] == "eve is at lunch"


@pytest.mark.slow
def test_queue_operations(service: Service, tmp_path: Path) -> None:
    bench = service.bench(user="gil")
    bench.stop_queue()
    try:
        _a, b, c = (bench.add(short_session(tmp_path, 1.0, name=n)) for n in ("qa", "qb", "qc"))
        assert [i["name"] for i in bench.queue()["items"]] == ["qa", "qb", "qc"]
        bench.move(c["uid"], 0)
        bench.remove(b["uid"])
        assert [i["name"] for i in bench.queue()["items"]] == ["qc", "qa"]
        with pytest.raises(BenchError) as err:
            bench.remove(b["uid"])
        assert err.value.status == 404
        assert bench.clear()["removed"] == 2 and bench.queue()["items"] == []
        kept = bench.add(short_session(tmp_path, 1.0, name="qd"))
        assert bench.item(kept["uid"])["state"] == "queued"  # the queue is stopped
    finally:
        bench.start()
    assert bench.wait(kept["uid"])["status"] == "completed"
    listed = hil("queue", "list", "--bench", service.url, "--json")
    assert listed.returncode == 0 and json.loads(listed.stdout)["running"] is True


def test_a_run_on_the_services_ports_is_refused_naming_the_port_and_the_service(service: Service,
                                                                                tmp_path: Path) -> None:
    ports = service.bench().status()["worker"]["ports"]
    session = short_session(tmp_path, 1.0, name="intruder", ports={k: {"port": v} for k, v in ports.items()})
    data = yaml.safe_load(session.read_text())
    data["safety"].pop("emulator_stall_grace_ms", None)  # a lab session: its boards are never late
    session.write_text(yaml.safe_dump(data))
    run = hil("run", str(session), "--out", str(tmp_path))
    assert run.returncode == 2, run.stdout + run.stderr
    line = " ".join(run.stderr.split())
    assert "in use by pid" in line and "hil serve" in line and ports["servo"] in line
    assert len(run.stderr.strip().splitlines()) == 1


def test_a_second_service_on_the_same_ports_is_refused_naming_the_port_and_the_service(service: Service,
                                                                                    tmp_path: Path) -> None:
    ports = service.bench().status()["worker"]["ports"]
    lab = short_session(tmp_path, 1.0, name="lab", ports={k: {"port": v} for k, v in ports.items()})
    run = subprocess.run([sys.executable, "-m", "hil", "serve", "--lab", str(lab), "--port", str(free_port()),
                          "--state-dir", str(tmp_path / "state")], capture_output=True, text=True, timeout=120,
                         cwd=REPO, check=False)
    assert run.returncode == 2, run.stdout + run.stderr
    lines = run.stderr.strip().splitlines()
    line = " ".join(run.stderr.split())
    assert lines[0].startswith("error: hil serve: cannot serve the lab:"), run.stderr
    assert "in use by pid" in line and "hil serve (pid" in line and ports["servo"] in line
    assert service.bench().status()["worker"]["state"] == "ready"  # the first service serves on


def test_the_openapi_document_describes_every_route(service: Service) -> None:
    doc = service.bench().call("GET", "/openapi.json")
    assert doc["openapi"].startswith("3.1")
    for method, path, _handler, operator, model, _summary in API_ROUTES:
        op = doc["paths"][path][method.lower()]
        assert op["summary"]
        if model is not None:
            ref = op["requestBody"]["content"]["application/json"]["schema"]["$ref"]
            assert ref.rsplit("/", 1)[1] in doc["components"]["schemas"]
        if operator is not None:
            assert "403" in op["responses"]
    assert doc["components"]["schemas"]["SubmitItem"]["properties"]["kind"]["enum"] == ["session", "ident",
                                                                                       "campaign"]


HOLD_LEASE = """
import sys, time
from hil.service import Bench
with Bench(sys.argv[1], user="ci-job").leased(ttl_s=5):
    print("held", flush=True)
    time.sleep(600)
"""


@pytest.mark.slow
def test_a_lease_held_by_a_client_that_dies_lapses_by_itself(service: Service) -> None:
    holder = subprocess.Popen([sys.executable, "-c", HOLD_LEASE, service.url], stdout=subprocess.PIPE, text=True,
                              cwd=REPO)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        bench = service.bench(user="next-one")
        time.sleep(7)  # past its 5 s TTL: renewed meanwhile
        assert bench.status()["lease"]["holder"] == "ci-job"
    finally:
        holder.kill()  # the CI job is cancelled: no release, no more renewals
        holder.wait()
    wait_for(lambda: bench.status()["lease"] is None, timeout_s=30)  # within its TTL, give or take a poll
    events = bench.call("GET", "/api/lease")["events"]
    assert events[0]["event"] == "lapsed" and events[0]["holder"] == "ci-job"
    with bench.leased(ttl_s=5) as lease:  # and the next one takes it
        assert lease["holder"] == "next-one"
    assert bench.status()["lease"] is None  # released at the end of the block
