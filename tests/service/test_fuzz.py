"""The service's HTTP API fuzzed from its own OpenAPI document (`GET /openapi.json`, docs/service.md), on a real
`hil serve --loopback` with an item running.

Schemathesis draws requests for every operation of the document, valid and invalid ones (its examples, coverage
and fuzzing phases; positive and negative data), then scenarios that chain operations by the links it infers
(its stateful phase), and runs all its default checks on every answer: no 5xx, a status code the document lists
for the operation, the content type and the body schema the document gives, invalid input refused with a 4xx,
valid input not refused, an unsupported method answered 405 with an ``Allow`` header. One expectation is added: a
schema-valid submission may get 422, since an item's text is checked by its kind's own loader beyond the body's
JSON schema. The examples are bounded (``MAX_EXAMPLES`` per operation, ``MAX_EXAMPLES`` scenarios) and
derandomized, so a run is reproducible and takes a few minutes on a busy 2-core machine.

What the generator does not draw is sent by hand and its answer checked by the same Schemathesis checks: bodies
that are not a JSON object (nested 100 000 deep, not UTF-8, over the 2 MiB limit), strings no database or UTF-8
encoder takes (a NUL, a lone surrogate) in every kind of field and path, and routes and methods the document does
not have (one line of JSON, 404 or 405 with the path's methods in ``Allow``).

Load: before the fuzzing starts a ``LOAD_S`` session is submitted and the queue started, and while it runs a
thread (:class:`Load`) keeps an item running. The fuzzer may stop or abort the running item, clear or stop the
queue, take or break the lease: nothing is excluded, since those are the calls most likely to go wrong while the
bench is busy. Instead, whenever no item runs the thread starts the queue again and submits another session, as
the user the fuzzer's requests are made for (they carry no ``X-Hil-User``), so a lease the fuzzer took never
keeps it waiting. The last test checks that an item ran for most of the fuzzing and that the service still runs a
session to its end afterwards.

Every request goes to the service on 127.0.0.1: the HTTP session the fuzzer uses refuses any other address, and
ignores proxy settings from the environment.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import requests
import schemathesis
from hypothesis import HealthCheck, settings
from requests.adapters import BaseAdapter, HTTPAdapter

from hil.service import API_ROUTES, BenchError
from hil.service._auth import LOCAL_USER
from tests.factories import short_session
from tests.service.conftest import Service, wait_for

MAX_EXAMPLES = 30  # per operation, in the fuzzing phase (the examples and coverage phases add their own few)
LOAD_S = 120.0  # the session that runs while the fuzzer does
KEEP_EVERY_S = 0.5  # how often the load is looked at, and an item submitted again when none runs
STATEFUL_STEPS = 8  # calls per scenario of the stateful test (MAX_EXAMPLES scenarios)
MIN_BUSY = 0.5  # the share of those looks that found an item running
# what a schema-valid submission may get: as any operation, and 422 for a text its kind's loader refuses
SUBMIT_ACCEPTS = ["2xx", "3xx", "401", "403", "404", "409", "422", "429", "5xx"]  # 5xx: not_a_server_error


class Load:
    """Keeps an item running on the service: a ``LOAD_S`` session, submitted again (and the queue started) when the
    fuzzer ended the last one. Counts how often it found one running."""

    def __init__(self, service: Service, directory: Path) -> None:
        self.bench = service.bench(user=LOCAL_USER)
        self.session = short_session(directory, LOAD_S, name="load")
        self.looks = self.busy = self.submitted = 0
        self.errors: list[str] = []
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fuzz-load", daemon=True)

    def start(self) -> Load:
        self.keep()
        wait_for(lambda: self.bench.status()["running"] is not None, timeout_s=180)
        self.looks = self.busy = 0
        self._thread.start()
        return self

    def stop(self) -> None:
        self._done.set()
        self._thread.join(30)

    @property
    def share_busy(self) -> float:
        return self.busy / max(1, self.looks)

    def keep(self) -> None:
        status = self.bench.status()
        self.looks += 1
        if status["running"] is not None:
            self.busy += 1
            return
        if not status["queue"]["running"]:
            self.bench.start()
        if status["queue"]["waiting"] == 0:
            self.bench.add(self.session)
            self.submitted += 1

    def _run(self) -> None:
        while not self._done.wait(KEEP_EVERY_S):
            try:
                self.keep()
            except BenchError as exc:  # a refusal the fuzzer's last call caused (a lease, a full queue): try again
                self.errors.append(str(exc))


class _Refused(BaseAdapter):
    """The adapter for any address but the service's: nothing is sent."""

    def send(self, request: requests.PreparedRequest, *args: Any, **kwargs: Any) -> requests.Response:
        raise ConnectionRefusedError(f"{request.url}: the fuzzer talks to the service on 127.0.0.1 only")

    def close(self) -> None:
        pass


