"""Hostile callers of a real `hil serve --loopback` (docs/service.md, "Same origin"; docs/reliability.md, "The
service"): another site's page in the lab PC's browser, DNS rebinding, bodies built to break the parser or the
memory, names no file system takes. Every answer is one line of JSON, never a traceback, and none of them changes
the bench."""

from __future__ import annotations

import http.client
import json
import os
from collections.abc import Iterator
from pathlib import Path

import pytest
import websockets.sync.client
from websockets.exceptions import InvalidStatus

from tests.factories import short_session
from tests.service.conftest import Service

EVIL = "http://evil.example"


def call(svc: Service, method: str, path: str, body: bytes | None = None,
         headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], bytes]:
    """One raw request: (status, headers, body)."""
    conn = http.client.HTTPConnection("127.0.0.1", svc.port, timeout=60)
    try:
        conn.request(method, path, body=body, headers=headers or {})
        response = conn.getresponse()
        return response.status, {k.lower(): v for k, v in response.getheaders()}, response.read()
    finally:
        conn.close()


def one_json_line(status: int, headers: dict[str, str], body: bytes) -> str:
    """The error's one line, after checking that it is JSON and holds no traceback."""
    assert headers["content-type"].startswith("application/json"), (status, headers, body[:200])
    detail = json.loads(body)["detail"]
    assert "\n" not in detail and "Traceback" not in detail and "File \"" not in detail
    return str(detail)


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    service = Service(tmp_path_factory.mktemp("hostile") / "state").start()
    yield service
    service.stop()


def item_body(tmp_path: Path, **fields: object) -> bytes:
    text = short_session(tmp_path, 1.0, name="hostile").read_text()
    return json.dumps({"kind": "session", "file_name": "hostile.yaml", "body": text, **fields}).encode()


@pytest.mark.slow
def test_another_sites_page_can_neither_submit_start_abort_nor_watch(svc: Service, tmp_path: Path) -> None:
    bench = svc.bench()
    bench.stop_queue()
    try:
        before = len(bench.queue()["items"])
        simple = {"Origin": EVIL, "Content-Type": "text/plain"}  # what a browser sends cross-site with no preflight
        for method, path, body in (("POST", "/api/queue/items", item_body(tmp_path)),
                                   ("POST", "/api/queue/start", b"{}"), ("POST", "/api/bench/abort", b"{}"),
                                   ("POST", "/api/lease", b"{}"), ("DELETE", "/api/lease", None)):
            status, headers, raw = call(svc, method, path, body, simple)
            assert status == 403, (path, status, raw)
            assert "Origin" in one_json_line(status, headers, raw)
        # the same with the JSON content type a cross-site page cannot send without a preflight the service refuses
        status, headers, raw = call(svc, "POST", "/api/queue/start", b"{}",
                                    {"Origin": EVIL, "Content-Type": "application/json"})
        assert status == 403
        status, headers, raw = call(svc, "POST", "/api/queue/items", item_body(tmp_path),
                                    {"Sec-Fetch-Site": "cross-site", "Content-Type": "application/json"})
        assert status == 403 and "cross-site" in one_json_line(status, headers, raw)
        # a page of its own origin, and a client with no Origin, may; but only as JSON
        status, headers, raw = call(svc, "POST", "/api/queue/items", item_body(tmp_path),
                                    {"Content-Type": "text/plain"})
        assert status == 415 and "application/json" in one_json_line(status, headers, raw)
        own = f"http://127.0.0.1:{svc.port}"
        status, _, raw = call(svc, "POST", "/api/queue/items", item_body(tmp_path),
                              {"Origin": own, "Content-Type": "application/json"})
        assert status == 201, raw
        uid = json.loads(raw)["uid"]
        assert len(bench.queue()["items"]) == before + 1 and bench.queue()["running"] is False
        svc.bench(user="local").remove(uid)  # it was submitted without X-Hil-User: the service's "local" user's
    finally:
        bench.start()
    with pytest.raises(InvalidStatus) as refused:
        websockets.sync.client.connect(f"ws://127.0.0.1:{svc.port}/ws", origin=EVIL, open_timeout=30)
    assert refused.value.response.status_code == 403
    with websockets.sync.client.connect(f"ws://127.0.0.1:{svc.port}/ws", origin=f"http://127.0.0.1:{svc.port}",
                                        open_timeout=30) as ws:
        assert json.loads(ws.recv(timeout=30))["type"] == "status"


def test_a_host_name_the_service_does_not_serve_is_refused_dns_rebinding(svc: Service, tmp_path: Path) -> None:
    for method, path, body in (("GET", "/api/status", None), ("GET", "/", None),
                               ("POST", "/api/queue/start", b"{}")):
        status, headers, raw = call(svc, method, path, body, {"Host": f"evil.example:{svc.port}",
                                                              "Content-Type": "application/json"})
        assert status == 400
        assert "allow_host='evil.example'" in one_json_line(status, headers, raw)
    with pytest.raises(InvalidStatus):
        websockets.sync.client.connect(f"ws://127.0.0.1:{svc.port}/ws", additional_headers={"Host": "evil.example"},
                                       open_timeout=30)
    for host in (f"localhost:{svc.port}", f"127.0.0.1:{svc.port}", f"[::1]:{svc.port}"):
        status, _, _ = call(svc, "GET", "/api/status", None, {"Host": host})
        assert status == 200, host