def local_session(service: Service) -> requests.Session:
    """A requests session that reaches the service and nothing else (no proxy from the environment either)."""
    assert service.host == "127.0.0.1"
    session = requests.Session()
    session.trust_env = False
    session.mount("http://", _Refused())
    session.mount("https://", _Refused())
    session.mount(f"{service.url}/", HTTPAdapter())
    return session


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    """The module's service, its per-client rate limit raised out of the fuzzer's way: one client sending as fast as
    it can would be answered 429 (documented; tests/service/test_hostile.py checks the limit itself)."""
    svc = Service(tmp_path_factory.mktemp("fuzz") / "state", args=("--loopback", "--max-rate", "100000")).start()
    yield svc
    svc.stop()


@pytest.fixture(scope="module")
def load(service: Service, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Load]:
    keeper = Load(service, tmp_path_factory.mktemp("load")).start()
    yield keeper
    keeper.stop()


@pytest.fixture(scope="module")
def http(service: Service) -> Iterator[requests.Session]:
    with local_session(service) as session:
        yield session


@pytest.fixture(scope="module")
def api_schema(service: Service, http: requests.Session, load: Load) -> schemathesis.BaseSchema:
    """The service's own document, as `GET /openapi.json` gives it, aimed at the service."""
    answer = http.get(f"{service.url}/openapi.json", timeout=30)
    assert answer.status_code == 200, answer.text
    return schemathesis.openapi.from_dict(answer.json(), config=fuzz_config(service.url))


def fuzz_config(url: str) -> schemathesis.Config:
    """Schemathesis' defaults (every check on), aimed at ``url``; nothing is read from a schemathesis.toml."""
    return schemathesis.Config.from_dict({
        "base-url": url,
        "request-timeout": 60,
        "operations": [{  # an item's text is checked by its own loader, beyond the body's JSON schema
            "include-name": "POST /api/queue/items",
            "checks": {"positive_data_acceptance": {"expected-statuses": SUBMIT_ACCEPTS}}}],
    })


schema = schemathesis.pytest.from_fixture("api_schema")


@pytest.fixture
def node_nodeid(request: pytest.FixtureRequest) -> None:
    """Schemathesis' lazy schemas read and rename ``node._nodeid`` per operation, which pytest 9 nodes no longer
    have (they keep a NodeId in ``_id``): give the test's node the attribute it reads (each operation's results are
    still reported apart, as subtests named by the operation)."""
    if not hasattr(request.node, "_nodeid"):
        request.node._nodeid = request.node.nodeid


FUZZ_SETTINGS = settings(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True, database=None,
                         suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
                         stateful_step_count=STATEFUL_STEPS)


@pytest.mark.slow
@FUZZ_SETTINGS
@pytest.mark.usefixtures("node_nodeid")
@schema.parametrize()
def test_every_operation_answers_as_its_document_says(case: schemathesis.Case, http: requests.Session,
                                                      service: Service) -> None:
    response = case.call_and_validate(session=http)
    assert response.request.url.startswith(f"{service.url}/")


def test_chains_of_operations_answer_as_the_document_says(api_schema: schemathesis.BaseSchema,
                                                          http: requests.Session) -> None:
    """Scenarios of up to STATEFUL_STEPS calls that pass what one answer gives to the next (the links Schemathesis
    infers: a record's uid from the history to its log and report, a submitted item's uid to its moves), with the
    same checks on every answer."""

    class Scenarios(api_schema.as_state_machine()):  # type: ignore[misc]
        def get_call_kwargs(self, case: schemathesis.Case) -> dict[str, Any]:
            return {"session": http}

    Scenarios.run(settings=FUZZ_SETTINGS)


# --- what the generator does not draw: bodies that are not JSON objects, strings no database or UTF-8 encoder
# takes, a body over the limit, routes and methods the document does not have ---------------------------------