@pytest.mark.parametrize(("case", "payload", "status"), [
    ("deep JSON", b"[" * 100_000, 400),
    ("a NUL in file_name", None, 422),
    ("a 255-character multibyte file name", None, 422),
    ("a lone surrogate in body", b'{"kind": "session", "file_name": "a.yaml", "body": "\\ud800"}', 422),
    ("not JSON at all", b"\xff\xfe{", 400),
    ("a list", b"[]", 422),
])
def test_bodies_built_to_break_the_parser_are_one_line_of_json(svc: Service, tmp_path: Path, case: str,
                                                               payload: bytes | None, status: int) -> None:
    if payload is None:
        name = "a\x00b.yaml" if "NUL" in case else "é" * 250 + ".yaml"
        payload = item_body(tmp_path, file_name=name)
    got, headers, raw = call(svc, "POST", "/api/queue/items", payload, {"Content-Type": "application/json"})
    assert got == status, (case, raw[:300])
    one_json_line(got, headers, raw)


def manager_rss_kib(svc: Service) -> int:
    assert svc.proc is not None
    for line in Path(f"/proc/{svc.proc.pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


def test_a_huge_body_is_refused_before_it_is_held_in_memory(svc: Service) -> None:
    before = manager_rss_kib(svc)
    status, headers, raw = call(svc, "POST", "/api/queue/items", b"x" * 16, {
        "Content-Type": "application/json", "Content-Length": str(500 << 20)})
    assert status == 413 and "2097152" in one_json_line(status, headers, raw)
    # without a Content-Length (chunked), 64 MiB are sent until the service stops reading
    conn = http.client.HTTPConnection("127.0.0.1", svc.port, timeout=60)
    try:
        conn.putrequest("POST", "/api/queue/items")
        conn.putheader("Content-Type", "application/json")
        conn.putheader("Transfer-Encoding", "chunked")
        conn.endheaders()
        chunk = b"[" * (1 << 20)
        try:
            for _ in range(64):
                conn.send(f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n")
            conn.send(b"0\r\n\r\n")
        except (BrokenPipeError, ConnectionResetError):
            pass  # the service answered and closed before the rest came
        response = conn.getresponse()
        assert response.status == 413
        one_json_line(response.status, {k.lower(): v for k, v in response.getheaders()}, response.read())
    finally:
        conn.close()
    assert manager_rss_kib(svc) - before < 32 << 10  # never the 500 MB, nor the 64 MiB


def test_unknown_routes_and_methods_answer_json(svc: Service) -> None:
    status, headers, raw = call(svc, "GET", "/api/nothing-here")
    assert status == 404 and "no such route" in one_json_line(status, headers, raw)
    status, headers, raw = call(svc, "PUT", "/api/status", b"{}", {"Content-Type": "application/json"})
    assert status == 405 and "GET" in headers["allow"]
    one_json_line(status, headers, raw)
    status, headers, raw = call(svc, "GET", "/static/no-such-file.js")
    assert status == 404
    one_json_line(status, headers, raw)


def test_nothing_the_hostile_calls_did_reached_the_queue_or_the_log(svc: Service) -> None:
    """After the calls above: the service still serves, nothing ran, and its stderr holds no traceback of them."""
    bench = svc.bench()
    assert bench.status()["worker"]["state"] == "ready"
    assert bench.history() == []
    assert "Traceback" not in svc.output()
    assert os.path.exists(svc.state_dir / "service.sqlite3")


@pytest.mark.slow
def test_a_client_polling_in_a_tight_loop_is_told_to_wait_and_others_are_not(tmp_path: Path) -> None:
    """A token bucket per client (hil.service._limits; here `--max-rate 2`, bursts of 4, so that any machine, however
    loaded, asks faster than that): past it 429 with Retry-After and one line, another client answered meanwhile."""
    svc = Service(tmp_path / "state", args=("--loopback", "--max-rate", "2")).start(start_queue=False)
    conn = http.client.HTTPConnection("127.0.0.1", svc.port, timeout=60)
    codes: list[int] = []
    try:
        for _ in range(40):
            conn.request("GET", "/api/status", headers={"X-Hil-User": "poller"})
            response = conn.getresponse()
            body = response.read()
            codes.append(response.status)
            if response.status == 429:
                assert int(response.getheader("Retry-After") or "0") >= 1
                assert "too many requests from poller: at most 2 a second" in json.loads(body)["detail"]
        status, _, _ = call(svc, "GET", "/api/status", None, {"X-Hil-User": "someone-else"})
        assert status == 200
    finally:
        conn.close()
        svc.stop()
    assert codes.count(200) >= 4 and codes.count(429) >= 10 and set(codes) <= {200, 429}, codes