NUL, LONE = "a\x00b", "a\ud800b"  # a NUL character; a lone surrogate (valid JSON as "\ud800", not UTF-8)
RAW_BODIES = {  # sent as Content-Type: application/json to every operation that takes a body
    "deep": b"[" * 100_000,
    "deep-balanced": b"[" * 50_000 + b"]" * 50_000,
    "not-utf8": b'{"reason": "\xff\xfe"}',
    "not-an-object": b"[]",
    "surrogate-escape": b'{"reason": "\\udc80"}',
    "too-large": b'{"reason": "' + b"x" * (3 << 20) + b'"}',
}
BODY_OPERATIONS = [f"{method} {path}" for method, path, _handler, _op, model, _summary in API_ROUTES if model]
# one bad string in an otherwise valid body (a submitted item: the load's session text, which loads)
BAD_STRINGS: dict[str, tuple[str, str, dict[str, Any]]] = {
    "submit-file_name-nul": ("POST", "/api/queue/items", {"file_name": "a\x00.yaml"}),
    "submit-file_name-surrogate": ("POST", "/api/queue/items", {"file_name": "\ud800.yaml"}),
    "submit-body-nul": ("POST", "/api/queue/items", {"body": NUL}),
    "submit-body-surrogate": ("POST", "/api/queue/items", {"body": LONE}),
    "submit-files-surrogate": ("POST", "/api/queue/items", {"files": {"\ud800.yaml": "x"}}),
    "submit-options-nul": ("POST", "/api/queue/items", {"kind": "ident", "options": {"axis": NUL}}),
    "stop-uid-surrogate": ("POST", "/api/bench/stop", {"uid": LONE}),
    "stop-reason-nul": ("POST", "/api/bench/stop", {"reason": NUL}),
    "abort-reason-surrogate": ("POST", "/api/bench/abort", {"reason": LONE}),
    "break-reason-nul": ("POST", "/api/lease/break", {"reason": NUL}),
    "break-reason-surrogate": ("POST", "/api/lease/break", {"reason": LONE}),
}
BAD_PATHS = {"item-nul": "/api/items/%00", "item-not-utf8": "/api/items/%ED%A0%80",
             "record-nul": "/api/history/a%00b", "log-not-utf8": "/api/history/%FF/log"}
UNKNOWN_ROUTES = [("GET", "/api/nope"), ("POST", "/api/nope"), ("GET", "/nope"), ("DELETE", "/api/status"),
                  ("PUT", "/api/lease"), ("GET", "/api/queue/items"), ("PATCH", "/openapi.json")]


def release_the_fuzzers_lease(service: Service) -> None:
    """Release a lease the fuzzer took (its requests are LOCAL_USER's)."""
    lease = service.bench().status()["lease"]
    if lease is not None and lease["holder"] == LOCAL_USER:
        service.bench(user=LOCAL_USER).release()


def answered_as_documented(api_schema: schemathesis.BaseSchema, method: str, path: str,
                           response: requests.Response, **case: Any) -> None:
    """The answer checked by Schemathesis as a case of ``method path`` (not a server error, a documented status,
    its content type and schema)."""
    api_schema[path][method].Case(**case).validate_response(response)


@pytest.mark.parametrize("operation", BODY_OPERATIONS)
@pytest.mark.parametrize("raw", RAW_BODIES)
def test_a_body_that_is_not_a_json_object_is_refused_as_documented(api_schema: schemathesis.BaseSchema,
                                                                   http: requests.Session, service: Service,
                                                                   operation: str, raw: str) -> None:
    method, path = operation.split(" ")
    url = service.url + path.replace("{uid}", "0")
    response = http.request(method, url, data=RAW_BODIES[raw], headers={"Content-Type": "application/json"},
                            timeout=60)
    assert 400 <= response.status_code < 500, (response.status_code, response.text[:300])
    answered_as_documented(api_schema, method, path, response, path_parameters={"uid": "0"} if "{" in path else None)


@pytest.mark.parametrize("bad", BAD_STRINGS)
def test_a_string_no_database_takes_is_refused_or_kept_as_documented(api_schema: schemathesis.BaseSchema,
                                                                      http: requests.Session, service: Service,
                                                                      load: Load, bad: str) -> None:
    method, path, changes = BAD_STRINGS[bad]
    body: dict[str, Any] = dict(changes)
    if path == "/api/queue/items":
        body = {"kind": "session", "file_name": "hostile.yaml", "body": load.session.read_text(), **changes}
    other = service.bench(user="other")
    if path == "/api/lease/break":  # someone else's lease, so that the reason is written into the history
        release_the_fuzzers_lease(service)
        other.lease(ttl_s=60)
    try:
        response = http.request(method, service.url + path, data=json.dumps(body).encode(),
                                headers={"Content-Type": "application/json"}, timeout=60)
    finally:
        if path == "/api/lease/break" and service.bench().status()["lease"] is not None:
            other.release()
    assert response.status_code < 500, (response.status_code, response.text[:300])
    answered_as_documented(api_schema, method, path, response)
    assert service.bench().status()["worker"]["state"] in ("ready", "starting")


@pytest.mark.parametrize("bad", BAD_PATHS)
def test_a_path_no_database_takes_is_refused_as_documented(api_schema: schemathesis.BaseSchema,
                                                           http: requests.Session, service: Service,
                                                           bad: str) -> None:
    raw_path = BAD_PATHS[bad]
    path = "/api/history/{uid}/log" if raw_path.endswith("/log") else (
        "/api/items/{uid}" if raw_path.startswith("/api/items/") else "/api/history/{uid}")
    response = http.get(service.url + raw_path, timeout=60)
    assert response.status_code == 404, (response.status_code, response.text[:300])
    answered_as_documented(api_schema, "GET", path, response, path_parameters={"uid": "0"})


@pytest.mark.parametrize(("method", "path"), UNKNOWN_ROUTES, ids=[f"{m} {p}" for m, p in UNKNOWN_ROUTES])
def test_an_unknown_route_or_method_is_one_line_of_json(api_schema: schemathesis.BaseSchema,
                                                        http: requests.Session, service: Service, method: str,
                                                        path: str) -> None:
    response = http.request(method, service.url + path, data=b"{}", headers={"Content-Type": "application/json"},
                            timeout=60)
    documented = {m.upper() for m in api_schema.raw_schema["paths"].get(path, {})}
    assert response.status_code == (405 if documented else 404), (response.status_code, response.text[:300])
    assert response.headers["content-type"].startswith("application/json"), response.headers
    detail = response.json()["detail"]
    assert isinstance(detail, str) and detail and "\n" not in detail and list(response.json()) == ["detail"]
    if documented:  # the methods the path takes
        assert documented <= {m.strip() for m in response.headers["allow"].split(",")}, response.headers


@pytest.mark.slow
def test_an_item_ran_while_the_api_was_fuzzed_and_the_service_still_serves(api_schema: schemathesis.BaseSchema,
                                                                            http: requests.Session, service: Service,
                                                                            load: Load, tmp_path: Path) -> None:
    """The load was there, and afterwards a session runs to its end; its record, its log, its report, its files and
    its series are answered as the document says."""
    load.stop()
    assert load.looks > 0 and load.share_busy >= MIN_BUSY, (load.looks, load.busy, load.submitted, load.errors)
    bench = service.bench(user=LOCAL_USER)
    release_the_fuzzers_lease(service)
    if bench.status()["running"] is not None:
        bench.abort(reason="the fuzzing is over")  # an abort also stops the queue
        wait_for(lambda: bench.status()["running"] is None, timeout_s=60)
    bench.clear()
    bench.start()
    record = bench.run(short_session(tmp_path, 1.0, name="after-fuzz"), out=tmp_path)
    assert record.status == "completed" and record.exit_code == 0, record.message
    assert bench.status()["worker"]["state"] == "ready"
    uid = bench.history(limit=1)[0]["uid"]
    report = bench.call("GET", f"/api/history/{uid}")["report_path"].split(f"/{uid}/", 1)[1]
    for path, params in (("/api/items/{uid}", {}), ("/api/history/{uid}", {}), ("/api/history/{uid}/log", {}),
                         ("/api/history/{uid}/report", {}), ("/api/history/{uid}/files", {}),
                         ("/api/history/{uid}/files/{path}", {"path": report}), ("/api/history/{uid}/series", {})):
        response = http.get(service.url + path.replace("{uid}", uid).replace("{path}", params.get("path", "")),
                            timeout=60)
        assert response.status_code == 200, (path, response.status_code, response.text[:300])
        answered_as_documented(api_schema, "GET", path, response, path_parameters={"uid": uid, **params})
